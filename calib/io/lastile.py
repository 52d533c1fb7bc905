"""Survey tiles: LAS 1.4 / LAZ (point format 6) with per-point uncertainty and provenance.

What ``mls georef`` writes for each tile (a line, or a square of the projected CRS). The points
arrive as the file's own point records (:func:`record_dtype`: coordinates already on the output
CRS's LAS grid; :mod:`office.deliver.lasrecords` encodes them), part by part, and a tile is
written whole or not at all: :func:`write_tile` writes ``<name>.laz.partial`` and renames it when
the last point is in (the rename is atomic: a reader, or a resumed job, sees either no tile or a
complete one).

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
from functools import cache
from pathlib import Path

import numpy as np

from calib.core import frames
from calib.io.laz import PASS_ID_DIMENSION, LasOutputError, OutputCrs, las_source_id

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
    bytes ``pass_id``, ``sigma_h_m``, ``sigma_v_m``)."""
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


@cache
def record_dtype() -> np.dtype:
    """The dtype of one point record of a tile (point format 6 and its extra bytes)."""
    from calib.io.laz import SCALE_M

    crs = OutputCrs("LGF", "", (SCALE_M,) * 3, (0.0, 0.0, 0.0), frames.LocalFrame(0.0, 0.0), None)
    return tile_header(crs, 0, "", {}, _survey_date(1e9)).point_format.dtype()


def _pass_ids(pass_id: np.ndarray) -> np.ndarray:
    """The sorted distinct pass ids of a part (one line's part: no sort)."""
    if pass_id.min() == pass_id.max():
        return np.asarray(pass_id[:1])
    return np.unique(pass_id)


class _Tally:
    """What a tile holds, counted part by part as it is written. The bounds and the time span are those laspy's writer keeps in the header while it writes
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


def write_tile(
    path: str | Path,
    parts: Iterable[np.ndarray],
    crs: OutputCrs,
    software: str,
    provenance: dict,
    first_t_gps_s: float,
) -> TileSummary:
    """Write the tile ``path`` (``.laz`` compressed, ``.las`` not) from ``parts`` (arrays of
    :func:`record_dtype`, in the order they are to appear: the records go to the compressor as
    they are) and return its summary. The file appears only complete (module docstring);
    ``first_t_gps_s`` (the survey's first point) dates the header."""
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
                header = tile_header(crs, source_id, software, provenance, _survey_date(first_t_gps_s))
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


def read_provenance(path: str | Path) -> dict:
    """The provenance VLR of a tile (what :func:`write_tile` stored)."""
    import laspy

    with laspy.open(path) as f:
        for vlr in f.header.vlrs:
            if vlr.user_id == PROVENANCE_USER_ID and vlr.record_id == PROVENANCE_RECORD_ID:
                return json.loads(bytes(vlr.record_data).decode("utf-8"))
    raise LasOutputError(f"{path}: no marine-mls provenance VLR")
