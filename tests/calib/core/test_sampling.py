import numpy as np

from calib.core.sampling import random_subset


def test_a_profile_pattern_is_sampled_in_every_sector_where_a_stride_keeps_one():
    """Profiles of 50 returns, 4 % kept: every 25th return is sectors 0 and 25 only; the draw
    keeps every sector about equally."""
    idx = np.arange(50 * 2000)
    sector = idx % 50
    stride = idx[::25]
    assert set(sector[stride].tolist()) == {0, 25}
    kept = random_subset(idx, idx.size // 25, seed=3)
    counts = np.bincount(sector[kept], minlength=50)
    assert kept.size == idx.size // 25 and counts.min() > 0.5 * counts.mean()


def test_the_draw_is_in_order_without_repeats_and_the_same_every_time():
    idx = np.arange(100, 10_100, 3)
    a, b = random_subset(idx, 500, seed=7), random_subset(idx, 500, seed=7)
    assert np.array_equal(a, b) and np.all(np.diff(a) > 0) and np.isin(a, idx).all()
    assert not np.array_equal(a, random_subset(idx, 500, seed=8))
    assert random_subset(idx, idx.size, seed=7) is idx  # nothing to thin
