"""Survey tiles: LAS 1.4 / LAZ (point format 6) with per-point uncertainty and provenance.

What ``mls georef`` writes for each tile (a line, or a square of the projected CRS). The points
arrive in parts (:mod:`calib.io.tileparts`: the file's own point records — coordinates already on
the output CRS's LAS grid, :mod:`office.deliver.lasrecords` encodes them — compressed into LAZ
chunks by the chunk that found them, or raw for a ``.las``), and
:func:`calib.io.tileparts.write_tile` joins them under the tile's header (:func:`tile_header`)
without decoding them. A tile is written whole or not at all:
``<name>.laz.partial`` first, renamed when the last point is in (the rename is atomic: a reader,
or a resumed job, sees either no tile or a complete one).

Every tile carries, beside what :class:`calib.io.laz.LasPassWriter` writes (CRS as WKT, adjusted
standard GPS time, intensity, scan angle, the pass id in ``point_source_id`` and as the int64
extra-bytes dimension ``pass_id``):

- the extra-bytes dimensions ``sigma_h_m`` and ``sigma_v_m`` (float32): the point's horizontal
  (radial, 1σ) and vertical standard deviation from the trajectory, the scanner and the mount
  covariance of the calibration (:mod:`calib.core.tpu`);
- a provenance VLR (user id :data:`PROVENANCE_USER_ID`, record id :data:`PROVENANCE_RECORD_ID`):
  UTF-8 JSON with the mount id, the calibration's fingerprint and boresight, the software
  version and the source of the trajectory;
- LAZ with variable-size chunks of at most 50,000 points (a part's points end its last chunk),
  each compressed on one thread (lazrs, not its parallel variant): a task of ``mls georef``
  uses one core, so N workers use N;
- a creation date that is the survey's (the first point's GPS day), not the day the file was
  written, so that the same inputs give the same bytes on any machine and any day.
"""

from __future__ import annotations

import datetime as _dt
import json
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np

from calib.core import frames
from calib.io.laz import PASS_ID_DIMENSION, LasOutputError, OutputCrs

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


def survey_date(t_gps_s: float) -> _dt.date:
    return _GPS_EPOCH + _dt.timedelta(days=int(t_gps_s // 86400))


def quantiles(v: np.ndarray) -> dict[str, float]:
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
    return tile_header(crs, 0, "", {}, survey_date(1e9)).point_format.dtype()


def read_provenance(path: str | Path) -> dict:
    """The provenance VLR of a tile (what :func:`calib.io.tileparts.write_tile` stored)."""
    import laspy

    with laspy.open(path) as f:
        for vlr in f.header.vlrs:
            if vlr.user_id == PROVENANCE_USER_ID and vlr.record_id == PROVENANCE_RECORD_ID:
                return json.loads(bytes(vlr.record_data).decode("utf-8"))
    raise LasOutputError(f"{path}: no marine-mls provenance VLR")
