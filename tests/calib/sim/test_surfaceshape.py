"""Real walls: a surface's waviness (smooth, its RMS and wavelengths as configured) and
roughness (a fixed texture), the same wall on every run and from every pass; rays return the
range to the displaced surface, flat stays bit-identical, targets stay untouched, and the
scenario keys are validated."""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest

from calib.core.geometry import Rectangle
from calib.core.georef import georeference
from calib.io.configfile import ConfigError
from calib.sim.scenario import with_flat_surfaces
from calib.sim.scenariofile import SCENARIO_DIR, load_scenario, parse_scenario
from calib.sim.scene import Scene
from calib.sim.simulate import simulate
from calib.sim.surfaceshape import WAVINESS_COMPONENTS, DisplacementField, SurfaceShape

NOISE_FREE = {
    "noise.pos.model": "none",
    "noise.scanner.sigma_range_m": 0.0,
    "noise.scanner.beam_divergence_mrad": 0.0,
    "noise.scanner.sigma_scan_angle_deg": 0.0,
}
FLAT = {"scene.flat_surfaces": True}


def _grid(f: DisplacementField, step_m: float):
    a = np.arange(-f.half_width_m + step_m / 2, f.half_width_m, step_m)
    b = np.arange(-f.half_height_m + step_m / 2, f.half_height_m, step_m)
    A, B = np.meshgrid(a, b, indexing="ij")
    return A, B


# -- the field ------------------------------------------------------------------------------


def test_waviness_has_its_rms_zero_mean_and_tilt_and_is_smooth():
    f = SurfaceShape(0.01, (3.0, 8.0), 0.0).field("quay_wall", 6.0, 2.2)
    assert f is not None
    A, B = _grid(f, 0.01)
    h = f.height_m(A, B)
    assert np.sqrt(np.mean(h**2)) == pytest.approx(0.01, rel=1e-3)  # RMS over the rectangle
    # the rectangle is the surface's least-squares plane: no mean, no tilt
    coef = np.linalg.lstsq(np.column_stack([np.ones(A.size), A.ravel(), B.ravel()]), h.ravel(), rcond=None)[0]
    assert abs(coef[0]) < 1e-5 and abs(coef[1]) * 3.0 < 1e-5 and abs(coef[2]) * 1.1 < 1e-5
    # a few components, wavelengths inside the range and spanning it
    wl = f.wavelength_m
    assert wl.size == WAVINESS_COMPONENTS and 3 <= WAVINESS_COMPONENTS <= 6
    assert np.all((wl >= 3.0) & (wl <= 8.0))
    step = (8.0 / 3.0) ** (1 / WAVINESS_COMPONENTS)
    assert wl.min() < 3.0 * step and wl.max() > 8.0 / step
    # smooth: the gradient is the derivative and the curvature is bounded by Σ A·k²
    ga, gb = f.waviness_gradient(A, B)
    d = 1e-3
    fd = (f.height_m(A + d, B) - f.height_m(A - d, B)) / (2 * d)
    np.testing.assert_allclose(fd, ga, rtol=0, atol=1e-7)
    curvature = np.sum(np.abs(f.amplitude_m) * (2 * np.pi / wl) ** 2)
    second = (f.height_m(A + d, B) - 2 * h + f.height_m(A - d, B)) / d**2
    assert np.abs(second).max() <= curvature * 1.01
    assert np.hypot(ga, gb).max() < 0.05  # a few cm over metres
    # a fixed property of the surface's name: the same wall every time, another wall elsewhere
    again = SurfaceShape(0.01, (3.0, 8.0), 0.0).field("quay_wall", 6.0, 2.2)
    np.testing.assert_array_equal(again.height_m(A, B), h)
    other = SurfaceShape(0.01, (3.0, 8.0), 0.0).field("other_wall", 6.0, 2.2)
    assert np.abs(other.height_m(A, B) - h).max() > 0.005


def test_waviness_energy_lies_in_the_configured_wavelength_band():
    """On a long wall the 2-D spectrum of h has its energy between 1/λmax and 1/λmin."""
    f = SurfaceShape(0.02, (2.0, 5.0), 0.0).field("long_wall", 80.0, 40.0)
    step = 0.2
    A, B = _grid(f, step)
    win = np.outer(np.hanning(A.shape[0]), np.hanning(A.shape[1]))
    P = np.abs(np.fft.fft2(f.height_m(A, B) * win)) ** 2
    fa = np.fft.fftfreq(A.shape[0], step)[:, None]
    fb = np.fft.fftfreq(A.shape[1], step)[None, :]
    k = np.hypot(fa, fb)  # cycles per metre
    band = (k >= 0.85 / 5.0) & (k <= 1.15 / 2.0)
    assert P[band].sum() / P.sum() > 0.95
    assert np.sqrt(np.mean(f.height_m(A, B) ** 2)) == pytest.approx(0.02, rel=0.02)


def test_roughness_is_a_fixed_mm_texture():
    f = SurfaceShape(0.0, (3.0, 8.0), 0.001).field("quay_wall", 6.0, 2.2)
    rng = np.random.default_rng(0)
    a, b = rng.uniform(-3.0, 3.0, 200_000), rng.uniform(-1.1, 1.1, 200_000)
    r = f.height_m(a, b)
    assert np.sqrt(np.mean(r**2)) == pytest.approx(0.001, rel=0.05)
    assert abs(r.mean()) < 1e-4
    # the same at the same place, whatever else is evaluated with it and in whichever order
    idx = rng.permutation(a.size)[:5000]
    np.testing.assert_array_equal(f.height_m(a[idx], b[idx]), r[idx])
    np.testing.assert_array_equal(f.height_m(a[idx[:7]], b[idx[:7]]), r[idx[:7]])
    # continuous (1 mm apart: nearly the same) and uncorrelated beyond a few cells
    near = f.height_m(a + 0.001, b)
    far = f.height_m(a + 0.2, b + 0.1)
    assert np.corrcoef(near, r)[0, 1] > 0.95
    assert abs(np.corrcoef(far, r)[0, 1]) < 0.05


def test_roughness_lookup_table_is_the_hash(monkeypatch):
    """The node deviates are tabulated around the surface and hashed beyond: the same values."""
    import calib.sim.surfaceshape as surfaceshape

    shape = SurfaceShape(0.01, (3.0, 8.0), 0.001)
    tabulated = shape.field("quay_wall", 6.0, 2.2)
    assert tabulated._node_table is not None  # built lazily: now, before the limit drops
    monkeypatch.setattr(surfaceshape, "_MAX_TABLE_NODES", 0)
    hashed = shape.field("quay_wall", 6.0, 2.2)
    rng = np.random.default_rng(1)
    a, b = rng.uniform(-8.0, 8.0, 50_000), rng.uniform(-5.0, 5.0, 50_000)  # inside and beyond the table
    np.testing.assert_array_equal(tabulated.height_m(a, b), hashed.height_m(a, b))
    assert hashed._node_table is None


def test_shape_of_another_size_or_flat():
    assert SurfaceShape().flat and SurfaceShape().field("x", 1.0, 1.0) is None
    assert SurfaceShape(0.0, (3.0, 8.0), 0.0).field("x", 1.0, 1.0) is None
    with pytest.raises(ValueError, match="wavelengths"):
        SurfaceShape(0.01, (8.0, 3.0))
    with pytest.raises(ValueError, match="negative"):
        SurfaceShape(-0.01)


# -- ray casting ----------------------------------------------------------------------------


def _wall(shape=None) -> Scene:
    wall = Rectangle.from_orientation("quay_wall", [0.0, 15.0, -5.0], 6.0, 2.2, np.pi / 2, np.radians(270.0))
    return Scene((wall,), ("wall",), (shape,))


def test_rays_return_the_range_to_the_displaced_surface():
    shape = SurfaceShape(0.01, (3.0, 8.0), 0.001)
    scene, flat = _wall(shape), _wall()
    rng = np.random.default_rng(3)
    # rays from many places toward the wall, incidences up to ~75°
    o = np.column_stack([rng.uniform(-30, 30, 40000), rng.uniform(5, 12, 40000), rng.uniform(-3, 1, 40000)])
    aim = np.column_stack(
        [rng.uniform(-3.2, 3.2, 40000), np.full(40000, 15.0), rng.uniform(-6.2, -3.8, 40000)]
    )
    d = aim - o
    d /= np.linalg.norm(d, axis=1)[:, None]
    hits, plane = scene.intersect(o, d), flat.intersect(o, d)
    h = hits.hit
    assert h.sum() > 25000
    x = o[h] + hits.range_m[h, None] * d[h]
    # on the displaced surface, inside the rectangle (exact edges)
    assert np.abs(scene.distance_m(0, x)).max() < 1e-12
    assert scene.rectangles[0].contains(x, margin_m=1e-12).all()
    # first order: ρ = ρ_plane + h / cos(incidence); the rest is |h(hit) − h(plane hit)|/cos,
    # at most the largest slope G times the correction times tan(incidence)
    both = h & plane.hit
    xp = o[both] + plane.range_m[both, None] * d[both]
    cos_plane = plane.cos_incidence[both]
    first = plane.range_m[both] - scene.displacement_m(0, xp) / cos_plane
    correction = np.abs(hits.range_m[both] - plane.range_m[both])
    err = np.abs(hits.range_m[both] - first)
    f = scene.fields[0]
    A, B = _grid(f, 0.005)
    g = np.hypot(*np.gradient(f.height_m(A, B), 0.005))
    assert 0.05 < g.max() < 0.5
    tan = np.sqrt(1 - cos_plane**2) / cos_plane
    assert np.all(err <= 1.1 * g.max() * correction * tan + 1e-12)
    assert np.median(correction) > 0.004 and np.median(err) < 0.1 * np.median(correction)
    # the normal at the hit carries the waviness's tilt
    tilt = np.degrees(np.arccos(np.clip(scene.normals(0, x) @ scene.rectangles[0].normal, -1, 1)))
    assert 0.1 < tilt.max() < 3.0


def test_a_wall_point_seen_from_another_place_has_the_same_displacement():
    scene = _wall(SurfaceShape(0.01, (3.0, 8.0), 0.001))
    rng = np.random.default_rng(4)
    n = 5000
    aim = np.column_stack([rng.uniform(-2.8, 2.8, n), np.full(n, 15.0), rng.uniform(-5.9, -4.1, n)])
    oa = np.array([-12.0, 0.0, 0.0])  # two viewpoints ~ 40° apart
    ob = np.array([10.0, 3.0, -1.0])
    da = (aim - oa) / np.linalg.norm(aim - oa, axis=1)[:, None]
    ha = scene.intersect(oa, da)
    assert ha.hit.all()
    xa = oa + ha.range_m[:, None] * da
    db = (xa - ob) / np.linalg.norm(xa - ob, axis=1)[:, None]
    hb = scene.intersect(ob, db)
    xb = ob + hb.range_m[:, None] * db
    np.testing.assert_allclose(xb, xa, rtol=0, atol=1e-10)
    sa = scene.rectangles[0].signed_distance(xa)
    np.testing.assert_allclose(scene.rectangles[0].signed_distance(xb), sa, rtol=0, atol=1e-10)
    assert sa.std() > 0.005


def test_a_flat_shape_changes_nothing_bit_for_bit():
    rng = np.random.default_rng(5)
    o = rng.uniform(-5, 5, (5000, 3))
    d = rng.normal(0.0, 2.0, (5000, 3)) + [0.0, 15.0, -5.0] - o
    d /= np.linalg.norm(d, axis=1)[:, None]
    a = _wall().intersect(o, d)
    b = _wall(SurfaceShape(0.0, (3.0, 8.0), 0.0)).intersect(o, d)
    assert 500 < a.hit.sum() < 4500
    for f in ("range_m", "surface", "cos_incidence"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))


# -- the simulator --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def montreal():
    return simulate("montreal", seed=4, overrides=NOISE_FREE), simulate(
        "montreal", seed=4, overrides={**NOISE_FREE, **FLAT}
    )


def test_simulated_returns_lie_on_the_wavy_wall(montreal):
    r, _ = montreal
    wall = r.scene.names.index("quay_wall")
    assert r.scene.fields[wall] is not None
    x = georeference(
        r.points.t_gps_s, r.points.range_m, r.points.scan_angle_rad, r.trajectory_true, r.mount_true
    )
    np.testing.assert_allclose(x, r.p_true_lgf_m, rtol=0, atol=1e-9)
    assert np.abs(r.scene.distance_m(r.surface_index, x)).max() < 1e-9
    w = r.surface_index == wall
    off = r.scene.rectangles[wall].signed_distance(x[w])
    assert np.sqrt(np.mean(off**2)) == pytest.approx(np.hypot(0.01, 0.001), rel=0.15)
    # the same wall from every pass: each pass's offsets are the field at its points
    for p in r.plan.passes:
        s = r.points.pass_id[w] == p.id
        np.testing.assert_allclose(off[s], r.scene.displacement_m(wall, x[w][s]), rtol=0, atol=1e-9)
    assert r.truth["background"][0]["shape"]["waviness"]["amplitude_m"] == 0.01


def test_wall_points_of_one_pass_are_met_by_rays_from_another(montreal):
    """The points one pass sees on the wall, aimed at from the scanner positions of the
    reciprocal pass, are hit exactly there: the wall is the same whichever pass looks."""
    r, _ = montreal
    wall = r.scene.names.index("quay_wall")
    geom = replace(r.mount_true, range_offset_m=0.0)
    pa, pb = r.plan.passes[0].id, r.plan.passes[1].id
    sa = (r.points.pass_id == pa) & (r.surface_index == wall)
    sb = r.points.pass_id == pb
    xa = r.p_true_lgf_m[sa][::5]
    tb = r.points.t_gps_s[sb]
    ob_all = georeference(tb, np.zeros(tb.size), r.points.scan_angle_rad[sb], r.trajectory_true, geom)[::20]
    # from each point, the pass-b scanner position nearest along the wall
    u = r.scene.rectangles[wall].u_axis
    ob = ob_all[np.argmin(np.abs((xa @ u)[:, None] - (ob_all @ u)[None, :]), axis=1)]
    d = (xa - ob) / np.linalg.norm(xa - ob, axis=1)[:, None]
    hits = r.scene.intersect(ob, d, 0.3, 119.0)
    seen = hits.surface == wall  # not hidden behind a target from there
    assert seen.sum() > 0.8 * len(xa) > 400
    xb = ob[seen] + hits.range_m[seen, None] * d[seen]
    np.testing.assert_allclose(xb, xa[seen], rtol=0, atol=1e-9)


def test_targets_are_untouched_by_the_wavy_wall(montreal):
    wavy, flat = montreal
    for r in (wavy, flat):
        assert all(r.scene.fields[i] is None for i in r.scene.indices("target"))
    tw, tf = wavy.target_index >= 0, flat.target_index >= 0
    assert tw.sum() > 3000
    np.testing.assert_array_equal(wavy.points.t_gps_s[tw], flat.points.t_gps_s[tf])
    np.testing.assert_array_equal(wavy.points.scan_angle_rad[tw], flat.points.scan_angle_rad[tf])
    np.testing.assert_array_equal(wavy.target_index[tw], flat.target_index[tf])
    np.testing.assert_allclose(wavy.points.range_m[tw], flat.points.range_m[tf], rtol=0, atol=1e-9)
    np.testing.assert_allclose(wavy.p_true_lgf_m[tw], flat.p_true_lgf_m[tf], rtol=0, atol=1e-9)
    # and the wall differs
    ww = wavy.surface_index == wavy.scene.names.index("quay_wall")
    off = wavy.scene.rectangles[wavy.scene.names.index("quay_wall")].signed_distance(wavy.p_true_lgf_m[ww])
    assert np.abs(off).max() > 0.01


def test_terrestrial_targets_on_the_uneven_ground_are_untouched():
    wavy = simulate("terrestrial", seed=1, overrides=NOISE_FREE)
    flat = simulate("terrestrial", seed=1, overrides={**NOISE_FREE, **FLAT})
    tw, tf = wavy.target_index >= 0, flat.target_index >= 0
    assert tw.sum() > 3000
    np.testing.assert_array_equal(wavy.points.t_gps_s[tw], flat.points.t_gps_s[tf])
    np.testing.assert_array_equal(wavy.target_index[tw], flat.target_index[tf])
    np.testing.assert_allclose(wavy.points.range_m[tw], flat.points.range_m[tf], rtol=0, atol=1e-9)


def test_amplitude_zero_is_todays_flat_wall_bit_for_bit():
    text = (SCENARIO_DIR / "montreal.yaml").read_text()
    shape = ",\n       waviness: {amplitude_m: 0.01, wavelength_m: [3.0, 8.0]}, roughness_m: 0.001}"
    assert shape in text
    before = simulate(parse_scenario(text.replace(shape, "}"), source="montreal.yaml"), seed=9)
    zero = simulate(
        "montreal",
        seed=9,
        overrides=[
            "scene.surfaces[quay_wall].waviness.amplitude_m=0",
            "scene.surfaces[quay_wall].roughness_m=0",
        ],
    )
    flat = simulate("montreal", seed=9, overrides=["scene.flat_surfaces=true"])
    for r in (zero, flat):
        for f in ("pass_id", "t_gps_s", "range_m", "scan_angle_rad", "intensity"):
            np.testing.assert_array_equal(getattr(r.points, f), getattr(before.points, f))
        np.testing.assert_array_equal(r.p_true_lgf_m, before.p_true_lgf_m)
        np.testing.assert_array_equal(r.trajectory_observed.p_lgf_m, before.trajectory_observed.p_lgf_m)


# -- scenario keys --------------------------------------------------------------------------


def test_shipped_walls_are_realistic_and_targets_flat():
    for name in ("montreal", "tower", "terrestrial"):
        sc = load_scenario(name)
        for s in sc.surfaces:
            if s.kind in ("target", "validation"):
                assert s.shape is None, (name, s.name)
            else:
                assert s.shape is not None and 0.002 <= s.shape.waviness_amplitude_m <= 0.02, (name, s.name)
                assert 0 < s.shape.roughness_m <= 0.002
    wall = {s.name: s for s in load_scenario("montreal").surfaces}["quay_wall"].shape
    assert wall == SurfaceShape(0.01, (3.0, 8.0), 0.001)


def test_one_override_makes_montreal_flat():
    flat = load_scenario("montreal", ["scene.flat_surfaces=true"])
    assert all(s.shape is None for s in flat.surfaces)
    assert flat.surfaces == with_flat_surfaces(load_scenario("montreal")).surfaces
    by_name = load_scenario("montreal", {"scene.surfaces.quay_wall.waviness.amplitude_m": 0})
    wall = {s.name: s for s in by_name.surfaces}["quay_wall"].shape
    assert wall == SurfaceShape(0.0, (3.0, 8.0), 0.001)
    # targets by name too, like by index
    t2 = load_scenario("montreal", ["scene.targets[T2].up_m=4.5"])
    assert {s.name: s.up_m for s in t2.surfaces}["T2"] == 4.5
    with pytest.raises(
        ConfigError,
        match=re.escape("'pier' is not an index of the 1-item list") + r".*nor the name.*quay_wall",
    ):
        load_scenario("montreal", ["scene.surfaces[pier].roughness_m=0"])


MINIMAL_WALL = """
reference: {lat_deg: 45.5, lon_deg: -73.55}
site: {standoff_m: 15.0}
scene:
  targets:
    - {name: T, up_m: 5.0, size_m: [1.0, 1.0]}
  surfaces:
    - {name: W, kind: wall, up_m: 5.0, size_m: [6.0, 2.0], WAVY}
"""


@pytest.mark.parametrize(
    ("shape", "message"),
    [
        (
            "waviness: {amplitude_m: -0.01, wavelength_m: [3, 8]}",
            r"scene\.surfaces\[0\]\.waviness\.amplitude_m: got -0\.01, expected a number ≥ 0",
        ),
        (
            "waviness: {amplitude_m: 0.01, wavelength_m: [8, 3]}",
            r"scene\.surfaces\[0\]\.waviness\.wavelength_m: got \[8, 3\], expected \[shortest, longest\] "
            r"wavelengths in metres, shortest first",
        ),
        (
            "waviness: {amplitude_m: 0.01, wavelength_m: [0, 3]}",
            r"scene\.surfaces\[0\]\.waviness\.wavelength_m: got \[0, 3\], expected .*both > 0",
        ),
        (
            "waviness: {amplitude_m: 0.01, wavelength_m: 3}",
            r"scene\.surfaces\[0\]\.waviness\.wavelength_m: got 3, expected a list of 2 numbers",
        ),
        (
            "waviness: {amplitude_m: 0.01}",
            r"scene\.surfaces\[0\]\.waviness: missing required key 'wavelength_m'",
        ),
        (
            "waviness: {amplitude: 0.01, wavelength_m: [3, 8]}",
            r"scene\.surfaces\[0\]\.waviness\.amplitude: unknown key 'amplitude'",
        ),
        ("roughness_m: -0.001", r"scene\.surfaces\[0\]\.roughness_m: got -0\.001, expected a number ≥ 0"),
        ("roughness: 0.001", r"scene\.surfaces\[0\]\.roughness: unknown key 'roughness'"),
    ],
)
def test_bad_shape_keys_are_named(shape, message):
    with pytest.raises(ConfigError, match=r"wall\.yaml:\d+:\d+: " + message):
        parse_scenario(MINIMAL_WALL.replace("WAVY", shape), source="wall.yaml")


def test_shape_keys_parse_and_flat_surfaces_is_validated():
    sc = parse_scenario(
        MINIMAL_WALL.replace("WAVY", "waviness: {amplitude_m: 0.005, wavelength_m: [2, 2]}"), source="w.yaml"
    )
    assert sc.surfaces[1].shape == SurfaceShape(0.005, (2.0, 2.0), 0.0)
    sc = parse_scenario(MINIMAL_WALL.replace("WAVY", "roughness_m: 0.002"), source="w.yaml")
    assert sc.surfaces[1].shape == SurfaceShape(0.0, (3.0, 8.0), 0.002)
    assert parse_scenario(MINIMAL_WALL.replace(", WAVY", ""), source="w.yaml").surfaces[1].shape is None
    with pytest.raises(ConfigError, match=r"scene\.flat_surfaces: got 'maybe', expected true or false"):
        parse_scenario(MINIMAL_WALL.replace(", WAVY", ""), overrides=["scene.flat_surfaces=maybe"])
