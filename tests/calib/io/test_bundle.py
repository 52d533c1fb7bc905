"""calib.io.bundle: reading/writing the calibration bundle; every error names file, line, column."""

from __future__ import annotations

import gzip
import shutil

import numpy as np
import pytest

from calib.io import sbet
from calib.io.bundle import (
    BundleError,
    ScanPoints,
    read_bundle,
    read_points_csv,
    read_trajectory_csv,
    read_truth,
    write_bundle,
)
from calib.io.site import parse_site

SITE = """\
reference: {lat_deg: 45.5, lon_deg: -73.55, height_m: -30.0}
mount: {lever_arm_m: [0.4, -0.3, -1.8]}
targets: []
passes: [{id: 1, relative_heading_deg: 0.0}, {id: 2, relative_heading_deg: 180.0}]
"""


@pytest.fixture
def bundle_parts(wave_trajectory):
    traj = wave_trajectory(duration_s=2.0, rate_hz=50.0, sigmas=True)
    rng = np.random.default_rng(11)
    n = 400
    t = np.sort(rng.uniform(traj.t_gps_s[0], traj.t_gps_s[-1], n))
    pts = ScanPoints(
        np.repeat([1, 2], n // 2),
        t,
        rng.uniform(1, 80, n),
        rng.uniform(0, 2 * np.pi, n),
        rng.uniform(0, 1, n).astype(np.float32),
    )
    return parse_site(SITE), traj, pts


@pytest.fixture
def bundle_dir(tmp_path, bundle_parts):
    return write_bundle(tmp_path / "b", *bundle_parts, truth={"boresight_deg": [0.1, 0.2, 0.3]})


def test_write_read_round_trip(bundle_dir, bundle_parts):
    site, traj, pts = bundle_parts
    b = read_bundle(bundle_dir)
    assert b.frame == site.reference
    np.testing.assert_array_equal(b.trajectory.t_gps_s, traj.t_gps_s)
    assert np.abs(b.trajectory.p_lgf_m - traj.p_lgf_m).max() < 1e-5  # 1e-12° and 1 µm on disk
    np.testing.assert_allclose(b.trajectory.rpy_rad, traj.rpy_rad, atol=1e-13)
    np.testing.assert_allclose(b.trajectory.sigma_p_m, traj.sigma_p_m, rtol=1e-5)
    np.testing.assert_array_equal(b.points.pass_id, pts.pass_id)
    np.testing.assert_array_equal(b.points.t_gps_s, pts.t_gps_s)  # %.9f is exact for float64
    np.testing.assert_array_equal(b.points.range_m, pts.range_m)  # %.17g is exact
    np.testing.assert_allclose(b.points.scan_angle_rad, pts.scan_angle_rad, rtol=1e-15)
    np.testing.assert_allclose(b.points.intensity, pts.intensity, rtol=1e-5)
    assert b.points.pass_ids() == [1, 2]
    assert read_truth(bundle_dir) == {"boresight_deg": [0.1, 0.2, 0.3]}


def test_gzip_points_and_no_sigmas(tmp_path, bundle_parts, wave_trajectory):
    site, _, pts = bundle_parts
    traj = wave_trajectory(duration_s=2.0, rate_hz=50.0)
    d = write_bundle(tmp_path / "gz", site, traj, pts, compress_points=True)
    assert (d / "points.csv.gz").exists() and not (d / "points.csv").exists()
    b = read_bundle(d)
    assert not b.trajectory.has_sigmas
    np.testing.assert_array_equal(b.points.range_m, pts.range_m)
    assert "sigma" not in (d / "trajectory.csv").read_text().splitlines()[0]


def test_sbet_bundle_infers_the_week_from_the_points(tmp_path, bundle_dir, bundle_parts):
    _, traj, _ = bundle_parts
    (bundle_dir / "trajectory.csv").unlink()
    rec, _ = sbet.sbet_records(traj)
    sbet.write_sbet(bundle_dir / "trajectory.sbet", rec)
    sbet.write_smrmsg(bundle_dir / "trajectory.smrmsg", sbet.smrmsg_records(traj))
    b = read_bundle(bundle_dir)
    np.testing.assert_array_equal(b.trajectory.t_gps_s, traj.t_gps_s)
    assert np.abs(b.trajectory.p_lgf_m - traj.p_lgf_m).max() < 1e-6
    np.testing.assert_allclose(b.trajectory.sigma_p_m, traj.sigma_p_m, rtol=1e-14)
    (bundle_dir / "trajectory.sbet").write_bytes(rec.tobytes()[:-5])
    with pytest.raises(
        BundleError,
        match=rf"trajectory\.sbet: size {rec.nbytes - 5} bytes is not "
        rf"a multiple of the SBET record size \(136 bytes",
    ):
        read_bundle(bundle_dir)


def edit_line(path, line_no, new):
    lines = path.read_text().splitlines(keepends=True)
    lines[line_no - 1] = new
    path.write_text("".join(lines))


def test_missing_files(tmp_path, bundle_dir):
    with pytest.raises(BundleError, match=r"nowhere: not a directory \(a calibration bundle"):
        read_bundle(tmp_path / "nowhere")
    for name, message in [
        ("points.csv", "no points.csv or points.csv.gz"),
        ("trajectory.csv", "no trajectory.csv or trajectory.sbet"),
        ("site.yaml", r"site\.yaml: file not found"),
    ]:
        d = tmp_path / f"without-{name}"
        shutil.copytree(bundle_dir, d)
        (d / name).unlink()
        with pytest.raises(BundleError, match=message):
            read_bundle(d)
    (bundle_dir / "truth.json").unlink()
    with pytest.raises(BundleError, match=r"truth\.json: not found \(only simulated bundles"):
        read_truth(bundle_dir)


# (file, line, new text, expected message): one case per error the readers report
POINTS_CASES = [
    (
        1,
        "pass,gps_time,range_m,scan_angle_deg,intensity\n",
        r"points\.csv:1: header is 'pass,gps_time,.*', expected it to start with 'pass_id,gps_time",
    ),
    (
        1,
        "pass_id,gps_time,range_m,scan_angle_deg,intensity,colour\n",
        r"points\.csv:1: unexpected columns 'colour'",
    ),
    (3, "1,1313000000.5,10.0,45.0\n", r"points\.csv:3: 4 fields, expected 5 \(pass_id,"),
    (3, "1,1313000000.5,ten,45.0,0.5\n", r"points\.csv:3:3: column 'range_m' is 'ten', expected a number"),
    (
        4,
        "1,1313000000.5,10.0,nan,0.5\n",
        r"points\.csv:4:4: column 'scan_angle_deg' is 'nan', expected a finite number",
    ),
    (3, "\n", r"points\.csv:3: empty line, expected 5 fields"),
    (
        3,
        "1.5,1313000000.5,10.0,45.0,0.5\n",
        r"points\.csv:3:1: pass_id is 1\.5, expected a non-negative integer",
    ),
    (
        3,
        "-1,1313000000.5,10.0,45.0,0.5\n",
        r"points\.csv:3:1: pass_id is -1\.0, expected a non-negative integer",
    ),
    (
        3,
        "1,1313000000.5,-10.0,45.0,0.5\n",
        r"points\.csv:3:3: range_m is -10\.0, expected 0\.3…119 m \(the Z\+F 9012's range window\)",
    ),
    (3, "1,1313000000.5,0.29,45.0,0.5\n", r"points\.csv:3:3: range_m is 0\.29, expected 0\.3…119 m"),
    (5, "1,1313000000.5,119.001,45.0,0.5\n", r"points\.csv:5:3: range_m is 119\.001, expected 0\.3…119 m"),
    (
        4,
        "1,1313000000.2,10.0,360.0,0.5\n",
        r"points\.csv:4:4: scan_angle_deg is 360\.0, expected 0 ≤ angle < 360 \(the scanner's full circle\)",
    ),
    (
        3,
        "1,1313000000.1,10.0,-0.5,0.5\n",
        r"points\.csv:3:4: scan_angle_deg is -0\.5, expected 0 ≤ angle < 360",
    ),
    (
        4,
        "1,1313000000.2,10.0,45.0,1.5\n",
        r"points\.csv:4:5: intensity is 1\.5, expected 0…1: the file holds fractions \(line 2: 0\.5\), "
        r"read as reflectances 0…1; counts must all be whole numbers 0…65535",
    ),
    (
        3,
        "99999999999999999999,1313000000.1,10.0,45.0,0.5\n",
        r"points\.csv:3:1: pass_id is 99999999999999999999, expected a non-negative integer ≤ 9223372036854775807",
    ),
    (
        4,
        "1,1312999999.0,10.0,45.0,0.5\n",
        r"points\.csv:4:2: gps_time 1312999999\.0 follows 1313000000\.[0-9]+; times must not "
        r"decrease within a pass",
    ),
]


def test_a_short_line_next_to_a_long_one_is_not_taken_for_two_good_lines(tmp_path):
    path = tmp_path / "points.csv"
    path.write_text(
        "pass_id,gps_time,range_m,scan_angle_deg,intensity\n"
        "1,1313000000.0,10.0,45.0\n1,1313000000.1,10.0,45.0,0.5,0.5\n"
    )
    with pytest.raises(BundleError, match=r"points\.csv:2: 4 fields, expected 5"):
        read_points_csv(path)


def test_points_with_time_order_across_passes(tmp_path):
    path = tmp_path / "points.csv"
    path.write_text(
        "pass_id,gps_time,range_m,scan_angle_deg,intensity\n"
        "1,20.0,1,0,0\n1,21.0,1,0,0\n2,10.0,1,0,0\n2,11.0,1,0,0\n"
    )
    assert read_points_csv(path).pass_ids() == [1, 2]  # each pass runs forward: fine
    path.write_text("pass_id,gps_time,range_m,scan_angle_deg,intensity\n")
    with pytest.raises(BundleError, match=r"points\.csv: no points"):
        read_points_csv(path)


TRAJ_HEADER = (
    "gps_time,lat_deg,lon_deg,height_m,roll_deg,pitch_deg,heading_deg,sigma_north_m,"
    "sigma_east_m,sigma_down_m,sigma_roll_deg,sigma_pitch_deg,sigma_heading_deg\n"
)
TRAJ_CASES = [
    (
        2,
        "100.0,45.5,-73.55,0,0,0,0,0.02,0.02,0.03,0.01,0.01,0\n",
        r"trajectory\.csv:2:13: sigma_heading_deg is 0\.0, expected a positive sigma",
    ),
    (
        3,
        "100.0,45.5,-73.55,0,0,0,0,0.02,0.02,0.03,0.01,0.01,0.02\n",
        r"trajectory\.csv:3:1: gps_time 100\.0 follows 100\.0; times must increase strictly",
    ),
    (
        2,
        "100.0,95.5,-73.55,0,0,0,0,0.02,0.02,0.03,0.01,0.01,0.02\n",
        r"trajectory\.csv:2:2: lat_deg is 95\.5, expected -90…90",
    ),
    (
        2,
        "100.0,45.5,-181.0,0,0,0,0,0.02,0.02,0.03,0.01,0.01,0.02\n",
        r"trajectory\.csv:2:3: lon_deg is -181\.0, expected -180…360",
    ),
    (
        2,
        "100.0,45.5,-73.55,0,0,95,0,0.02,0.02,0.03,0.01,0.01,0.02\n",
        r"trajectory\.csv:2:6: pitch_deg is 95\.0, expected -90…90",
    ),
    (
        2,
        "100.0,45.5,-73.55,0,-190,0,0,0.02,0.02,0.03,0.01,0.01,0.02\n",
        r"trajectory\.csv:2:5: roll_deg is -190\.0, expected -180…180",
    ),
    (
        3,
        "101.0,45.5,-73.55,0,0,0,720,0.02,0.02,0.03,0.01,0.01,0.02\n",
        r"trajectory\.csv:3:7: heading_deg is 720\.0, expected -360…360",
    ),
    (2, "100.0,45.5,-73.55,0,0,0,0,0.02,0.02,0.03,0.01,0.01\n", r"trajectory\.csv:2: 12 fields, expected 13"),
    (
        1,
        TRAJ_HEADER.replace(",sigma_heading_deg", ""),
        r"trajectory\.csv:1: unexpected columns 'sigma_north_m,.*'; after 'gps_time,.*' only "
        r"'sigma_north_m,.*,sigma_heading_deg' may follow",
    ),
]


POINTS_TEXT = "pass_id,gps_time,range_m,scan_angle_deg,intensity\n" + "".join(
    f"1,{1_313_000_000.0 + 0.1 * i:.9f},{10.0 + i},{5.0 * i},0.5\n" for i in range(5)
)
TRAJ_TEXT = TRAJ_HEADER + "".join(
    f"{100.0 + i},45.5,-73.55,0,0,0,{i},0.02,0.02,0.03,0.01,0.01,0.02\n" for i in range(3)
)


@pytest.mark.parametrize(
    ("name", "line_no", "new", "message"),
    [("points.csv", *c) for c in POINTS_CASES] + [("trajectory.csv", *c) for c in TRAJ_CASES],
)
def test_csv_errors(tmp_path, name, line_no, new, message):
    path = tmp_path / name
    reader = read_points_csv if name == "points.csv" else read_trajectory_csv
    path.write_text(POINTS_TEXT if name == "points.csv" else TRAJ_TEXT)
    reader(path)  # valid before the edit
    edit_line(path, line_no, new)
    with pytest.raises(BundleError, match=message):
        reader(path)


def test_trajectory_needs_two_epochs_and_text_files_must_be_text(tmp_path):
    path = tmp_path / "trajectory.csv"
    path.write_text(TRAJ_HEADER + "100.0,45.5,-73.55,0,0,0,0,0.02,0.02,0.03,0.01,0.01,0.02\n")
    with pytest.raises(BundleError, match=r"trajectory\.csv: 1 trajectory epochs, expected at"):
        read_trajectory_csv(path)
    path.write_bytes(TRAJ_HEADER.encode() + b"100.0,45.5,\xff\n")
    with pytest.raises(BundleError, match=r"trajectory\.csv:2: not UTF-8 text"):
        read_trajectory_csv(path)
    gz = tmp_path / "points.csv.gz"
    gz.write_bytes(b"not gzip at all")
    with pytest.raises(BundleError, match=r"points\.csv\.gz: not a valid gzip file"):
        read_points_csv(gz)
    gz.write_bytes(gzip.compress(b"pass_id,gps_time,range_m,scan_angle_deg,intensity\n1,2,3,4,5\n"))
    assert len(read_points_csv(gz)) == 1


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (("targets: []", "targets: []\ntargtes: []"), r"site\.yaml:4:10: targtes: unknown key"),
        (("targets: []\n", ""), r"site\.yaml:1:1: <top level>: missing required key 'targets'"),
        (
            ("lever_arm_m: [0.4, -0.3, -1.8]", "lever_arm_m: [0.4, -0.3, abc]"),
            r"site\.yaml:2:34: mount\.lever_arm_m\[2\]: got 'abc', expected a finite number",
        ),
    ],
)
def test_site_errors_come_through_read_bundle(bundle_dir, edit, message):
    path = bundle_dir / "site.yaml"
    path.write_text(SITE.replace(*edit))
    with pytest.raises(BundleError, match=message):
        read_bundle(bundle_dir)


def test_truth_json_errors(bundle_dir):
    (bundle_dir / "truth.json").write_text('{"boresight_deg": [1, 2,\n}')
    with pytest.raises(BundleError, match=r"truth\.json:2:1: not valid JSON"):
        read_truth(bundle_dir)


HEADER = "pass_id,gps_time,range_m,scan_angle_deg,intensity\n"


def test_pass_ids_are_int64_end_to_end(tmp_path):
    """Survey line ids exceed 32 bits (and ids above 2⁵³ exceed float64): each keeps its own
    pass, exactly, through reading and writing."""
    big = 2**53 + 1  # float64 would read it as 2**53
    path = tmp_path / "points.csv"
    path.write_text(
        HEADER
        + "20240709001,10.0,10,0,0.5\n20240709001,11.0,10,0,0.5\n"
        + "20240709002,10.5,10,0,0.5\n"
        + f"{big - 1},12.0,10,0,0.5\n{big},12.5,10,0,0.5\n"
    )
    pts = read_points_csv(path)
    assert pts.pass_id.dtype == np.int64
    assert pts.pass_ids() == [20240709001, 20240709002, big - 1, big]
    out = tmp_path / "again.csv"
    from calib.io.bundle import write_points_csv

    write_points_csv(out, pts)
    assert out.read_text().splitlines()[4].startswith(f"{big - 1},")
    np.testing.assert_array_equal(read_points_csv(out).pass_id, pts.pass_id)


def test_intensity_has_one_scale_per_file_and_a_stray_value_names_its_line(tmp_path):
    from calib.io.bundle import intensity_scale

    path = tmp_path / "points.csv"
    rows = [f"1,{10 + i},10,0,{v}\n" for i, v in enumerate((0.25, 1.0, 0.0))]
    path.write_text(HEADER + "".join(rows))
    assert intensity_scale(read_points_csv(path).intensity).describe() == "reflectance 0…1, ×65535"
    counts = [f"1,{10 + i},10,0,{v}\n" for i, v in enumerate((120, 0, 65535, 7))]
    path.write_text(HEADER + "".join(counts))
    assert intensity_scale(read_points_csv(path).intensity).kind == "counts"
    # one count beyond 16 bits, or below zero: refused at its line, never clipped or rescaled
    for bad, line in (("70000", 4), ("-3", 5)):
        edited = counts.copy()
        edited[line - 2] = f"1,{10 + line - 2},10,0,{bad}\n"
        path.write_text(HEADER + "".join(edited))
        with pytest.raises(
            BundleError, match=rf"points\.csv:{line}:5: intensity is {bad}\.0, expected 0…65535"
        ):
            read_points_csv(path)
    # reflectances with one whole number above 1: the line of that value, not a rescaled file
    path.write_text(HEADER + "".join(rows) + "1,13,10,0,2\n")
    with pytest.raises(
        BundleError, match=r"points\.csv:5:5: intensity is 2\.0, expected 0…1: .*\(line 2: 0\.25\)"
    ):
        read_points_csv(path)


def test_a_directory_where_a_bundle_file_belongs_is_one_line(tmp_path, bundle_dir):
    for name, message in (
        ("points.csv", r"points\.csv: is a directory, expected a file"),
        ("trajectory.csv", r"trajectory\.csv: is a directory, expected a file"),
        ("site.yaml", r"site\.yaml: is a directory, expected a YAML file"),
    ):
        d = tmp_path / f"dir-{name}"
        shutil.copytree(bundle_dir, d)
        (d / name).unlink()
        (d / name).mkdir()
        with pytest.raises(BundleError, match=message):
            read_bundle(d)
    (bundle_dir / "truth.json").unlink()
    (bundle_dir / "truth.json").mkdir()
    with pytest.raises(BundleError, match=r"truth\.json: is a directory, expected a file"):
        read_truth(bundle_dir)


def test_passes_of_the_plan_and_of_the_points_are_compared(tmp_path, bundle_parts):
    site, traj, pts = bundle_parts  # site plans passes 1 and 2
    pts = ScanPoints(
        np.where(pts.pass_id == 2, 7, 1), pts.t_gps_s, pts.range_m, pts.scan_angle_rad, pts.intensity
    )
    b = read_bundle(write_bundle(tmp_path / "b", site, traj, pts))
    warnings = b.pass_warnings()
    assert warnings == [
        f"pass 2 planned in {b.path / 'site.yaml'} has no points in {b.path / 'points.csv'}",
        f"{b.path / 'points.csv'} holds points of pass 7 (200 points) not planned in {b.path / 'site.yaml'}",
    ]
    (b.path / "site.yaml").write_text(SITE.replace(SITE.splitlines()[-1], ""))  # no passes listed
    warnings = read_bundle(b.path).pass_warnings()
    assert warnings[0].startswith(
        f"passes 2, 3, 4, 5, 6 planned in {b.path / 'site.yaml'} (it lists no passes: the default "
        f"six-fold plan, ids 1–6) have no points in"
    )


def test_write_bundle_leaves_no_file_of_another_bundle(tmp_path, bundle_dir, bundle_parts):
    (bundle_dir / "trajectory.sbet").write_bytes(b"old")
    (bundle_dir / "notes.txt").write_text("mine")
    write_bundle(bundle_dir, *bundle_parts, compress_points=True)  # no truth this time
    names = sorted(p.name for p in bundle_dir.iterdir())
    assert names == ["notes.txt", "points.csv.gz", "site.yaml", "trajectory.csv"]
