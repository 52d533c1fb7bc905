"""LAS 1.4 / LAZ output of georeferenced points (point format 6), written in chunks.

Every file carries: coordinates in a chosen CRS, adjusted standard GPS time (GPS seconds − 1e9,
global-encoding bit 0 set), intensity (u16), return 1 of 1, the scan angle (see
:class:`LasPassWriter`), the CRS as an OGC WKT VLR (global-encoding WKT bit set), and the pass
id twice:

- the extra-bytes dimension ``pass_id`` (int64): always the real id (survey line ids such as
  20240709001 do not fit LAS's own fields);
- ``point_source_id`` and the header's file source ID (u16): the pass id when it is 0 … 65535,
  else 0 (LAS's "not assigned"; :func:`las_source_id`). The file name ``pass-<id>.laz`` carries
  the real id as well.

CRS choices (:func:`output_crs`):

- ``utm`` (default): the WGS84 UTM zone of the LGF reference point; z is the WGS84 ellipsoidal
  height (the WKT is the 2D projected CRS; WKT1 cannot name an ellipsoidal vertical axis).
- ``lgf``: the local geodetic frame as a local engineering CRS with x = east, y = north,
  z = up (ENU, not the NED used inside the project) so that viewers show the cloud upright;
  the CRS name gives the reference point.
- any CRS pyproj understands (``EPSG:2950``, ``EPSG:4979``…); a 2D CRS gets the ellipsoidal
  height as z. A CRS whose vertical datum needs a geoid grid that is not installed is refused.
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from calib.core import frames
from calib.core.errors import CalibError

if TYPE_CHECKING:
    from pyproj import Transformer

#: Coordinate resolution: 0.1 mm in metres, ~0.1 mm in degrees of latitude.
SCALE_M = 1e-4
SCALE_DEG = 1e-9
#: LAS scan angle unit (point formats 6–10).
SCAN_ANGLE_UNIT_DEG = 0.006
#: The extra-bytes dimension holding the real pass id (int64).
PASS_ID_DIMENSION = "pass_id"
_U16_MAX = 65535


def las_source_id(pass_id: int) -> int:
    """The pass id in LAS's u16 source-id fields: itself when it fits, else 0 ("not assigned"; the
    real id is in the ``pass_id`` extra-bytes dimension)."""
    return int(pass_id) if 0 <= int(pass_id) <= _U16_MAX else 0


class LasOutputError(CalibError, ValueError):
    """The output CRS or the points cannot be written as asked (the message says why)."""


@dataclass(frozen=True)
class OutputCrs:
    """Where LGF points go in the LAS file: a name, the WKT, the per-axis scales and offsets,
    and the transform itself (:meth:`from_lgf`)."""

    name: str
    wkt: str
    scales: tuple[float, float, float]
    offsets: tuple[float, float, float]
    frame: frames.LocalFrame
    transformer: Transformer | None  # pyproj Transformer from ECEF, None for the LGF itself

    def from_lgf(self, p_lgf_m: np.ndarray) -> np.ndarray:
        """(n, 3) LGF NED metres → (n, 3) x, y, z in this CRS."""
        p = np.asarray(p_lgf_m, dtype=float)
        if self.transformer is None:
            return np.stack([p[:, 1], p[:, 0], -p[:, 2]], axis=1)  # NED → ENU
        ecef = p @ self.frame.r_ecef_to_ned + self.frame.origin_ecef_m
        x, y, z = self.transformer.transform(ecef[:, 0], ecef[:, 1], ecef[:, 2])
        xyz = np.stack([np.asarray(x), np.asarray(y), np.asarray(z)], axis=1)
        if not np.all(np.isfinite(xyz)):
            raise LasOutputError(
                f"{self.name}: pyproj returned non-finite coordinates (is a transformation grid missing?)"
            )
        return xyz


def output_crs(spec: str | None, frame: frames.LocalFrame) -> OutputCrs:
    """The output CRS for ``spec`` (None or ``utm``, ``lgf``, or a pyproj CRS string)."""
    from pyproj import CRS, Transformer
    from pyproj.exceptions import CRSError, ProjError

    key = (spec or "utm").strip()
    if key.lower() == "lgf":
        name = (
            f"marine-mls LGF (x east, y north, z up) at lat {frame.lat_deg:.9f}, "
            f"lon {frame.lon_deg:.9f}, h {frame.height_m:.3f} m WGS84"
        )
        axes = ",".join(
            f'AXIS["{a} ({c})",{d},ORDER[{i + 1}],LENGTHUNIT["metre",1]]'
            for i, (a, c, d) in enumerate(
                [("easting", "E", "east"), ("northing", "N", "north"), ("up", "U", "up")]
            )
        )
        crs = CRS.from_wkt(f'ENGCRS["{name}",EDATUM["{name}"],CS[Cartesian,3],{axes}]')
        return OutputCrs("LGF", _wkt1(crs), (SCALE_M,) * 3, (0.0, 0.0, 0.0), frame, None)
    try:
        crs = (
            CRS.from_epsg(frames.utm_epsg(frame.lat_deg, frame.lon_deg))
            if key.lower() == "utm"
            else CRS.from_user_input(key)
        )
    except CRSError as e:
        raise LasOutputError(f"CRS {spec!r}: not a CRS pyproj knows ({e})") from None
    target = crs if len(crs.axis_info) == 3 else crs.to_3d()
    try:
        transformer = Transformer.from_crs("EPSG:4978", target, always_xy=True, only_best=True)
    except ProjError as e:
        raise LasOutputError(f"CRS {spec!r}: no usable transformation from WGS84 ({e})") from None
    degrees = crs.is_geographic
    scales = (SCALE_DEG, SCALE_DEG, SCALE_M) if degrees else (SCALE_M,) * 3
    out = OutputCrs(crs.to_string(), _wkt1(crs), scales, (0.0, 0.0, 0.0), frame, transformer)
    origin = out.from_lgf(np.zeros((1, 3)))[0]  # (PROJ settles the operation on first use)
    if "ballpark vertical" in transformer.description.lower():
        raise LasOutputError(
            f"CRS {spec!r}: its heights need a geoid model that PROJ does not "
            f"have here ({transformer.description}); use a CRS with "
            f"ellipsoidal heights or install the grid"
        )
    steps = np.array([1.0, 1.0, 1000.0] if degrees else [1000.0] * 3)
    ox, oy, oz = (float(v) + 0.0 for v in np.round(origin / steps) * steps)  # no −0.0
    offsets = (ox, oy, oz)
    return OutputCrs(out.name, out.wkt, scales, offsets, frame, transformer)


def _wkt1(crs) -> str:
    """OGC WKT1 (what LAS 1.4 readers expect), or WKT2 when the CRS has no WKT1 form."""
    from pyproj.exceptions import CRSError

    try:
        return crs.to_wkt("WKT1_GDAL")
    except CRSError:
        return crs.to_wkt("WKT2_2019")


class LasPassWriter:
    """Write one pass into one LAS/LAZ file, chunk by chunk (memory stays bounded)::

        with LasPassWriter(path, crs, pass_id, software="mls 0.1") as w:
            for chunk in ...:
                w.write(p_lgf_m, t_gps_s, intensity_u16, scan_angle_rad)

    The LAS scan angle is the scanner's own angle measured from its nadir (α = 90°), positive
    counter-clockwise seen from behind (toward decreasing α), in (−180°, 180°]: exact for a
    scanner mounted with the identity nominal rotation, indicative otherwise.
    """

    def __init__(self, path: str | Path, crs: OutputCrs, pass_id: int, software: str):
        import laspy
        from laspy.vlrs.known import WktCoordinateSystemVlr

        if not 0 <= int(pass_id) < 2**63:
            raise LasOutputError(f"pass id {pass_id}: expected a non-negative 64-bit integer")
        self.path = Path(path)
        self.crs = crs
        self.pass_id = int(pass_id)
        self.source_id = las_source_id(self.pass_id)
        header = laspy.LasHeader(point_format=6, version="1.4")
        header.scales = np.array(crs.scales)
        header.offsets = np.array(crs.offsets)
        header.file_source_id = self.source_id
        header.system_identifier = "marine-mls MLS (Z+F + Hydrins)"[:32]
        header.generating_software = software[:32]
        header.creation_date = _dt.date.today()
        header.global_encoding.gps_time_type = laspy.header.GpsTimeType.STANDARD
        header.global_encoding.wkt = True
        header.vlrs.append(WktCoordinateSystemVlr(crs.wkt))
        header.add_extra_dim(  # after the WKT: the CRS stays the first VLR
            laspy.ExtraBytesParams(
                name=PASS_ID_DIMENSION, type=np.int64, description="pass id (point_source_id: u16)"
            )
        )
        self._header = header
        self._laspy = laspy
        self._writer = laspy.open(
            self.path, mode="w", header=header, do_compress=self.path.suffix.lower() == ".laz"
        )
        self.n_points = 0

    def write(self, p_lgf_m, t_gps_s, intensity_u16, scan_angle_rad) -> None:
        xyz = self.crs.from_lgf(p_lgf_m)
        n = xyz.shape[0]
        rec = self._laspy.ScaleAwarePointRecord.zeros(n, header=self._header)
        try:
            rec.x, rec.y, rec.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        except OverflowError:
            raise LasOutputError(
                f"{self.path}: coordinates {xyz.min(axis=0)} … {xyz.max(axis=0)} do not fit the "
                f"LAS integer range around offsets {self.crs.offsets} at scales {self.crs.scales}"
            ) from None
        rec.gps_time = frames.gps_seconds_to_las(t_gps_s)
        rec.intensity = np.asarray(intensity_u16, dtype=np.uint16)
        rec.return_number = np.ones(n, np.uint8)
        rec.number_of_returns = np.ones(n, np.uint8)
        rec.point_source_id = np.full(n, self.source_id, np.uint16)
        rec[PASS_ID_DIMENSION] = np.full(n, self.pass_id, np.int64)
        nadir_deg = np.degrees(frames.wrap_pi(np.pi / 2 - np.asarray(scan_angle_rad, float)))
        rec.scan_angle = np.round(nadir_deg / SCAN_ANGLE_UNIT_DEG).astype(np.int16)
        self._writer.write_points(rec)
        self.n_points += n

    def close(self) -> None:
        self._writer.close()

    def __enter__(self) -> LasPassWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
