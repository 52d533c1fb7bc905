"""Tie-cylinder candidates (calib.extraction.cylinders): piles seen by two to four passes in front
of a quay wall, over the ground, next to a fender-like box and a shed corner; a pile seen by one
pass, targets kept out, subsampling, determinism, empty and malformed input, on synthetic points
(NED: "up" is −z)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import cKDTree

from calib.core.geometry import VerticalCylinder
from calib.extraction.cylinders import (
    REASONS,
    CylinderCandidates,
    CylinderError,
    CylinderOptions,
    extract_cylinders,
)

NOISE_M = 0.005  # range noise, along the beam
GROUND_Z_M = 2.0  # the ground, 2 m below the LGF origin
TOP_Z_M = -1.0  # the piles' tops
#: per pass: the azimuth (from north toward east) from the scene toward the track, and the
#: track's heading; passes 1 and 2 run along the quay both ways, 3 and 4 come in obliquely
VIEW_AZ_DEG = {1: 270.0, 2: 270.0, 3: 315.0, 4: 225.0, 5: 290.0}
HEADINGS_DEG = {1: 0.0, 2: 180.0, 3: 45.0, 4: 135.0, 5: 20.0}  # pass 5: 20° off pass 1
#: per pass: its POS error, which moves all its points (2 cm horizontally, 1 cm vertically)
OFFSET_M = {
    k: np.array([0.02 * np.cos(np.radians(a)), 0.02 * np.sin(np.radians(a)), 0.01 * np.sign(a - 150.0)])
    for k, a in {1: 20.0, 2: 140.0, 3: 250.0, 4: 300.0, 5: 80.0}.items()
}
#: the piles: centre (north, east), radius, passes
PILES = (
    ((2.0, 0.0), 0.15, (1, 2)),
    ((6.0, 0.0), 0.3, (1, 2, 3)),
    ((10.0, 0.2), 0.45, (1, 2, 3, 4)),
    ((14.0, 0.3), 0.6, (3, 4)),
    ((18.0, 0.0), 0.25, (2, 4)),
)
WALL_EAST_M = 2.0  # the quay wall's face, 2 m behind the piles (the water is to the west)
BOX = ((8.0, -2.5), (0.6, 0.4))  # a fender-like box on the ground: centre, size (north, east)
CORNER = (16.0, -2.5)  # the south-west corner of a shed: walls 1 m to the north and east of it
TAG_GROUND, TAG_WALL, TAG_BOX, TAG_CORNER, TAG_PILE = 1, 2, 3, 4, 10  # pile k: TAG_PILE + k


def _view(pass_id: int) -> np.ndarray:
    az = np.radians(VIEW_AZ_DEG[pass_id])
    return np.array([np.cos(az), np.sin(az), 0.0])


class Scene:
    """Points of the scene's surfaces, pass by pass: each surface seen from its pass's side only,
    with range noise along the beam and the pass's offset."""

    def __init__(self, seed: int = 0):
        self.rng = np.random.default_rng(seed)
        self.p: list[np.ndarray] = []
        self.pass_id: list[np.ndarray] = []
        self.tag: list[np.ndarray] = []

    def _add(self, p: np.ndarray, pass_id: int, tag: int, noise_dir) -> None:
        p = p + self.rng.normal(0.0, NOISE_M, (p.shape[0], 1)) * np.asarray(noise_dir) + OFFSET_M[pass_id]
        self.p.append(p)
        self.pass_id.append(np.full(p.shape[0], pass_id, np.int64))
        self.tag.append(np.full(p.shape[0], tag, np.int64))

    def pile(
        self,
        center,
        radius_m,
        passes,
        tag,
        per_m2=1500.0,
        top_m=TOP_Z_M,
        bottom_m=GROUND_Z_M,
        lean_ne=(0.0, 0.0),
    ):
        """The half of a vertical cylinder that faces each pass, ``per_m2`` points per m² seen;
        ``lean_ne``: its axis displaced that much (north, east) per metre up."""
        for pid in passes:
            view = _view(pid)
            side = np.cross([0.0, 0.0, 1.0], view)
            k = int(round(per_m2 * 2 * radius_m * (bottom_m - top_m)))
            s = self.rng.uniform(-1.0, 1.0, (k, 1))  # uniform across the beam, as a scanner sees it
            radial = np.sqrt(1.0 - s * s) * view + s * side
            z = self.rng.uniform(top_m, bottom_m, (k, 1)) * np.array([0.0, 0.0, 1.0])
            lean = -z[:, 2:] * np.array([lean_ne[0], lean_ne[1], 0.0])
            self._add(np.r_[center, 0.0] + radius_m * radial + z + lean, pid, tag, view)

    def face(self, corner, u, half_u_m, top_m, bottom_m, passes, tag, per_m2=800.0):
        """A vertical rectangle from ``corner`` along ``u`` (2 × ``half_u_m``) between the heights
        ``top_m`` and ``bottom_m``, seen by the passes on the side of its normal."""
        u = np.r_[np.asarray(u, float), 0.0]
        normal = np.cross(u, [0.0, 0.0, 1.0])  # left of u, seen from above (NED)
        for pid in passes:
            cos_i = float(np.dot(normal, _view(pid)))
            sign = 1.0 if cos_i > 0 else -1.0
            k = int(round(per_m2 * abs(cos_i) * 2 * half_u_m * (bottom_m - top_m)))
            a = self.rng.uniform(0.0, 2 * half_u_m, (k, 1)) * u
            z = self.rng.uniform(top_m, bottom_m, (k, 1)) * np.array([0.0, 0.0, 1.0])
            self._add(np.r_[corner, 0.0] + a + z, pid, tag, sign * normal)

    def ground(self, lo, hi, passes, holes, per_m2=150.0):
        """The ground between (north, east) ``lo`` and ``hi``, but under the ``holes`` (centre,
        radius)."""
        for pid in passes:
            k = int(round(per_m2 * np.prod(np.subtract(hi, lo))))
            xy = self.rng.uniform(lo, hi, (k, 2))
            for c, r in holes:
                xy = xy[np.hypot(*(xy - c).T) > r]
            self._add(
                np.column_stack([xy, np.full(xy.shape[0], GROUND_Z_M)]), pid, TAG_GROUND, [0.0, 0.0, 1.0]
            )

    def run(self, exclude=None, headings_deg=None, **options) -> CylinderCandidates:
        p, pid = self.arrays()
        ex = np.zeros(p.shape[0], bool) if exclude is None else exclude
        headings = {k: float(np.radians(h)) for k, h in (headings_deg or HEADINGS_DEG).items()}
        res = extract_cylinders(p, pid, headings, ex, CylinderOptions(**options))
        _check_invariants(res, p.shape[0])
        return res

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        return np.vstack(self.p), np.concatenate(self.pass_id)

    @property
    def tags(self) -> np.ndarray:
        return np.concatenate(self.tag)


def _check_invariants(res: CylinderCandidates, n: int) -> None:
    m = len(res)
    assert set(res.rejected) == set(REASONS)
    assert m + sum(res.rejected.values()) == res.n_components
    assert res.labels.shape == res.leaning_points.shape == (n,)
    assert res.labels.min(initial=-1) >= -1
    assert res.labels.max(initial=-1) < m
    assert np.array_equal(res.n_points, np.bincount(res.labels[res.labels >= 0], minlength=m))
    assert res.centers_m.shape == (m, 3)
    assert res.radius_m.shape == res.height_m.shape == res.rms_m.shape == res.arc_deg.shape == (m,)
    assert len(res.passes) == len(res.names) == m
    assert len(set(res.names)) == m
    assert all(name.startswith("cyl_") for name in res.names)


def _quay(scene: Scene, piles=PILES, pile_passes=None) -> None:
    """The piles, the wall behind them, the ground, the box and the corner."""
    every = (1, 2, 3, 4)
    for k, (c, r, passes) in enumerate(piles):
        scene.pile(c, r, passes if pile_passes is None else pile_passes, TAG_PILE + k)
    scene.face((21.0, WALL_EAST_M), (-1.0, 0.0), 11.0, -1.5, GROUND_Z_M, every, TAG_WALL)  # faces west
    (bx, by), (sx, sy) = BOX
    lo_x, lo_y = bx - sx / 2, by - sy / 2
    box_top_m = 0.0
    scene.face((lo_x + sx, lo_y), (-1.0, 0.0), sx / 2, box_top_m, GROUND_Z_M, every, TAG_BOX)  # west
    scene.face((lo_x + sx, lo_y + sy), (0.0, -1.0), sy / 2, box_top_m, GROUND_Z_M, every, TAG_BOX)  # north
    scene.face((lo_x, lo_y), (0.0, 1.0), sy / 2, box_top_m, GROUND_Z_M, every, TAG_BOX)  # south
    cx, cy = CORNER
    scene.face((cx + 1.0, cy), (-1.0, 0.0), 0.5, -1.0, GROUND_Z_M, every, TAG_CORNER)  # west wall
    scene.face((cx, cy), (0.0, 1.0), 0.5, -1.0, GROUND_Z_M, every, TAG_CORNER)  # south wall
    holes = [(np.asarray(c), r) for c, r, _ in piles] + [
        (np.asarray(BOX[0]), 0.4),
        (np.array(CORNER) + 0.5, 0.75),
    ]
    scene.ground((-1.0, -5.0), (21.0, WALL_EAST_M), every, holes)


def _truth_center(c, passes) -> np.ndarray:
    """The axis as the mean of its passes sees it: the passes' mean offset is the datum."""
    return np.r_[c, 0.5 * (TOP_Z_M + GROUND_Z_M)] + np.mean([OFFSET_M[k] for k in passes], axis=0)


def _match(res: CylinderCandidates, c) -> int:
    """The candidate whose axis is nearest (north, east) ``c``."""
    return int(np.argmin(np.hypot(*(res.centers_m[:, :2] - c).T)))


def test_every_pile_is_found_with_its_axis_and_radius_and_nothing_else():
    scene = Scene(1)
    _quay(scene)
    res = scene.run()
    p, _ = scene.arrays()
    tags = scene.tags
    assert len(res) == len(PILES)
    for k, (c, r, passes) in enumerate(PILES):
        j = _match(res, c)
        truth = _truth_center(c, passes)
        assert np.hypot(*(res.centers_m[j, :2] - truth[:2])) < 0.01
        assert abs(res.radius_m[j] - r) < 0.01
        assert abs(res.centers_m[j, 2] - truth[2]) < 0.05
        assert abs(res.height_m[j] - (GROUND_Z_M - TOP_Z_M)) < 0.05
        assert res.passes[j] == passes
        # the noise seen across the circle (the range noise's radial part: √⅔ of it over a half
        # sampled evenly across the beam), the passes' offsets removed
        assert abs(res.rms_m[j] / (NOISE_M * np.sqrt(2.0 / 3.0)) - 1.0) < 0.1
        assert 170.0 < res.arc_deg[j] < 360.0
        # no wall; the ground only at the foot, where it touches the pile's surface
        stray = (res.labels == j) & (tags != TAG_PILE + k)
        assert np.all(tags[stray] == TAG_GROUND)
        assert np.count_nonzero(stray) <= 4
        assert np.all(np.abs(p[stray, 2] - GROUND_Z_M) < 0.05)
        assert np.all(np.abs(res.cylinders()[j].signed_distance(p[stray])) < 0.03)
        assert res.n_points[j] == 400
    on = tags[res.labels >= 0]
    assert not np.isin(on, [TAG_WALL, TAG_BOX, TAG_CORNER]).any()
    assert res.rejected["too wide"] == 1  # the wall
    assert res.rejected["not circular"] == 2  # the box and the corner
    assert sum(res.rejected.values()) == 3


def test_the_cylinders_are_vertical_cylinders_of_the_geometry():
    scene = Scene(2)
    _quay(scene)
    res = scene.run()
    cyls = res.cylinders(reflectivity=0.4)
    assert all(isinstance(c, VerticalCylinder) for c in cyls)
    assert [c.name for c in cyls] == res.names == [f"cyl_{k:03d}" for k in range(1, len(PILES) + 1)]
    p, _ = scene.arrays()
    for k, cyl in enumerate(cyls):
        assert cyl.reflectivity == 0.4
        assert cyl.radius_m == res.radius_m[k]
        assert np.array_equal(cyl.center_m, res.centers_m[k])
        d = cyl.signed_distance(p[res.labels == k])
        assert np.sqrt(np.mean(d**2)) < 3 * NOISE_M  # with the passes' offsets in


def test_a_pile_a_few_cells_off_the_wall_is_found_and_one_against_it_is_lost():
    scene = Scene(12)
    scene.face((10.0, WALL_EAST_M), (-1.0, 0.0), 5.0, -1.5, GROUND_Z_M, (1, 3, 4), TAG_WALL)
    scene.pile((3.0, WALL_EAST_M - 0.6), 0.3, (1, 3, 4), TAG_PILE)  # 0.3 m off the wall
    scene.pile((7.0, WALL_EAST_M - 0.32), 0.3, (1, 3, 4), TAG_PILE + 1)  # 2 cm off: the known limit
    res = scene.run()
    assert len(res) == 1
    assert np.hypot(*(res.centers_m[0, :2] - _truth_center((3.0, WALL_EAST_M - 0.6), (1, 3, 4))[:2])) < 0.01
    assert res.rejected == {r: int(r == "too wide") for r in REASONS}  # the wall and its pile


def test_the_result_is_deterministic():
    scene = Scene(3)
    _quay(scene)
    a, b = scene.run(), scene.run()
    assert np.array_equal(a.labels, b.labels)
    assert a.names == b.names
    assert a.passes == b.passes
    for name in ("centers_m", "radius_m", "height_m", "rms_m", "arc_deg", "n_points"):
        assert np.array_equal(getattr(a, name), getattr(b, name))
    assert a.rejected == b.rejected


# -- the rules ---------------------------------------------------------------------------------


def test_a_pile_seen_by_one_pass_is_rejected_as_few_passes():
    scene = Scene(4)
    scene.pile((2.0, 0.0), 0.3, (1, 3), TAG_PILE)
    scene.pile((6.0, 0.0), 0.3, (1,), TAG_PILE + 1)
    scene.ground((-1.0, -3.0), (9.0, 2.0), (1, 3), [(np.array([2.0, 0.0]), 0.3), (np.array([6.0, 0.0]), 0.3)])
    res = scene.run()
    assert len(res) == 1
    assert res.passes == [(1, 3)]
    assert np.hypot(*(res.centers_m[0, :2] - _truth_center((2.0, 0.0), (1, 3))[:2])) < 0.01
    assert res.rejected == {r: int(r == "few passes") for r in REASONS}
    assert np.all(res.labels[scene.tags == TAG_PILE + 1] == -1)


def test_passes_too_close_in_heading_and_too_few_points_are_counted():
    scene = Scene(5)
    scene.pile((2.0, 0.0), 0.3, (1, 5), TAG_PILE)  # 20° apart
    scene.pile((6.0, 0.0), 0.3, (1, 2), TAG_PILE + 1, per_m2=60.0)  # 108 points per pass
    res = scene.run(min_points_per_pass=120)
    assert len(res) == 0
    assert res.rejected == {r: int(r in ("same heading", "few points")) for r in REASONS}
    res = scene.run(min_heading_spread_deg=15.0, min_points_per_pass=60)
    assert len(res) == 2
    assert res.passes == [(1, 5), (1, 2)]
    assert np.all(np.abs(res.radius_m - 0.3) < 0.01)


def test_a_thin_post_a_stub_and_a_glimpse_are_rejected_by_their_shape():
    scene = Scene(6)
    scene.pile((2.0, 0.0), 0.06, (1, 3), TAG_PILE)  # a thin post: r < min_radius_m
    scene.pile((6.0, 0.0), 0.3, (1, 3), TAG_PILE + 1, top_m=GROUND_Z_M - 0.7)  # a stub of 0.7 m
    for pid in (1, 2):  # a large pile, seen ±20° about the beam only (between two others)
        view, side = _view(pid), np.cross([0.0, 0.0, 1.0], _view(pid))
        t = scene.rng.uniform(-np.radians(20.0), np.radians(20.0), (3000, 1))
        z = scene.rng.uniform(TOP_Z_M, GROUND_Z_M, (3000, 1)) * np.array([0.0, 0.0, 1.0])
        radial = np.cos(t) * view + np.sin(t) * side
        scene._add(np.array([10.0, 0.0, 0.0]) + 0.6 * radial + z, pid, TAG_PILE + 2, view)
    res = scene.run()
    assert len(res) == 0
    assert res.rejected == {r: {"radius": 1, "short": 1, "narrow arc": 1}.get(r, 0) for r in REASONS}
    assert len(scene.run(min_radius_m=0.05, min_height_m=0.5, min_arc_deg=30.0)) == 3


def test_a_leaning_pile_is_rejected_and_an_upright_one_kept():
    """The adjustment models upright cylinders: a pile leaning 0.5° (its axis 2.6 cm off over its
    3 m) is rejected as ``leaning`` (0.3–1° biased roll by 1σ on montreal_piles), one leaning
    0.03° is kept."""
    scene = Scene(7)
    slope = np.tan(np.radians(0.5))
    scene.pile((2.0, 0.0), 0.3, (1, 2, 3), TAG_PILE, lean_ne=(0.6 * slope, 0.8 * slope))
    small = np.tan(np.radians(0.03))
    scene.pile((8.0, 0.0), 0.3, (1, 2, 3), TAG_PILE + 1, lean_ne=(small, 0.0))
    res = scene.run()
    assert len(res) == 1 and res.centers_m[0, 0] > 5.0, res.centers_m
    assert res.rejected == {r: {"leaning": 1}.get(r, 0) for r in REASONS}
    # the leaning pile's points are marked (no patch may be cut on them), the upright one's are not
    tags = scene.tags
    assert (
        res.leaning_points[tags == TAG_PILE].mean() > 0.9 and not res.leaning_points[tags != TAG_PILE].any()
    )
    assert len(scene.run(max_lean_deg=1.0)) == 2


def test_points_on_and_near_a_target_never_enter():
    scene = Scene(7)
    _quay(scene)
    p, _ = scene.arrays()
    c, r, passes = PILES[2]
    # a target board strapped around the pile, 0.3 m high
    exclude = (scene.tags == TAG_PILE + 2) & (p[:, 2] > 0.0) & (p[:, 2] < 0.3)
    res = scene.run(exclude=exclude, max_points_per_cylinder=100_000)
    assert len(res) == len(PILES)
    assert np.all(res.labels[exclude] == -1)
    dist, _ = cKDTree(p[exclude]).query(p[res.labels >= 0], k=1)
    assert dist.min() > 0.2  # the margin
    j = _match(res, c)
    assert np.hypot(*(res.centers_m[j, :2] - _truth_center(c, passes)[:2])) < 0.01
    assert abs(res.radius_m[j] - r) < 0.01
    assert np.count_nonzero(res.labels == j) > 0.6 * np.count_nonzero(scene.tags == TAG_PILE + 2)
    free = scene.run(max_points_per_cylinder=100_000)  # without the board: those points are in
    assert np.count_nonzero(free.labels[exclude] == _match(free, c)) > 0.9 * np.count_nonzero(exclude)


# -- subsampling -------------------------------------------------------------------------------


def test_a_dense_pile_is_subsampled_over_its_passes_and_its_height():
    scene = Scene(8)
    r = 0.4
    per_m2 = 25_000 / (2 * r * (GROUND_Z_M - TOP_Z_M))  # 25 000 points per pass
    scene.pile((2.0, 0.0), r, (1, 2, 3, 4), TAG_PILE, per_m2=per_m2)
    p, pid = scene.arrays()
    assert p.shape[0] == 100_000
    res = scene.run()
    assert len(res) == 1
    assert res.n_points[0] == 400
    for k in (1, 2, 3, 4):
        on = (res.labels == 0) & (pid == k)
        assert np.count_nonzero(on) == 100
        top = res.centers_m[0, 2] - res.height_m[0] / 2  # the members' span, all passes
        bins = np.floor((p[on, 2] - top) / res.height_m[0] * 8).astype(int)
        per_bin = np.bincount(np.clip(bins, 0, 7), minlength=8)
        assert per_bin.min() == 12  # 100 points over 8 bins
        assert per_bin.max() == 13
    assert abs(res.radius_m[0] - r) < 0.002  # fitted on all of them


def test_a_sparse_pass_keeps_its_points_and_the_dense_ones_fill_the_rest():
    scene = Scene(9)
    scene.pile((2.0, 0.0), 0.3, (1, 2), TAG_PILE, per_m2=2000.0)
    scene.pile((2.0, 0.0), 0.3, (3,), TAG_PILE, per_m2=40.0)
    _, pid = scene.arrays()
    res = scene.run()
    assert len(res) == 1
    assert res.passes == [(1, 2, 3)]
    assert res.n_points[0] == 400
    sparse = np.count_nonzero(pid == 3)
    assert sparse >= 15
    kept = [np.count_nonzero((res.labels == 0) & (pid == k)) for k in (1, 2, 3)]
    # all of its points but a few outliers and those in columns too sparse to be vertical on their
    # own (the edge of its half that the dense passes do not see)
    assert kept[2] >= 0.8 * sparse
    assert abs(kept[0] - kept[1]) <= 1


# -- size, scale, errors -----------------------------------------------------------------------


def test_an_empty_input_gives_no_cylinder():
    res = extract_cylinders(np.empty((0, 3)), np.empty(0, np.int64), {}, np.empty(0, bool))
    assert len(res) == 0
    assert res.n_components == 0
    assert res.labels.shape == (0,)
    assert res.centers_m.shape == (0, 3)
    assert res.cylinders() == []
    scene = Scene(10)
    scene.pile((2.0, 0.0), 0.3, (1, 3), TAG_PILE)
    p, _ = scene.arrays()
    res = scene.run(exclude=np.ones(p.shape[0], bool))  # all on targets
    assert len(res) == 0
    assert res.n_components == 0
    assert np.all(res.labels == -1)


def test_a_million_points_run():
    scene = Scene(11)
    _quay(scene)
    p, pid = scene.arrays()
    blocks = int(np.ceil(1_000_000 / p.shape[0]))
    p = np.vstack([p + [25.0 * i, 0.0, 0.0] for i in range(blocks)])  # quays end to end
    pid = np.tile(pid, blocks)
    exclude = np.zeros(p.shape[0], bool)
    exclude[::5000] = True  # the KD-tree at scale too
    headings = {k: float(np.radians(h)) for k, h in HEADINGS_DEG.items()}
    res = extract_cylinders(p, pid, headings, exclude)
    _check_invariants(res, p.shape[0])
    assert p.shape[0] >= 1_000_000
    assert len(res) == blocks * len(PILES)
    assert np.all(res.n_points <= 400)
    assert np.all(res.labels[exclude] == -1)
    assert res.rejected["too wide"] == blocks
    assert res.rejected["not circular"] == 2 * blocks


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"cell_m": 0.0}, "cell_m"),
        ({"min_column_height_m": -1.0}, "min_column_height_m"),
        ({"min_radius_m": float("nan")}, "min_radius_m"),
        ({"max_radius_m": 0.05}, "max_radius_m"),
        ({"min_height_m": -0.5}, "min_height_m"),
        ({"max_rms_m": 0.0}, "max_rms_m"),
        ({"max_lean_deg": 0.0}, "max_lean_deg"),
        ({"min_arc_deg": 400.0}, "min_arc_deg"),
        ({"min_passes": 0}, "min_passes"),
        ({"min_points_per_pass": 2}, "min_points_per_pass"),
        ({"min_heading_spread_deg": 190.0}, "min_heading_spread_deg"),
        ({"max_points_per_cylinder": 20}, "max_points_per_cylinder"),
        ({"exclusion_margin_m": float("inf")}, "exclusion_margin_m"),
    ],
)
def test_bad_options_are_refused_by_name(change, words):
    with pytest.raises(CylinderError, match=words):
        replace(CylinderOptions(), **change)


def test_malformed_input_is_refused_by_name():
    p = np.zeros((4, 3))
    ok = (p, np.array([1, 1, 2, 2]), {1: 0.0, 2: 1.0}, np.zeros(4, bool))
    extract_cylinders(*ok)
    with pytest.raises(CylinderError, match=r"p_lgf_m has shape \(4, 2\)"):
        extract_cylinders(p[:, :2], *ok[1:])
    with pytest.raises(CylinderError, match=r"pass_id has shape \(3,\)"):
        extract_cylinders(p, ok[1][:3], *ok[2:])
    with pytest.raises(CylinderError, match="pass_id has dtype"):
        extract_cylinders(p, np.array([1.0, 1.0, 2.0, 2.0]), *ok[2:])
    with pytest.raises(CylinderError, match=r"pass ids \[2\]"):
        extract_cylinders(p, ok[1], {1: 0.0}, ok[3])
    with pytest.raises(CylinderError, match="heading of pass 2"):
        extract_cylinders(p, ok[1], {1: 0.0, 2: float("nan")}, ok[3])
    with pytest.raises(CylinderError, match="exclude"):
        extract_cylinders(*ok[:3], np.zeros(5, bool))
    with pytest.raises(CylinderError, match="exclude"):
        extract_cylinders(*ok[:3], np.zeros(4, int))
    bad = p.copy()
    bad[2, 1] = np.nan
    with pytest.raises(CylinderError, match="point 2"):
        extract_cylinders(bad, *ok[1:])
    assert issubclass(CylinderError, ValueError)
