"""One time chunk of a survey: filter, georeference, per-point σ, sort into tile parts.

:func:`process_chunk` is the task a worker runs (this process, or a Dask worker process). It
reads the chunk's returns (:func:`office.deliver.sources.read_chunk`), drops what the filters
say (counted per reason), georeferences the rest on the chunk's slice of the trajectory,
computes σ_h and σ_v (:func:`calib.core.tpu.point_sigmas`), converts to the output CRS, and
writes one part per tile it touches, ``<out>/.georef/parts/<tile>/c<chunk>.npy``
(:data:`calib.io.lastile.TILE_POINT_DTYPE`, time order). Every file is written under a temporary
name and renamed; the chunk's record ``<out>/.georef/chunks/c<chunk>.json`` comes last. A chunk
is therefore idempotent: run twice (a worker killed, a job resumed) it writes the same bytes, and
a chunk without its record is simply run again.
"""

from __future__ import annotations

import json
import math
import os
import resource
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from office.deliver.options import Filters
from office.deliver.sources import ChunkSpec, Returns, read_chunk

if TYPE_CHECKING:
    from calib.core.frames import LocalFrame
    from calib.core.georef import Mount
    from calib.core.tpu import MountCovariance, ScannerSigmas
    from calib.core.trajectory import Trajectory

NS_PER_S = 1_000_000_000
STATE_DIR = ".georef"
TRANSIT = "transit"
#: trajectory kept on each side of a chunk (covers the mount's time offset and interpolation)
TRAJECTORY_OVERLAP_S = 2.0
#: returns georeferenced per step within a chunk (their temporaries stay in the CPU's caches)
BLOCK = 1 << 16


@dataclass(frozen=True)
class ChunkContext:
    """What every chunk of one job shares (small: the trajectory travels sliced per chunk)."""

    out_dir: str
    crs: str
    frame: LocalFrame
    mount: Mount
    covariance: MountCovariance
    scanner: ScannerSigmas
    filters: Filters
    tiling: str
    tile_m: float | None
    keep_transits: bool
    lines: np.ndarray  # (n, 3) int64: pass id, start GPS ns, end GPS ns; sorted by start


@dataclass(frozen=True)
class ChunkTask:
    context: ChunkContext
    spec: ChunkSpec
    trajectory: Trajectory  # the chunk's slice of the survey's trajectory


@dataclass(frozen=True)
class ChunkDone:
    index: int
    tiles: dict[str, dict]  # tile name → {"n": points, "t_first_gps_s": …}
    counters: dict[str, int]
    peak_rss_mb: float
    pid: int


def slice_trajectory(traj, t0_s: float, t1_s: float):
    """The epochs of ``traj`` within [t0 − overlap, t1 + overlap] (one more on each side)."""
    from calib.core.trajectory import Trajectory

    tt = traj.t_gps_s
    a = max(int(np.searchsorted(tt, t0_s - TRAJECTORY_OVERLAP_S)) - 1, 0)
    b = min(int(np.searchsorted(tt, t1_s + TRAJECTORY_OVERLAP_S)) + 1, tt.size)
    a = min(a, tt.size - 2)  # two epochs at least (a trajectory has two or more)
    b = max(b, a + 2)
    sl = slice(a, b)
    return Trajectory(
        tt[sl],
        traj.p_lgf_m[sl],
        traj.rpy_rad[sl],
        traj.frame,
        None if traj.sigma_p_m is None else traj.sigma_p_m[sl],
        None if traj.sigma_rpy_rad is None else traj.sigma_rpy_rad[sl],
        traj.max_gap_s,
        traj.name,
    )


CRS_CACHE: dict[tuple, object] = {}


def crs_for(spec: str, frame):
    from calib.io.laz import output_crs

    key = (spec, frame.lat_deg, frame.lon_deg, frame.height_m)
    if key not in CRS_CACHE:  # a pyproj transformer per process, not per chunk
        CRS_CACHE[key] = output_crs(spec, frame)
    return CRS_CACHE[key]


def state_dir(out_dir: str | Path) -> Path:
    return Path(out_dir) / STATE_DIR


def chunk_record_path(out_dir: str | Path, index: int) -> Path:
    return state_dir(out_dir) / "chunks" / f"c{index:06d}.json"


def part_path(out_dir: str | Path, tile: str, index: int) -> Path:
    return state_dir(out_dir) / "parts" / tile / f"c{index:06d}.npy"


def write_atomic(path: Path, data: bytes) -> None:
    """``path`` appears whole or not at all (temporary name, fsync, rename); a write that fails
    (the disk full) leaves no temporary file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _save_part(path: Path, part: np.ndarray) -> None:
    import io

    buf = io.BytesIO()
    np.save(buf, part, allow_pickle=False)
    write_atomic(path, buf.getbuffer().tobytes())


def _filter(r: Returns, f: Filters, counters: dict[str, int]) -> np.ndarray:
    keep = np.ones(r.size, bool)

    def drop(name: str, bad: np.ndarray) -> None:
        counters[name] = int((bad & keep).sum())
        keep[bad] = False

    drop("outside_range_window", (r.range_m < f.range_m[0]) | (r.range_m > f.range_m[1]))
    if f.scan_angle_deg is not None:
        a = np.degrees(r.scan_angle_rad)
        drop("outside_scan_angle_window", (a < f.scan_angle_deg[0]) | (a > f.scan_angle_deg[1]))
    if f.intensity_min:
        drop("below_intensity_floor", r.intensity < f.intensity_min)
    if f.time_gps_s is not None:
        lo, hi = (round(v * NS_PER_S) for v in f.time_gps_s)
        drop("outside_time_window", (r.t_gps_ns < lo) | (r.t_gps_ns > hi))
    return keep


def _vessel(range_m, scan_angle_rad, mount, box) -> np.ndarray:
    """Returns inside the body-frame box (the vessel's own structure)."""
    from calib.core.frames import scanner_vector

    v_b = scanner_vector(range_m, scan_angle_rad) @ mount.r_s_b.T + mount.lever_arm_m
    inside = np.ones(v_b.shape[0], bool)
    for j in range(3):
        inside &= (v_b[:, j] >= box[2 * j]) & (v_b[:, j] <= box[2 * j + 1])
    return inside


def _pass_ids(r: Returns, lines: np.ndarray) -> np.ndarray:
    if r.pass_id is not None:
        return np.asarray(r.pass_id, np.int64)
    if lines.size == 0:
        return np.full(r.size, -1, np.int64)
    k = np.searchsorted(lines[:, 1], r.t_gps_ns, side="right") - 1
    inside = (k >= 0) & (r.t_gps_ns <= lines[np.maximum(k, 0), 2])
    return np.where(inside, lines[np.maximum(k, 0), 0], -1)


def tile_names(
    ctx: ChunkContext, x: np.ndarray, y: np.ndarray, pass_id: np.ndarray
) -> tuple[np.ndarray, list[str]]:
    """(tile index per point, tile names): lines, or squares named by their south-west corner."""
    if ctx.tiling == "line":
        keys, inv = np.unique(pass_id, return_inverse=True)
        return inv, [TRANSIT if k < 0 else f"line-{int(k)}" for k in keys]
    assert ctx.tile_m is not None  # square tiling has its size (GeorefOptions checks it)
    s = float(ctx.tile_m)
    ix, iy = np.floor(x / s).astype(np.int64), np.floor(y / s).astype(np.int64)
    keys, inv = np.unique(np.stack([ix, iy]), axis=1, return_inverse=True)
    digits = 0 if s == math.floor(s) else 3
    names = [f"tile-{kx * s:.{digits}f}-{ky * s:.{digits}f}" for kx, ky in keys.T]
    return inv.reshape(-1), names


@dataclass(frozen=True)
class _Selection:
    """The returns of a chunk that go into the deliverable: their indices in the chunk (time
    order), their GPS times (s) and every return's pass id (-1: none)."""

    idx: np.ndarray
    t_s: np.ndarray
    pass_id: np.ndarray


def _select(r: Returns, ctx: ChunkContext, traj: Trajectory, counters: dict[str, int]) -> _Selection:
    """Apply the filters, the lines (without transits), the vessel box and the trajectory's
    coverage, counting what each drops into ``counters``."""
    from calib.core import frames

    keep = _filter(r, ctx.filters, counters)
    pid = _pass_ids(r, ctx.lines)
    if ctx.tiling == "line" and not ctx.keep_transits:
        counters["outside_lines"] = int((keep & (pid < 0)).sum())
        keep &= pid >= 0
    mount = ctx.mount
    if ctx.filters.vessel_box_m is not None:
        inside = np.zeros(r.size, bool)
        inside[keep] = _vessel(r.range_m[keep], r.scan_angle_rad[keep], mount, ctx.filters.vessel_box_m)
        counters["vessel_itself"] = int(inside.sum())
        keep &= ~inside
    t_s = frames.gps_ns_to_seconds(r.t_gps_ns[keep])
    uncovered = traj.uncovered(t_s + mount.time_offset_s)
    counters["outside_trajectory"] = int(uncovered.sum())
    return _Selection(idx=np.flatnonzero(keep)[~uncovered], t_s=t_s[~uncovered], pass_id=pid)


def _georeference_points(ctx: ChunkContext, traj: Trajectory, r: Returns, sel: _Selection) -> np.ndarray:
    """The selected returns as tile points (:data:`~calib.io.lastile.TILE_POINT_DTYPE`):
    georeferenced on the output CRS's LAS grid, with their σ_h and σ_v, in blocks that stay
    in the CPU's caches."""
    from calib.core.georef import georeference
    from calib.core.tpu import point_sigmas
    from calib.io.lastile import TILE_POINT_DTYPE

    idx, t_s, mount = sel.idx, sel.t_s, ctx.mount
    rng, ang = r.range_m[idx], r.scan_angle_rad[idx]
    crs = crs_for(ctx.crs, ctx.frame)
    scale, offset = np.asarray(crs.scales), np.asarray(crs.offsets)
    pts = np.empty(idx.size, TILE_POINT_DTYPE)
    for lo in range(0, idx.size, BLOCK):  # blocks that stay in cache, one output array
        b = slice(lo, lo + BLOCK)
        p = georeference(t_s[b], rng[b], ang[b], traj, mount)
        # on the LAS grid already, so that a square tile holds its points as stored
        xyz = np.round((crs.from_lgf(p) - offset) / scale) * scale + offset
        out = pts[b]
        out["x"], out["y"], out["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        out["sigma_h_m"], out["sigma_v_m"] = point_sigmas(
            t_s[b], rng[b], ang[b], traj, mount, ctx.scanner, ctx.covariance
        )
    pts["t_gps_s"] = t_s
    pts["intensity"] = r.intensity[idx]
    pts["scan_angle_rad"] = ang
    pts["pass_id"] = sel.pass_id[idx]
    return pts


def _write_parts(ctx: ChunkContext, index: int, pts: np.ndarray) -> dict[str, dict]:
    """Write one part per tile the points touch (time order within each); what each holds."""
    tiles: dict[str, dict] = {}
    inv, names = tile_names(ctx, pts["x"], pts["y"], pts["pass_id"])
    order = np.argsort(inv, kind="stable")  # time order within each tile
    bounds = np.searchsorted(inv[order], np.arange(len(names) + 1))
    for j, name in enumerate(names):
        part = pts[order[bounds[j] : bounds[j + 1]]]
        _save_part(part_path(ctx.out_dir, name, index), part)
        tiles[name] = {"n": int(part.size), "t_first_gps_s": float(part["t_gps_s"][0])}
    return tiles


def process_chunk(task: ChunkTask) -> ChunkDone:
    """Run one chunk (module docstring) and return what it wrote."""
    ctx, spec, traj = task.context, task.spec, task.trajectory
    r = read_chunk(spec)
    counters: dict[str, int] = dict(r.counters)
    counters["returns"] = r.size
    sel = _select(r, ctx, traj, counters)
    tiles: dict[str, dict] = {}
    if sel.idx.size:
        tiles = _write_parts(ctx, spec.index, _georeference_points(ctx, traj, r, sel))
    counters["written"] = int(sel.idx.size)
    record = {
        "index": spec.index,
        "t0_ns": spec.t0_ns,
        "t1_ns": spec.t1_ns,
        "tiles": tiles,
        "counters": counters,
    }
    write_atomic(chunk_record_path(ctx.out_dir, spec.index), json.dumps(record, sort_keys=True).encode())
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return ChunkDone(spec.index, tiles, counters, rss_mb, os.getpid())


def with_site_sigmas(traj, site):
    """The trajectory with the site's constant POS sigmas where it has none of its own."""
    if traj.has_sigmas:
        return traj
    n = traj.t_gps_s.size
    return replace(
        traj,
        sigma_p_m=np.tile(np.asarray(site.sigma_position_m, float), (n, 1)),
        sigma_rpy_rad=np.tile(np.asarray(site.sigma_attitude_rad, float), (n, 1)),
    )
