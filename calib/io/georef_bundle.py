"""A calibration bundle → one LAS/LAZ file per pass (what ``mls calib georef`` and ``mls export
--laz`` write).

:func:`georeference_bundle` georeferences every pass of a bundle with the mount of its
site.yaml (optionally another boresight) in chunks of :data:`DEFAULT_CHUNK_POINTS` points and
writes ``pass-<id>.laz`` (or ``.las``) through :class:`calib.io.laz.LasPassWriter`; it returns a
:class:`PassOutput` per pass and the facts a caption needs (CRS, boresight, intensity scale, the
pass ids that LAS's u16 ``point_source_id`` cannot hold). Coverage is checked for every pass
before the first file is written: an error leaves no partial output.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # annotations only: the work imports its modules when it runs
    from calib.core.georef import Mount
    from calib.io.bundle import Bundle, IntensityScale
    from calib.io.laz import OutputCrs

#: Points georeferenced and written per step (bounds the memory a pass needs).
DEFAULT_CHUNK_POINTS = 1_000_000


@dataclass(frozen=True)
class PassOutput:
    """What ``mls calib georef`` wrote for one pass."""

    pass_id: int
    n_points: int
    n_dropped: int
    t_first_gps_s: float
    t_last_gps_s: float
    path: Path


def _covered_passes(
    bundle: Bundle, mount: Mount, skip_uncovered: bool, max_gap_s: float
) -> list[tuple[int, object, int]]:
    """Per pass (id, the indices of its points the trajectory covers, how many it does not),
    every pass checked before anything is written: without ``skip_uncovered`` an uncovered
    point is a :class:`calib.core.trajectory.TrajectoryError`."""
    import numpy as np

    from calib.core.trajectory import TrajectoryError

    pts, traj = bundle.points, bundle.trajectory
    selected = []
    for pass_id in pts.pass_ids():
        idx = np.flatnonzero(pts.pass_id == pass_id)
        bad = traj.uncovered(pts.t_gps_s[idx] + mount.time_offset_s)
        if bad.any() and not skip_uncovered:
            tb = pts.t_gps_s[idx[bad]]
            raise TrajectoryError(
                f"{bundle.points_path}: pass {pass_id}: {int(bad.sum())} of {idx.size} points fall "
                f"outside the trajectory {traj.name} ({traj.t_gps_s[0]:.3f} … {traj.t_gps_s[-1]:.3f} s) "
                f"or in a gap > {max_gap_s:g} s (first {tb.min():.3f} s, last {tb.max():.3f} s: "
                f"{traj.where_uncovered(tb + mount.time_offset_s)}); use --skip-uncovered to drop them"
            )
        selected.append((pass_id, idx[~bad], int(bad.sum())))
    return selected


@dataclass(frozen=True, kw_only=True)
class _PassWriting:
    """How every pass is written: the bundle, the mount, the output CRS and intensity scale."""

    bundle: Bundle
    mount: Mount
    out_crs: OutputCrs
    scale: IntensityScale
    software: str
    chunk_points: int


def _write_pass(w: _PassWriting, path: Path, pass_id: int, idx, n_dropped: int, progress) -> PassOutput:
    """Georeference one pass's points chunk by chunk into ``path``."""
    import numpy as np

    from calib.core.georef import georeference
    from calib.io.laz import LasPassWriter

    pts, traj = w.bundle.points, w.bundle.trajectory
    task = None
    if progress is not None:
        task = progress.add_task(f"pass {pass_id}", total=max(idx.size, 1))
    with LasPassWriter(path, w.out_crs, pass_id, w.software) as writer:
        for lo in range(0, idx.size, w.chunk_points):
            sel = idx[lo : lo + w.chunk_points]
            t = pts.t_gps_s[sel]
            p = georeference(t, pts.range_m[sel], pts.scan_angle_rad[sel], traj, w.mount)
            intensity = np.round(pts.intensity[sel] * w.scale.factor)  # in 0…65535 (checked)
            writer.write(p, t, intensity, pts.scan_angle_rad[sel])
            if task is not None:
                progress.advance(task, sel.size)
    if task is not None and idx.size == 0:
        progress.advance(task, 1)
    t_pass = pts.t_gps_s[idx]
    return PassOutput(
        pass_id,
        int(idx.size),
        n_dropped,
        float(t_pass.min()) if t_pass.size else float("nan"),
        float(t_pass.max()) if t_pass.size else float("nan"),
        path,
    )


def _output_warnings(outputs: list[PassOutput]) -> tuple[list[int], list[str]]:
    """The pass ids LAS's u16 ``point_source_id`` cannot hold, and the warnings: points left
    out of a pass, those ids."""
    from calib.io.laz import las_source_id

    wide = [o.pass_id for o in outputs if las_source_id(o.pass_id) != o.pass_id]
    warnings = [
        f"pass {o.pass_id}: {o.n_dropped:,} points outside the trajectory's coverage are not in {o.path}"
        for o in outputs
        if o.n_dropped
    ]
    if wide:
        warnings.append(
            f"pass ids {', '.join(map(str, wide))} exceed LAS's 16-bit point_source_id: 0 there; "
            f"each point's extra-bytes dimension pass_id holds the id"
        )
    return wide, warnings


def georeference_bundle(
    bundle_dir: Path,
    out_dir: Path,
    crs: str = "utm",
    boresight_deg: tuple[float, float, float] | None = None,
    compress: bool = True,
    max_gap_s: float = 1.0,
    skip_uncovered: bool = False,
    chunk_points: int = DEFAULT_CHUNK_POINTS,
    progress=None,
    boresight_source: str = "--boresight-deg",
    out_option: str = "--out",
) -> tuple[list[PassOutput], dict]:
    """Georeference every pass of a bundle into ``out_dir/pass-<id>.laz``.

    ``boresight_deg`` (canonical roll, pitch, yaw) overrides site.yaml's a-priori boresight;
    ``boresight_source`` names where it came from for the caption. Returns the per-pass outputs
    and facts for the caption (CRS, boresight, intensity scale). ``progress`` is an optional
    rich Progress that gets one task per pass.
    """
    import numpy as np

    from calib.core.version import software_version
    from calib.io.bundle import intensity_scale, read_bundle
    from calib.io.laz import output_crs
    from calib.io.outputs import make_output_dir

    bundle = read_bundle(bundle_dir, max_gap_s=max_gap_s)
    mount = bundle.site.mount
    if boresight_deg is not None:
        mount = mount.with_boresight(np.radians(boresight_deg))
    out_crs = output_crs(crs, bundle.frame)
    # intensity → u16: one scale for the bundle, decided and checked by the reader (reflectances
    # 0…1 span the full range, counts are kept), so that the passes compare
    scale = intensity_scale(bundle.points.intensity, bundle.points_path)
    suffix = ".laz" if compress else ".las"
    writing = _PassWriting(
        bundle=bundle,
        mount=mount,
        out_crs=out_crs,
        scale=scale,
        software=software_version(),
        chunk_points=chunk_points,
    )
    selected = _covered_passes(bundle, mount, skip_uncovered, max_gap_s)
    make_output_dir(out_dir, out_option)
    outputs = [
        _write_pass(writing, out_dir / f"pass-{pass_id}{suffix}", pass_id, idx, n_dropped, progress)
        for pass_id, idx, n_dropped in selected
    ]
    wide, warnings = _output_warnings(outputs)
    facts = {
        "crs": out_crs.name,
        "boresight_deg": tuple(float(v) for v in np.degrees(mount.boresight_rad)),
        "boresight_source": boresight_source if boresight_deg is not None else "site.yaml",
        "intensity": scale.describe(),
        "source_id_zero": wide,  # pass ids u16 point_source_id cannot hold: 0 there
        "warnings": warnings,  # for callers that print no table (mls export --laz)
    }
    return outputs, facts
