"""Per-point total propagated uncertainty (TPU) of georeferenced points.

The georeferencing model is that of :mod:`calib.core.georef` (docs/architecture.md §3):

    x^n = p^n(t) + R_b^n(t) · (R_bs · R_nom · r_S(ρ + δρ, α + δα) + a^b),   t = t_point + Δt

Error sources, independent of each other, are propagated linearly, ``Σ_x = Σ J Σ_src Jᵀ``, with
analytic Jacobians:

* POS position: diagonal σ_N², σ_E², σ_D² of the trajectory at the point's instant;
* POS attitude: diagonal σ² of roll, pitch, heading (the Euler angles of
  ``R_b^n = Rz(heading)·Ry(pitch)·Rx(roll)``) at that instant;
* range: ``σ_ρ = sigma_range_m + sigma_range_per_m · ρ`` (the project's definition, as in
  ``calib.io.site.Site``, ``calib.sim.noise.ScannerNoise`` and the adjustment's observations:
  the proportional part adds linearly; ρ the measured range);
* scan angle: ``sigma_angle_rad``;
* boresight: full 3 × 3 covariance of the Euler angles (roll, pitch, yaw) of
  ``R_bs = Rz(γ)·Ry(β)·Rx(α_b)`` (``Mount.boresight_rad``), shared by all points;
* lever arm: 3 × 3 body-frame covariance.

The trajectory's sigmas (``Trajectory.sigma_p_m``, ``sigma_rpy_rad``) are interpolated linearly
at the point times, as :meth:`calib.core.trajectory.Trajectory.interpolate` does; **a
trajectory without sigmas contributes no POS error** (its position and attitude σ are taken as
zero), and so does a missing one of the two. Not modelled: time-correlation of the POS errors
(each point gets its marginal σ), the uncertainty of the time offset Δt and of the nominal
mount, the beam footprint (``beam_divergence_rad``, which depends on the surface hit).

Derivatives of an Euler ZYX rotation: for ``R = Rz(γ)·Ry(β)·Rx(α)``,
``∂(R·u)/∂θ_i = k_i × (R·u)`` with the axes ``k = [R·e_x, Rz(γ)·e_y, e_z]`` (:func:`euler_zyx_axes`).

:func:`point_jacobian` and :func:`point_covariance` build the full 3 × 14 Jacobian and 3 × 3
covariance per point (tests, small n). :func:`point_sigmas` (millions of points) needs only the
horizontal and vertical variances. With ``d`` the third row of ``R_b^n`` (the down axis seen in
the body frame), a body-frame error vector u gives the vertical error ``d·u`` and the horizontal
radial error² ``|u|² − (d·u)²``; the heading error rotates about the vertical and only moves
points horizontally. So only ``d`` (its interpolation by the slerp of the trajectory) and
body-frame vectors are evaluated per point, in blocks, with plain column arithmetic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.core import frames
from calib.core.errors import CalibError
from calib.core.georef import Mount
from calib.core.trajectory import Poses, Trajectory, TrajectoryError

#: The columns of :func:`point_jacobian`.
SOURCES = (
    "north_m",
    "east_m",
    "down_m",
    "roll_rad",
    "pitch_rad",
    "heading_rad",
    "range_m",
    "scan_angle_rad",
    "boresight_roll_rad",
    "boresight_pitch_rad",
    "boresight_yaw_rad",
    "lever_arm_x_m",
    "lever_arm_y_m",
    "lever_arm_z_m",
)
#: Relative tolerance of the symmetry and positive semi-definiteness checks of a covariance.
_COV_RTOL = 1e-9


class TpuError(CalibError, ValueError):
    """Bad input to the uncertainty propagation; the message names the field."""


@dataclass(frozen=True)
class ScannerSigmas:
    """Random errors of the profiler's observations (1σ, SI / radians).

    ``σ_ρ = sigma_range_m + sigma_range_per_m · ρ`` (the proportional part adds linearly, as in
    ``calib.io.site.Site``).
    """

    sigma_range_m: float = 0.0  # constant part of the range σ
    sigma_range_per_m: float = 0.0  # proportional part (σ grows by this × range)
    sigma_angle_rad: float = 0.0  # scan-angle σ

    def __post_init__(self):
        for attr in ("sigma_range_m", "sigma_range_per_m", "sigma_angle_rad"):
            try:
                v = float(getattr(self, attr))
            except (TypeError, ValueError):
                raise TpuError(
                    f"ScannerSigmas.{attr} must be a number, got {getattr(self, attr)!r}"
                ) from None
            if not np.isfinite(v) or v < 0:
                raise TpuError(f"ScannerSigmas.{attr} must be a finite number ≥ 0, got {v!r}")
            object.__setattr__(self, attr, v)

    def range_sigma_m(self, range_m) -> np.ndarray:
        """σ_ρ of returns at the given (measured) ranges."""
        return self.sigma_range_m + self.sigma_range_per_m * np.asarray(range_m, dtype=float)


def _covariance(owner: str, name: str, value) -> np.ndarray:
    """A finite, symmetric, positive semi-definite 3 × 3 matrix, or a TpuError naming it."""
    field_name = f"{owner}.{name}"
    try:
        c = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise TpuError(f"{field_name} must be a 3 × 3 matrix of numbers, got {value!r}") from None
    if c.shape != (3, 3):
        raise TpuError(f"{field_name} must have shape (3, 3), got {c.shape}")
    if not np.all(np.isfinite(c)):
        raise TpuError(f"{field_name} has non-finite entries: {c.tolist()!r}")
    scale = float(np.abs(c).max())
    asym = float(np.abs(c - c.T).max())
    if asym > _COV_RTOL * scale:
        raise TpuError(f"{field_name} is not symmetric (largest |C − Cᵀ| = {asym:.3g})")
    c = 0.5 * (c + c.T)
    lam = np.linalg.eigvalsh(c)
    if lam[0] < -_COV_RTOL * scale:
        raise TpuError(
            f"{field_name} is not positive semi-definite (eigenvalues {', '.join(f'{x:.3g}' for x in lam)})"
        )
    c.setflags(write=False)
    return c


@dataclass(frozen=True)
class MountCovariance:
    """Uncertainty of the mount, shared by all points.

    ``boresight_cov_rad2``: covariance of the boresight Euler angles (roll, pitch, yaw) of
    ``Mount.boresight_rad``; ``lever_arm_cov_m2``: body-frame (FRD) covariance of the lever arm.
    Both (3, 3), symmetric, positive semi-definite (zeros allowed).
    """

    boresight_cov_rad2: np.ndarray
    lever_arm_cov_m2: np.ndarray

    def __post_init__(self):
        for attr in ("boresight_cov_rad2", "lever_arm_cov_m2"):
            object.__setattr__(self, attr, _covariance("MountCovariance", attr, getattr(self, attr)))

    @classmethod
    def zero(cls) -> MountCovariance:
        return cls(np.zeros((3, 3)), np.zeros((3, 3)))


# ---------------------------------------------------------------------------------------------
# Jacobians (full, per point).
# ---------------------------------------------------------------------------------------------


def euler_zyx_axes(roll_rad, pitch_rad, yaw_rad) -> np.ndarray:
    """(..., 3, 3) whose columns are the axes k_i with ``∂(R·u)/∂θ_i = k_i × (R·u)`` for
    ``R = Rz(yaw)·Ry(pitch)·Rx(roll)``: ``[R·e_x, Rz(yaw)·e_y, e_z]`` (in R's output frame)."""
    r, p, y = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (roll_rad, pitch_rad, yaw_rad)))
    cp, sp, cy, sy = np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    out = np.zeros(r.shape + (3, 3))
    out[..., 0, 0], out[..., 1, 0], out[..., 2, 0] = cy * cp, sy * cp, -sp
    out[..., 0, 1], out[..., 1, 1] = -sy, cy
    out[..., 2, 2] = 1.0
    return out


def _check_observations(t_gps_s, range_m, scan_angle_rad) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    arrays = []
    for name, a in (("t_gps_s", t_gps_s), ("range_m", range_m), ("scan_angle_rad", scan_angle_rad)):
        try:
            arrays.append(np.asarray(a, dtype=float))
        except (TypeError, ValueError):
            raise TpuError(f"{name} must be an array of numbers") from None
    n = arrays[0].shape[0] if arrays[0].ndim == 1 else -1
    for name, a in zip(("t_gps_s", "range_m", "scan_angle_rad"), arrays, strict=False):
        if a.ndim != 1 or a.shape[0] != n:
            shapes = ", ".join(str(x.shape) for x in arrays)
            raise TpuError(
                f"{name} has shape {a.shape}: t_gps_s, range_m and scan_angle_rad must be 1-D arrays "
                f"of one length (got {shapes})"
            )
    return arrays[0], arrays[1], arrays[2]


def point_jacobian(poses: Poses, range_m, scan_angle_rad, mount: Mount) -> np.ndarray:
    """(n, 3, 14) Jacobian of the NED point w.r.t. the error sources :data:`SOURCES`, at the
    given per-point poses (attitude axes from ``poses.rpy_rad``, rotation ``poses.r_b_n``)."""
    rho = np.asarray(range_m, dtype=float) + mount.range_offset_m
    alpha = np.asarray(scan_angle_rad, dtype=float) + mount.scan_angle_offset_rad
    n = rho.size
    m_sb = mount.r_s_b
    e_b = np.cos(alpha)[:, None] * m_sb[:, 1] + np.sin(alpha)[:, None] * m_sb[:, 2]  # range direction
    e_perp_b = -np.sin(alpha)[:, None] * m_sb[:, 1] + np.cos(alpha)[:, None] * m_sb[:, 2]
    s_b = rho[:, None] * e_b  # scanner vector in the body frame
    R = poses.r_b_n
    rot = lambda u: np.einsum("nij,nj->ni", R, u)  # noqa: E731
    w_n = rot(s_b + mount.lever_arm_m)  # x − p
    J = np.zeros((n, 3, len(SOURCES)))
    J[:, :, 0:3] = np.eye(3)
    att_axes = euler_zyx_axes(*poses.rpy_rad.T)
    for i in range(3):
        J[:, :, 3 + i] = np.cross(att_axes[:, :, i], w_n)
    J[:, :, 6] = rot(e_b)
    J[:, :, 7] = rho[:, None] * rot(e_perp_b)
    bs_axes = euler_zyx_axes(*mount.boresight_rad)
    for i in range(3):
        J[:, :, 8 + i] = rot(np.cross(bs_axes[:, i], s_b))
    J[:, :, 11:14] = R
    return J


def _pos_sigmas(poses: Poses, n: int) -> tuple[np.ndarray, np.ndarray]:
    sp = np.zeros((n, 3)) if poses.sigma_p_m is None else poses.sigma_p_m
    sa = np.zeros((n, 3)) if poses.sigma_rpy_rad is None else poses.sigma_rpy_rad
    return sp, sa


def point_covariance(
    t_gps_s,
    range_m,
    scan_angle_rad,
    traj: Trajectory,
    mount: Mount,
    scanner: ScannerSigmas,
    mount_cov: MountCovariance,
) -> np.ndarray:
    """(n, 3, 3) NED covariance of each georeferenced point (allocates (n, 3, 14): small n).

    The pose is the trajectory's at ``t_gps_s + mount.time_offset_s``; see the module docstring
    for the error sources (a trajectory without sigmas contributes no POS error)."""
    t, rho, alpha = _check_observations(t_gps_s, range_m, scan_angle_rad)
    _check_types(traj, mount, scanner, mount_cov)
    n = t.size
    if n == 0:
        return np.zeros((0, 3, 3))
    poses = traj.interpolate(t + mount.time_offset_s)
    J = point_jacobian(poses, rho, alpha, mount)
    sp, sa = _pos_sigmas(poses, n)
    sig = np.concatenate(
        [sp, sa, scanner.range_sigma_m(rho)[:, None], np.full((n, 1), scanner.sigma_angle_rad)], axis=1
    )
    Jd = J[:, :, :8] * sig[:, None, :]
    cov = Jd @ Jd.transpose(0, 2, 1)
    for cols, c in (
        (slice(8, 11), mount_cov.boresight_cov_rad2),
        (slice(11, 14), mount_cov.lever_arm_cov_m2),
    ):
        Jc = J[:, :, cols]
        cov += Jc @ c @ Jc.transpose(0, 2, 1)
    return cov


def _check_types(traj, mount, scanner, mount_cov) -> None:
    for name, v, cls in (
        ("traj", traj, Trajectory),
        ("mount", mount, Mount),
        ("scanner", scanner, ScannerSigmas),
        ("mount_cov", mount_cov, MountCovariance),
    ):
        if not isinstance(v, cls):
            raise TpuError(f"{name} must be a {cls.__name__}, got {type(v).__name__}")


# ---------------------------------------------------------------------------------------------
# Horizontal and vertical σ of many points, in blocks.
# ---------------------------------------------------------------------------------------------

# rows of the per-interval table (leading axis), then gathered per point:
# d(w) = D0 + s·D1 + c·D2 with s = sin(wθ), c = 1 − cos(wθ) (the slerp, Rodrigues), and the
# sigmas σ(w) = S0 + w·S1
_D0, _D1, _D2, _S0, _S1 = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 15), slice(15, 21)
_N_ROWS = 21


def _interval_table(traj: Trajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rows, m) table of the m trajectory intervals (see _D0 …), their rotation angles θ and
    1 / length."""
    R = traj.r_b_n[:-1]
    phi = traj.interval_rotvec
    theta = np.linalg.norm(phi, axis=1)
    K = frames.skew(phi / np.where(theta > 0, theta, 1.0)[:, None])
    RK = R @ K
    m = theta.size
    tab = np.zeros((_N_ROWS, m))
    tab[_D0] = R[:, 2, :].T
    tab[_D1] = RK[:, 2, :].T
    tab[_D2] = (RK @ K)[:, 2, :].T
    for cols, sig in ((slice(0, 3), traj.sigma_p_m), (slice(3, 6), traj.sigma_rpy_rad)):
        if sig is not None:
            tab[_S0][cols] = sig[:-1].T
            tab[_S1][cols] = np.diff(sig, axis=0).T
    return tab, theta, 1.0 / np.diff(traj.t_gps_s)


@dataclass(frozen=True)
class _Constants:
    """Per-call constants of the block kernel (body frame)."""

    m2: np.ndarray  # scan-plane columns of R_S^b
    m3: np.ndarray
    lever_m: np.ndarray
    bs_cov: np.ndarray  # boresight covariance as a body rotation-vector covariance: M Σ Mᵀ
    bs_ee: tuple[float, float, float]  # m2ᵀCm2, 2·m2ᵀCm3, m3ᵀCm3
    bs_trace: float
    la_cov: np.ndarray
    la_trace: float


def _constants(mount: Mount, mount_cov: MountCovariance) -> _Constants:
    m_sb = mount.r_s_b
    m2, m3 = m_sb[:, 1].copy(), m_sb[:, 2].copy()
    axes = euler_zyx_axes(*mount.boresight_rad)
    C = axes @ mount_cov.boresight_cov_rad2 @ axes.T
    return _Constants(
        m2,
        m3,
        mount.lever_arm_m,
        C,
        (float(m2 @ C @ m2), float(2.0 * m2 @ C @ m3), float(m3 @ C @ m3)),
        float(np.trace(C)),
        mount_cov.lever_arm_cov_m2,
        float(np.trace(mount_cov.lever_arm_cov_m2)),
    )


def _quadratic(C: np.ndarray, x, y, z) -> np.ndarray:
    """uᵀ C u for the columns u = (x, y, z), C symmetric."""
    q = C[0, 0] * x * x
    q += C[1, 1] * y * y
    q += C[2, 2] * z * z
    q += (2.0 * C[0, 1]) * x * y
    q += (2.0 * C[0, 2]) * x * z
    q += (2.0 * C[1, 2]) * y * z
    return q


def _block_variances(g, w, theta, rho_meas, rho, alpha, scanner, k: _Constants, pos_sig: bool):
    """Horizontal (radial) and vertical variances of one block; ``g`` the gathered table rows."""
    x = w * theta
    s = np.sin(x)
    c = np.sin(0.5 * x)
    c *= c
    c *= 2.0  # 1 − cos x, without cancellation
    dx = g[0] + s * g[3] + c * g[6]
    dy = g[1] + s * g[4] + c * g[7]
    dz = g[2] + s * g[5] + c * g[8]
    ca, sa = np.cos(alpha), np.sin(alpha)
    m2, m3, a = k.m2, k.m3, k.lever_m
    # range direction e and its perpendicular in the scan plane, body frame
    e0, e1, e2 = ca * m2[0] + sa * m3[0], ca * m2[1] + sa * m3[1], ca * m2[2] + sa * m3[2]
    de = dx * e0 + dy * e1 + dz * e2
    de_perp = dx * (ca * m3[0] - sa * m2[0]) + dy * (ca * m3[1] - sa * m2[1]) + dz * (ca * m3[2] - sa * m2[2])
    de *= de
    de_perp *= de_perp
    var_r = scanner.range_sigma_m(rho_meas)
    var_r *= var_r
    var_a = rho * rho
    var_a *= scanner.sigma_angle_rad**2
    var_v = var_r * de
    var_v += var_a * de_perp
    var_h = var_r + var_a
    var_h -= var_v
    if pos_sig:
        v0, v1, v2 = rho * e0 + a[0], rho * e1 + a[1], rho * e2 + a[2]  # body vector p → x
        p_dz = dy * v1 + dz * v2
        w_d = dx * v0 + p_dz  # its down component
        w_d2 = w_d * w_d
        sig = g[9:15] + w * g[15:21]  # N, E, D, roll, pitch, heading
        sig *= sig
        var_h += sig[0] + sig[1]
        var_v += sig[2]
        # roll: u = e_x × v
        u_d = dz * v1 - dy * v2
        u_d *= u_d
        var_v += sig[3] * u_d
        var_h += sig[3] * (v1 * v1 + v2 * v2 - u_d)
        # pitch: u = (Rxᵀ e_y) × v, with Rxᵀ e_y = (0, dz, −dy) / cos(pitch)
        cp = np.sqrt(dy * dy + dz * dz)
        u_d = dx * p_dz / cp - cp * v0
        var_v += sig[4] * (u_d * u_d)
        var_h += sig[4] * w_d2
        # heading: about the vertical, horizontal only
        var_h += sig[5] * (v0 * v0 + v1 * v1 + v2 * v2 - w_d2)
    if k.bs_trace > 0:  # boresight: u = δφ × (ρ e), δφ ~ (0, C)
        ee = (ca * ca) * k.bs_ee[0] + (ca * sa) * k.bs_ee[1] + (sa * sa) * k.bs_ee[2]
        v_bs = _quadratic(k.bs_cov, dy * e2 - dz * e1, dz * e0 - dx * e2, dx * e1 - dy * e0)
        r2 = rho * rho
        var_v += r2 * v_bs
        var_h += r2 * (k.bs_trace - ee - v_bs)
    if k.la_trace > 0:
        v_la = _quadratic(k.la_cov, dx, dy, dz)
        var_v += v_la
        var_h += k.la_trace - v_la
    return var_h, var_v


def _interval_index(tt: np.ndarray, tb: np.ndarray) -> np.ndarray:
    """The trajectory interval of each time ``tb``: ``searchsorted(tt, tb, "right") − 1`` clipped
    to [0, m − 2]. For time-sorted ``tb`` longer than ``tt`` (a profiler's block), counted from
    where each epoch falls among them — tt[j] ≤ tb[i] exactly when i ≥ searchsorted(tb, tt[j]) —
    instead of a search per point: the same integers."""
    if tt.size < tb.size and bool(np.all(tb[1:] >= tb[:-1])):  # (False with a NaN: searched then)
        first = np.searchsorted(tb, tt, side="left")
        kb = np.bincount(first, minlength=tb.size + 1)[: tb.size].cumsum()
    else:
        kb = np.searchsorted(tt, tb, side="right")
    kb -= 1
    return np.clip(kb, 0, tt.size - 2, out=kb)


def _outputs(n: int, dtype, out: tuple[np.ndarray, np.ndarray] | None) -> tuple[np.ndarray, np.ndarray]:
    """The arrays :func:`point_sigmas` writes into: ``out`` (checked), else new ones of ``dtype``."""
    if out is None:
        return np.empty(n, dtype), np.empty(n, dtype)
    if len(out) != 2 or any(o.shape != (n,) or o.dtype.kind != "f" for o in out):
        raise TpuError(
            f"out must be two float arrays of {n} elements, got {[(o.shape, o.dtype) for o in out]}"
        )
    return out[0], out[1]


def point_sigmas(
    t_gps_s,
    range_m,
    scan_angle_rad,
    traj: Trajectory,
    mount: Mount,
    scanner: ScannerSigmas,
    mount_cov: MountCovariance,
    block: int = 65536,
    dtype=np.float64,
    out: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal radial and vertical 1σ (m) of each georeferenced point: ``sigma_h_m =
    sqrt(Σ_NN + Σ_EE)``, ``sigma_v_m = sqrt(Σ_DD)`` of :func:`point_covariance`, computed
    ``block`` points at a time (memory: a few dozen floats per point of a block, plus the
    outputs, of ``dtype`` float64 or float32). ``out``: two arrays of n floats (views too, e.g.
    the fields of a structured array) to write σ_h and σ_v into, instead of new arrays of
    ``dtype``; the values are those of new arrays of their own dtype.

    Raises :class:`TrajectoryError` if the trajectory does not cover the point times (+ Δt).
    """
    t, rho_meas, alpha = _check_observations(t_gps_s, range_m, scan_angle_rad)
    _check_types(traj, mount, scanner, mount_cov)
    if int(block) < 1:
        raise TpuError(f"block must be ≥ 1, got {block!r}")
    if np.dtype(dtype) not in (np.dtype(np.float32), np.dtype(np.float64)):
        raise TpuError(f"dtype must be float32 or float64, got {dtype!r}")
    block = int(block)
    n = t.size
    sigma_h_m, sigma_v_m = _outputs(n, dtype, out)
    if n == 0:
        return sigma_h_m, sigma_v_m
    tab, theta, inv_dt = _interval_table(traj)
    consts = _constants(mount, mount_cov)
    pos_sig = traj.sigma_p_m is not None or traj.sigma_rpy_rad is not None
    tt = traj.t_gps_s
    dt_s, d_rho, d_alpha = mount.time_offset_s, mount.range_offset_m, mount.scan_angle_offset_rad
    n_bad = 0
    bad_times: list[np.ndarray] = []
    for lo in range(0, n, block):
        hi = min(lo + block, n)
        tb = t[lo:hi] + dt_s
        bad = traj.uncovered(tb)
        if bad.any():
            n_bad += int(bad.sum())
            if len(bad_times) < 16:
                bad_times.append(tb[bad])
            continue
        kb = _interval_index(tt, tb)
        w = tb - tt.take(kb)
        w *= inv_dt.take(kb)
        g = tab.take(kb, axis=1) if pos_sig else tab[:9].take(kb, axis=1)
        rho_b = rho_meas[lo:hi]
        var_h, var_v = _block_variances(
            g, w, theta.take(kb), rho_b, rho_b + d_rho, alpha[lo:hi] + d_alpha, scanner, consts, pos_sig
        )
        np.sqrt(np.maximum(var_h, 0.0, out=var_h), out=var_h)
        np.sqrt(np.maximum(var_v, 0.0, out=var_v), out=var_v)
        sigma_h_m[lo:hi] = var_h
        sigma_v_m[lo:hi] = var_v
    if n_bad:
        where = traj.where_uncovered(np.concatenate(bad_times))
        raise TrajectoryError(
            f"{traj.name} does not cover {n_bad} of {n} point times (time offset {dt_s:g} s included; "
            f"{traj.max_gap_s:g} s gaps refused); among them: {where}"
        )
    return sigma_h_m, sigma_v_m
