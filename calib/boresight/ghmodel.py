"""The plane condition of the boresight adjustment and its derivatives, vectorized over points.

For point i on plane j (docs/architecture.md §3, §7):

    F_i = n_jᵀ x_i + d_j = 0,
    x_i = p_i + o_k(i) + R_b^n(φ_i, θ_i, ψ_i) · (R_bs(α_b, β, γ) · R_nom · r_S(ρ_i + δρ, α_i + δα) + a)

Observations per point (8, in this order): position N, E, D; roll, pitch, heading; range; scan
angle. Unknowns: boresight (3), optional extras (range offset δρ, scan-angle offset δα, lever
arm x and y, latency Δt), per plane a unit normal (2 tangent-space increments) and d (relative to a fixed point near
the plane's points, so that tilting the normal pivots the plane about its own points), optional
per-pass translations o_k. This module evaluates F, ``A = ∂F/∂unknowns`` (as named columns) and
``B = ∂F/∂observations`` (n × 8).

**Cylinders.** A feature may instead be a cylinder with a fixed axis direction a (a pile, a
post: vertical), its axis through c_j and its radius r_j = −d_j:

    F_i = |(x_i − c_j) − ((x_i − c_j)·a) a| + d_j = u_iᵀ (x_i − c_j) + d_j,

u_i the unit vector from the axis to the point, perpendicular to it. Everything that is ``n_jᵀ``
of a derivative of x for a plane is ``u_iᵀ`` of the same derivative for a cylinder (``∂F/∂x =
u_iᵀ``), so the two share every column but the feature's own: a cylinder's three unknowns are
the axis's shift along the two tangent vectors of a (``−u_iᵀ e_1``, ``−u_iᵀ e_2``) and d (1),
where a plane's are its normal's tilt and d. A yaw moves a point along the track; on a
cylinder that changes its distance from the axis wherever the beam is not head-on, which is
what gives yaw to piles when a flat wall gives it almost nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.core import frames

EXTRA_NAMES = ("range_offset", "scan_angle_offset", "lever_arm_x", "lever_arm_y", "latency")

_EX, _EY, _EZ = np.eye(3)


def tangent_bases(normals: np.ndarray) -> np.ndarray:
    """(m, 3, 2): an orthonormal basis of the plane orthogonal to each unit normal, row by row
    of ``normals`` (m, 3) (deterministic: the first vector is n × z, or n × x near vertical)."""
    n = np.asarray(normals, float).reshape(-1, 3)
    helper = np.where((np.abs(n[:, 2]) < 0.9)[:, None], _EZ, _EX)
    e1 = _cross(n, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return np.stack([e1, _cross(n, e1)], axis=2)


def _cross(a, b):
    """Row-wise cross product of (n, 3) arrays (faster than np.cross for this shape)."""
    return np.stack(
        [
            a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
            a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0],
        ],
        axis=1,
    )


@dataclass
class State:
    """Current values of the unknowns (SI, radians)."""

    boresight_rad: np.ndarray  # (3,)
    normals: np.ndarray  # (m, 3) unit
    d_m: np.ndarray  # (m,) plane offsets relative to ``centers_m``: nᵀ(x − c) + d = 0
    centers_m: np.ndarray  # (m, 3) fixed reference point of each plane (near its points)
    pass_offsets_m: np.ndarray  # (K, 3)
    lever_arm_m: np.ndarray  # (3,)
    range_offset_m: float = 0.0
    scan_angle_offset_rad: float = 0.0
    latency_s: float = 0.0
    #: (m,) bool: the features that are cylinders (``normals`` their axes, ``centers_m`` points
    #: of their axes, ``d_m`` minus their radii); None: every feature is a plane
    cylinders: np.ndarray | None = None

    @property
    def d_lgf_m(self) -> np.ndarray:
        """Plane offsets in the LGF: nᵀx + d = 0 (a cylinder's entry has no meaning)."""
        return self.d_m - np.einsum("ij,ij->i", self.normals, self.centers_m)

    @property
    def is_cylinder(self) -> np.ndarray:
        """(m,) bool: which features are cylinders."""
        if self.cylinders is None:
            return np.zeros(self.normals.shape[0], bool)
        return self.cylinders

    def cylinder_rows(self, feature_index: np.ndarray) -> np.ndarray | None:
        """The rows of points (``feature_index``: each point's feature) that lie on cylinders;
        None when none does."""
        if self.cylinders is None or not self.cylinders.any():
            return None
        rows = np.flatnonzero(self.cylinders[feature_index])
        return rows if rows.size else None

    def copy(self) -> State:
        return State(
            self.boresight_rad.copy(),
            self.normals.copy(),
            self.d_m.copy(),
            self.centers_m.copy(),
            self.pass_offsets_m.copy(),
            self.lever_arm_m.copy(),
            self.range_offset_m,
            self.scan_angle_offset_rad,
            self.latency_s,
            None if self.cylinders is None else self.cylinders.copy(),
        )


@dataclass
class Linearization:
    F: np.ndarray  # (n,) condition values at the linearization point
    x_lgf_m: np.ndarray  # (n, 3) georeferenced points
    A_boresight: np.ndarray  # (n, 3)
    A_extra: dict  # name -> (n,)
    A_plane: np.ndarray  # (n, 3): two tangent increments of the normal, then d
    A_offset: np.ndarray  # (n, 3): ∂F/∂o_k = n_j
    B: np.ndarray  # (n, 8)


def _mat_rows(M: np.ndarray, v):
    """M (3, 3) applied to component rows v = (x, y, z) of arrays."""
    return tuple(M[i, 0] * v[0] + M[i, 1] * v[1] + M[i, 2] * v[2] for i in range(3))


def _cross_axis(axis: int, v):
    """The unit vector along ``axis`` (x, y, z) × component rows v, without the products by 0
    and 1 of the general cross product (the same numbers; a zero component as a scalar 0)."""
    if axis == 0:
        return (0.0, -v[2], v[1])
    if axis == 1:
        return (v[2], 0.0, -v[0])
    return (-v[1], v[0], 0.0)


def _boresight_rotations(state: State) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The boresight's elementary rotations Rx(roll), Ry(pitch), Rz(yaw)."""
    br, bp, by = state.boresight_rad
    return frames.rot_x(br), frames.rot_y(bp), frames.rot_z(by)


def _lever_plus(state: State, m2: np.ndarray, m3: np.ndarray, e1: np.ndarray, e2: np.ndarray):
    """``v_b``: the lever arm plus the scanner's vector ``m2·e1 + m3·e2`` (component rows)."""
    return tuple(m2[i] * e1 + m3[i] * e2 + state.lever_arm_m[i] for i in range(3))


def _body_vector(state: State, r_nom: np.ndarray, lt: np.ndarray):
    """``v_b`` of :func:`_scanner_vectors` alone (the same operations, the same numbers)."""
    rho_t = lt[6] + state.range_offset_m
    a = lt[7] + state.scan_angle_offset_rad
    ca, sa = np.cos(a), np.sin(a)
    Rx, Ry, Rz = _boresight_rotations(state)
    M = Rz @ Ry @ Rx @ r_nom
    return _lever_plus(state, M[:, 1], M[:, 2], rho_t * ca, rho_t * sa)


def _scanner_vectors(state: State, r_nom: np.ndarray, lt: np.ndarray):
    """The lever arm plus the scanner's vector in the body frame ``v_b`` (component rows), its
    derivatives by the range and the scan angle, and by the boresight roll, pitch and yaw."""
    rho_t = lt[6] + state.range_offset_m
    a = lt[7] + state.scan_angle_offset_rad
    ca, sa = np.cos(a), np.sin(a)

    Rx, Ry, Rz = _boresight_rotations(state)
    R_bs = Rz @ Ry @ Rx
    M = R_bs @ r_nom  # R_S^b
    # r_S = ρ[0, cos α, sin α]; with the two scan-plane columns of the mounts:
    m2, m3 = M[:, 1], M[:, 2]
    q2, q3 = r_nom[:, 1], r_nom[:, 2]
    e1, e2 = rho_t * ca, rho_t * sa
    q = tuple(q2[i] * e1 + q3[i] * e2 for i in range(3))  # R_nom r_S
    v_b = _lever_plus(state, m2, m3, e1, e2)
    drho = tuple(m2[i] * ca + m3[i] * sa for i in range(3))  # ∂(M r_S)/∂ρ
    dalpha = tuple(rho_t * (m3[i] * ca - m2[i] * sa) for i in range(3))  # ∂(M r_S)/∂α
    # ∂v_b/∂(boresight roll, pitch, yaw)
    dv_br = _mat_rows(R_bs, _cross_axis(0, q))
    dv_bp = _mat_rows(Rz @ Ry, _cross_axis(1, _mat_rows(Rx, q)))
    dv_by = _cross_axis(2, _mat_rows(R_bs, q))
    return v_b, drho, dalpha, (dv_br, dv_bp, dv_by)


def attitude_trig(l: np.ndarray) -> np.ndarray:
    """(6, n): cos and sin of the roll, pitch and heading of observations ``l`` (n, 8)."""
    angles = np.ascontiguousarray(l[:, 3:6].T)  # contiguous, as the linearization evaluates them
    out = np.empty((6, l.shape[0]))
    for i in range(3):
        np.cos(angles[i], out=out[2 * i])
        np.sin(angles[i], out=out[2 * i + 1])
    return out


class _Attitude:
    """Each point's attitude R = Rz(ψ) Ry(θ) Rx(φ), applied to component rows, and the plane
    normals' dot product with them."""

    def __init__(self, trig: np.ndarray, nrm: np.ndarray):
        """``trig`` (6, n): cos and sin of roll, pitch and heading (:func:`attitude_trig`)."""
        self.cr, self.sr, self.cp, self.sp, self.ch, self.sh = trig
        self.nrm = nrm  # (3, n)

    def rx(self, v):
        return (v[0], self.cr * v[1] - self.sr * v[2], self.sr * v[1] + self.cr * v[2])

    def ry(self, v):
        return (self.cp * v[0] + self.sp * v[2], v[1], self.cp * v[2] - self.sp * v[0])

    def rz(self, v):
        return (self.ch * v[0] - self.sh * v[1], self.sh * v[0] + self.ch * v[1], v[2])

    def n_dot(self, v):
        return self.nrm[0] * v[0] + self.nrm[1] * v[1] + self.nrm[2] * v[2]

    def n_dot_R(self, v):
        return self.n_dot(self.rz(self.ry(self.rx(v))))


def _fill_extra_columns(out: Linearization, att: _Attitude, v_b, rates, n: int) -> None:
    """The Jacobian columns of the extra unknowns that ``out.A_extra`` holds (range and
    scan-angle offsets: the range's and the scan angle's own; the lever arm; the latency with
    the trajectory's rates)."""
    extra = out.A_extra
    ones, zeros = (np.ones(n), np.zeros(n)) if "lever_arm_x" in extra or "lever_arm_y" in extra else (0, 0)
    if "range_offset" in extra:
        extra["range_offset"][:] = out.B[:, 6]
    if "scan_angle_offset" in extra:
        extra["scan_angle_offset"][:] = out.B[:, 7]
    if "lever_arm_x" in extra:
        extra["lever_arm_x"][:] = att.n_dot_R((ones, zeros, zeros))
    if "lever_arm_y" in extra:
        extra["lever_arm_y"][:] = att.n_dot_R((zeros, ones, zeros))
    if rates is not None and "latency" in extra:
        vel, omega_b = rates
        w_x_v = _cross(omega_b, np.stack(v_b, axis=1))
        extra["latency"][:] = att.n_dot(tuple(vel[:, i] for i in range(3))) + att.n_dot_R(
            tuple(w_x_v[:, i] for i in range(3))
        )


def linearize_block(
    state: State,
    r_nom: np.ndarray,
    plane_index: np.ndarray,
    pass_index: np.ndarray,
    l: np.ndarray,
    rates: tuple[np.ndarray, np.ndarray] | None,
    bases: np.ndarray,
    out: Linearization,
    trig: np.ndarray | None = None,
) -> None:
    """Evaluate the condition and its Jacobians at observations ``l`` (n, 8) into ``out``
    (views of the caller's arrays). Vectors are kept as three contiguous component arrays.

    Only the extra columns ``out.A_extra`` holds are filled, and the georeferenced points and
    the pass offsets' column only when ``out.x_lgf_m`` and ``out.A_offset`` have rows; ``trig``: :func:`attitude_trig` of ``l`` when the caller
    keeps it (the poses do not change between the iterations)."""
    n = l.shape[0]
    lt = np.ascontiguousarray(l.T)
    nrm = np.ascontiguousarray(state.normals[plane_index].T)  # (3, n)
    v_b, drho, dalpha, dv_boresight = _scanner_vectors(state, r_nom, lt)
    att = _Attitude(attitude_trig(l) if trig is None else trig, nrm)

    # nᵀR for the constant-direction derivatives: uᵀ = nᵀ R = (Rᵀ n)ᵀ
    rx_v = att.rx(v_b)
    Rv = att.rz(att.ry(rx_v))
    x_rel = _relative_points(state, plane_index, pass_index, lt, Rv)
    cyl = _cylinder_gradients(state, plane_index, x_rel, nrm)
    out.F[:] = att.n_dot((x_rel[:, 0], x_rel[:, 1], x_rel[:, 2])) + state.d_m[plane_index]
    if out.x_lgf_m.shape[0]:
        out.x_lgf_m[:] = x_rel + state.centers_m[plane_index]
    if out.A_offset.shape[0]:
        out.A_offset[:] = nrm.T

    B = out.B
    B[:, 0:3] = nrm.T
    B[:, 3] = att.n_dot_R(_cross_axis(0, v_b))
    B[:, 4] = att.n_dot(att.rz(att.ry(_cross_axis(1, rx_v))))
    B[:, 5] = att.n_dot(_cross_axis(2, Rv))
    B[:, 6] = att.n_dot_R(drho)
    B[:, 7] = att.n_dot_R(dalpha)

    for c, dv in enumerate(dv_boresight):
        out.A_boresight[:, c] = att.n_dot_R(dv)
    _fill_extra_columns(out, att, v_b, rates, n)
    E = bases[plane_index]  # (n, 3, 2)
    out.A_plane[:, 0:2] = np.einsum("ni,nij->nj", x_rel, E)
    if cyl is not None:  # a cylinder's axis shifts along its tangent vectors
        out.A_plane[cyl, 0:2] = -np.einsum("in,nij->nj", nrm[:, cyl], E[cyl])
    out.A_plane[:, 2] = 1.0


def _cylinder_gradients(state: State, plane_index, x_rel: np.ndarray, nrm: np.ndarray) -> np.ndarray | None:
    """Put each cylinder point's condition gradient, the radial unit vector, in place of its
    axis in ``nrm`` (3, n); the rows on cylinders (None: none)."""
    cyl = state.cylinder_rows(plane_index)
    if cyl is not None:
        nrm[:, cyl] = _radial_units(x_rel[cyl], nrm[:, cyl])
    return cyl


def _radial_units(x_rel: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """(3, k): the unit vectors perpendicular to the ``axes`` (3, k) from the axis to the points
    ``x_rel`` (k, 3), which are relative to a point of their axis."""
    along = np.einsum("ki,ik->k", x_rel, axes)
    radial = x_rel.T - along * axes
    return radial / np.sqrt(np.einsum("ik,ik->k", radial, radial))


def _relative_points(state: State, plane_index, pass_index, lt: np.ndarray, Rv) -> np.ndarray:
    """(n, 3): the georeferenced points (position + pass offset + ``Rv``, the rotated body
    vector) relative to their plane's center."""
    ctr = state.centers_m[plane_index]
    x_rel = np.empty((lt.shape[1], 3))
    if not np.any(state.pass_offsets_m):  # p + 0 is p: the same numbers without the gather
        for i in range(3):
            x_rel[:, i] = lt[i] + Rv[i] - ctr[:, i]
        return x_rel
    off = state.pass_offsets_m[pass_index]
    for i in range(3):
        x_rel[:, i] = lt[i] + off[:, i] + Rv[i] - ctr[:, i]
    return x_rel


def georeferenced(
    state: State, r_nom: np.ndarray, plane_index: np.ndarray, pass_index: np.ndarray, l: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The condition values F (n,) and the georeferenced points (n, 3) at observations ``l``
    (n, 8) without the Jacobians: the numbers of :func:`linearize`'s ``F`` and ``x_lgf_m``."""
    n = l.shape[0]
    F, x = np.empty(n), np.empty((n, 3))
    for lo in range(0, n, LINEARIZE_BLOCK):
        sl = slice(lo, min(lo + LINEARIZE_BLOCK, n))
        lt = np.ascontiguousarray(l[sl].T)
        j = plane_index[sl]
        att = _Attitude(attitude_trig(l[sl]), np.ascontiguousarray(state.normals[j].T))
        Rv = att.rz(att.ry(att.rx(_body_vector(state, r_nom, lt))))
        x_rel = _relative_points(state, j, pass_index[sl], lt, Rv)
        _cylinder_gradients(state, j, x_rel, att.nrm)
        F[sl] = att.n_dot((x_rel[:, 0], x_rel[:, 1], x_rel[:, 2])) + state.d_m[j]
        x[sl] = x_rel + state.centers_m[j]
    return F, x


#: Points per block: the temporaries of a block stay in the CPU cache.
LINEARIZE_BLOCK = 1 << 15


def linearize(
    state: State,
    r_nom: np.ndarray,
    plane_index: np.ndarray,
    pass_index: np.ndarray,
    l: np.ndarray,
    rates: tuple[np.ndarray, np.ndarray] | None = None,
    bases: np.ndarray | None = None,
) -> Linearization:
    """Evaluate the condition and its Jacobians at observations ``l`` (n, 8), in blocks.

    ``rates`` = (velocity (n, 3) in the LGF, angular rate (n, 3) in the body frame) is needed
    only for the latency column; ``bases`` (m, 3, 2) are the tangent bases of the normals.
    """
    n = l.shape[0]
    if bases is None:
        bases = tangent_bases(state.normals)
    names = list(EXTRA_NAMES[:4]) + (["latency"] if rates is not None else [])
    res = Linearization(
        F=np.empty(n),
        x_lgf_m=np.empty((n, 3)),
        A_boresight=np.empty((n, 3)),
        A_extra={k: np.empty(n) for k in names},
        A_plane=np.empty((n, 3)),
        A_offset=np.empty((n, 3)),
        B=np.empty((n, 8)),
    )
    for lo in range(0, n, LINEARIZE_BLOCK):
        sl = slice(lo, min(lo + LINEARIZE_BLOCK, n))
        r = None if rates is None else (rates[0][sl], rates[1][sl])
        view = Linearization(
            res.F[sl],
            res.x_lgf_m[sl],
            res.A_boresight[sl],
            {k: v[sl] for k, v in res.A_extra.items()},
            res.A_plane[sl],
            res.A_offset[sl],
            res.B[sl],
        )
        linearize_block(state, r_nom, plane_index[sl], pass_index[sl], l[sl], r, bases, view)
    return res
