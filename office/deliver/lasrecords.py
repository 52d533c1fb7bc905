"""Chunk points as the tile file's own LAS records (:func:`calib.io.lastile.record_dtype`: LAS 1.4
point format 6 with the extra bytes ``pass_id``, ``sigma_h_m``, ``sigma_v_m``): a chunk encodes
its points straight into them, and :func:`calib.io.tileparts.make_part` hands them to the LAZ
compressor as they are. The GPS time of a record, adjusted standard time, gives back the point's
GPS seconds exactly (t − 10⁹ is exact for t within [5·10⁸, 2·10⁹] s, i.e. 1995–2043).
"""

from __future__ import annotations

import numpy as np

from calib.io.laz import SCAN_ANGLE_UNIT_DEG, LasOutputError, OutputCrs, las_source_id

#: the bit fields of return 1 of 1 (return number in bits 0–3, number of returns in 4–7)
FIRST_OF_ONE = 0x11
_I32 = (-(2**31), 2**31 - 1)


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


def source_ids(pass_id: np.ndarray) -> np.ndarray:
    """LAS's u16 point source id of each pass id (:func:`calib.io.laz.las_source_id`)."""
    if pass_id.size and pass_id.min() == pass_id.max():  # one line: no sort
        return np.full(pass_id.size, las_source_id(int(pass_id[0])), np.uint16)
    ids, inv = np.unique(pass_id, return_inverse=True)
    return np.array([las_source_id(int(i)) for i in ids], np.uint16)[inv.reshape(-1)]
