"""Point-cloud files (calib.io.cloudio): LAS/LAZ with extra dimensions, ASCII with extra columns,
and errors that name the file and line."""

from __future__ import annotations

import laspy
import numpy as np
import pytest

from calib.io.cloudio import CloudError, PointCloud, read_cloud, write_cloud


@pytest.fixture
def xyz():
    rng = np.random.default_rng(0)
    return rng.uniform(0, 50, (500, 3)) + [612345.0, 5041234.0, 10.0]  # UTM-sized


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_ascii_cloud_to_las_round_trip_with_extra_dimension(tmp_path, xyz, suffix):
    d = np.linspace(-0.1, 0.1, len(xyz))
    path = write_cloud(tmp_path / f"out{suffix}", PointCloud(xyz), {"c2c_distance_m": d})
    back = read_cloud(path)
    las = back.las
    assert las.header.version.major == 1 and las.header.version.minor == 4
    assert las.header.point_format.id == 6
    assert las.header.scales.tolist() == [1e-4, 1e-4, 1e-4]
    assert np.abs(back.xyz_m - xyz).max() <= 0.5e-4 + 1e-9  # 0.1 mm quantisation
    assert list(las.point_format.extra_dimension_names) == ["c2c_distance_m"]
    np.testing.assert_array_equal(np.asarray(las["c2c_distance_m"]), d)  # float64, exact
    with laspy.open(path) as f:
        assert f.header.point_format.id == 6
    assert (path.read_bytes()[:4]) == b"LASF"


def test_las_input_keeps_its_fields_and_overwrites_an_existing_dimension(tmp_path, xyz):
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = [0.001] * 3, [612000.0, 5041000.0, 0.0]
    src = laspy.LasData(header)
    src.x, src.y, src.z = xyz.T
    src.intensity = np.arange(len(xyz), dtype=np.uint16)
    src.gps_time = np.linspace(1e9, 1e9 + 1, len(xyz))
    src.classification = np.full(len(xyz), 2, dtype=np.uint8)
    src.write(tmp_path / "in.laz")

    cloud = read_cloud(tmp_path / "in.laz")
    write_cloud(tmp_path / "a.laz", cloud, {"c2c_distance_m": np.ones(len(xyz))})
    again = read_cloud(tmp_path / "a.laz")
    write_cloud(
        tmp_path / "b.las",
        again,
        {"c2c_distance_m": np.full(len(xyz), 2.0), "c2c_signed_distance_m": -np.ones(len(xyz))},
    )
    out = read_cloud(tmp_path / "b.las").las
    assert list(out.point_format.extra_dimension_names) == ["c2c_distance_m", "c2c_signed_distance_m"]
    np.testing.assert_array_equal(np.asarray(out["c2c_distance_m"]), 2.0)
    np.testing.assert_array_equal(np.asarray(out.intensity), np.arange(len(xyz)))
    np.testing.assert_allclose(np.asarray(out.gps_time), np.linspace(1e9, 1e9 + 1, len(xyz)))
    assert (np.asarray(out.classification) == 2).all()
    assert out.header.scales.tolist() == [0.001] * 3
    # the source cloud in memory is untouched
    assert "c2c_distance_m" not in cloud.las.point_format.extra_dimension_names


@pytest.mark.parametrize(
    ("text", "delimiter", "columns"),
    [
        ("1 2 3\n4 5 6\n", None, {}),
        ("1\t2\t3\t7\n4\t5\t6\t8\n", "\t", {"column_4": [7, 8]}),
        ("# exported\nX,Y,Z,Intensity\n1, 2, 3, 7\n\n4,5,6,8\n", ",", {"Intensity": [7, 8]}),
        (
            "//X Y Z R G B\n1 2 3 10 20 30\n4 5 6 11 21 31\n",
            None,
            {"R": [10, 11], "G": [20, 21], "B": [30, 31]},
        ),
        ("1;2;3\n# a comment between points\n4;5;6\n", ";", {}),
    ],
)
def test_ascii_variants(tmp_path, text, delimiter, columns):
    p = tmp_path / "c.txt"
    p.write_text(text)
    c = read_cloud(p)
    np.testing.assert_array_equal(c.xyz_m, [[1, 2, 3], [4, 5, 6]])
    assert c.delimiter == delimiter
    assert {k: v.tolist() for k, v in c.columns.items()} == columns


def test_ascii_output_appends_columns_under_a_cloudcompare_header(tmp_path):
    p = tmp_path / "c.csv"
    p.write_text("x,y,z,intensity\n1.5,2,3,7\n4,5,6.25,8\n")
    c = read_cloud(p)
    out = write_cloud(tmp_path / "o.csv", c, {"c2c_distance_m": np.array([0.0123456, -0.5])})
    lines = out.read_text().splitlines()
    assert lines[0] == "//x,y,z,intensity,c2c_distance_m"
    assert lines[1] == "1.500000,2.000000,3.000000,7,0.012346"
    back = read_cloud(out)
    np.testing.assert_array_equal(back.xyz_m, c.xyz_m)
    np.testing.assert_allclose(back.columns["c2c_distance_m"], [0.012346, -0.5])
    # an ASCII cloud written to LAS keeps its extra columns as dimensions (no clash with the
    # standard 'intensity')
    las = read_cloud(write_cloud(tmp_path / "o.las", c, {"d": np.zeros(2)})).las
    assert list(las.point_format.extra_dimension_names) == ["ascii_intensity", "d"]
    np.testing.assert_array_equal(np.asarray(las["ascii_intensity"]), [7, 8])


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("1 2 3\n4 5 x\n", "c.txt:2: column 3 is 'x', expected a number"),
        ("1 2 3\n4 5 6 7\n", "c.txt:2: 4 columns, expected 3 like line 1"),
        ("# header only\n", "c.txt: no points"),
        ("1 2\n3 4\n", "c.txt:1: 2 column(s), expected at least x y z"),
        ("1 2 3\n4 nan 6\n", "c.txt:2: column 2 is 'nan', expected a finite number"),
        ("x y z i\n1 2 3\n", "header names 4 columns"),
    ],
)
def test_ascii_errors_name_file_and_line(tmp_path, text, message):
    p = tmp_path / "c.txt"
    p.write_text(text)
    with pytest.raises(CloudError) as e:
        read_cloud(p)
    assert message in str(e.value)


def test_other_file_errors(tmp_path):
    with pytest.raises(CloudError, match="missing.las: file not found"):
        read_cloud(tmp_path / "missing.las")
    (tmp_path / "bad.las").write_bytes(b"not a las file at all")
    with pytest.raises(CloudError, match="bad.las: not a readable LAS/LAZ file"):
        read_cloud(tmp_path / "bad.las")
    (tmp_path / "bin.xyz").write_bytes(b"\xff\xfe\x00\x01")
    with pytest.raises(CloudError, match="bin.xyz: not a text file"):
        read_cloud(tmp_path / "bin.xyz")
    with pytest.raises(CloudError, match="column 'd' has shape"):
        write_cloud(tmp_path / "o.txt", PointCloud(np.zeros((3, 3))), {"d": np.zeros(2)})
