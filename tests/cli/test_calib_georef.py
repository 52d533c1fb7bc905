"""``mls calib georef`` and ``mls demo``: the LAZ files read back with laspy hold what they should."""

from __future__ import annotations

import re
import shutil

import laspy
import numpy as np
import pytest
from pyproj import Transformer
from typer.testing import CliRunner

from calib.core import frames
from calib.core.georef import georeference_poses
from calib.io.bundle import read_bundle, read_truth
from cli.app import app

runner = CliRunner()
WIDE = {"COLUMNS": "250"}  # rich folds long paths at the default 80 columns


def plain(text: str) -> str:
    """Output without rich's box drawing, whitespace collapsed (wrapped words join again)."""
    return " ".join(re.sub(r"[│╭╮╰╯─]", " ", text).split())


def truth_boresight_deg(bundle_dir):
    b = read_truth(bundle_dir)["boresight_deg"]
    return b["roll"], b["pitch"], b["yaw"]


def georef(bundle_dir, out_dir, *args):
    return runner.invoke(app, ["calib", "georef", str(bundle_dir), "--out", str(out_dir), *args], env=WIDE)


def expected_lgf(bundle, pass_id, boresight_deg):
    """Pass points georeferenced by the plain reference implementation (not the fast kernel)."""
    pts = bundle.points.select(bundle.points.pass_id == pass_id)
    mount = bundle.site.mount.with_boresight(np.radians(boresight_deg))
    poses = bundle.trajectory.interpolate(pts.t_gps_s + mount.time_offset_s)
    return pts, georeference_poses(poses, pts.range_m, pts.scan_angle_rad, mount)


def test_utm_output_matches_georeference_and_pyproj(tmp_path, example_bundle):
    bs = truth_boresight_deg(example_bundle)
    result = georef(
        example_bundle, tmp_path, "--boresight-deg", ",".join(map(str, bs)), "--chunk-points", "1000"
    )  # several chunks per pass
    assert result.exit_code == 0, result.output
    assert "pass-1.laz" in result.output and "EPSG:32618" in result.output
    bundle = read_bundle(example_bundle)
    to_utm = Transformer.from_crs("EPSG:4979", "EPSG:32618", always_xy=True)
    for pass_id in (1, 2):
        las = laspy.read(tmp_path / f"pass-{pass_id}.laz")
        h = las.header
        assert (str(h.version), h.point_format.id) == ("1.4", 6)
        assert h.global_encoding.gps_time_type == laspy.header.GpsTimeType.STANDARD
        assert h.global_encoding.wkt
        assert h.parse_crs().to_epsg() == 32618
        assert h.file_source_id == pass_id
        pts, p_lgf = expected_lgf(bundle, pass_id, bs)
        assert len(las.points) == len(pts) > 7000
        lat, lon, hgt = bundle.frame.to_geodetic(p_lgf)
        east, north = to_utm.transform(lon, lat)
        xyz = np.stack([las.x, las.y, las.z], axis=1)
        # 0.1 mm resolution: within half a step (and a little float noise)
        assert np.abs(xyz - np.stack([east, north, hgt], axis=1)).max() < 0.5e-4 + 1e-6
        np.testing.assert_array_equal(las.gps_time, pts.t_gps_s - 1e9)
        assert np.all(las.point_source_id == pass_id)
        np.testing.assert_array_equal(las.intensity, np.round(pts.intensity * 65535))
        assert np.all(las.return_number == 1) and np.all(las.number_of_returns == 1)


def test_lgf_output_is_enu_and_true_boresight_puts_targets_on_their_planes(tmp_path, example_bundle):
    bundle = read_bundle(example_bundle)
    rects = {t.name: t.rectangle(bundle.frame) for t in bundle.site.targets}

    def target_misfit_m(out_dir, *args):
        result = georef(example_bundle, out_dir, "--crs", "lgf", *args)
        assert result.exit_code == 0, result.output
        worst = {}
        for pass_id in (1, 2):
            las = laspy.read(out_dir / f"pass-{pass_id}.laz")
            assert "LOCAL_CS" in las.header.vlrs[0].string and "marine-mls LGF" in las.header.vlrs[0].string
            p_ned = np.stack([las.y, las.x, -np.asarray(las.z)], axis=1)  # x east, y north, z up
            for name, rect in rects.items():
                d = rect.signed_distance(p_ned)
                on = rect.contains(p_ned, margin_m=0.1) & (np.abs(d) < 0.5)
                assert on.sum() > 300, f"pass {pass_id} should see {name}"
                worst[name] = max(worst.get(name, 0.0), float(np.abs(d[on]).max()))
        return worst

    bs = ",".join(map(str, truth_boresight_deg(example_bundle)))
    assert max(target_misfit_m(tmp_path / "true", "--boresight-deg", bs).values()) < 1e-4
    # site.yaml's a-priori boresight is zero: the targets come out centimetres off their planes
    assert min(target_misfit_m(tmp_path / "apriori").values()) > 0.02


def test_lgf_coordinates_equal_the_ned_points(tmp_path, example_bundle):
    bs = truth_boresight_deg(example_bundle)
    result = georef(
        example_bundle, tmp_path, "--crs", "lgf", "--las", "--boresight-deg", ",".join(map(str, bs))
    )
    assert result.exit_code == 0, result.output
    las = laspy.read(tmp_path / "pass-2.las")
    assert not las.header.are_points_compressed
    _, p = expected_lgf(read_bundle(example_bundle), 2, bs)
    xyz = np.stack([las.x, las.y, las.z], axis=1)
    assert np.abs(xyz - np.stack([p[:, 1], p[:, 0], -p[:, 2]], axis=1)).max() < 0.5e-4 + 1e-9


def test_geographic_crs_gives_degrees_and_ellipsoidal_heights(tmp_path, example_bundle):
    result = georef(example_bundle, tmp_path, "--crs", "EPSG:4979")
    assert result.exit_code == 0, result.output
    bundle = read_bundle(example_bundle)
    las = laspy.read(tmp_path / "pass-1.laz")
    assert las.header.parse_crs().to_epsg() == 4979
    _, p = expected_lgf(bundle, 1, (0.0, 0.0, 0.0))
    lat, lon, h = bundle.frame.to_geodetic(p)
    assert np.abs(las.x - lon).max() < 1e-9 and np.abs(las.y - lat).max() < 1e-9
    assert np.abs(las.z - h).max() < 0.5e-4 + 1e-6


def test_geocentric_crs_gives_ecef(tmp_path, example_bundle):
    result = georef(example_bundle, tmp_path, "--crs", "EPSG:4978")
    assert result.exit_code == 0, result.output
    bundle = read_bundle(example_bundle)
    las = laspy.read(tmp_path / "pass-2.laz")
    _, p = expected_lgf(bundle, 2, (0.0, 0.0, 0.0))
    ecef = frames.geodetic_to_ecef(*bundle.frame.to_geodetic(p))
    assert np.abs(np.stack([las.x, las.y, las.z], axis=1) - ecef).max() < 0.5e-4 + 1e-6


def test_uncovered_points_stop_unless_skipped(tmp_path, example_bundle):
    d = tmp_path / "short"
    shutil.copytree(example_bundle, d)
    lines = (d / "trajectory.csv").read_text().splitlines(keepends=True)
    (d / "trajectory.csv").write_text("".join(lines[:-75]))  # pass 2 ends 1.5 s early
    result = georef(d, tmp_path / "out")
    assert result.exit_code == 1
    assert "pass 2:" in result.output and "fall outside the trajectory" in result.output
    assert "--skip-uncovered" in result.output
    result = georef(d, tmp_path / "out", "--skip-uncovered")
    assert result.exit_code == 0, result.output
    assert "dropped" in result.output
    n2 = len(laspy.read(tmp_path / "out" / "pass-2.laz").points)
    assert 0 < n2 < int(np.sum(read_bundle(example_bundle).points.pass_id == 2))


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (["--boresight-deg", "0.2,1.2"], 2, "expected three numbers 'roll,pitch,yaw'"),
        (["--boresight-deg", "a,b,c"], 2, "expected three numbers"),
        (["--crs", "EPSG:999999"], 1, "not a CRS pyproj knows"),
        (["--crs", "EPSG:32618+5703"], 1, "its heights need a geoid model that PROJ does not have"),
    ],
)
def test_bad_options(tmp_path, example_bundle, args, code, message):
    result = georef(example_bundle, tmp_path, *args)
    assert result.exit_code == code
    assert message in plain(result.output)


def test_bad_bundle_is_one_clear_line(tmp_path):
    result = georef(tmp_path / "nope", tmp_path / "out")
    assert result.exit_code == 1
    assert "error:" in result.output and "nope: not a directory" in result.output
    assert "Traceback" not in result.output


def test_help_explains_the_commands():
    top = runner.invoke(app, ["--help"])
    assert top.exit_code == 0
    for word in ("calib", "demo", "version"):
        assert word in top.output
    result = runner.invoke(app, ["calib", "georef", "--help"], env=WIDE)
    assert result.exit_code == 0
    text = plain(result.output)
    for words in ("LAS 1.4", "--crs", "--boresight-deg", "--out", "point_source_id", "canonical convention"):
        assert words in text
    result = runner.invoke(app, ["demo", "--help"], env=WIDE)
    text = plain(result.output)
    for words in ("simulated devices", "mls export and mls calib run", "Ctrl-C", "--line-m"):
        assert words in text


def test_example_bundle_is_small_and_what_its_script_makes(tmp_path, example_bundle):
    import runpy

    size = sum(f.stat().st_size for f in example_bundle.iterdir())
    assert size <= 1_000_000
    script = example_bundle.parent / "make_example_bundle.py"
    runpy.run_path(str(script), run_name="make_example_bundle")["main"](tmp_path / "mini")
    shipped, fresh = read_bundle(example_bundle), read_bundle(tmp_path / "mini")
    np.testing.assert_array_equal(fresh.points.t_gps_s, shipped.points.t_gps_s)
    np.testing.assert_allclose(fresh.points.range_m, shipped.points.range_m, atol=1e-12)
    np.testing.assert_array_equal(fresh.trajectory.t_gps_s, shipped.trajectory.t_gps_s)
    assert (tmp_path / "mini" / "site.yaml").read_text() == (example_bundle / "site.yaml").read_text()
    assert frames.gps_ns_to_utc(frames.seconds_to_gps_ns(shipped.points.t_gps_s[0])).year == 2021
