"""Expected level of the C2C after a calibration: what the sensors' noise, the POS errors and the
result's own boresight σ leave between two passes whose patches agree exactly.

With a perfect mount the distance of a compared return q to the local plane of the reference
is its own noise along the normal minus the error of the local plane at q:

    d = e_q − Σ_j w_j e_j,    w_j = 1/k + (x_q − c)ᵀ S⁻¹ (x_j − c)

(the least-squares plane through the k neighbours j with in-plane coordinates x_j, centroid c
and scatter S, evaluated at q), so ``var d = σ_q² + Σ_j w_j² σ_j²`` and, for equal σ,
``Σ_j w_j² = h(q) = 1/k + (x_q − c)ᵀ S⁻¹ (x_q − c)``, the leverage of q in the local fit.
The median of |d| over a patch is then the median of a mixture of half-normals of variances
``σ²(1 + h)``: for an evenly sampled plane 0.87 σ with k = 6 and 0.73 σ with k = 12 (the
leverage has a heavy tail: neighbourhoods whose centroid lies off the compared point).
A profiler's sampling is anisotropic (scan lines), so some neighbourhoods are nearly collinear,
their planes tilt freely about the line and the distances grow
(:func:`calib.assess.surfaces.collinear_fraction` counts them; above 10 % a note suggests a
larger k); the expected level is therefore computed with C2C itself on the real sampling
(:func:`expected_c2c`: both patches put on one plane, synthetic normal errors with each
return's σ). The σ along the normal comes from the site's scanner sigmas and the geometry,
``σ_ρ² (n·∂x/∂ρ)² + σ_α² (n·∂x/∂α)²``. POS errors are correlated in time (docs/architecture.md §7): during
the few seconds a pass sees a surface they act as one offset per pass, of variance
``Σ σ_c² n_c²`` (position) plus ``Σ σ_k² ((r × n)·a_k)²`` (attitude; r from the INS to the
return, a_k the axes of roll, pitch and heading), independent between passes; *expected* adds
the two passes' offsets to the scanner noise, *expected (scanner)* leaves them out. One pair of
passes draws one offset, so its median scatters: the 95th percentile of the median over the
draws is the *upper* bound the verdict uses; a second bound adds the relative offset the
result's own boresight σ allows, ``(J_A − J_B)·δb`` with J the derivative of each return along
the normal by the boresight angles and δb ~ N(0, Σ_b)
(realistic σ and correlation of result.json).
"""

from __future__ import annotations

import numpy as np

from calib.assess.c2c import c2c
from calib.assess.results import ANGLES
from calib.core.georef import Mount, georeference

_ALPHA_STEP_RAD = 1e-6


def expected_c2c(
    q_m: np.ndarray,
    ref_m: np.ndarray,
    normal,
    var_q_m2: np.ndarray,
    var_ref_m2: np.ndarray,
    k: int,
    offset_basis_m: np.ndarray | None = None,
    draws: int = 8,
    offset_draws: int = 256,
    seed: int = 0,
) -> tuple[float, float]:
    """(median, 95th percentile of the patch's median) of the C2C of two patches that agree
    exactly but for their errors.

    Both patches are put on one plane (their in-plane positions kept, so the sampling and C2C's
    local planes are the real ones) and each return gets a normal error N(0, var); C2C gives
    the signed distances e of ``draws`` such draws. Offsets of the compared returns
    ``o = offset_basis_m @ z``, z ~ N(0, I) (a POS offset common to a pass, the effect of the
    boresight's σ), are then added to e for ``offset_draws`` draws of z (each with one of the
    noise draws) — what C2C gives for offsets small against the patch. The 95th percentile of
    the per-draw medians bounds the median one pair of passes can show."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    c = q_m.mean(axis=0)
    base_q = q_m - np.outer((q_m - c) @ n, n)
    base_r = ref_m - np.outer((ref_m - c) @ n, n)
    rng = np.random.default_rng(seed)
    sq, sr = np.sqrt(var_q_m2), np.sqrt(var_ref_m2)
    e = []
    for _ in range(draws):
        q = base_q + np.outer(rng.standard_normal(len(q_m)) * sq, n)
        r = base_r + np.outer(rng.standard_normal(len(ref_m)) * sr, n)
        e.append(c2c(q, r, k, orient_direction=n).signed())
    if offset_basis_m is None:
        d = np.abs(np.stack(e, axis=1))
    else:
        m = int(np.clip(4_000_000 // max(len(q_m), 1), 32, offset_draws))
        z = rng.standard_normal((offset_basis_m.shape[1], m))
        d = np.abs(np.stack([e[i % draws] for i in range(m)], axis=1) + offset_basis_m @ z)
    return float(np.median(d)), float(np.percentile(np.median(d, axis=0), 95.0))


def boresight_covariance(result: dict) -> tuple[np.ndarray, str]:
    """(3, 3) covariance (rad²) of a result's boresight from its realistic σ (else the scaled
    σ) and its correlation matrix; and which σ it used."""
    from calib.assess.history import validate_result

    v = validate_result(result)
    kind = "realistic" if v["sigma_realistic_deg"] is not None else "scaled"
    sig = np.radians([v[f"sigma_{kind}_deg"][a] for a in ANGLES])
    return np.asarray(v["correlation"]) * np.outer(sig, sig), kind


def boresight_normal_jacobian(
    t_gps_s, range_m, scan_angle_rad, traj, mount: Mount, normal, step_rad: float = 1e-6
) -> np.ndarray:
    """(n, 3) derivative of each return's position along ``normal`` by the boresight roll,
    pitch and yaw (central differences)."""
    n = np.asarray(normal, float)
    out = np.empty((len(t_gps_s), 3))
    for j in range(3):
        e = np.zeros(3)
        e[j] = step_rad
        hi = georeference(
            t_gps_s, range_m, scan_angle_rad, traj, mount.with_boresight(mount.boresight_rad + e)
        )
        lo = georeference(
            t_gps_s, range_m, scan_angle_rad, traj, mount.with_boresight(mount.boresight_rad - e)
        )
        out[:, j] = ((hi - lo) @ n) / (2.0 * step_rad)
    return out


def scanner_normal_variance(
    t_gps_s,
    range_m,
    scan_angle_rad,
    traj,
    mount: Mount,
    normal,
    sigma_range_m: float,
    sigma_scan_angle_rad: float,
) -> np.ndarray:
    """Variance of each return along ``normal`` from the range and scan-angle noise:
    ``σ_ρ² (n·∂x/∂ρ)² + σ_α² (n·∂x/∂α)²`` (the derivatives by georeferencing)."""
    n = np.asarray(normal, float)
    x = georeference(t_gps_s, range_m, scan_angle_rad, traj, mount)
    dx_rho = x - georeference(t_gps_s, np.zeros_like(range_m), scan_angle_rad, traj, mount)
    dx_rho /= np.maximum(np.asarray(range_m, float), 1e-9)[:, None]
    dx_alpha = (
        georeference(t_gps_s, range_m, np.asarray(scan_angle_rad) + _ALPHA_STEP_RAD, traj, mount) - x
    ) / _ALPHA_STEP_RAD
    return (sigma_range_m * (dx_rho @ n)) ** 2 + (sigma_scan_angle_rad * (dx_alpha @ n)) ** 2


def pos_normal_variance(
    t_gps_s, p_m, traj, mount: Mount, normal, sigma_position_m, sigma_attitude_rad
) -> np.ndarray:
    """Variance along ``normal`` of each return's displacement by the POS errors (position
    N, E, D and roll, pitch, heading; the trajectory's per-epoch σ when it has them, else the
    given ones)."""
    n = np.asarray(normal, float)
    poses = traj.interpolate(np.asarray(t_gps_s, float) + mount.time_offset_s)
    shape = (len(p_m), 3)
    sp = poses.sigma_p_m if poses.sigma_p_m is not None else np.broadcast_to(sigma_position_m, shape)
    sa = (
        poses.sigma_rpy_rad if poses.sigma_rpy_rad is not None else np.broadcast_to(sigma_attitude_rad, shape)
    )
    var = (sp**2) @ (n**2)
    rxn = np.cross(np.asarray(p_m, float) - poses.p_lgf_m, n)
    h, pitch = poses.rpy_rad[:, 2], poses.rpy_rad[:, 1]
    a_head = np.broadcast_to([0.0, 0.0, 1.0], rxn.shape)
    a_pitch = np.stack([-np.sin(h), np.cos(h), np.zeros_like(h)], axis=1)  # Rz(ψ)·e_y
    a_roll = np.stack(
        [np.cos(h) * np.cos(pitch), np.sin(h) * np.cos(pitch), -np.sin(pitch)], axis=1
    )  # Rz(ψ)·Ry(θ)·e_x
    for j, a in enumerate((a_roll, a_pitch, a_head)):
        var = var + (sa[:, j] * np.einsum("ij,ij->i", rxn, a)) ** 2
    return var
