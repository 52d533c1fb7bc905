"""The block's curvature check (:func:`calib.watch.patchtests.curved_patches`)."""

import numpy as np

from calib.watch.patchtests import curved_patches


def rms_about_own_plane(q: np.ndarray) -> float:
    """The oracle: the RMS of the points about their best plane, from their SVD."""
    return float(np.linalg.svd(q - q.mean(axis=0), compute_uv=False)[-1] / np.sqrt(q.shape[0] - 1))


def test_a_patch_is_curved_when_one_line_sees_it_rough_beyond_the_limit():
    """Flat patches at harbour coordinates, one of them rough (3 cm) in one line only, one with
    two points in a line (not judged), labels −1 ignored; against the SVD of every pair."""
    rng = np.random.default_rng(5)
    n = 6000
    labels = rng.integers(-1, 12, n)
    pass_id = rng.choice([7, 11, 4002], n)
    p = np.column_stack([rng.uniform(0, 1.5, n), rng.uniform(0, 1.5, n), np.zeros(n)])
    p += [3.2e5, 5.04e6, 12.0]
    p[:, 2] += 0.004 * rng.standard_normal(n)
    rough = (labels == 3) & (pass_id == 11)
    p[rough, 2] += 0.03 * rng.standard_normal(rough.sum())
    few = np.flatnonzero((labels == 5) & (pass_id == 4002))
    labels[few[2:]] = -1  # two points of patch 5 in line 4002: not judged
    p[few[:2], 2] += 1.0  # (far off its plane: would be curved if judged)
    expected = [
        j
        for j in range(12)
        if any(
            (m := (labels == j) & (pass_id == k)).sum() >= 3 and rms_about_own_plane(p[m]) > 0.015
            for k in (7, 11, 4002)
        )
    ]
    assert expected == [3]
    assert curved_patches(labels, p, pass_id, 0.015).tolist() == [3]
    assert curved_patches(labels, p, pass_id, 0.001).tolist() == list(range(12))  # 4 mm noise
    assert curved_patches(np.full(n, -1), p, pass_id, 0.015).size == 0
