"""Scenarios: the shipped montreal, terrestrial and tower scenarios hold what the
thesis describes; loading by name or path; dotted-key overrides; errors that say where."""

from __future__ import annotations

import numpy as np
import pytest

from calib.io.configfile import ConfigError
from calib.sim.scenariofile import load_scenario, parse_scenario, scenario_names
from calib.sim.simulate import simulate

MINIMAL = """
reference: {lat_deg: 45.5, lon_deg: -73.55}
site: {standoff_m: 15.0}
scene:
  targets:
    - {name: T, up_m: 5.0, size_m: [1.0, 1.0]}
"""


def test_shipped_scenarios():
    assert set(scenario_names()) >= {"harbour", "montreal", "terrestrial", "tower"}


def test_montreal_is_the_thesis_site():
    sc = load_scenario("montreal")
    t = {s.name: s for s in sc.surfaces if s.kind == "target"}
    assert (t["T1"].width_m, t["T1"].height_m, np.degrees(t["T1"].inclination_rad)) == (1.23, 1.22, 90.0)
    assert (t["T2"].width_m, t["T2"].height_m) == (1.23, 0.76)
    assert np.degrees(t["T2"].inclination_rad) == pytest.approx(45.0)
    assert 2.0 < abs(t["T1"].along_m - t["T2"].along_m) < 6.0  # a few metres apart
    wall = [s for s in sc.surfaces if s.kind == "wall"]
    assert len(wall) == 1 and wall[0].reflectivity < 0.5 < t["T1"].reflectivity
    # 15 m standoff, targets 5 m above the scanner (scanner at up = 0 on a level vessel)
    assert sc.standoff_m == 15.0
    assert t["T1"].up_m == t["T2"].up_m == 5.0
    res = simulate(sc, seed=0)
    scanner_down = res.plan.passes[0].start_lgf_m[2] + sc.mount.lever_arm_m[2]
    for i in res.scene.indices("target"):
        assert res.scene.rectangles[i].center_m[2] - scanner_down == pytest.approx(-5.0)
    assert [np.degrees(p.relative_heading_rad) for p in sc.passes] == [0, 180, 45, 225, 315, 135]
    # POS sigma 2 cm / 0.012°, the thesis boresight (canonical: pitch sign flipped)
    np.testing.assert_allclose(sc.pos_noise.sigma_position_m, 0.02)
    np.testing.assert_allclose(np.degrees(sc.pos_noise.sigma_attitude_rad), 0.012)
    np.testing.assert_allclose(np.degrees(sc.truth.boresight_rad), [0.208, 1.245, 0.149])
    assert res.truth["boresight_thesis_deg"]["pitch"] == pytest.approx(-1.245)
    # Z+F 9012 rates (the scenario thins them with point_rate_scale)
    assert (sc.scanner.profile_rate_hz, sc.scanner.points_per_360, sc.scanner.max_range_m) == (
        200.0,
        5080,
        119.0,
    )


def test_terrestrial_scanner_is_2_5_m_above_the_ground_targets():
    sc = load_scenario("terrestrial")
    ground = [s for s in sc.surfaces if s.kind == "ground"]
    assert len(ground) == 1 and ground[0].up_m == -2.5 and ground[0].inclination_rad == 0.0
    for s in sc.surfaces:
        if s.kind == "target":
            lowest = s.up_m - 0.5 * s.height_m * np.sin(s.inclination_rad)
            assert -2.5 <= lowest and s.up_m < 0.0  # on the ground, below the scanner
    incl = sorted(round(np.degrees(s.inclination_rad)) for s in sc.surfaces if s.kind == "target")
    assert incl == [0, 40, 90]


def test_tower_validation_planes_reach_40_m():
    sc = load_scenario("tower")
    v = {s.name: s for s in sc.surfaces if s.kind == "validation"}
    assert sorted(v) == ["V1", "V2", "V3", "V4", "V5"]
    tops = {n: s.up_m + 0.5 * s.height_m for n, s in v.items()}
    assert 38.0 <= max(tops.values()) <= 40.0 + 1e-9
    assert abs(v["V1"].up_m) < 3 and abs(v["V5"].up_m) < 3  # at the platform's height
    assert v["V2"].up_m - 0.5 * v["V2"].height_m == pytest.approx(0.0)  # water line to the top
    assert sc.capture_validation_planes


@pytest.mark.parametrize("name", ["montreal", "terrestrial", "tower"])
def test_every_shipped_scenario_sees_all_its_planes(name):
    res = simulate(name, seed=1)
    counts = res.point_counts()
    named = [r.name for r, k in zip(res.scene.rectangles, res.scene.kinds) if k in ("target", "validation")]
    for n in named:
        assert sum(c[n] for c in counts.values()) > 100, n
    for p in res.plan.passes:  # every pass sees every target
        for i in res.scene.indices("target"):
            assert counts[p.id][res.scene.rectangles[i].name] > 20
    assert 10_000 < len(res.points) < 80_000  # a few MB as a bundle


def test_overrides_by_dotted_key(tmp_path):
    sc = load_scenario(
        "montreal",
        [
            "noise.pos.model=white",
            "truth.boresight_deg=[1, 2, 3]",
            "scene.targets.1.up_m=4.5",
            "motion.turns=true",
        ],
    )
    assert sc.pos_noise.model == "white"
    np.testing.assert_allclose(np.degrees(sc.truth.boresight_rad), [1, 2, 3])
    assert [s.up_m for s in sc.surfaces if s.name == "T2"] == [4.5]
    assert sc.motion.turns is True
    # a mapping of values works the same, and creates missing optional sections
    sc2 = parse_scenario(
        MINIMAL,
        overrides={
            "motion.rate_hz": 20,
            "noise.pos.model": "white",
            "scanner.angular_windows_deg": [[300, 20]],
        },
    )
    assert sc2.motion.rate_hz == 20 and sc2.pos_noise.model == "white"
    np.testing.assert_allclose(sc2.scanner.angular_windows_rad, np.radians([[300, 20]]))
    mask = sc2.scanner.window_mask()  # wraps through 0°
    a = np.degrees(np.arange(mask.size) * 2 * np.pi / mask.size)
    assert np.array_equal(mask, (a >= 300) | (a <= 20))
    # by path
    p = tmp_path / "mine.yaml"
    p.write_text(MINIMAL)
    sc3 = load_scenario(p)
    assert sc3.name == "mine" and sc3.standoff_m == 15.0 and len(sc3.surfaces) == 1


def test_errors_name_the_place_and_what_was_expected(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text(MINIMAL + "scanner:\n  max_rnage_m: 100\n")
    with pytest.raises(
        ConfigError,
        match=r"bad\.yaml:\d+:\d+: scanner\.max_rnage_m: unknown key "
        r"'max_rnage_m'.*allowed keys here: .*max_range_m",
    ):
        load_scenario(p)
    p.write_text(MINIMAL.replace("size_m: [1.0, 1.0]", "size_m: [1.0, -1.0]"))
    with pytest.raises(
        ConfigError,
        match=r"bad\.yaml:6:\d+: scene\.targets\[0\]\.size_m: got "
        r"\[1\.0, -1\.0\], expected 2 positive numbers",
    ):
        load_scenario(p)
    with pytest.raises(
        ConfigError,
        match="'atlantis': neither a shipped scenario "
        r"\(harbour, harbour_cal, montreal, montreal_piles, terrestrial, tower\) nor an existing file",
    ):
        load_scenario("atlantis")
    with pytest.raises(
        ConfigError,
        match=r"--set:1:1: noise\.pos\.model: got 'pink', expected one "
        r"of gauss_markov, none, per_point, white",
    ):
        load_scenario("montreal", ["noise.pos.model=pink"])
    with pytest.raises(ConfigError, match="expected key=value"):
        load_scenario("montreal", ["noise.pos.model"])
    with pytest.raises(ConfigError, match=r"'7' is not an index of the 2-item list"):
        load_scenario("montreal", ["scene.targets.7.up_m=3"])
    with pytest.raises(
        ConfigError,
        match=r"--set site\.standoff_m\.x: 'site\.standoff_m' is a value "
        r"\(15\.0 at .*montreal\.yaml:\d+:\d+",
    ):
        load_scenario("montreal", {"site.standoff_m.x": 3})
    with pytest.raises(ConfigError, match=r"unknown key 'colour'"):
        load_scenario("montreal", ["scene.targets.0.colour=red"])
    with pytest.raises(ConfigError, match=r"scanner\.point_rate_scale: got 0, expected a number > 0"):
        load_scenario("montreal", ["scanner.point_rate_scale=0"])
    with pytest.raises(ConfigError, match=r"start_utc: got 'yesterday', expected an ISO 8601"):
        parse_scenario(MINIMAL + "start_utc: yesterday\n")
