"""Cloud-to-cloud distances with a local least-squares plane model (CloudCompare's C2C).

For every point q of the *compared* cloud:

1. find its nearest point p in the *reference* cloud (distance ``d_nn = |q − p|``);
2. take the k nearest neighbours **of p** in the reference cloud (p itself is one of them, at
   distance 0), or all reference points when the cloud has fewer than k;
3. fit a least-squares plane to them (centroid and the eigenvector of the smallest eigenvalue of
   their covariance);
4. the distance is ``min(d_nn, |n·(q − centroid)|)``; when no plane can be fitted (fewer than 3
   neighbours, all neighbours at one place, or collinear neighbours) it is ``d_nn``.

This is what CloudCompare computes for ``-C2C_DIST -MODEL LS KNN k`` (CCCoreLib
``DistanceComputationTools::computeCellHausdorffDistanceWithLocalModel``, ``LocalModel`` and
``Neighbourhood::computeLeastSquareBestFittingPlane``). The facts relied on:

- the local model is built around the *nearest reference point*, not around the compared point,
  from its k nearest neighbours in the reference cloud, the nearest point included (a kNN search
  centred on a cloud point returns that point first);
- with fewer than k reference points, all of them are used; with fewer than 3
  (``CC_LOCAL_MODEL_MIN_SIZE[LS] = 3``) no model is built and the plain nearest-neighbour
  distance is reported; likewise when all neighbours coincide (CloudCompare tests that the
  farthest neighbour is at a distance > 0);
- the model distance is unsigned (``LSLocalModel::computeDistanceFromModelToPoint`` returns
  ``|n·q + d|``), and the reported value is the smaller of the model distance and the
  nearest-neighbour distance ("we take the best estimation between the nearest neighbor and the
  model");
- with a maximum search distance, a point whose nearest reference point is farther away gets
  the maximum distance itself as its value (not "no value").

Where this module differs, on purpose:

- **Collinear neighbourhoods** (the fallback): CloudCompare detects them only for exactly three
  points (their cross product vanishes); with more than three collinear points its eigen solver
  returns *some* normal perpendicular to the line, so its value is an arbitrary number between 0
  and ``d_nn``. Here a neighbourhood whose width is below ``collinear_tol`` times its length
  (``sqrt(λ2/λ1) < collinear_tol``, default 1e-5) has no model and the point gets ``d_nn``,
  deterministically — an upper bound of what CloudCompare can report there. Raise
  ``collinear_tol`` (e.g. 0.05) when the reference is made of single scan lines.
- CloudCompare's optional "use the same model for nearby points" speed-up is not implemented
  (one model per nearest reference point: CloudCompare with that option off, the default of
  its dialog and of its command line, which cannot turn it on).
- CloudCompare works in single precision relative to a global shift; this module in double
  precision, so the two agree to CloudCompare's float rounding (≈ 1e-7 of the coordinates'
  span after its shift).

**Signed distances** (not offered by CloudCompare's C2C): the local normal is oriented toward a
given direction (e.g. the facing normal of a validation plane) or toward a given point (e.g. the
scanner position: positive = in front of the reference surface as seen from there); the sign is
that of ``n·(q − centroid)``, the magnitude the unsigned C2C value. Points without a model take
the sign of ``(q − p)·v``. Where the local normal is nearly perpendicular to the orientation
(``|n·v̂| < 0.1``) the sign is unreliable; those points are counted in ``n_ambiguous_sign``.

The computation is vectorized: both clouds are put in the order of a KD-tree's leaves (so that
neighbouring queries touch neighbouring memory), compared points are processed in blocks, one
model per distinct nearest reference point of the block, the plane of every model from a
closed-form 3×3 symmetric eigen solution (see :func:`smallest_eigenvector`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from calib.core.errors import CalibError

#: A least-squares plane needs at least this many points (CloudCompare's CC_LOCAL_MODEL_MIN_SIZE).
MIN_MODEL_POINTS = 3
#: |n·v̂| below this: the orientation of a local normal is ambiguous for signed distances.
AMBIGUOUS_SIGN_COS = 0.1
DEFAULT_CHUNK = 1 << 17


class C2CError(CalibError, ValueError):
    """Bad input to a cloud-to-cloud computation (the message names the cloud and the problem)."""


@dataclass(frozen=True)
class DistanceStats:
    """Statistics of a set of distances (NaNs ignored). ``std_m`` is the population standard
    deviation about the mean; ``p95_m`` and ``max_m`` are of the absolute values, so they read
    "95 % of the points are within" for signed distances too."""

    count: int
    mean_m: float
    median_m: float
    rms_m: float
    std_m: float
    p95_m: float
    max_m: float

    def as_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def distance_stats(d_m) -> DistanceStats:
    d = np.asarray(d_m, dtype=float).ravel()
    d = d[np.isfinite(d)]
    if d.size == 0:
        nan = float("nan")
        return DistanceStats(0, nan, nan, nan, nan, nan, nan)
    a = np.abs(d)
    return DistanceStats(
        count=int(d.size),
        mean_m=float(d.mean()),
        median_m=float(np.median(d)),
        rms_m=float(np.sqrt(np.mean(d * d))),
        std_m=float(d.std()),
        p95_m=float(np.percentile(a, 95.0)),
        max_m=float(a.max()),
    )


@dataclass(frozen=True)
class C2CResult:
    """Per compared point (in the compared cloud's order)."""

    distance_m: np.ndarray  # CloudCompare's C2C value (unsigned); = max_distance_m beyond it
    nn_distance_m: np.ndarray  # plain nearest-neighbour distance; inf beyond max_distance_m
    nearest_index: np.ndarray  # index of the nearest reference point; −1 beyond max_distance_m
    normal: np.ndarray  # (n, 3) local plane normal (oriented when signed); NaN without a model
    has_model: np.ndarray  # False where the nearest-neighbour fallback was used
    within_max: np.ndarray  # False where the nearest reference point is beyond max_distance_m
    signed_distance_m: np.ndarray | None  # when an orientation was given
    k: int
    max_distance_m: float | None
    n_ambiguous_sign: int = 0

    def __len__(self) -> int:
        return self.distance_m.shape[0]

    @property
    def n_fallback(self) -> int:
        """Points (within the maximum distance) that got the nearest-neighbour distance because
        no plane could be fitted."""
        return int(np.count_nonzero(self.within_max & ~self.has_model))

    def signed(self) -> np.ndarray:
        """The signed distances (:class:`C2CError` when no orientation was given)."""
        if self.signed_distance_m is None:
            raise C2CError("no signed distances: give orient_direction or orient_toward_m")
        return self.signed_distance_m

    def stats(self, signed: bool = False) -> DistanceStats:
        """Statistics over the points within the maximum distance."""
        d = self.signed() if signed else self.distance_m
        return distance_stats(d[self.within_max])

    def nn_stats(self) -> DistanceStats:
        """Statistics of the plain nearest-neighbour distances (the biased comparison)."""
        return distance_stats(self.nn_distance_m[self.within_max])

    def extra_dimensions(self) -> dict[str, np.ndarray]:
        """The per-point values written with the compared cloud (``extra`` of
        :func:`calib.io.cloudio.write_cloud`): ``c2c_distance_m``, and ``c2c_signed_distance_m``
        when the distances are signed."""
        extra = {"c2c_distance_m": self.distance_m}
        if self.signed_distance_m is not None:
            extra["c2c_signed_distance_m"] = self.signed_distance_m
        return extra


# -- local planes ---------------------------------------------------------------------------


#: Below this eigenvalue separation (λ2 − λ3)/λ1 the closed form is not accurate enough and
#: LAPACK's eigh is used for those rows (rare: nearly collinear neighbourhoods).
_EIGH_BELOW_SEPARATION = 1e-5


def smallest_eigenvector(xx, yy, zz, xy, xz, yz) -> np.ndarray:
    """Unit eigenvectors (n, 3) for the smallest eigenvalue of symmetric 3×3 matrices given by
    their six distinct entries.

    Closed form (trigonometric eigenvalue, then the largest cross product of two rows of
    A − λI), refined by one inverse-iteration step with the Rayleigh quotient as shift (the
    closed form alone loses accuracy as ε/sep² when the spectrum is flat; after the step the
    error is ≈ ε/sep like LAPACK's). Rows whose separation (λ2 − λ3)/λ1 is below 1e-5 go to
    ``numpy.linalg.eigh``. Where the smallest eigenvalue is repeated the vector is arbitrary —
    callers detect that case.
    """
    scale = np.maximum.reduce([np.abs(xx), np.abs(yy), np.abs(zz), np.abs(xy), np.abs(xz), np.abs(yz)])
    scale = np.where(scale > 0, scale, 1.0)
    a, b, c = xx / scale, yy / scale, zz / scale
    d, e, f = xy / scale, xz / scale, yz / scale
    q = (a + b + c) / 3.0
    a0, b0, c0 = a - q, b - q, c - q
    p = np.sqrt((a0 * a0 + b0 * b0 + c0 * c0 + 2.0 * (d * d + e * e + f * f)) / 6.0)
    pp = np.where(p > 0, p, 1.0)
    det = a0 * (b0 * c0 - f * f) - d * (d * c0 - f * e) + e * (d * f - b0 * e)
    phi = np.arccos(np.clip(det / (2.0 * pp**3), -1.0, 1.0)) / 3.0
    lam_min = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    lam_max = q + 2.0 * p * np.cos(phi)
    x, y, z = _null_vector(a, b, c, d, e, f, lam_min)
    norm = np.sqrt(x * x + y * y + z * z)
    inv = 1.0 / np.where(norm > 0, norm, 1.0)
    x, y, z = x * inv, y * inv, z * inv
    # one inverse-iteration step: v ← adj(A − ρI)·v with ρ the Rayleigh quotient of v
    rho = a * x * x + b * y * y + c * z * z + 2.0 * (d * x * y + e * x * z + f * y * z)
    a1, b1, c1 = a - rho, b - rho, c - rho
    x, y, z = (
        (b1 * c1 - f * f) * x + (e * f - d * c1) * y + (d * f - b1 * e) * z,
        (e * f - d * c1) * x + (a1 * c1 - e * e) * y + (d * e - a1 * f) * z,
        (d * f - b1 * e) * x + (d * e - a1 * f) * y + (a1 * b1 - d * d) * z,
    )
    norm = np.sqrt(x * x + y * y + z * z)
    inv = 1.0 / np.where(norm > 0, norm, 1.0)
    out = np.stack([x * inv, y * inv, z * inv], axis=-1)
    lam_mid = 3.0 * q - lam_min - lam_max
    hard = np.flatnonzero(lam_mid - lam_min < _EIGH_BELOW_SEPARATION * np.maximum(lam_max, 0.0))
    if hard.size:
        A = np.empty((hard.size, 3, 3))
        A[:, 0, 0], A[:, 1, 1], A[:, 2, 2] = a[hard], b[hard], c[hard]
        A[:, 0, 1] = A[:, 1, 0] = d[hard]
        A[:, 0, 2] = A[:, 2, 0] = e[hard]
        A[:, 1, 2] = A[:, 2, 1] = f[hard]
        out[hard] = np.linalg.eigh(A)[1][:, :, 0]
    return out


def _null_vector(a, b, c, d, e, f, lam):
    """The largest of the cross products of two rows of A − λI (not normalised)."""
    a1, b1, c1 = a - lam, b - lam, c - lam
    # rows r0 = (a1, d, e), r1 = (d, b1, f), r2 = (e, f, c1)
    cands = (
        (d * f - e * b1, e * d - a1 * f, a1 * b1 - d * d),  # r0 × r1
        (d * c1 - e * f, e * e - a1 * c1, a1 * f - d * e),  # r0 × r2
        (b1 * c1 - f * f, f * e - d * c1, d * f - b1 * e),  # r1 × r2
    )
    x, y, z = cands[0]
    best = x * x + y * y + z * z
    for cx, cy, cz in cands[1:]:
        nn = cx * cx + cy * cy + cz * cz
        use = nn > best
        x, y, z, best = np.where(use, cx, x), np.where(use, cy, y), np.where(use, cz, z), np.maximum(nn, best)
    return x, y, z


def _local_planes(ref_cols, anchor, neighbours, collinear_tol):
    """Planes of the neighbourhoods ``neighbours`` (m, k) (indices into the reference columns),
    expressed relative to the anchor points ``anchor`` (m,) (each neighbourhood's nearest point).

    Returns (centroid relative to the anchor (m, 3), unit normal (m, 3), ok (m,) bool)."""
    rel = []
    for col in ref_cols:
        r = col[neighbours]
        r -= col[anchor][:, None]  # identical points give exact zeros
        rel.append(r)
    cent = np.stack([r.mean(axis=1) for r in rel], axis=-1)
    for j, r in enumerate(rel):
        r -= cent[:, j, None]
    X, Y, Z = rel
    xx = np.einsum("ij,ij->i", X, X)
    yy = np.einsum("ij,ij->i", Y, Y)
    zz = np.einsum("ij,ij->i", Z, Z)
    xy = np.einsum("ij,ij->i", X, Y)
    xz = np.einsum("ij,ij->i", X, Z)
    yz = np.einsum("ij,ij->i", Y, Z)
    tr = xx + yy + zz
    # λ1λ2 + λ1λ3 + λ2λ3 ≈ λ1·λ2 for a flat neighbourhood; ≈ 0 for a line
    s2 = 0.5 * (tr * tr - (xx * xx + yy * yy + zz * zz + 2.0 * (xy * xy + xz * xz + yz * yz)))
    ok = (tr > 0) & (s2 > (collinear_tol * tr) ** 2)
    return cent, smallest_eigenvector(xx, yy, zz, xy, xz, yz), ok


# -- the distance ---------------------------------------------------------------------------


def _as_cloud(p, what: str) -> np.ndarray:
    a = np.asarray(p, dtype=float)
    if a.ndim != 2 or a.shape[1] != 3:
        raise C2CError(f"{what} cloud: expected an (n, 3) array of coordinates, got shape {a.shape}")
    if a.shape[0] == 0:
        raise C2CError(f"{what} cloud is empty")
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise C2CError(f"{what} cloud: point {i} has a non-finite coordinate {a[i].tolist()}")
    return a


def _orientation_vector(orient_direction, orient_toward_m):
    if orient_direction is not None and orient_toward_m is not None:
        raise C2CError("give orient_direction or orient_toward_m, not both")
    v = orient_direction if orient_direction is not None else orient_toward_m
    if v is None:
        return None
    v = np.asarray(v, dtype=float).reshape(-1)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise C2CError(f"orientation must be 3 finite numbers, got {v.tolist()}")
    if orient_direction is not None:
        norm = np.linalg.norm(v)
        if norm == 0:
            raise C2CError("orient_direction is the zero vector")
        v = v / norm
    return v


def _checked_k(k, max_distance_m, collinear_tol) -> int:
    """``k`` as an int, once the arguments are checked (:class:`C2CError` with what to give)."""
    if int(k) != k or k < MIN_MODEL_POINTS:
        raise C2CError(f"k = {k!r}: a least-squares plane needs k ≥ {MIN_MODEL_POINTS} neighbours")
    if max_distance_m is not None and not (np.isfinite(max_distance_m) and max_distance_m > 0):
        raise C2CError(f"max_distance_m = {max_distance_m!r}: expected a positive distance")
    if not (0 <= collinear_tol < 1):
        raise C2CError(f"collinear_tol = {collinear_tol!r}: expected 0 ≤ tol < 1")
    return int(k)


def _leaf_order(p: np.ndarray) -> np.ndarray:
    """The points' order in a KD-tree's leaves: neighbouring queries then touch neighbouring
    memory."""
    from scipy.spatial import cKDTree

    return cKDTree(p, leafsize=64, balanced_tree=False, compact_nodes=False).indices


class _Reference:
    """The reference cloud in the order of a KD-tree's leaves (copied in that order, the tree
    built on the copy), with the scratch arrays of the local planes."""

    def __init__(self, ref: np.ndarray):
        from scipy.spatial import cKDTree

        self.order = _leaf_order(ref)
        self.points = ref[self.order]
        self.tree = cKDTree(self.points, balanced_tree=False, compact_nodes=False)
        self.cols = [np.ascontiguousarray(self.points[:, j]) for j in range(3)]
        self.used = np.zeros(len(ref), dtype=bool)
        self.slot = np.empty(len(ref), dtype=np.intp)

    def local_models(self, q, d_nn, i_nn, fi, dist, nrm, side, model, k_eff, collinear_tol, workers) -> None:
        """The distance to the local plane of the nearest reference point of each found query
        ``fi``, one model per distinct nearest point (a mask, not a sort); writes ``dist``,
        ``nrm``, ``side`` (n·(q − centroid)) and ``model`` where a plane was fitted."""
        used, slot = self.used, self.slot
        used[i_nn[fi]] = True
        anchors = np.flatnonzero(used)
        used[anchors] = False
        slot[anchors] = np.arange(anchors.size)
        inv = slot[i_nn[fi]]
        _, nb = self.tree.query(self.points[anchors], k=k_eff, workers=workers)
        cent_rel, nrm_u, ok_u = _local_planes(self.cols, anchors, nb, collinear_tol)
        ok = ok_u[inv]
        mi = fi[ok]
        rel = q[mi] - self.points[i_nn[mi]] - cent_rel[inv[ok]]
        nrm[mi] = nrm_u[inv[ok]]
        side[mi] = np.einsum("ij,ij->i", rel, nrm[mi])
        dist[mi] = np.minimum(d_nn[mi], np.abs(side[mi]))
        model[mi] = True


def _signs(q, v, toward_point: bool, ref_pts, i_nn, found, dist, nrm, side, model):
    """The signed distances of a block of queries along the orientation ``v`` (the normals
    ``nrm`` flipped to it, in place) and how many of its model points have an ambiguous sign."""
    vv = (v - q) if toward_point else np.broadcast_to(v, q.shape)
    dots = np.einsum("ij,ij->i", np.nan_to_num(nrm), vv)
    flip = np.where(dots < 0, -1.0, 1.0)
    nrm *= flip[:, None]
    vnorm = np.linalg.norm(vv, axis=1)
    n_ambiguous = int(np.count_nonzero(model & (np.abs(dots) < AMBIGUOUS_SIGN_COS * vnorm)))
    # without a model: the side of the nearest point along the orientation
    fb_side = np.einsum("ij,ij->i", q - ref_pts[np.maximum(i_nn, 0)], vv)
    s = np.where(model, side * flip, fb_side)
    return np.where(found, np.where(s >= 0, 1.0, -1.0) * dist, np.nan), n_ambiguous


def c2c(
    compared_m,
    reference_m,
    k: int = 6,
    *,
    max_distance_m: float | None = None,
    orient_direction=None,
    orient_toward_m=None,
    collinear_tol: float = 1e-5,
    chunk_size: int = DEFAULT_CHUNK,
    workers: int = 1,
    progress: Callable[[int, int], None] | None = None,
) -> C2CResult:
    """Distances of the compared points to the reference cloud (see the module docstring).

    ``k``: neighbours of the nearest reference point in the local plane (≥ 3; CloudCompare's
    ``KNN k``). ``max_distance_m``: CloudCompare's ``-MAX_DIST``. ``orient_direction`` (a vector)
    or ``orient_toward_m`` (a point) turn on signed distances. ``workers``: threads for the
    KD-tree queries (1 = one core). ``progress(done, total)`` is called after each block.
    """
    q_all = _as_cloud(compared_m, "compared")
    ref_cloud = _as_cloud(reference_m, "reference")
    k = _checked_k(k, max_distance_m, collinear_tol)
    v = _orientation_vector(orient_direction, orient_toward_m)
    toward_point = orient_toward_m is not None

    n, n_ref = q_all.shape[0], ref_cloud.shape[0]
    ref = _Reference(ref_cloud)
    k_eff = min(k, n_ref)
    order = _leaf_order(q_all)

    distance = np.empty(n)
    nn_dist = np.empty(n)
    nearest = np.empty(n, dtype=np.intp)
    normal = np.full((n, 3), np.nan)
    has_model = np.zeros(n, dtype=bool)
    signed = np.empty(n) if v is not None else None
    n_ambiguous = 0
    ub = np.inf if max_distance_m is None else float(max_distance_m)

    for lo in range(0, n, chunk_size):
        idx = order[lo : lo + chunk_size]
        q = q_all[idx]
        d_nn, i_nn = ref.tree.query(q, k=1, distance_upper_bound=ub, workers=workers)
        found = i_nn < n_ref
        i_nn = np.where(found, i_nn, -1)
        nn_dist[idx] = d_nn
        nearest[idx] = np.where(found, ref.order[np.maximum(i_nn, 0)], -1)
        dist = d_nn.copy()
        model = np.zeros(idx.size, dtype=bool)
        nrm = np.full((idx.size, 3), np.nan)
        side = np.zeros(idx.size)  # n·(q − centroid), signed, for the model points
        fi = np.flatnonzero(found)
        if k_eff >= MIN_MODEL_POINTS and fi.size:
            ref.local_models(q, d_nn, i_nn, fi, dist, nrm, side, model, k_eff, collinear_tol, workers)
        if v is not None and signed is not None:  # signed exists exactly when v does
            signed[idx], n_amb = _signs(q, v, toward_point, ref.points, i_nn, found, dist, nrm, side, model)
            n_ambiguous += n_amb
        if max_distance_m is not None:
            dist[~found] = max_distance_m
        distance[idx] = dist
        has_model[idx] = model
        normal[idx] = nrm
        if progress is not None:
            progress(min(lo + chunk_size, n), n)

    return C2CResult(
        distance_m=distance,
        nn_distance_m=nn_dist,
        nearest_index=nearest,
        normal=normal,
        has_model=has_model,
        within_max=nearest >= 0,
        signed_distance_m=signed,
        k=k,
        max_distance_m=max_distance_m,
        n_ambiguous_sign=n_ambiguous,
    )
