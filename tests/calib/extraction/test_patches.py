"""Tie-patch candidates (calib.extraction.patches): walls from several headings, one heading,
targets kept out, a pile, clutter, a railing, a bollard, a plate across a cell corner,
subsampling, the rejection counters and a million points, on synthetic points."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import cKDTree

from calib.extraction.patches import (
    AUTO_SIZES_M,
    REASONS,
    PatchCandidates,
    PatchError,
    PatchOptions,
    extract_candidates,
)

STANDOFF_M = 15.0  # scanner to surface
NOISE_M = 0.002
HEADINGS_DEG = {1: 0.0, 2: 180.0, 3: 45.0, 4: 225.0}


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def _angle_deg(a, b) -> float:
    return float(np.degrees(np.arccos(np.clip(float(np.dot(a, b)), -1.0, 1.0))))


# A wall of the quay in NED: vertical, 30° off north, the water toward −E (rotated).
WALL_U = _unit([np.cos(np.radians(30.0)), np.sin(np.radians(30.0)), 0.0])  # along the wall
WALL_V = np.array([0.0, 0.0, 1.0])  # down
WALL_N = _unit(np.cross(WALL_V, WALL_U))  # horizontal, toward the water
WALL_C = np.array([103.3, 57.1, 1.2])


class Scene:
    """Points of surfaces from several passes: per point its scanner position and pass id."""

    def __init__(self, seed: int = 0):
        self.rng = np.random.default_rng(seed)
        self.p: list[np.ndarray] = []
        self.origin: list[np.ndarray] = []
        self.pass_id: list[np.ndarray] = []
        self.tag: list[np.ndarray] = []

    def _add(self, p, view, pass_id: int, tag: int) -> None:
        along = self.rng.uniform(-5.0, 5.0, (p.shape[0], 1)) * np.cross(view, [0.0, 0.0, 1.0])
        self.p.append(p)
        self.origin.append(p + STANDOFF_M * np.asarray(view) + along)
        self.pass_id.append(np.full(p.shape[0], pass_id, np.int64))
        self.tag.append(np.full(p.shape[0], tag, np.int64))

    def rectangle(self, center, u, v, half_u, half_v, per_m2, passes, tag=0, noise_m=NOISE_M):
        """A planar rectangle, ``per_m2`` points per m² in each pass; seen along its normal."""
        n = _unit(np.cross(v, u))
        k = int(round(per_m2 * 4 * half_u * half_v))
        for pid in passes:
            a = self.rng.uniform(-half_u, half_u, (k, 1))
            b = self.rng.uniform(-half_v, half_v, (k, 1))
            p = np.asarray(center) + a * u + b * v + self.rng.normal(0.0, noise_m, (k, 1)) * n
            self._add(p, n, pid, tag)

    def cylinder(self, center, radius_m, height_m, per_m2, passes, view, tag=0):
        """The half of a vertical cylinder (a pile) that faces ``view``."""
        view = _unit(view)
        side = np.cross([0.0, 0.0, 1.0], view)
        k = int(round(per_m2 * np.pi * radius_m * height_m))
        for pid in passes:
            t = self.rng.uniform(-np.pi / 2, np.pi / 2, (k, 1))
            z = self.rng.uniform(-height_m / 2, height_m / 2, (k, 1))
            radial = np.cos(t) * view + np.sin(t) * side
            p = np.asarray(center) + radius_m * radial + z * [0.0, 0.0, 1.0]
            p += self.rng.normal(0.0, NOISE_M, (k, 1)) * radial
            self._add(p, view, pid, tag)

    def box(self, lo, hi, per_pass: int, passes, tag=0):
        """A random cloud (hull clutter)."""
        for pid in passes:
            p = self.rng.uniform(lo, hi, (per_pass, 3))
            self._add(p, [0.0, -1.0, 0.0], pid, tag)

    def line(self, a, b, per_m: float, passes, radius_m=0.01, tag=0):
        """Points along a segment, within a tube (a railing)."""
        a, b = np.asarray(a, float), np.asarray(b, float)
        k = int(round(per_m * np.linalg.norm(b - a)))
        for pid in passes:
            t = self.rng.uniform(0.0, 1.0, (k, 1))
            p = a + t * (b - a) + self.rng.normal(0.0, radius_m / 2, (k, 3))
            self._add(p, [0.0, -1.0, 0.0], pid, tag)

    def run(self, exclude=None, headings_deg=HEADINGS_DEG, **options) -> PatchCandidates:
        p, origin, pid = self.arrays()
        ex = np.zeros(p.shape[0], bool) if exclude is None else exclude
        headings = {k: float(np.radians(h)) for k, h in headings_deg.items()}
        res = extract_candidates(p, origin, pid, headings, ex, PatchOptions(**options))
        _check_invariants(res, p.shape[0])
        return res

    def arrays(self):
        return np.vstack(self.p), np.vstack(self.origin), np.concatenate(self.pass_id)

    @property
    def tags(self) -> np.ndarray:
        return np.concatenate(self.tag)


def _check_invariants(res: PatchCandidates, n: int) -> None:
    m = len(res)
    assert set(res.rejected) == set(REASONS)
    assert m + sum(res.rejected.values()) == res.n_cells
    assert res.labels.shape == (n,) and res.labels.min(initial=-1) >= -1 and res.labels.max(initial=-1) < m
    assert np.array_equal(res.n_points, np.bincount(res.labels[res.labels >= 0], minlength=m))
    assert res.normals.shape == (m, 3) and res.centers_m.shape == (m, 3)
    assert res.d_m.shape == res.rms_m.shape == res.n_points.shape == (m,)
    assert np.allclose(np.linalg.norm(res.normals, axis=1), 1.0)
    assert np.allclose(np.einsum("ij,ij->i", res.normals, res.centers_m) + res.d_m, 0.0, atol=1e-9)
    assert len(res.passes) == len(res.names) == m and len(set(res.names)) == m
    assert all(name.startswith("patch") for name in res.names)


def _wall(scene: Scene, passes=(1, 2, 3, 4), per_m2=300.0, half_u=12.0, half_v=1.5, tag=1):
    scene.rectangle(WALL_C, WALL_U, WALL_V, half_u, half_v, per_m2, passes, tag=tag)


def _assert_along(res: PatchCandidates, p: np.ndarray, normal) -> None:
    """Every patch on the plane of ``normal``, facing the scanners, with the noise as its RMS."""
    angle_deg = np.array([_angle_deg(res.normals[k], normal) for k in range(len(res))])
    for k in range(len(res)):
        # within 0.5° or, for the few small pieces at a surface's ends and edges (a few dozen
        # points over 0.2 m), within 4σ of their noise
        q = p[res.labels == k]
        spread_m2 = np.linalg.eigvalsh(np.cov(q.T, bias=True))[1]  # the narrower in-plane axis
        sigma_deg = np.degrees(NOISE_M / np.sqrt(spread_m2 * q.shape[0]))
        assert angle_deg[k] < max(0.5, 4 * sigma_deg)
        assert abs(res.rms_m[k] / NOISE_M - 1.0) < 4.0 / np.sqrt(2.0 * q.shape[0])
        assert len(res.passes[k]) >= 2 and set(res.passes[k]) <= set(HEADINGS_DEG)
    assert np.mean(angle_deg < 0.5) > 0.9 and np.median(angle_deg) < 0.1
    assert np.all(np.abs(res.rms_m / NOISE_M - 1.0)[res.n_points > 500] < 0.1)


# -- the wall ----------------------------------------------------------------------------------


def test_a_wall_from_four_headings_is_covered_by_patches_along_its_normal():
    scene = Scene(1)
    _wall(scene)
    res = scene.run(max_points_per_patch=100_000)
    assert res.size_m in AUTO_SIZES_M and set(res.scores) == set(AUTO_SIZES_M)
    assert len(res) >= 20
    p, _, _ = scene.arrays()
    _assert_along(res, p, WALL_N)
    on = res.labels >= 0
    # the wall, bar the 3σ outliers and the strips along its edges too narrow for a cell of
    # either grid (line-like): 0.3 m of its 3 m height at 1.5 m
    assert on.mean() > 0.85
    residual = np.einsum("ij,ij->i", p[on], res.normals[res.labels[on]]) + res.d_m[res.labels[on]]
    assert np.abs(residual).max() < 4 * NOISE_M


def test_a_sloping_plane_crossing_the_cells_diagonally_is_covered():
    scene = Scene(20)
    n = _unit([0.3, -0.5, 0.8])  # not along any axis of the grid
    u = _unit(np.cross(n, [0.0, 0.0, 1.0]))
    v = np.cross(n, u)
    scene.rectangle([20.3, 7.7, -3.1], u, v, 5.0, 3.0, 200.0, (1, 2, 3, 4))
    res = scene.run(max_points_per_patch=100_000)
    p, _, _ = scene.arrays()
    _assert_along(res, p, np.cross(v, u))
    assert (res.labels >= 0).mean() > 0.9


def test_the_result_is_deterministic():
    scene = Scene(2)
    _wall(scene, half_u=4.0)
    a, b = scene.run(max_points_per_patch=60), scene.run(max_points_per_patch=60)
    assert np.array_equal(a.labels, b.labels) and np.array_equal(a.normals, b.normals)
    assert a.passes == b.passes and a.rejected == b.rejected and a.size_m == b.size_m


def test_a_wall_seen_from_one_heading_gives_no_patch():
    scene = Scene(3)
    _wall(scene, passes=(1, 2), half_u=5.0)
    res = scene.run(headings_deg={1: 0.0, 2: 10.0})  # two passes, the same way
    assert len(res) == 0 and np.all(res.labels == -1)
    assert res.rejected["same heading"] > 0
    one = Scene(3)
    _wall(one, passes=(1,), half_u=5.0)
    res = one.run(size_m=1.0)
    assert len(res) == 0 and res.rejected["few passes"] > 0


def test_headings_across_north_differ_by_their_wrapped_difference():
    scene = Scene(4)
    _wall(scene, passes=(1, 2), half_u=3.0)
    assert len(scene.run(size_m=1.0, headings_deg={1: 350.0, 2: 20.0})) > 0  # 30° apart
    assert len(scene.run(size_m=1.0, headings_deg={1: 350.0, 2: 10.0})) == 0  # 20° apart


# -- what must not become a patch --------------------------------------------------------------


def test_points_on_and_near_a_target_are_not_used():
    scene = Scene(5)
    _wall(scene, half_u=6.0)
    p, _, _ = scene.arrays()
    u = (p - WALL_C) @ WALL_U
    v = (p - WALL_C) @ WALL_V
    target = (np.abs(u - 1.0) < 0.6) & (np.abs(v) < 0.6)
    res = scene.run(exclude=target, size_m=1.0)
    assert len(res) > 0 and np.all(res.labels[target] == -1)
    dist, _ = cKDTree(p[target]).query(p[res.labels >= 0])
    assert dist.min() > 0.2
    big = (np.abs(u - 1.0) < 1.6) & (np.abs(v) < 1.6)  # covers whole cells
    res = scene.run(exclude=big, size_m=1.0)
    assert res.rejected["near a target"] > 0 and np.all(res.labels[big] == -1)


def test_a_pile_is_not_planar_except_in_cells_where_it_is():
    scene = Scene(6)
    scene.cylinder([40.2, 10.3, 0.7], 0.5, 3.0, 400.0, (1, 2, 3, 4), view=[0.0, -1.0, 0.0])
    p, _, _ = scene.arrays()
    for size in (None, 1.0):
        res = scene.run(size_m=size)
        assert res.rejected["not planar"] > 0
        for k in range(len(res)):  # a patch is planar within max_rms_m, measured afresh
            q = p[res.labels == k]
            assert np.sqrt(np.mean((q @ res.normals[k] + res.d_m[k]) ** 2)) <= 0.02


def test_hull_clutter_gives_no_patch():
    scene = Scene(7)
    scene.box([0.0, 0.0, 0.0], [12.0, 12.0, 3.0], 40_000, (1, 2, 3, 4))
    res = scene.run()
    assert len(res) == 0 and res.rejected["not planar"] > 0


def test_a_railing_is_line_like():
    scene = Scene(8)
    scene.line([0.3, 5.2, -1.1], [10.3, 5.2, -1.1], 300.0, (1, 2, 3, 4))
    res = scene.run(size_m=1.0)
    assert len(res) == 0 and res.rejected["line-like"] > 0


def test_a_bollard_clipping_a_cell_is_dropped_by_the_refit():
    scene = Scene(9)
    north, east, down = np.eye(3)
    # a wall along north at E = 10.5 (mid-cell), facing +E; a compact clump 0.3 m in front of it
    # in the cell N ∈ [5, 6), E ∈ [10, 11), D ∈ [1, 2): 1/6 of its points, enough to keep the
    # plain RMS of the first fit above 0.1 m (3 × RMS would keep the clump) but not the robust one
    scene.rectangle([5.0, 10.5, 1.5], north, down, 3.0, 1.5, 150.0, HEADINGS_DEG)
    for pid in HEADINGS_DEG:
        scene._add(np.array([5.5, 10.8, 1.5]) + scene.rng.normal(0.0, 0.03, (30, 3)), east, pid, tag=2)
    res = scene.run(size_m=1.0, max_points_per_patch=100_000)
    assert np.all(res.labels[scene.tags == 2] == -1)
    p, _, _ = scene.arrays()
    k = res.labels[np.argmin(np.linalg.norm(p - [5.5, 10.5, 1.5], axis=1))]
    assert k >= 0 and _angle_deg(res.normals[k], [0.0, 1.0, 0.0]) < 0.5
    assert 0.8 * NOISE_M < res.rms_m[k] < 1.2 * NOISE_M


def test_a_plate_across_a_cell_corner_is_found_whole_by_the_shifted_grid():
    scene = Scene(10)
    # a 0.9 m plate facing +E, centred on a corner of the 1 m grid: each quarter alone is too
    # sparse (≈ 10 points per pass), the whole plate is not (≈ 32)
    u, v = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])
    scene.rectangle([5.0, 10.3, 2.0], u, v, 0.45, 0.45, 40.0, (1, 2, 3, 4))
    res = scene.run(size_m=1.0)
    assert len(res) == 1
    assert (res.labels == 0).mean() > 0.95
    assert _angle_deg(res.normals[0], [0.0, 1.0, 0.0]) < 1.0


# -- subsampling -------------------------------------------------------------------------------


def test_subsampling_caps_the_points_and_keeps_every_pass_and_the_extent():
    scene = Scene(11)
    _wall(scene, half_u=4.0, per_m2=600.0)
    cap = 100
    full = scene.run(size_m=1.0, max_points_per_patch=100_000)
    res = scene.run(size_m=1.0, max_points_per_patch=cap)
    assert len(res) == len(full) > 0
    assert np.all(res.n_points <= cap) and np.all(res.n_points[full.n_points >= cap] == cap)
    p, _, pid = scene.arrays()
    for k in range(len(res)):
        sub, whole = res.labels == k, full.labels == k
        assert np.all(whole[sub])  # a subset of the same patch
        share = cap // len(res.passes[k])
        for j in res.passes[k]:  # each pass its share, or all it has
            has = np.count_nonzero(whole & (pid == j))
            assert np.count_nonzero(sub & (pid == j)) >= min(share, has)
        # spread over the patch: each quadrant about its centroid keeps its share of the points
        c = p[whole].mean(axis=0)
        axes = np.linalg.svd(p[whole] - c, full_matrices=False)[2][:2]
        share_all, share_sub = (_quadrant_shares((p[w] - c) @ axes.T) for w in (whole, sub))
        assert np.abs(share_sub - share_all).max() < 0.1
        assert np.linalg.norm(p[sub].mean(axis=0) - c) < 0.1 * res.size_m


def _quadrant_shares(uv: np.ndarray) -> np.ndarray:
    q = (uv[:, 0] > 0).astype(int) * 2 + (uv[:, 1] > 0)
    return np.bincount(q, minlength=4) / q.size


def test_subsampling_is_balanced_over_passes_of_unequal_density():
    scene = Scene(12)
    _wall(scene, passes=(1, 2), half_u=3.0, per_m2=800.0)
    _wall(scene, passes=(3,), half_u=3.0, per_m2=40.0)
    res = scene.run(size_m=1.0, max_points_per_patch=90, headings_deg={1: 0.0, 2: 180.0, 3: 90.0})
    _, _, pid = scene.arrays()
    for k in range(len(res)):
        if 3 in res.passes[k]:
            sparse = np.count_nonzero((res.labels == k) & (pid == 3))
            assert sparse >= 15  # the sparse pass keeps its points; the dense ones fill the rest
            assert res.n_points[k] == 90


# -- size, scale, errors -----------------------------------------------------------------------


def test_an_empty_input_gives_no_patch():
    res = extract_candidates(np.empty((0, 3)), np.empty((0, 3)), np.empty(0, np.int64), {}, np.empty(0, bool))
    assert len(res) == 0 and res.n_cells == 0 and res.labels.shape == (0,)


def test_a_million_points_run():
    scene = Scene(13)
    scene.rectangle(WALL_C, WALL_U, WALL_V, 100.0, 2.5, 225.0, (1, 2, 3, 4))
    scene.box(WALL_C - [20.0, 20.0, 3.0], WALL_C + [20.0, 20.0, 3.0], 25_000, (1, 2, 3, 4))
    p, _, _ = scene.arrays()
    assert p.shape[0] >= 1_000_000
    exclude = np.zeros(p.shape[0], bool)
    exclude[::5000] = True  # the KD-tree at scale too
    # one size (the automatic one tries three, ≈ 3× the time: see the module docstring)
    res = scene.run(exclude=exclude, size_m=1.0)
    assert len(res) > 500 and np.all(res.n_points <= 400) and np.all(res.labels[exclude] == -1)


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"size_m": 0.0}, "size_m"),
        ({"min_points_per_pass": 2}, "min_points_per_pass"),
        ({"min_passes": 0}, "min_passes"),
        ({"min_heading_spread_deg": 190.0}, "min_heading_spread_deg"),
        ({"max_rms_m": -1.0}, "max_rms_m"),
        ({"min_extent_ratio": 1.5}, "min_extent_ratio"),
        ({"max_points_per_patch": 20}, "max_points_per_patch"),
        ({"exclusion_margin_m": float("nan")}, "exclusion_margin_m"),
    ],
)
def test_bad_options_are_refused_by_name(change, words):
    with pytest.raises(PatchError, match=words):
        replace(PatchOptions(), **change)


def test_inconsistent_input_is_refused_by_name():
    p = np.zeros((4, 3))
    ok = (p, p + 1.0, np.array([1, 1, 2, 2]), {1: 0.0, 2: 1.0}, np.zeros(4, bool))
    extract_candidates(*ok)
    with pytest.raises(PatchError, match="origin_lgf_m"):
        extract_candidates(p, p[:3], *ok[2:])
    with pytest.raises(PatchError, match="pass_id"):
        extract_candidates(p, p, np.array([1.0, 1.0, 2.0, 2.0]), *ok[3:])
    with pytest.raises(PatchError, match=r"pass ids \[2\]"):
        extract_candidates(p, p, ok[2], {1: 0.0}, ok[4])
    with pytest.raises(PatchError, match="exclude"):
        extract_candidates(*ok[:4], np.zeros(4, int))
    bad = p.copy()
    bad[2, 1] = np.nan
    with pytest.raises(PatchError, match="point 2"):
        extract_candidates(bad, *ok[1:])
