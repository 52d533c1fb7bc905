"""The checks of one mount-watch block's tie patches (:mod:`calib.watch.block`): which patches
a line sees curved (:func:`curved_patches`) or that moved between lines (:func:`moved_planes`),
the σ of each angle at the calibrated mount (:func:`sigma_at_calibrated`), and the group and
link tests of the patches split along the scene (:func:`patch_groups`, :func:`group_test`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from calib.boresight.adjust import adjust
from calib.boresight.observability import ObservabilityError
from calib.boresight.observations import AdjustmentError, AdjustOptions
from calib.core.georef import Mount

MOVED_Z = 6.0  # robust z of a (patch, line) mean residual beyond which the patch moved
MIN_MOVED_SCALE_M = 0.002  # the robust scale's floor (noise-free data)
HOLD_SIGMA_RAD = 1e-7  # the prior σ that holds an unobserved angle at the calibrated value
MIN_PATCHES_PER_GROUP = 2  # a group of the group test holds at least this many patches


def curved_patches(
    labels: np.ndarray, p_lgf_m: np.ndarray, pass_id: np.ndarray, max_rms_m: float
) -> np.ndarray:
    """The patches (label values, sorted) that some line sees curved: the RMS of that line's
    points about their own best plane (the smallest eigenvalue of their covariance) beyond
    ``max_rms_m``; a (patch, line) of fewer than 3 points is not judged. Each line apart, so
    that a mount change — which tilts one line's points against the other's — does not make a
    patch look curved. Every (patch, line) at once: sums over the points by group, not a mask of
    the whole block per pair (which took two thirds of a block's CPU)."""
    on = np.flatnonzero(labels >= 0)
    if on.size == 0:
        return np.zeros(0, np.int64)
    pid = pass_id[on].astype(np.int64)
    pid -= pid.min()
    n_lines = int(pid.max()) + 1
    key = labels[on].astype(np.int64) * n_lines + pid
    keys, group = np.unique(key, return_inverse=True)
    n = np.bincount(group, minlength=keys.size).astype(float)
    q = p_lgf_m[on]
    mean = np.stack([np.bincount(group, q[:, c], keys.size) for c in range(3)], axis=1) / n[:, None]
    d = q - mean[group]  # about each group's own mean: no cancellation at harbour coordinates
    cov = np.empty((keys.size, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            cov[:, a, b] = cov[:, b, a] = np.bincount(group, d[:, a] * d[:, b], keys.size)
    judged = n >= 3
    smallest = np.linalg.eigvalsh(cov[judged] / (n[judged] - 1.0)[:, None, None])[:, 0]
    curved = keys[judged][np.sqrt(np.maximum(smallest, 0.0)) > max_rms_m] // n_lines
    return np.unique(curved)


def patch_groups(centers_m: np.ndarray, max_groups: int) -> list[np.ndarray] | None:
    """The chosen patches (their centres, LGF) split into contiguous groups along the scene's
    longest horizontal extent — neighbours share a stretch of wall, its waviness, the moment
    each line passed it — or None when there are too few for two groups."""
    n = centers_m.shape[0]
    k = min(max_groups, n // MIN_PATCHES_PER_GROUP)
    if k < 2:
        return None
    xy = centers_m[:, :2] - centers_m[:, :2].mean(axis=0)
    axis = np.linalg.svd(xy, full_matrices=False)[2][0]
    return np.array_split(np.argsort(xy @ axis, kind="stable"), k)


@dataclass(frozen=True)
class GroupTest:
    """The block's patches split into groups along the scene, each solved alone (the free
    angles; the held ones pinned as in the block's solution)."""

    chi2: float  # dispersion: the groups' estimates about their information-weighted mean
    df: int
    limit: float  # dispersion χ² beyond which the block is no verdict
    #: the block's estimate against the groups' combination (a Hausman test): what the block
    #: knows beyond its groups comes only from the POS processes linking them across time
    link_chi2: float = 0.0
    link_df: int = 0
    link_limit: float = float("inf")

    @property
    def factor(self) -> float:
        """The variance factor of the groups' dispersion (≥ 1)."""
        return max(1.0, self.chi2 / self.df) if self.df else 1.0

    @property
    def failed(self) -> str | None:
        """Why the block is no verdict, or None."""
        if self.chi2 > self.limit:
            return (
                f"its tie patch groups disagree (χ² = {self.chi2:.0f} over {self.df} degrees of "
                f"freedom, limit {self.limit:.0f})"
            )
        if self.link_chi2 > self.link_limit:
            return (
                f"its estimate is not its patch groups' (χ² = {self.link_chi2:.1f} over "
                f"{self.link_df} degrees of freedom, limit {self.link_limit:.1f}): it rests on the "
                "POS error model across the lines, not on the patches"
            )
        return None


def group_test(
    sub,
    mount: Mount,
    planes,
    adj: AdjustOptions,
    groups,
    free: np.ndarray,
    full,
    alpha: float,
    max_factor: float,
) -> GroupTest:
    """Each group of patches solved alone (the prior of ``adj`` on the correction).

    **Dispersion**: ``χ² = Σ_g (δ_g − δ̄)ᵀ C_g⁻¹ (δ_g − δ̄)`` about their information-weighted
    mean ``δ̄``, on ``n_free·(G − 1)`` degrees of freedom: a wall that bends, a patch that is not
    one plane from both lines, a hull that moved — each shows as groups that disagree beyond
    their σ. Its χ²/df scales the block's covariance; beyond ``max_factor``
    (:attr:`~calib.watch.block.WatchOptions.max_group_factor`) the block is no verdict.

    **Link**: ``χ² = (δ − δ̄)ᵀ (C̄ − C)⁺ (δ − δ̄)`` of the block's estimate ``δ`` (``full``)
    against the groups' combination (its covariance ``C̄`` with the prior counted once): under
    the model, the block's estimate is the more precise and their difference has covariance
    ``C̄ − C``. What the block knows beyond its groups comes from the POS processes linking
    the groups across time; on an oblique line the wall-normal position drift and yaw both
    grow with the range, and a block that leaned on that link gave yaw 4σ wrong with a flat
    wall and no POS error at all (the beam footprint's noise alone). Beyond the χ² quantile
    ``alpha`` (:attr:`~calib.watch.block.WatchOptions.group_alpha`) the block is no verdict."""
    from scipy import stats

    prior_info = np.diag(1.0 / adj.boresight_prior_rad[1][free] ** 2)  # type: ignore[index]
    deltas, infos = [], []
    for g in groups:
        order = sorted(int(j) for j in g)
        part = sub.of_planes(order)
        try:
            r = adjust(part, mount, [planes[j] for j in order], adj)
        except (ObservabilityError, AdjustmentError, np.linalg.LinAlgError):
            continue
        deltas.append((r.boresight_rad - mount.boresight_rad)[free])
        cov = r.cov_realistic * max(1.0, float(r.sigma0_squared))
        infos.append(np.linalg.inv(cov[np.ix_(free, free)]))
    n_free = int(np.count_nonzero(free))
    df = n_free * (len(deltas) - 1)
    if df <= 0:
        return GroupTest(float("inf"), 0, 0.0)
    mean = np.linalg.solve(sum(infos), sum(w @ d for w, d in zip(infos, deltas, strict=False)))
    chi2 = sum(float((d - mean) @ w @ (d - mean)) for w, d in zip(infos, deltas, strict=False))
    # the combination: each group's information holds the prior once; count it once
    info_comb = sum(infos) - (len(deltas) - 1) * prior_info
    cov_comb = np.linalg.inv(info_comb)
    comb = cov_comb @ sum(w @ d for w, d in zip(infos, deltas, strict=False))
    cov_full = (full.cov_realistic * max(1.0, float(full.sigma0_squared)))[np.ix_(free, free)]
    diff = (full.boresight_rad - mount.boresight_rad)[free] - comb
    link = float(diff @ np.linalg.solve(cov_comb + cov_full, diff))
    link_df = n_free
    link_limit = float(stats.chi2.isf(alpha, link_df))
    return GroupTest(chi2, df, max_factor * df, link, link_df, link_limit)


def sigma_at_calibrated(sub, mount: Mount, planes, adj: AdjustOptions) -> np.ndarray:
    """The σ of each angle (with the correction's prior, scaled by the variance factor when
    above 1) linearized at the **calibrated** boresight — the hypothesis the watch tests.

    Judged at the solution instead, an angle the block barely sees looked resolved: on a pair
    sailed back along one oblique track (montreal seed 3, lines 3–4 and 5–6) yaw moves every
    point the same way from both lines and is not seen at first order; the solution wandered
    to +3.8° and −3.4°, where the second-order terms are large, and its σ there (0.4°) was a
    tenth of what the data say about yaw near the calibrated value. The nuisance unknowns
    (planes, roughness, POS processes) are solved with the boresight pinned; its information
    is the pinned covariance's inverse less the pin."""
    pin = np.full(3, HOLD_SIGMA_RAD)
    res = adjust(sub, mount, planes, replace(adj, boresight_prior_rad=np.stack([mount.boresight_rad, pin])))
    info_rad2 = np.linalg.inv(res.cov_realistic) - np.diag(1.0 / pin**2)
    info_rad2 = 0.5 * (info_rad2 + info_rad2.T) + np.eye(3) / adj.boresight_prior_rad[1] ** 2  # type: ignore[index]
    cov = np.linalg.inv(info_rad2) * max(1.0, float(res.sigma0_squared))
    return np.sqrt(np.clip(np.diag(cov), 0.0, None))


def unresolved(sigma_rad: np.ndarray, max_sigma_rad: float) -> str:
    """Why a block has no verdict when no angle is resolved to ``max_sigma_rad``."""
    parts = ", ".join(
        f"{a} {np.degrees(s):.3f}°" for a, s in zip(("roll", "pitch", "yaw"), sigma_rad, strict=False)
    )
    return f"no angle resolved to {np.degrees(max_sigma_rad):.3f}° at the calibrated mount (σ {parts})"


def pinned_correction(res, mount: Mount, held: np.ndarray, sigma_cal_rad: np.ndarray, factor: float):
    """The correction and its covariance from the solution with the ``held`` angles pinned at
    the calibrated value: the covariance scaled by the variance factor when above 1 and by the
    group test's ``factor``; a held angle's correction is 0 with its σ at the calibrated mount,
    uncorrelated (no evidence)."""
    delta = np.where(held, 0.0, res.boresight_rad - mount.boresight_rad)
    cov = res.cov_realistic * max(1.0, float(res.sigma0_squared)) * factor
    cov[held, :] = 0.0
    cov[:, held] = 0.0
    cov[held, held] = sigma_cal_rad[held] ** 2
    return delta, cov


def moved_planes(obs, res) -> np.ndarray:
    """Indices of the planes of ``obs`` with a (plane, line) mean residual beyond
    :data:`MOVED_Z` robust σ of all such means."""
    used = np.isin(obs.point_ids, res.used_point_ids)
    plane, line = obs.plane_index[used], obs.pass_index[used]
    m = int(line.max()) + 1
    key = plane * m + line
    uniq, inv = np.unique(key, return_inverse=True)
    mean = np.bincount(inv, res.residual_m) / np.bincount(inv)
    dev = np.abs(mean - np.median(mean))
    scale = max(1.4826 * float(np.median(dev)), MIN_MOVED_SCALE_M)
    return np.unique(uniq[dev > MOVED_Z * scale] // m)
