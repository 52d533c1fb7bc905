"""Survey tiles: LAS 1.4 / LAZ (point format 6) with per-point uncertainty and provenance.

What ``mls georef`` writes for each tile (a line, or a square of the projected CRS). The points
arrive as :data:`TILE_POINT_DTYPE` records (coordinates already in the output CRS), part by
part, and a tile is written whole or not at all: :func:`write_tile` writes ``<name>.laz.partial``
and renames it when the last point is in (the rename is atomic: a reader, or a resumed job,
sees either no tile or a complete one).

Every tile carries, beside what :class:`calib.io.laz.LasPassWriter` writes (CRS as WKT, adjusted
standard GPS time, intensity, scan angle, the pass id in ``point_source_id`` and as the int64
extra-bytes dimension ``pass_id``):

- the extra-bytes dimensions ``sigma_h_m`` and ``sigma_v_m`` (float32): the point's horizontal
  (radial, 1σ) and vertical standard deviation from the trajectory, the scanner and the mount
  covariance of the calibration (:mod:`calib.core.tpu`);
- a provenance VLR (user id :data:`PROVENANCE_USER_ID`, record id :data:`PROVENANCE_RECORD_ID`):
  UTF-8 JSON with the mount id, the calibration's fingerprint and boresight, the software
  version and the source of the trajectory;
- LAZ compressed on the calling thread only (lazrs, not its parallel variant): a task of
  ``mls georef`` uses one core, so N workers use N;
- a creation date that is the survey's (the first point's GPS day), not the day the file was
  written, so that the same inputs give the same bytes on any machine and any day.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calib.core import frames
from calib.io.laz import PASS_ID_DIMENSION, SCAN_ANGLE_UNIT_DEG, LasOutputError, OutputCrs, las_source_id

#: One point of a tile, as the chunks hand it over: coordinates in the output CRS.
TILE_POINT_DTYPE = np.dtype(
    [
        ("x", "<f8"),
        ("y", "<f8"),
        ("z", "<f8"),
        ("t_gps_s", "<f8"),
        ("intensity", "<u2"),
        ("scan_angle_rad", "<f4"),
        ("pass_id", "<i8"),
        ("sigma_h_m", "<f4"),
        ("sigma_v_m", "<f4"),
    ]
)
PROVENANCE_USER_ID = "marine-mls"
PROVENANCE_RECORD_ID = 1
SIGMA_DIMENSIONS = ("sigma_h_m", "sigma_v_m")
_GPS_EPOCH = _dt.date(1980, 1, 6)


@dataclass(frozen=True)
class TileSummary:
    """What one tile holds (``summary.json`` of the survey lists these)."""

    name: str
    path: str
    n_points: int
    t_first_gps_s: float
    t_last_gps_s: float
    bbox: tuple[float, float, float, float, float, float]  # x, y, z min then max (output CRS)
    sigma_h_m: dict[str, float]  # median, p95, max
    sigma_v_m: dict[str, float]
    passes: list[int]

    def as_dict(self) -> dict:
        return {
            "name": self.name,
            "path": self.path,
            "n_points": self.n_points,
            "t_first_gps_s": self.t_first_gps_s,
            "t_last_gps_s": self.t_last_gps_s,
            "bbox": list(self.bbox),
            "sigma_h_m": self.sigma_h_m,
            "sigma_v_m": self.sigma_v_m,
            "passes": self.passes,
        }


def _survey_date(t_gps_s: float) -> _dt.date:
    return _GPS_EPOCH + _dt.timedelta(days=int(t_gps_s // 86400))


def _quantiles(v: np.ndarray) -> dict[str, float]:
    if v.size == 0:
        return {"median": float("nan"), "p95": float("nan"), "max": float("nan")}
    q = np.quantile(v, [0.5, 0.95])
    return {"median": round(float(q[0]), 5), "p95": round(float(q[1]), 5), "max": round(float(v.max()), 5)}


def tile_header(crs: OutputCrs, source_id: int, software: str, provenance: dict, date: _dt.date):
    """The LAS 1.4 header of a tile (point format 6, the WKT and provenance VLRs, the extra
    bytes ``pass_id``, ``sigma_h_m``, ``sigma_v_m``): every writer of a tile starts from it
    (:func:`write_tile`, :mod:`office.deliver.lasrecords`)."""
    import laspy
    from laspy.vlrs.known import WktCoordinateSystemVlr

    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array(crs.scales)
    header.offsets = np.array(crs.offsets)
    header.file_source_id = source_id
    header.system_identifier = "marine-mls MLS (Z+F + Hydrins)"[:32]
    header.generating_software = software[:32]
    header.creation_date = date
    header.global_encoding.gps_time_type = laspy.header.GpsTimeType.STANDARD
    header.global_encoding.wkt = True
    header.vlrs.append(WktCoordinateSystemVlr(crs.wkt))
    header.vlrs.append(
        laspy.VLR(
            user_id=PROVENANCE_USER_ID,
            record_id=PROVENANCE_RECORD_ID,
            description="calibration provenance (JSON)",
            record_data=json.dumps(provenance, sort_keys=True).encode("utf-8"),
        )
    )
    header.add_extra_dims(
        [
            laspy.ExtraBytesParams(name=PASS_ID_DIMENSION, type=np.int64, description="pass / line id"),
            laspy.ExtraBytesParams(name="sigma_h_m", type=np.float32, description="horizontal 1-sigma (m)"),
            laspy.ExtraBytesParams(name="sigma_v_m", type=np.float32, description="vertical 1-sigma (m)"),
        ]
    )
    return header


class _Tally:
    """What a tile holds, counted part by part as it is written."""

    def __init__(self) -> None:
        self.pass_ids: set[int] = set()
        self.n = 0
        self.t_lo, self.t_hi = np.inf, -np.inf
        self.lo, self.hi = np.full(3, np.inf), np.full(3, -np.inf)
        self.sh: list[np.ndarray] = []
        self.sv: list[np.ndarray] = []

    def add(self, part: np.ndarray) -> None:
        self.n += part.size
        self.t_lo = min(self.t_lo, float(part["t_gps_s"].min()))
        self.t_hi = max(self.t_hi, float(part["t_gps_s"].max()))
        xyz = np.stack([part["x"], part["y"], part["z"]])
        self.lo, self.hi = np.minimum(self.lo, xyz.min(axis=1)), np.maximum(self.hi, xyz.max(axis=1))
        # the σ summary from a thinned copy (every 16th point: a tile may hold 10⁸)
        self.sh.append(part["sigma_h_m"][::16].copy())
        self.sv.append(part["sigma_v_m"][::16].copy())

    def summary(self, path: Path) -> TileSummary:
        return TileSummary(
            name=path.stem,
            path=path.name,
            n_points=int(self.n),
            t_first_gps_s=float(self.t_lo),
            t_last_gps_s=float(self.t_hi),
            bbox=(*(round(float(v), 4) for v in self.lo), *(round(float(v), 4) for v in self.hi)),  # type: ignore[arg-type]
            sigma_h_m=_quantiles(np.concatenate(self.sh)),
            sigma_v_m=_quantiles(np.concatenate(self.sv)),
            passes=sorted(self.pass_ids),
        )


def _point_record(laspy, header, part: np.ndarray, ids: np.ndarray, crs: OutputCrs, path: Path):
    """The LAS points of ``part`` (its pass ids ``ids``, sorted)."""
    rec = laspy.ScaleAwarePointRecord.zeros(part.size, header=header)
    try:
        rec.x, rec.y, rec.z = part["x"], part["y"], part["z"]
    except OverflowError:
        raise LasOutputError(
            f"{path}: coordinates do not fit the LAS integer range around offsets "
            f"{crs.offsets} at scales {crs.scales}"
        ) from None
    rec.gps_time = frames.gps_seconds_to_las(part["t_gps_s"])
    rec.intensity = part["intensity"]
    rec.return_number = np.ones(part.size, np.uint8)
    rec.number_of_returns = np.ones(part.size, np.uint8)
    rec.point_source_id = np.array([las_source_id(int(i)) for i in ids], np.uint16)[
        np.searchsorted(ids, part["pass_id"])
    ]
    rec[PASS_ID_DIMENSION] = part["pass_id"]
    rec["sigma_h_m"] = part["sigma_h_m"]
    rec["sigma_v_m"] = part["sigma_v_m"]
    nadir_deg = np.degrees(frames.wrap_pi(np.pi / 2 - part["scan_angle_rad"].astype(float)))
    rec.scan_angle = np.round(nadir_deg / SCAN_ANGLE_UNIT_DEG).astype(np.int16)
    return rec


def write_tile(
    path: str | Path,
    parts: Iterable[np.ndarray],
    crs: OutputCrs,
    software: str,
    provenance: dict,
    first_t_gps_s: float,
) -> TileSummary:
    """Write the tile ``path`` (``.laz`` compressed, ``.las`` not) from ``parts`` (arrays of
    :data:`TILE_POINT_DTYPE`, in the order they are to appear) and return its summary. The file
    appears only complete (module docstring); ``first_t_gps_s`` (the survey's first point) dates
    the header."""
    import laspy

    path = Path(path)
    partial = path.with_name(path.name + ".partial")
    tally = _Tally()
    writer = None
    try:
        for part in parts:
            if part.dtype != TILE_POINT_DTYPE:
                raise LasOutputError(f"{path}: a part of dtype {part.dtype}, expected TILE_POINT_DTYPE")
            if part.size == 0:
                continue
            ids = np.unique(part["pass_id"])
            tally.pass_ids.update(int(i) for i in ids)
            if writer is None:
                # one source id per file: the line's (LAS's u16, else 0); square tiles mix lines
                source_id = las_source_id(int(ids[0])) if ids.size == 1 else 0
                header = tile_header(crs, source_id, software, provenance, _survey_date(first_t_gps_s))
                writer = laspy.open(
                    partial,
                    mode="w",
                    header=header,
                    do_compress=path.suffix == ".laz",
                    laz_backend=laspy.LazBackend.Lazrs,  # one thread: one task is one core
                )
            writer.write_points(_point_record(laspy, writer.header, part, ids, crs, path))
            tally.add(part)
        if writer is None:
            raise LasOutputError(f"{path}: a tile without points (nothing to write)")
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
    return tally.summary(path)


def read_provenance(path: str | Path) -> dict:
    """The provenance VLR of a tile (what :func:`write_tile` stored)."""
    import laspy

    with laspy.open(path) as f:
        for vlr in f.header.vlrs:
            if vlr.user_id == PROVENANCE_USER_ID and vlr.record_id == PROVENANCE_RECORD_ID:
                return json.loads(bytes(vlr.record_data).decode("utf-8"))
    raise LasOutputError(f"{path}: no marine-mls provenance VLR")
