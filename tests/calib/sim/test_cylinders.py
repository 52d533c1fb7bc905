"""Vertical cylinders in the simulator's scene (piles, posts, dolphins): exact ray–cylinder hits
against an independent solution, scan-plane sectors that hold every hit of a profile, piles in
the harbour's production survey and in a scenario file, and scenes without cylinders unchanged."""

from __future__ import annotations

import numpy as np
import pytest

from calib.core.geometry import Rectangle, VerticalCylinder
from calib.core.georef import georeference
from calib.io.configfile import ConfigError
from calib.sim.cylinders import LeaningCylinder
from calib.sim.harbour import harbour_piles, harbour_surfaces
from calib.sim.production import ProductionSpec, simulate_production
from calib.sim.scanning import scan
from calib.sim.scenariofile import load_scenario, parse_scenario
from calib.sim.scene import Scene
from tests.calib.sim.test_scene import _random_scene

NOISE_FREE = {
    "noise.pos.model": "none",
    "noise.scanner.sigma_range_m": 0.0,
    "noise.scanner.beam_divergence_mrad": 0.0,
    "noise.scanner.sigma_scan_angle_deg": 0.0,
}


def _cylinder(name, center, radius, height, refl=0.3) -> VerticalCylinder:
    return VerticalCylinder(
        name=name, center_m=np.asarray(center, float), radius_m=radius, height_m=height, reflectivity=refl
    )


def _random_cylinders(rng, n) -> list[VerticalCylinder]:
    return [
        _cylinder(f"C{i}", rng.uniform(-20, 20, 3), rng.uniform(0.15, 0.6), rng.uniform(2.0, 10.0))
        for i in range(n)
    ]


def _reference_entry(c: VerticalCylinder, o, d):
    """Where rays enter the cylinder's side, by the closest approach of the ray's horizontal
    projection to the axis: (range, inside) with the range NaN where the ray passes beside."""
    q = o[:, :2] - c.center_m[:2]
    dh = d[:, :2]
    a = np.sum(dh * dh, axis=1)
    t_close = -np.sum(q * dh, axis=1) / a
    perp2 = np.sum((q + t_close[:, None] * dh) ** 2, axis=1)
    half = np.sqrt(np.maximum(c.radius_m**2 - perp2, 0.0) / a)
    t = np.where(perp2 <= c.radius_m**2, t_close - half, np.nan)
    z = o[:, 2] + t * d[:, 2]
    inside = np.isfinite(t) & (np.abs(z - c.center_m[2]) <= 0.5 * c.height_m)
    return t, inside


# -- ray–cylinder hits ----------------------------------------------------------------------------


def test_ray_cylinder_hits_equal_an_independent_solution():
    rng = np.random.default_rng(11)
    c = _cylinder("P", [3.0, -2.0, -1.0], 0.45, 6.0)
    n = 40000
    # origins outside, 1–80 m from the axis; rays aimed at points around the pile, beside it and
    # beyond its ends
    az = rng.uniform(0, 2 * np.pi, n)
    dist = rng.uniform(1.0, 80.0, n)
    o = c.center_m + np.column_stack([dist * np.cos(az), dist * np.sin(az), rng.uniform(-8, 8, n)])
    az2 = rng.uniform(0, 2 * np.pi, n)
    r2 = c.radius_m * rng.uniform(0.0, 1.6, n)
    aim = c.center_m + np.column_stack([r2 * np.cos(az2), r2 * np.sin(az2), rng.uniform(-4.5, 4.5, n)])
    d = aim - o
    d /= np.linalg.norm(d, axis=1)[:, None]
    scene = Scene((), ("other",), cylinders=(c,))
    rho, inside = scene.hit_range(0, *o.T, *d.T)
    t_ref, in_ref = _reference_entry(c, o, d)
    assert np.array_equal(inside, in_ref)
    assert inside.sum() > 15000
    np.testing.assert_allclose(rho[inside], t_ref[inside], rtol=0, atol=1e-9)
    beside = np.isnan(t_ref)
    above_below = ~beside & ~in_ref
    assert beside.sum() > 5000
    assert above_below.sum() > 5000
    # the hits lie on the side, within the height; cos incidence from the radial normal
    hits = scene.intersect(o, d, min_range_m=0.3, max_range_m=200.0)
    assert np.array_equal(hits.hit, inside)
    x = o[inside] + hits.range_m[inside, None] * d[inside]
    assert np.abs(c.signed_distance(x)).max() < 1e-9
    assert np.abs(x[:, 2] - c.center_m[2]).max() <= 3.0 + 1e-12
    np.testing.assert_allclose(
        hits.cos_incidence[inside], np.abs(np.sum(d[inside] * c.outward_normals(x), axis=1))
    )
    np.testing.assert_allclose(scene.distance_m(0, x), 0.0, atol=1e-9)
    # vertical rays and rays from inside give no return
    up = scene.intersect(c.center_m + [0.3, 0.0, 5.0], [[0.0, 0.0, -1.0]])
    assert not up.hit.any()
    out = scene.intersect(c.center_m + [0.1, 0.0, 0.0], [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    assert not out.hit.any()


def _leaning(name, center, radius, height, slope_ne) -> LeaningCylinder:
    return LeaningCylinder(
        name=name, center_m=np.asarray(center, float), radius_m=radius, height_m=height, slope_ne=slope_ne
    )


def test_a_leaning_pile_is_hit_on_its_leaning_side_and_an_upright_one_as_before():
    rng = np.random.default_rng(12)
    n = 20000
    o = np.column_stack([rng.uniform(-40, 40, n), rng.uniform(5, 40, n), rng.uniform(-6, 6, n)])
    aim = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), rng.uniform(-4, 4, n)])
    d = aim - o
    d /= np.linalg.norm(d, axis=1)[:, None]
    upright = _cylinder("P", [0.0, 0.0, 0.0], 0.45, 6.0)
    rho_v, in_v = Scene((), ("other",), cylinders=(upright,)).hit_range(0, *o.T, *d.T)
    rho_0, in_0 = Scene(
        (), ("other",), cylinders=(_leaning("P", [0, 0, 0], 0.45, 6.0, (0.0, 0.0)),)
    ).hit_range(0, *o.T, *d.T)
    assert np.array_equal(in_0, in_v) and np.allclose(rho_0[in_v], rho_v[in_v], rtol=0, atol=1e-9)
    lean = _leaning("P", [0, 0, 0], 0.45, 6.0, (np.tan(np.radians(3.0)), np.tan(np.radians(-2.0))))
    rho, inside = Scene((), ("other",), cylinders=(lean,)).hit_range(0, *o.T, *d.T)
    x = o[inside] + rho[inside, None] * d[inside]
    assert inside.sum() > 5000 and np.abs(lean.radial_distance_m(x) - 0.45).max() < 1e-9
    # within its height: the ends are square to the axis, so a rim point lies up to r·sin(lean) beyond
    assert np.abs(x[:, 2]).max() <= 3.0 + 0.45 * np.sin(np.arccos(-lean.axis_up[2])) + 1e-9
    # the top leans north by tan 3° per metre up, the foot south: the hits follow the axis
    top, foot = x[:, 2] < -2.0, x[:, 2] > 2.0
    assert x[top, 0].mean() - x[foot, 0].mean() > 4.0 * np.tan(np.radians(3.0)) * 0.8


def test_the_nearest_of_rectangles_and_cylinders_wins():
    wall = Rectangle.from_orientation(
        "wall", [0.0, 15.0, -3.0], 20.0, 6.0, np.pi / 2, np.radians(270.0), 0.25
    )
    pile = _cylinder("pile", [0.0, 14.0, -3.0], 0.5, 6.0, 0.4)
    scene = Scene((wall,), ("wall", "other"), cylinders=(pile,))
    x = np.linspace(-2.0, 2.0, 401)
    d = np.column_stack([x, np.full_like(x, 15.0), np.full_like(x, -3.0)])
    d /= np.linalg.norm(d, axis=1)[:, None]
    hits = scene.intersect(np.zeros(3), d)
    on_pile = hits.surface == 1
    assert on_pile.sum() > 100
    assert (hits.surface == 0).sum() > 250
    assert hits.hit.all()
    p = d[on_pile] * hits.range_m[on_pile, None]
    assert np.abs(pile.signed_distance(p)).max() < 1e-9
    assert np.all(hits.range_m[on_pile] < 14.5 / d[on_pile, 1])  # in front of the wall
    np.testing.assert_array_equal(scene.reflectivity, [0.25, 0.4])
    assert scene.names == ["wall", "pile"]
    assert len(scene) == 2
    assert list(scene.cylinder_indices) == [1]
    # local coordinates on the pile: arc length from due north, height, radial distance
    a, b, s = scene.local_coordinates(1, [[0.0, 13.5, -4.0]])
    np.testing.assert_allclose([a[0], b[0], s[0]], [0.5 * np.pi * 0.5 * -1, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(scene.normals(1, [[0.0, 13.5, -4.0]]), [[0.0, -1.0, 0.0]])


def test_a_scene_checks_its_cylinders():
    pile = _cylinder("pile", [0.0, 0.0, 0.0], 0.5, 4.0)
    with pytest.raises(ValueError, match="0 rectangles and 1 cylinders but 2 kinds"):
        Scene((), ("other", "other"), cylinders=(pile,))
    with pytest.raises(ValueError, match="a cylinder is background"):
        Scene((), ("target",), cylinders=(pile,))
    wall = Rectangle.from_orientation("pile", [0.0, 15.0, -3.0], 2.0, 2.0, np.pi / 2, 0.0, 0.25)
    with pytest.raises(ValueError, match="repeated: pile"):
        Scene((wall,), ("wall", "other"), cylinders=(pile,))
    with pytest.raises(ValueError, match="not a rectangle"):
        Scene((wall,), ("wall",)).with_rectangles({1: wall})


# -- sectors --------------------------------------------------------------------------------------


def _rotation_with_x(rng, ex) -> np.ndarray:
    """A rotation whose first column is ``ex`` (the scan plane's normal)."""
    ey = np.cross(ex, rng.normal(size=3))
    ey /= np.linalg.norm(ey)
    return np.column_stack([ex, ey, np.cross(ex, ey)])


def _sectored_hits(scene: Scene, sec, p, o, d, alpha):
    """The nearest hit of each ray testing only the surfaces whose sector holds its angle."""
    best = np.full(alpha.size, np.inf)
    surf = np.full(alpha.size, -1)
    for j in np.flatnonzero(sec.hit[p]).tolist():
        inside_sector = np.mod(alpha - sec.start_rad[p, j], 2 * np.pi) <= sec.width_rad[p, j]
        k = np.flatnonzero(inside_sector)
        rho, inside = scene.hit_range(j, *np.broadcast_to(o, (k.size, 3)).T, *d[k].T)
        ok = inside & (rho > 0.3) & (rho <= 119.0) & (rho < best[k])
        best[k[ok]], surf[k[ok]] = rho[ok], j
    return np.where(surf >= 0, best, np.nan), surf


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_sectors_hold_every_ray_that_hits_a_cylinder(seed):
    rng = np.random.default_rng(seed)
    cyls = _random_cylinders(rng, 10)
    cyls[:3] = [  # three leaning up to 8°: their sectors grown by how far the axis strays
        LeaningCylinder(**{**c.__dict__, "slope_ne": tuple(np.tan(np.radians(rng.uniform(-8, 8, 2))))})
        for c in cyls[:3]
    ]
    rects = _random_scene(rng, 6).rectangles
    scene = Scene(rects, ("other",) * 16, cylinders=tuple(cyls))
    n_poses, K = 40, 36000  # 0.01° between rays
    o_list, r_list = [], []
    for _ in range(n_poses):
        c = cyls[rng.integers(len(cyls))]
        o = c.center_m + np.concatenate([rng.uniform(-25, 25, 2), rng.uniform(-6, 6, 1)])
        if np.hypot(*(o - c.center_m)[:2]) < 1.5:
            o[:2] += 2.0
        # a plane through the scanner that passes through a point on the cylinder
        on = c.center_m + [c.radius_m * 0.9, 0.0, rng.uniform(-0.4, 0.4) * c.height_m]
        ex = np.cross(on - o, rng.normal(size=3))
        r_list.append(_rotation_with_x(rng, ex / np.linalg.norm(ex)))
        o_list.append(o)
    origins, rots = np.array(o_list), np.array(r_list)
    sec = scene.scan_sectors(origins, rots[:, :, 0], rots[:, :, 1], rots[:, :, 2], grow_m=0.0)
    assert sec.hit.shape == (n_poses, 16)
    assert np.all(sec.width_rad[:, 6:] < np.pi)
    alpha = np.arange(K) * (2 * np.pi / K)
    n_cyl_hits = 0
    for p in range(n_poses):
        d = np.cos(alpha)[:, None] * rots[p, :, 1] + np.sin(alpha)[:, None] * rots[p, :, 2]
        brute = scene.intersect(origins[p], d, min_range_m=0.3, max_range_m=119.0)
        rng_s, surf_s = _sectored_hits(scene, sec, p, origins[p], d, alpha)
        assert np.array_equal(surf_s, brute.surface)
        np.testing.assert_array_equal(rng_s, brute.range_m)
        n_cyl_hits += int((brute.surface >= 6).sum())
    assert n_cyl_hits > 2000


def test_a_scanner_beside_a_pile_gets_the_full_circle():
    pile = _cylinder("pile", [0.0, 0.0, 0.0], 0.5, 4.0)
    scene = Scene((), ("other",), cylinders=(pile,))
    o = np.array([[0.55, 0.0, 0.0], [10.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    e = np.eye(3)
    # vertical planes across and along the line of sight, and a horizontal one
    sec = scene.scan_sectors(o, e[[1, 1, 2]], e[[0, 0, 0]], e[[2, 2, 1]], grow_m=0.1)
    assert sec.hit.all()
    assert sec.width_rad[0, 0] == pytest.approx(2 * np.pi)
    # the plane holding the axis: the pile's 4.2 m grown height seen from 9.4 m (its grown side)
    assert 2 * np.arctan(2.1 / 9.4) <= sec.width_rad[1, 0] < 2 * np.arctan(2.1 / 9.4) + 0.01
    # the horizontal plane: the grown radius 0.6 m seen from 10 m, at most 10 % more
    assert 2 * np.arcsin(0.06) <= sec.width_rad[2, 0] < 1.1 * 2 * np.arcsin(0.06)


# -- the harbour ----------------------------------------------------------------------------------


def test_the_harbour_has_round_piles_a_dolphin_and_boxed_fenders():
    piles = harbour_piles(80.0)
    dia = np.array([p.diameter_m for p in piles])
    assert len(piles) == 12
    assert np.all((dia >= 0.3) & (dia <= 1.2))
    assert len(set(dia)) >= 5
    row = sorted(p.along_m for p in piles if p.name.startswith("pile_"))
    assert np.all((np.diff(row) >= 5.0) & (np.diff(row) <= 8.0))
    assert sum(p.name.startswith("dolphin_") for p in piles) == 4
    names = {s.name: s for s in harbour_surfaces(80.0)}
    for k in range(12):
        front, a, b = names[f"fender_{k}"], names[f"fender_{k}_side_a"], names[f"fender_{k}_side_b"]
        assert a.width_m == b.width_m == 0.45
        assert abs(np.degrees(a.facing_rad - front.facing_rad)) == pytest.approx(90.0)
        # the box's outermost edge is 0.45 m proud of the wall
        t = front.facing_rad
        proud = front.out_m + 0.5 * front.width_m * abs(np.sin(t))
        assert proud == pytest.approx(0.45)


@pytest.fixture(scope="module")
def harbour_run():
    harbour = load_scenario("harbour", NOISE_FREE)
    spec = ProductionSpec(n_lines=2, line_length_m=80.0, offsets_m=(12.0, 20.0), rate_scale=0.01)
    return simulate_production(harbour, spec, seed=3)


def test_a_harbour_survey_returns_points_on_its_piles(harbour_run):
    r = harbour_run
    scene = r.scene
    assert len(scene.cylinders) == 12
    assert len(scene) == len(scene.rectangles) + 12
    on = np.flatnonzero(r.surface_index >= len(scene.rectangles))
    assert on.size > 200
    hit = np.unique(r.surface_index[on])
    assert hit.size >= 3  # the row's first pile and the dolphin's
    # the noise-free returns, georeferenced with the true mount, lie on their cylinders
    x = georeference(
        r.points.t_gps_s[on],
        r.points.range_m[on],
        r.points.scan_angle_rad[on],
        r.trajectory_true,
        r.mount_true,
    )
    assert np.abs(scene.distance_m(r.surface_index[on], x)).max() < 1e-6
    for j in hit:
        c = scene.cylinder(j)
        assert c is not None
        assert 0.3 <= 2 * c.radius_m <= 1.2
        s = r.surface_index[on] == j
        assert np.abs(c.signed_distance(r.p_true_lgf_m[on][s])).max() < 1e-6
    truth = {c["name"]: c for c in r.truth["cylinders"]}
    assert set(truth) == {c.name for c in scene.cylinders}
    assert all(0.3 <= c["diameter_m"] <= 1.2 and c["height_m"] == pytest.approx(4.5) for c in truth.values())


# -- scenario files -------------------------------------------------------------------------------

PILES_SCENE = """
reference: {lat_deg: 45.5, lon_deg: -73.55}
site: {standoff_m: 15.0}
scene:
  targets:
    - {name: T, up_m: 5.0, size_m: [1.0, 1.0]}
  piles:
    - {name: P1, along_m: 6.0, out_m: 2.0, diameter_m: 0.8, bottom_up_m: -1.5, top_up_m: 6.0}
    - {name: P2, along_m: -9.0, out_m: 1.0, diameter_m: 0.4, bottom_up_m: -1.5, top_up_m: 4.0,
       kind: wall, reflectivity: 0.5}
"""


def test_piles_in_a_scenario_file_become_cylinders():
    sc = parse_scenario(PILES_SCENE)
    assert [p.name for p in sc.piles] == ["P1", "P2"]
    assert sc.piles[1].kind == "wall"
    scene = sc.scene()
    assert scene.names == ["T", "P1", "P2"]
    assert scene.kinds == ("target", "other", "wall")
    c = scene.cylinders[0]
    np.testing.assert_allclose(c.center_m, sc.site_to_lgf(6.0, 2.0, 2.25)[0])
    assert (c.radius_m, c.height_m, c.reflectivity) == (0.4, 7.5, 0.3)
    assert scene.cylinders[1].reflectivity == 0.5
    leaning = parse_scenario(PILES_SCENE, overrides=["scene.piles.P1.lean_deg=[0, 2]"]).scene().cylinders[0]
    assert isinstance(leaning, LeaningCylinder)  # 2° toward the water: its top moves out, to the west here
    np.testing.assert_allclose(leaning.slope_ne, sc.site_to_lgf(0.0, np.tan(np.radians(2.0)), 0.0)[0, :2])
    shipped = load_scenario("montreal_piles")
    dia = [p.diameter_m for p in shipped.piles]
    assert 4 <= len(dia) <= 6
    assert len(set(dia)) == len(dia)
    assert min(dia) >= 0.3
    assert max(dia) <= 1.2
    for p in shipped.piles:
        assert 5.0 <= min(abs(p.along_m - t.along_m) for t in shipped.surfaces if t.kind == "target") <= 15.0
        assert 1.0 <= p.out_m <= 4.0


@pytest.mark.parametrize(
    ("override", "where"),
    [
        ("scene.piles.P1.diameter_m=0", r"scene\.piles\[0\]\.diameter_m: got 0, expected a number > 0"),
        (
            "scene.piles.P1.top_up_m=-2",
            r"scene\.piles\[0\]\.top_up_m: got -2, expected a height above bottom_up_m",
        ),
        ("scene.piles.P2.radius_m=0.3", r"scene\.piles\[1\]\.radius_m: unknown key 'radius_m'"),
        ("scene.piles.P2.kind=target", r"scene\.piles\[1\]\.kind: got 'target', expected one of"),
        ("scene.piles.P2.along_m=x", r"scene\.piles\[1\]\.along_m: got 'x', expected a finite number"),
        ("scene.piles.P2.name=T", r"unique surface names \('T' appears twice\)"),
        (
            "scene.piles.P1.lean_deg=[25, 0]",
            r"scene\.piles\[0\]\.lean_deg\[0\]: got 25, expected a number ≤ 20",
        ),
        ("scene.piles.P1.lean_deg=[1]", r"scene\.piles\[0\]\.lean_deg: .*expected a list of 2 numbers"),
    ],
)
def test_bad_pile_values_name_the_field(override, where):
    with pytest.raises(ConfigError, match=where):
        parse_scenario(PILES_SCENE, overrides=[override])


def test_a_pile_needs_its_diameter():
    with pytest.raises(ConfigError, match=r"scene\.piles\[0\].*diameter_m"):
        parse_scenario(PILES_SCENE.replace("diameter_m: 0.8, ", ""))


# -- scenes without cylinders ---------------------------------------------------------------------


def test_a_scene_without_cylinders_casts_as_before():
    sc = load_scenario("montreal", NOISE_FREE)
    new = sc.scene()
    # the scene built the old way: rectangles, kinds and shapes only
    old = Scene(
        tuple(sc.rectangle(s) for s in sc.surfaces),
        tuple(s.kind for s in sc.surfaces),
        tuple(s.shape for s in sc.surfaces),
    )
    # … and with piles far out of view (they must not disturb the rectangles' returns)
    far = Scene(
        old.rectangles,
        old.kinds + ("other", "other"),
        old.shapes,
        (
            _cylinder("far_a", [5000.0, 0.0, 0.0], 0.5, 5.0),
            _cylinder("far_b", [3000.0, -4000.0, 0.0], 1.0, 5.0),
        ),
    )
    plan = sc.pass_plan()
    from calib.sim.motion import sail

    run = sail(plan, sc.motion, sc.start_gps_s, sc.reference, np.random.default_rng(0))
    mount = sc.truth.true_mount(sc.mount)
    t0, t1 = run.capture_times[plan.passes[0].id]
    a, b, c = (scan(sc.scanner, s, run.trajectory, mount, t0, t1) for s in (new, old, far))
    assert a.range_true_m.size > 1000
    for other in (b, c):
        for f in ("t_gps_s", "alpha_rad", "range_true_m", "surface", "cos_incidence", "p_lgf_m"):
            np.testing.assert_array_equal(getattr(a, f), getattr(other, f))
    # cylinders come after the rectangles: the per-surface arrays keep the rectangles' numbers
    np.testing.assert_array_equal(far.reflectivity[:-2], old.reflectivity)
    sec_old = old.scan_sectors(np.zeros((1, 3)), [[1.0, 0, 0]], [[0, 1.0, 0]], [[0, 0, 1.0]], 0.1)
    sec_far = far.scan_sectors(np.zeros((1, 3)), [[1.0, 0, 0]], [[0, 1.0, 0]], [[0, 0, 1.0]], 0.1)
    np.testing.assert_array_equal(sec_far.start_rad[:, :-2], sec_old.start_rad)
    np.testing.assert_array_equal(sec_far.width_rad[:, :-2], sec_old.width_rad)
    assert not sec_far.hit[:, -2:].any()
