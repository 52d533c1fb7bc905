"""``mls calib c2c``, ``mls calib history`` and ``mls calib compare`` end to end (typer runner)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from typer.testing import CliRunner

from calib.assess.c2c import c2c
from calib.assess.history import get_result, record_result
from calib.io.cloudio import read_cloud, write_cloud
from cli.app import app
from tests.calib.assess.test_history import make_bundle, make_result

ENV = {"COLUMNS": "200", "MLS_HISTORY_DB": "/nonexistent/never-used.sqlite"}


def run(*args):
    return CliRunner().invoke(app, [str(a) for a in args], env=ENV)


def table_row(output: str, label: str) -> list[str]:
    line = next(l for l in output.splitlines() if l.strip("│ ").startswith(label))
    return [c.strip() for c in line.strip().strip("│").split("│")]


@pytest.fixture
def planes(tmp_path):
    """Two noisy 10 m × 10 m planes at 100 points/m², 20 mm apart (σ = 2 mm each)."""
    rng = np.random.default_rng(30)
    n = 10_000

    def plane(z):
        return np.c_[rng.uniform(0, 10, n), rng.uniform(0, 10, n), z + rng.normal(0, 0.002, n)]

    ref, cmp_ = plane(0.0), plane(0.020)
    np.savetxt(tmp_path / "reference.xyz", ref, fmt="%.6f")
    np.savetxt(tmp_path / "compared.txt", cmp_, fmt="%.6f", delimiter=",", header="x,y,z", comments="")
    return tmp_path / "compared.txt", tmp_path / "reference.xyz"


def test_c2c_offset_20mm_median_within_1mm_and_the_biased_nearest_neighbour(planes, tmp_path):
    compared, reference = planes
    out = tmp_path / "distances.txt"
    res = run("calib", "c2c", compared, reference, "--knn", 6, "--out", out)
    assert res.exit_code == 0, res.output
    d = read_cloud(out).columns["c2c_distance_m"]
    assert d.size == 10_000
    assert abs(np.median(d) - 0.020) < 0.001
    # the printed statistics (mm): local plane vs plain nearest neighbour
    row = table_row(res.output, "local plane, k=6")
    assert row[1] == "10,000" and abs(float(row[3]) - 20.0) < 1.0
    nn_median = float(table_row(res.output, "nearest neighbour")[3])
    assert nn_median > 45.0  # ≈ sqrt(20² + 47²) mm: biased by the point spacing
    assert f"distances written to {out}" in res.output


def test_c2c_las_to_laz_with_signed_distances_matches_the_api(planes, tmp_path):
    compared, reference = planes
    las_in = write_cloud(tmp_path / "compared.las", read_cloud(compared))
    out = tmp_path / "out.laz"
    res = run(
        "calib",
        "c2c",
        las_in,
        reference,
        "--signed",
        "--toward-direction",
        "0,0,-1",
        "--out",
        out,
        "--knn",
        8,
    )
    assert res.exit_code == 0, res.output
    las = read_cloud(out).las
    assert set(las.point_format.extra_dimension_names) == {"c2c_distance_m", "c2c_signed_distance_m"}
    expected = c2c(read_cloud(las_in).xyz_m, read_cloud(reference).xyz_m, 8, orient_direction=[0, 0, -1])
    np.testing.assert_array_equal(np.asarray(las["c2c_distance_m"]), expected.distance_m)
    np.testing.assert_array_equal(np.asarray(las["c2c_signed_distance_m"]), expected.signed_distance_m)
    assert float(table_row(res.output, "signed")[2]) == pytest.approx(-20.0, abs=0.3)


def test_c2c_reports_fallbacks_and_points_beyond_the_maximum(tmp_path):
    ref = np.c_[np.linspace(0, 1, 11), np.zeros(11), np.zeros(11)]  # a line: no planes
    np.savetxt(tmp_path / "ref.xyz", ref)
    np.savetxt(tmp_path / "cmp.xyz", [[0.5, 0.1, 0.0], [5.0, 0.0, 0.0]])
    res = run("calib", "c2c", tmp_path / "cmp.xyz", tmp_path / "ref.xyz", "--max-dist", 1.0)
    assert res.exit_code == 0, res.output
    assert "1 points without a plane" in res.output
    assert "1 points beyond --max-dist 1 m" in res.output


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--toward-point", "0,0,1"], "only apply with --signed"),
        (["--signed", "--toward-direction", "0,1"], "expected three comma-separated numbers"),
        (["--signed", "--toward-direction", "0,0,1", "--toward-point", "1,2,3"], "not both"),
    ],
)
def test_c2c_option_errors(planes, extra, message):
    res = run("calib", "c2c", *planes, *extra)
    assert res.exit_code == 2 and message in res.output


def test_c2c_file_errors(tmp_path, planes):
    res = run("calib", "c2c", planes[0], tmp_path / "missing.laz")
    assert res.exit_code == 2 and "missing.laz: file not found" in res.output
    (tmp_path / "bad.xyz").write_text("1 2 3\n1 2\n")
    res = run("calib", "c2c", tmp_path / "bad.xyz", planes[1])
    assert res.exit_code == 2 and "bad.xyz:2: 2 columns, expected 3" in res.output


# -- history and compare --------------------------------------------------------------------


@pytest.fixture
def history(tmp_path):
    db = tmp_path / "h.sqlite"
    b1 = make_bundle(tmp_path / "jul")
    b2 = make_bundle(tmp_path / "oct", gps_s=1_254_042_018.0, points="2,0,15,90,0.9\n")
    sig = [0.011, 0.0155563, 0.011]
    ids = [
        record_result(
            make_result([0.208, 1.245, 0.149], [0.001, 0.012, 0.001], sig), b1, "survey-1", "A", db=db
        ),
        record_result(
            make_result([0.210, 1.685, 0.151], [0.001, 0.012, 0.001], sig), b2, "survey-1", "A", db=db
        ),
        record_result(make_result([0.1, 0.5, 0.2], [0.001, 0.012, 0.001]), b1, "survey-2", "B", db=db),
    ]
    return db, ids


def test_history_lists_and_filters(history):
    db, ids = history
    res = run("calib", "history", "--db", db)
    assert res.exit_code == 0, res.output
    row = table_row(res.output, str(ids[0]))
    assert row[1].startswith("2019-07-09") and row[2:4] == ["survey-1", "A"]
    assert row[4] == "0.2080 ± 0.0110" and row[7] == "realistic"
    assert table_row(res.output, str(ids[2]))[7] == "scaled"
    res = run("calib", "history", "--db", db, "--vessel", "survey-2")
    ids_shown = [l.strip("│ ").split()[0] for l in res.output.splitlines() if re.match(r"│\s+\d+ ", l)]
    assert ids_shown == [str(ids[2])]
    res = run("calib", "history", "--db", db, "--vessel", "nobody")
    assert res.exit_code == 0 and "no calibrations recorded" in res.output


def test_compare_ids_and_result_files(history, tmp_path):
    db, ids = history
    res = run("calib", "compare", ids[0], f"#{ids[1]}", "--db", db)
    assert res.exit_code == 0, res.output
    assert table_row(res.output, "pitch")[-1] == "CHANGED"
    assert table_row(res.output, "roll")[-1] == "ok"
    flat = " ".join(res.output.split())
    assert "pitch changed by 0.440°, 20σ: the mount has moved; recalibrate after each re-installation" in flat
    # result.json paths (a file and a directory holding one) work as well
    (tmp_path / "r1").mkdir()
    (tmp_path / "r1" / "result.json").write_text(json.dumps(get_result(ids[0], db=db).result))
    (tmp_path / "r2.json").write_text(json.dumps(get_result(ids[0], db=db).result))
    res = run("calib", "compare", tmp_path / "r1", tmp_path / "r2.json", "--db", db)
    assert res.exit_code == 0 and "no angle changed beyond 3σ" in " ".join(res.output.split())


def test_compare_errors(history, tmp_path):
    db, _ = history
    bad = make_result([0.2, 1.2, 0.1], [0.001, 0.01, 0.001])
    del bad["sigma_scaled_deg"]
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    res = run("calib", "compare", tmp_path / "bad.json", "1", "--db", db)
    assert res.exit_code == 2 and "required field 'sigma_scaled_deg' is missing" in res.output
    res = run("calib", "compare", "1", "999", "--db", db)
    assert res.exit_code == 2 and "no calibration #999" in res.output
    res = run("calib", "compare", "1", "nonsense", "--db", db)
    assert res.exit_code == 2 and "neither a result.json path nor a history id" in res.output
