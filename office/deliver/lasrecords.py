"""Tile points as the tile file's own LAS records, and a tile file made of them.

A chunk encodes its points straight into the point records of the tile files (LAS 1.4 point
format 6 with the extra bytes ``pass_id``, ``sigma_h_m``, ``sigma_v_m``: the layout of
:func:`calib.io.lastile.write_tile`, :func:`record_dtype`); its parts are arrays of these
records. :func:`write_tile` then writes a tile from its parts without converting anything: the
records go to the LAZ compressor as they are. The file, its header and its summary are those
:func:`calib.io.lastile.write_tile` writes for the same points, byte for byte (the GPS time of
a record, adjusted standard time, gives back the point's GPS seconds exactly: t − 10⁹ is exact
for t within [5·10⁸, 2·10⁹] s, i.e. 1995–2043).
"""

from __future__ import annotations

import datetime as _dt
import os
from collections.abc import Iterable
from functools import cache
from pathlib import Path

import numpy as np

from calib.core import frames
from calib.io.lastile import TileSummary
from calib.io.laz import SCAN_ANGLE_UNIT_DEG, LasOutputError, OutputCrs, las_source_id

_GPS_EPOCH = _dt.date(1980, 1, 6)
#: the bit fields of return 1 of 1 (return number in bits 0–3, number of returns in 4–7)
FIRST_OF_ONE = 0x11
_I32 = (-(2**31), 2**31 - 1)


def _header(crs: OutputCrs, source_id: int, software: str, provenance: dict, t_gps_s: float):
    from calib.io.lastile import tile_header  # the one header of a tile

    date = _GPS_EPOCH + _dt.timedelta(days=int(t_gps_s // 86400))
    return tile_header(crs, source_id, software, provenance, date)


@cache
def record_dtype() -> np.dtype:
    """The dtype of one point record of a tile (point format 6 and its extra bytes)."""
    from calib.io.laz import SCALE_M

    crs = OutputCrs("LGF", "", (SCALE_M,) * 3, (0.0, 0.0, 0.0), frames.LocalFrame(0.0, 0.0), None)
    return _header(crs, 0, "", {}, 1e9).point_format.dtype()


def check_grid(xyz_grid: np.ndarray, crs: OutputCrs, where: str) -> None:
    """:class:`LasOutputError` when LAS integers (3, n) do not fit the record's int32."""
    if xyz_grid.size and (xyz_grid.min() < _I32[0] or xyz_grid.max() > _I32[1]):
        raise LasOutputError(
            f"{where}: coordinates do not fit the LAS integer range around offsets "
            f"{crs.offsets} at scales {crs.scales}"
        )


def _wrap_pi_in_place(a: np.ndarray) -> np.ndarray:
    """``a`` (float64) wrapped to (−π, π] in place, bit for bit :func:`calib.core.frames.wrap_pi`:
    π − ((π − a) mod 2π). Where 0 ≤ π − a < 4π everywhere (a scan angle in [0, 2π) always), the
    remainder is π − a itself or π − a − 2π, a subtraction that is exact (Sterbenz: the operands
    within a factor of 2), as the remainder is: the same bits for a fraction of ``np.mod``'s time."""
    two_pi = 2.0 * np.pi
    np.subtract(np.pi, a, out=a)
    if a.size and a.min() >= 0.0 and a.max() < 2.0 * two_pi:  # (False with a NaN: np.mod then)
        np.subtract(a, two_pi, out=a, where=a >= two_pi)
    else:
        np.mod(a, two_pi, out=a)
    return np.subtract(np.pi, a, out=a)


def scan_angle_units(scan_angle_rad_f4: np.ndarray) -> np.ndarray:
    """The LAS scan angle (int16, 0.006° from the scanner's nadir) of float32 scan angles."""
    a = np.subtract(np.pi / 2, scan_angle_rad_f4, dtype=float)
    nadir_deg = np.degrees(_wrap_pi_in_place(a), out=a)
    nadir_deg /= SCAN_ANGLE_UNIT_DEG
    return np.round(nadir_deg, out=nadir_deg).astype(np.int16)


def _pass_ids(pass_id: np.ndarray) -> np.ndarray:
    """The sorted distinct pass ids of a part (one line's part: no sort)."""
    if pass_id.min() == pass_id.max():
        return np.asarray(pass_id[:1])
    return np.unique(pass_id)


def source_ids(pass_id: np.ndarray) -> np.ndarray:
    """LAS's u16 point source id of each pass id (:func:`calib.io.laz.las_source_id`)."""
    if pass_id.size and pass_id.min() == pass_id.max():  # one line: no sort
        return np.full(pass_id.size, las_source_id(int(pass_id[0])), np.uint16)
    ids, inv = np.unique(pass_id, return_inverse=True)
    return np.array([las_source_id(int(i)) for i in ids], np.uint16)[inv.reshape(-1)]


class _Tally:
    """What a tile holds, counted part by part (as :mod:`calib.io.lastile` counts it). The
    bounds and the time span are those laspy's writer keeps in the header while it writes
    (the least and greatest X, Y, Z and GPS time, scaled and offset: a monotonic map of the
    least and greatest record gives the least and greatest coordinate, the same bits), not
    counted again here."""

    def __init__(self) -> None:
        self.pass_ids: set[int] = set()
        self.n = 0
        self.sh: list[np.ndarray] = []
        self.sv: list[np.ndarray] = []

    def add(self, part: np.ndarray, ids: np.ndarray) -> None:
        self.n += part.size
        self.pass_ids.update(int(i) for i in ids)
        # the σ summary from a thinned copy (every 16th point: a tile may hold 10⁸)
        self.sh.append(part["sigma_h_m"][::16].copy())
        self.sv.append(part["sigma_v_m"][::16].copy())

    def summary(self, path: Path, header) -> TileSummary:
        """The tile's summary; ``header`` is the writer's, after its last points."""
        lo, hi = np.asarray(header.mins, float), np.asarray(header.maxs, float)
        return TileSummary(
            name=path.stem,
            path=path.name,
            n_points=int(self.n),
            t_first_gps_s=float(frames.las_to_gps_seconds(header.min_gps_time)),
            t_last_gps_s=float(frames.las_to_gps_seconds(header.max_gps_time)),
            bbox=tuple(round(float(v), 4) for v in (*lo, *hi)),  # type: ignore[arg-type]
            sigma_h_m=_quantiles(np.concatenate(self.sh)),
            sigma_v_m=_quantiles(np.concatenate(self.sv)),
            passes=sorted(self.pass_ids),
        )


def _quantiles(v: np.ndarray) -> dict[str, float]:
    if v.size == 0:
        return {"median": float("nan"), "p95": float("nan"), "max": float("nan")}
    q = np.quantile(v, [0.5, 0.95])
    return {"median": round(float(q[0]), 5), "p95": round(float(q[1]), 5), "max": round(float(v.max()), 5)}


def write_tile(
    path: str | Path,
    parts: Iterable[np.ndarray],
    crs: OutputCrs,
    software: str,
    provenance: dict,
    first_t_gps_s: float,
) -> TileSummary:
    """Write the tile ``path`` (``.laz`` compressed, ``.las`` not) from ``parts`` (arrays of
    :func:`record_dtype`, in order) and return its summary; the file appears only complete
    (``<name>.partial`` renamed once written and synced), as :func:`calib.io.lastile.write_tile`."""
    import laspy

    path = Path(path)
    partial = path.with_name(path.name + ".partial")
    tally = _Tally()
    writer = None
    try:
        for part in parts:
            if part.dtype != record_dtype():
                raise LasOutputError(f"{path}: a part of dtype {part.dtype}, expected the tile's records")
            if part.size == 0:
                continue
            ids = _pass_ids(part["pass_id"])
            if writer is None:
                # one source id per file: the line's (LAS's u16, else 0); square tiles mix lines
                source_id = las_source_id(int(ids[0])) if ids.size == 1 else 0
                header = _header(crs, source_id, software, provenance, first_t_gps_s)
                writer = laspy.open(
                    partial,
                    mode="w",
                    header=header,
                    do_compress=path.suffix == ".laz",
                    laz_backend=laspy.LazBackend.Lazrs,  # one thread: one task is one core
                )
            writer.write_points(laspy.PackedPointRecord(part, writer.header.point_format))
            tally.add(part, ids)
        if writer is None:
            raise LasOutputError(f"{path}: a tile without points (nothing to write)")
        summary = tally.summary(path, writer.header)
        writer.close()
        writer = None
        with open(partial, "rb") as f:
            os.fsync(f.fileno())
        os.replace(partial, path)
    finally:
        if writer is not None:
            writer.close()
        if partial.exists():
            partial.unlink()
    return summary
