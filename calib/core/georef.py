"""Direct georeferencing (docs/architecture.md §3) and its inverse.

    x^n = p^n(t) + R_b^n(t) · (R_bs · R_nom · r_S(ρ + δρ, α + δα) + a^b),   t = t_point + Δt

The forward transform is vectorized and organised for speed. Within trajectory interval k the
attitude is ``R_k · Exp(w·φ_k)`` (the slerp of :mod:`calib.core.trajectory`), which Rodrigues'
formula turns into ``R_k · (I + s·K + c·K²)`` with s = sin(wθ_k), c = 1 − cos(wθ_k). The point
is then a linear combination of ten per-point features (1, w, s, c, e1, e2 and the products of
s, c with e1, e2, where (e1, e2) = ρ·(cos α, sin α)) with a 3 × 10 coefficient matrix
precomputed per interval. Per point that leaves the scan angle's cosine and sine (tabulated,
see :func:`_cos_sin`), a short series for s and c, and the product with the coefficients:
one matrix product per interval for dense, time-sorted points (a profiler), a per-point gather
for sparse or unsorted ones. Both paths share the features and agree to ~1e-13 m with the
plain :func:`georeference_poses`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from calib.core import frames
from calib.core.trajectory import Trajectory


@dataclass(frozen=True)
class Mount:
    """Scanner mounting and scanner-level systematic parameters (all SI / radians).

    ``boresight_rad`` and ``nominal_rad`` are (roll, pitch, yaw) of ``R_bs`` and ``R_nom``;
    ``range_offset_m`` δρ and ``scan_angle_offset_rad`` δα are added to the measured values;
    ``time_offset_s`` Δt is added to the point time before the trajectory is sampled.
    """

    lever_arm_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    nominal_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))
    boresight_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))
    range_offset_m: float = 0.0
    scan_angle_offset_rad: float = 0.0
    time_offset_s: float = 0.0

    def __post_init__(self):
        for attr in ("lever_arm_m", "nominal_rad", "boresight_rad"):
            v = np.asarray(getattr(self, attr), dtype=float).reshape(-1)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise ValueError(f"Mount.{attr} must be 3 finite numbers, got {v!r}")
            object.__setattr__(self, attr, v)

    @property
    def r_s_b(self) -> np.ndarray:
        """``R_S^b = R_bs · R_nom``."""
        return frames.mount_matrix(self.boresight_rad, self.nominal_rad)

    def with_boresight(self, boresight_rad) -> Mount:
        return replace(self, boresight_rad=np.asarray(boresight_rad, dtype=float))


#: Below this many points per trajectory interval the per-point gather path is used.
_DENSE_POINTS_PER_INTERVAL = 64
#: Points processed per block: small enough that the block's temporaries stay in cache and in
#: the allocator's free lists (larger blocks are slower, not faster).
_BLOCK = 1 << 14
#: Interval rotation angles above this use exact sin/cos instead of the series.
_SERIES_MAX_ANGLE_RAD = 0.2
#: Table for :func:`_cos_sin`: cos and sin at the multiples of 2π/N.
_TRIG_N = 4096
_TRIG_STEP = 2.0 * np.pi / _TRIG_N
_TRIG_COS = np.cos(np.arange(_TRIG_N) * _TRIG_STEP)
_TRIG_SIN = np.sin(np.arange(_TRIG_N) * _TRIG_STEP)

#: The kernel is linear in these per-point features (row 0 is the constant 1):
#:     x = C_k · [1, w, s, c, e1, e2, s·e1, s·e2, c·e1, c·e2]
#: with w the fraction of interval k, s = sin(wθ_k), c = 1 − cos(wθ_k) (the slerp), and
#: (e1, e2) = ρ·(cos α, sin α) the scan-plane coordinates. C_k (3 × 10) is per interval.
_N_FEATURES = 10


@dataclass(frozen=True)
class _Tables:
    """Per-interval constants of the kernel (leading axis: the trajectory interval)."""

    t0: np.ndarray  # (m,) interval start times
    inv_dt: np.ndarray  # (m,) 1 / interval length
    theta: np.ndarray  # (m,) rotation angle across the interval
    coef: np.ndarray  # (m, 3, 10) C_k, see _N_FEATURES


def _interval_tables(traj: Trajectory, mount: Mount) -> _Tables:
    """With ``R(w) = R_k·(I + s·K + c·K²)`` (Rodrigues, K = [n̂_k]× the interval's unit axis),
    ``x = p_k + w·Δp_k + R(w)·(e1·m2 + e2·m3 + a)`` expands into the ten features' columns."""
    R = traj.r_b_n[:-1]  # (m, 3, 3)
    phi = traj.interval_rotvec  # (m, 3)
    theta = np.linalg.norm(phi, axis=1)
    n_hat = phi / np.where(theta > 0, theta, 1.0)[:, None]
    K = frames.skew(n_hat)
    RK = R @ K
    RKK = RK @ K
    m2, m3 = mount.r_s_b[:, 1], mount.r_s_b[:, 2]  # the scan-plane columns of R_S^b
    lever = mount.lever_arm_m
    t = traj.t_gps_s
    columns = [
        traj.p_lgf_m[:-1] + R @ lever,  # 1
        np.diff(traj.p_lgf_m, axis=0),  # w
        RK @ lever,  # s
        RKK @ lever,  # c
        R @ m2,
        R @ m3,  # e1, e2
        RK @ m2,
        RK @ m3,  # s·e1, s·e2
        RKK @ m2,
        RKK @ m3,  # c·e1, c·e2
    ]
    return _Tables(t[:-1], 1.0 / np.diff(t), theta, np.stack(columns, axis=-1))


#: sin x = x·Σ SIN[k]·x^(2k) and 1 − cos x = x²·Σ VERSIN[k]·x^(2k) (Taylor series).
_SIN_SERIES = [(-1) ** k / math.factorial(2 * k + 1) for k in range(8)]
_VERSIN_SERIES = [(-1) ** k / math.factorial(2 * k + 2) for k in range(8)]


def _series_length(theta_max: float) -> int | None:
    """How many terms of each series make sin and 1 − cos exact to < 1e-17 on |x| ≤ theta_max
    (the first omitted terms are x^(2n+1)/(2n+1)! and a smaller x^(2n+2)/(2n+2)!), or None
    where exact sin/cos are cheaper."""
    if theta_max > _SERIES_MAX_ANGLE_RAD:
        return None
    n = 1
    while theta_max ** (2 * n + 1) / math.factorial(2 * n + 1) >= 1e-17:
        n += 1
    return n


def _sin_versin(x: np.ndarray, n_terms: int | None, s: np.ndarray, c: np.ndarray) -> None:
    """Write sin x into ``s`` and 1 − cos x into ``c``: their series to ``n_terms`` terms each
    (Horner form, in place), or exactly if ``n_terms`` is None."""
    if n_terms is None:
        np.sin(x, out=s)
        np.cos(x, out=c)
        np.subtract(1.0, c, out=c)
        return
    x2 = x * x
    for out, series in ((s, _SIN_SERIES), (c, _VERSIN_SERIES)):
        out[...] = series[n_terms - 1]
        for a in reversed(series[: n_terms - 1]):
            out *= x2
            out += a
    s *= x
    c *= x2


def _cos_sin(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """cos a and sin a, about twice as fast as ``np.cos`` + ``np.sin``; the error is below
    2.5e-16 on [0, 2π), and 1e-15 plus one unit in the last place of a elsewhere.

    a = a_k + r with a_k the nearest multiple of 2π/N (tabulated) and |r| ≤ π/N < 7.7e-4; then
    the angle-sum formulas with cos r ≈ 1 − r²/2 + r⁴/24 and sin r ≈ r − r³/6 (the first
    omitted terms are below 3e-22 and 3e-18).
    """
    k = np.rint(a * (1.0 / _TRIG_STEP))
    r = a - k * _TRIG_STEP
    i = k.astype(np.intp)
    i &= _TRIG_N - 1  # k mod N, also for negative k
    ck, sk = _TRIG_COS.take(i), _TRIG_SIN.take(i)
    r2 = r * r
    sin_r = r2 * (-1.0 / 6.0)
    sin_r += 1.0
    sin_r *= r
    cos_r = r2 * (1.0 / 24.0)
    cos_r -= 0.5
    cos_r *= r2
    cos_r += 1.0
    cos_a = ck * cos_r
    cos_a -= sk * sin_r
    sin_a = sk * cos_r
    sin_a += ck * sin_r
    return cos_a, sin_a


def _features(tab: _Tables, k, t, rho, alpha, n_terms, F: np.ndarray) -> None:
    """Fill the features F (10, b) of b points whose intervals are ``k`` (b ints)."""
    w = F[1]
    np.subtract(t, tab.t0[k], out=w)
    w *= tab.inv_dt[k]
    _sin_versin(w * tab.theta[k], n_terms, F[2], F[3])
    cos_a, sin_a = _cos_sin(alpha)
    np.multiply(rho, cos_a, out=F[4])
    np.multiply(rho, sin_a, out=F[5])
    np.multiply(F[2], F[4], out=F[6])
    np.multiply(F[2], F[5], out=F[7])
    np.multiply(F[3], F[4], out=F[8])
    np.multiply(F[3], F[5], out=F[9])


def georeference(
    t_gps_s,
    range_m,
    scan_angle_rad,
    traj: Trajectory,
    mount: Mount,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """LGF coordinates (n, 3) of raw scanner returns (time, range, scan angle).

    The result is column-major (``out[:, j]`` contiguous) unless ``out`` is given.

    Raises :class:`calib.core.trajectory.TrajectoryError` if the trajectory does not cover a point.
    """
    t = np.asarray(t_gps_s, dtype=float) + mount.time_offset_s
    rho = np.asarray(range_m, dtype=float)
    alpha = np.asarray(scan_angle_rad, dtype=float)
    n = t.size
    if rho.shape != (n,) or alpha.shape != (n,):
        raise ValueError(
            f"georeference: time, range and scan angle must be 1-D arrays of equal length, "
            f"got {t.shape}, {rho.shape}, {alpha.shape}"
        )
    if out is None:
        out = np.empty((3, n)).T  # column-major: each coordinate is contiguous
    rows = out.T
    if n == 0:
        return out
    traj.check_coverage(t)
    tab = _interval_tables(traj, mount)
    theta_max = float(tab.theta.max())
    n_terms = _series_length(theta_max)
    tt = traj.t_gps_s
    d_rho, d_alpha = mount.range_offset_m, mount.scan_angle_offset_rad

    # interval of every point: as runs for time-sorted input (a profiler's stream), where each
    # interval's 3 × 10 coefficients multiply its run of features in one matrix product;
    # gathered per point otherwise
    sorted_times = n == 1 or bool(np.all(t[1:] >= t[:-1]))
    if sorted_times:
        first = int(np.clip(np.searchsorted(tt, t[0], "right") - 1, 0, tt.size - 2))
        last = int(np.clip(np.searchsorted(tt, t[-1], "right") - 1, 0, tt.size - 2))
        # run_start[i]: index of the first point in interval first + i
        run_start = np.concatenate([[0], np.searchsorted(t, tt[first + 1 : last + 1], "left")])
        n_runs = int(np.count_nonzero(np.diff(run_start, append=n)))
        dense = n >= _DENSE_POINTS_PER_INTERVAL * n_runs
    else:
        dense = False
    if not dense:
        k_all = np.clip(np.searchsorted(tt, t, side="right") - 1, 0, tt.size - 2)

    F = np.empty((_N_FEATURES, min(n, _BLOCK)))
    F[0] = 1.0
    with np.errstate(invalid="ignore"):  # NaN inputs give NaN outputs, without warnings
        for lo in range(0, n, _BLOCK):
            hi = min(lo + _BLOCK, n)
            f = F[:, : hi - lo]
            if dense:  # the runs of intervals first + i0 … first + i1 − 1 meet this block
                i0 = int(np.searchsorted(run_start, lo, "right")) - 1
                i1 = int(np.searchsorted(run_start, hi, "left"))
                edges = np.append(np.maximum(run_start[i0:i1], lo), hi) - lo
                k = np.repeat(np.arange(first + i0, first + i1), np.diff(edges))
            else:
                k = k_all[lo:hi]
            _features(tab, k, t[lo:hi], rho[lo:hi] + d_rho, alpha[lo:hi] + d_alpha, n_terms, f)
            if dense:
                for i in np.flatnonzero(np.diff(edges)):
                    a, b = edges[i], edges[i + 1]
                    np.matmul(tab.coef[first + i0 + i], f[:, a:b], out=rows[:, lo + a : lo + b])
            else:
                np.einsum("njf,fn->jn", tab.coef[k], f, out=rows[:, lo:hi])
    return out


@dataclass(frozen=True)
class ScannerObservations:
    """The inverse of georeferencing: what the scanner measured for given LGF points."""

    range_m: np.ndarray
    scan_angle_rad: np.ndarray  # in [0, 2π)
    out_of_plane_m: np.ndarray  # x_S component: 0 when the point lies in the scan plane


def inverse_georeference(p_lgf_m, t_gps_s, traj: Trajectory, mount: Mount) -> ScannerObservations:
    """Range and scan angle (as the scanner reports them, i.e. before δρ, δα) of LGF points
    observed at the given times; ``out_of_plane_m`` says how far each point is from the plane
    the scanner swept at that time."""
    poses = traj.interpolate(np.asarray(t_gps_s, dtype=float) + mount.time_offset_s)
    d_n = np.asarray(p_lgf_m, dtype=float) - poses.p_lgf_m
    v_b = np.einsum("nji,nj->ni", poses.r_b_n, d_n) - mount.lever_arm_m
    r_s = v_b @ mount.r_s_b  # R_S^bᵀ · v_b for every row
    rho = np.hypot(r_s[:, 1], r_s[:, 2])
    alpha = np.arctan2(r_s[:, 2], r_s[:, 1])
    return ScannerObservations(
        range_m=rho - mount.range_offset_m,
        scan_angle_rad=frames.wrap_2pi(alpha - mount.scan_angle_offset_rad),
        out_of_plane_m=r_s[:, 0],
    )


def georeference_poses(poses, range_m, scan_angle_rad, mount: Mount) -> np.ndarray:
    """Georeference with poses already interpolated per point (reference implementation)."""
    r_s = frames.scanner_vector(
        np.asarray(range_m, float) + mount.range_offset_m,
        np.asarray(scan_angle_rad, float) + mount.scan_angle_offset_rad,
    )
    v_b = r_s @ mount.r_s_b.T + mount.lever_arm_m
    return poses.p_lgf_m + np.einsum("nij,nj->ni", poses.r_b_n, v_b)
