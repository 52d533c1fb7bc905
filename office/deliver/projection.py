"""LGF → output CRS for one chunk: a local cubic model fitted to pyproj, exact to ≤ 0.01 mm.

pyproj transforms a point in about 0.35 µs (LGF → ECEF → the CRS, per point); a chunk's points
span at most a few kilometres, over which the projection is a smooth function of the LGF
coordinates. :func:`chunk_projection` fits, per chunk, a full cubic polynomial in the LGF
north, east and down offsets from the chunk's centre (20 terms per axis) to pyproj at
:data:`FIT_NODES`³ nodes spanning the chunk's bounding box, and checks it against pyproj at
:data:`CHECK_NODES`³ other points of the box (corners, edges, centre). The model is used only
when it agrees with pyproj to :data:`TOLERANCE_M` (0.01 mm; in degrees, that length on the
meridian) everywhere it was checked; otherwise the chunk is projected by pyproj per point.

The residual of a cubic over a box of half-size L is of the order L⁴/R³ (R the Earth's
radius): 10⁻⁹ m at L = 300 m, 2·10⁻⁶ m at 5 km, also at the edge of a UTM zone. The stored
coordinates (0.1 mm LAS units) are therefore those pyproj gives, except for a point whose
coordinate falls within 0.01 mm of the middle between two LAS units: it may be stored one unit
(0.1 mm) away. ``tests/office/deliver/test_georef_projection.py`` checks the model against
pyproj on random chunks, at the zone's centre and far from its central meridian.
The LGF output CRS (no transformer) is an exact axis swap and needs no model.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import product

import numpy as np

from calib.io.laz import OutputCrs

#: the model's agreement with pyproj required for it to be used (metres)
TOLERANCE_M = 1e-5
#: metres of one degree on the meridian (converts the tolerance of a geographic CRS)
METRES_PER_DEGREE = 111_320.0
FIT_NODES = 5
CHECK_NODES = 4
#: exponents (i, j, k) of the cubic's monomials u^i v^j w^k, i + j + k ≤ 3
EXPONENTS = tuple((i, j, k) for i, j, k in product(range(4), repeat=3) if i + j + k <= 3)
BLOCK = 1 << 13


@dataclass(frozen=True)
class LocalModel:
    """x, y, z in the CRS = ``origin`` + Σ coef · u^i v^j w^k, with (u, v, w) = (p − centre) / half."""

    centre_m: np.ndarray  # (3,) LGF NED
    half_m: np.ndarray  # (3,) the box's half-size per axis (≥ 1 m)
    origin: np.ndarray  # (3,) the CRS coordinates of the centre
    coef: np.ndarray  # (20, 3)

    def features(self, p_lgf_m: np.ndarray) -> np.ndarray:
        """(20, n) monomials of the normalized offsets of ``p_lgf_m`` (n, 3)."""
        p = np.asarray(p_lgf_m, float)
        n = p.shape[0]
        f = np.empty((len(EXPONENTS), n))
        pows = np.empty((3, 4, n))  # u^0 … u^3, v^…, w^… (rows contiguous)
        for j in range(3):
            row = pows[j]
            row[0] = 1.0
            np.subtract(p[:, j], self.centre_m[j], out=row[1])
            row[1] *= 1.0 / self.half_m[j]
            np.multiply(row[1], row[1], out=row[2])
            np.multiply(row[2], row[1], out=row[3])
        for c, (i, j, k) in enumerate(EXPONENTS):
            factors = [pows[a][e] for a, e in enumerate((i, j, k)) if e]
            if not factors:
                f[c] = 1.0
            elif len(factors) == 1:
                f[c] = factors[0]
            else:
                np.multiply(factors[0], factors[1], out=f[c])
                if len(factors) == 3:
                    f[c] *= factors[2]
        return f

    def offsets(self, p_lgf_m: np.ndarray) -> np.ndarray:
        """(n, 3) CRS coordinates of ``p_lgf_m`` minus :attr:`origin`."""
        return (self.coef.T @ self.features(p_lgf_m)).T


def _grid(lo: np.ndarray, hi: np.ndarray, n: int) -> np.ndarray:
    """n³ points of the box [lo, hi]: Chebyshev–Lobatto nodes per axis (ends included)."""
    s = 0.5 - 0.5 * np.cos(np.pi * np.arange(n) / (n - 1))
    axes = [lo[j] + (hi[j] - lo[j]) * s for j in range(3)]
    return np.array(list(product(*axes)), float)


def fit_model(crs: OutputCrs, lo_m: np.ndarray, hi_m: np.ndarray) -> tuple[LocalModel, np.ndarray]:
    """The cubic model of ``crs.from_lgf`` over the LGF box [lo_m, hi_m], and its largest
    disagreement with pyproj at the check points, per axis (in the CRS's units)."""
    lo_m, hi_m = np.asarray(lo_m, float), np.asarray(hi_m, float)
    centre = 0.5 * (lo_m + hi_m)
    half = np.maximum(0.5 * (hi_m - lo_m), 1.0)
    lo, hi = centre - half, centre + half
    origin = crs.from_lgf(centre[None, :])[0]
    nodes = _grid(lo, hi, FIT_NODES)
    model = LocalModel(centre, half, origin, np.zeros((len(EXPONENTS), 3)))
    coef, *_ = np.linalg.lstsq(model.features(nodes).T, crs.from_lgf(nodes) - origin, rcond=None)
    model = LocalModel(centre, half, origin, coef)
    check = _grid(lo, hi, CHECK_NODES) + 0.37 * (hi - lo) / (CHECK_NODES * 7.0)
    check = np.clip(np.concatenate([check, _grid(lo, hi, 2), centre[None, :]]), lo, hi)
    err = np.abs(model.offsets(check) + origin - crs.from_lgf(check)).max(axis=0)
    return model, err


def is_geographic(crs: OutputCrs) -> bool:
    """The CRS's horizontal axes are in degrees (:data:`calib.io.laz.SCALE_DEG`)."""
    return crs.scales[0] < 1e-6


def tolerance(crs: OutputCrs) -> np.ndarray:
    """:data:`TOLERANCE_M` in the units of the CRS's three axes (degrees for the horizontal
    axes of a geographic CRS, the length on the meridian: stricter in longitude)."""
    horizontal = TOLERANCE_M / METRES_PER_DEGREE if is_geographic(crs) else TOLERANCE_M
    return np.array([horizontal, horizontal, TOLERANCE_M])


def project_on_grid(crs: OutputCrs, p_lgf_m: np.ndarray) -> np.ndarray:
    """(3, n) float64 LAS integers ``round((xyz − offset) / scale)`` of the chunk's LGF points
    ``p_lgf_m`` (n, 3; column-major is fastest) in ``crs``: the local model (module docstring)
    when it is exact enough over their box, else pyproj per point; the LGF itself by its axes."""
    p = np.asarray(p_lgf_m, float)
    n = p.shape[0]
    scale, offset = np.asarray(crs.scales)[:, None], np.asarray(crs.offsets)[:, None]
    out = np.empty((3, n))
    model = None
    # a geographic CRS's LAS unit (10⁻⁹°, 0.11 mm in latitude) is coarser than 0.1 mm: pyproj's
    # own values there, so that its coordinates are exactly pyproj's
    if crs.transformer is not None and n and not is_geographic(crs):
        model, err = fit_model(crs, p.min(axis=0), p.max(axis=0))
        if np.any(err > tolerance(crs)):
            model = None
    for lo in range(0, n, BLOCK):
        b = slice(lo, lo + BLOCK)
        if model is not None:
            xyz = model.coef.T @ model.features(p[b])
            xyz += (model.origin - np.asarray(crs.offsets))[:, None]
        else:
            xyz = crs.from_lgf(p[b]).T - offset
        xyz /= scale
        np.round(xyz, out=out[:, b])
    return out
