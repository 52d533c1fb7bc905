"""calib.io.site: the site config (docs/architecture.md §4): values, round trip, and located errors."""

from __future__ import annotations

import numpy as np
import pytest

from calib.core import frames
from calib.io.configfile import ConfigError
from calib.io.site import SIX_FOLD_RELATIVE_HEADINGS_DEG, load_site, parse_site, six_fold_passes

SITE_EXAMPLE = """\
vessel: survey-1
reference: {lat_deg: 45.5, lon_deg: -73.55, height_m: 0.0}
mount:
  lever_arm_m: [0.1, -0.2, -1.5]
  nominal_deg: [0.0, 0.0, 90.0]
  boresight_apriori_deg: [0.2, 1.2, 0.1]
scanner: {sigma_range_m: 0.003, sigma_scan_angle_deg: 0.005}
pos_sigmas:
  position_m: [0.02, 0.02, 0.03]
  attitude_deg: [0.012, 0.012, 0.012]
wall_azimuth_deg: 10.0
standoff_m: 15.0
targets:
  - name: T1
    center: {lat_deg: 45.5001, lon_deg: -73.5501, height_m: 5.0}
    size_m: [1.23, 1.22]
    inclination_deg: 90.0
    facing_azimuth_deg: 270.0
    reflectivity: 0.9
  - name: T2
    center: {lat_deg: 45.5002, lon_deg: -73.5501, height_m: 5.0}
    size_m: [1.23, 0.76]
    inclination_deg: 45.0
    facing_azimuth_deg: 270.0
passes:
  - {id: 1, relative_heading_deg: 0.0}
  - {id: 2, relative_heading_deg: 180.0, length_m: 60.0, speed_mps: 1.5, standoff_m: 25.0}
validation_planes: []
piles:
  - {name: P1, center: {lat_deg: 45.5001, lon_deg: -73.5502}, diameter_m: 0.6, bottom_height_m: -2.0,
     top_height_m: 5.5}
"""


def test_design_example_values_are_si_and_radians():
    site = parse_site(SITE_EXAMPLE)
    assert site.vessel == "survey-1"
    assert site.reference == frames.LocalFrame(45.5, -73.55, 0.0)
    np.testing.assert_allclose(site.mount.lever_arm_m, [0.1, -0.2, -1.5])
    np.testing.assert_allclose(site.mount.nominal_rad, np.radians([0, 0, 90]))
    np.testing.assert_allclose(site.mount.boresight_rad, np.radians([0.2, 1.2, 0.1]))
    assert site.sigma_scan_angle_rad == pytest.approx(np.radians(0.005))
    np.testing.assert_allclose(site.sigma_attitude_rad, np.radians([0.012] * 3))
    assert site.wall_azimuth_rad == pytest.approx(np.radians(10.0))
    t1, t2 = site.targets
    assert (t1.name, t1.width_m, t1.height_along_slope_m) == ("T1", 1.23, 1.22)
    assert t2.inclination_rad == pytest.approx(np.radians(45.0)) and t2.reflectivity == 0.9
    assert [p.id for p in site.passes] == [1, 2]
    assert (site.passes[1].length_m, site.passes[1].speed_mps) == (60.0, 1.5)
    # a line may keep its own standoff; the others the site's
    assert (site.passes[0].standoff_m, site.passes[1].standoff_m) == (None, 25.0)
    assert site.validation_planes == ()
    (pile,) = site.piles
    assert (pile.name, pile.diameter_m, pile.bottom_height_m, pile.top_height_m) == ("P1", 0.6, -2.0, 5.5)
    cyl = pile.cylinder(site.reference)
    assert (cyl.radius_m, cyl.height_m) == (0.3, 7.5) and cyl.center_m[2] == pytest.approx(-1.75, abs=1e-3)
    # the vertical target faces west: normal (0, −1, 0) in NED
    rect = t1.rectangle(site.reference)
    np.testing.assert_allclose(rect.normal, [0.0, -1.0, 0.0], atol=1e-15)


def test_minimal_site_gets_the_documented_defaults():
    site = parse_site("mount: {}\ntargets: []\n")
    assert site.reference is None and site.standoff_m == 15.0
    np.testing.assert_array_equal(site.mount.boresight_rad, np.zeros(3))
    assert [np.degrees(p.relative_heading_rad) for p in site.passes] == pytest.approx(
        list(SIX_FOLD_RELATIVE_HEADINGS_DEG)
    )
    assert [p.id for p in six_fold_passes()] == [1, 2, 3, 4, 5, 6]
    with pytest.raises(ConfigError, match="no reference point configured"):
        site.frame()


def test_dump_load_round_trip(tmp_path):
    site = parse_site(SITE_EXAMPLE)
    site.dump(tmp_path / "site.yaml")
    again = load_site(tmp_path / "site.yaml")
    assert again.targets == site.targets and again.passes == site.passes and again.piles == site.piles
    assert again.reference == site.reference and again.vessel == site.vessel
    for attr in ("lever_arm_m", "nominal_rad", "boresight_rad"):
        np.testing.assert_allclose(
            getattr(again.mount, attr), getattr(site.mount, attr), rtol=1e-15, atol=1e-18
        )
    np.testing.assert_allclose(again.sigma_position_m, site.sigma_position_m)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (
            ("standoff_m: 15.0", "standof_m: 15.0"),
            r"site\.yaml:12:12: standof_m: unknown key 'standof_m'; allowed keys here: .*standoff_m",
        ),
        (
            ("    reflectivity: 0.9\n", "    reflectivity: 0.9\n    colour: red\n"),
            r"site\.yaml:20:13: targets\[0\]\.colour: unknown key 'colour'",
        ),
        (("    size_m: [1.23, 0.76]\n", ""), r"site\.yaml:20:5: targets\[1\]: missing required key 'size_m'"),
        (
            ("standoff_m: 15.0", "standoff_m: far"),
            r"site\.yaml:12:13: standoff_m: got 'far', expected a finite number",
        ),
        (("standoff_m: 15.0", "standoff_m: -3"), r"standoff_m: got -3, expected a number > 0"),
        (
            ("  lever_arm_m: [0.1, -0.2, -1.5]", "  lever_arm_m: [0.1, -0.2]"),
            r"site\.yaml:4:16: mount\.lever_arm_m: got \[0\.1, -0\.2\], expected a list of 3 numbers",
        ),
        (
            ("    inclination_deg: 45.0", "    inclination_deg: 120.0"),
            r"targets\[1\]\.inclination_deg: got 120\.0, expected a number ≤ 90",
        ),
        (
            ("    size_m: [1.23, 1.22]", "    size_m: [1.23, 0.0]"),
            r"targets\[0\]\.size_m: got \[1\.23, 0\.0\], expected 2 positive numbers",
        ),
        (
            ("  - name: T2", "  - name: T1"),
            r"site\.yaml:20:5: targets\[1\]: .* expected a unique target name \('T1' appears twice\)",
        ),
        (("{id: 2, relative", "{id: 1, relative"), r"passes: .* expected unique pass ids"),
        (
            ("top_height_m: 5.5", "top_height_m: -2.0"),
            r"piles\[0\]\.top_height_m: got -2\.0, expected a number > -2",
        ),
        (("diameter_m: 0.6", "diameter_m: 0"), r"piles\[0\]\.diameter_m: got 0, expected a number > 0"),
        (("{id: 1, relative", "{id: 1.5, relative"), r"passes\[0\]\.id: got 1\.5, expected an integer"),
        (("standoff_m: 25.0}", "standoff_m: 0}"), r"passes\[1\]\.standoff_m: got 0, expected a number > 0"),
        (("vessel: survey-1", "vessel: [a, b]"), r"vessel: got \['a', 'b'\], expected a non-empty"),
        (("mount:\n", "mount: 3\nmount_:\n"), r"unknown key 'mount_'"),
        (
            ("wall_azimuth_deg: 10.0", "wall_azimuth_deg: 10.0\nwall_azimuth_deg: 12.0"),
            r"site\.yaml:12:1: wall_azimuth_deg: duplicate key",
        ),
        (("targets:\n", "targets: [\n"), r"site\.yaml:\d+:\d+: not valid YAML"),
    ],
)
def test_errors_name_file_line_column_key_and_expectation(edit, message):
    text = SITE_EXAMPLE.replace(*edit)
    assert text != SITE_EXAMPLE
    with pytest.raises(ConfigError, match=message):
        parse_site(text, source="site.yaml")


def test_missing_top_level_key_and_missing_file(tmp_path):
    with pytest.raises(
        ConfigError,
        match=r"site\.yaml:1:1: <top level>: missing required key "
        r"'mount'",
    ):
        parse_site("targets: []\n", source="site.yaml")
    with pytest.raises(ConfigError, match=r"nowhere\.yaml: file not found"):
        load_site(tmp_path / "nowhere.yaml")
