"""Inputs that cannot lie, outputs that are never overwritten silently: survey line ids (int64)
through ``mls calib run``, ``mls calib georef`` and ``mls export``; passes of the plan against
passes of the points; ``--skip-uncovered``; ``--force``; a directory where a file belongs (and
the reverse) and a "billion laughs" site.yaml as one line each."""

from __future__ import annotations

import json
import shutil
import subprocess
import time
from dataclasses import replace

import laspy
import numpy as np
import pytest
from typer.testing import CliRunner

from calib.io.bundle import read_bundle
from calib.io.site import PassSpec, load_site
from cli.app import app
from tests.calib.io.test_configfile import billion_laughs

runner = CliRunner()
WIDE = {"COLUMNS": "250"}
BIG = 20240709000  # survey line ids 20240709001 …: beyond 32 bits


def mls(*args):
    return runner.invoke(app, [str(a) for a in args], env=WIDE)


def one_line_error(res, code=1) -> str:
    assert res.exit_code == code, (res.exit_code, res.output)
    lines = [line for line in res.output.strip().splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("error: ")]
    assert len(errors) == 1, res.output
    assert "Traceback" not in res.output
    return errors[0]


def warnings_of(res) -> list[str]:
    return [line for line in res.stderr.splitlines() if line.startswith("warning: ")]


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "montreal"
    res = mls("sim", "dataset", "--scenario", "montreal", "--seed", "0", "--out", out)
    assert res.exit_code == 0, res.output
    return out


def copy_bundle(src, dst, pass_ids=None, site_passes=None):
    """A copy of ``src``; ``pass_ids`` maps the points' pass ids, ``site_passes`` edits the plan."""
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("calib"))
    if pass_ids is not None:
        lines = (dst / "points.csv").read_text().splitlines(keepends=True)
        for i in range(1, len(lines)):
            pid, rest = lines[i].split(",", 1)
            lines[i] = f"{pass_ids(int(pid))},{rest}"
        (dst / "points.csv").write_text("".join(lines))
    if site_passes is not None:
        site = load_site(dst / "site.yaml")
        replace(site, passes=tuple(site_passes(site.passes))).dump(dst / "site.yaml")
    return dst


# -- pass ids: int64 end to end -----------------------------------------------------------------


def test_survey_line_ids_keep_their_passes_through_calib_run_and_georef(tmp_path, sim):
    b = copy_bundle(
        sim,
        tmp_path / "lines",
        pass_ids=lambda p: BIG + p,
        site_passes=lambda passes: [replace(p, id=BIG + p.id) for p in passes],
    )
    res = mls("calib", "run", b, "--out", tmp_path / "out", "--no-history", "--no-plots")
    assert res.exit_code == 0, res.output
    assert warnings_of(res) == []  # the plan and the points agree
    doc = json.loads((tmp_path / "out" / "result.json").read_text())
    assert [p["id"] for p in doc["passes"]] == [BIG + k for k in range(1, 7)]
    counts = {int(k): sum(v.values()) for k, v in doc["extraction"]["points_per_pass"].items()}
    assert sorted(counts) == [BIG + k for k in range(1, 7)] and min(counts.values()) > 100
    report = (tmp_path / "out" / "report.md").read_text()
    assert f"{BIG + 1} (0°), {BIG + 2} (180°)" in report and f"| {BIG + 6} |" in report
    # LAS: point_source_id is 16 bits; the id lives in the extra-bytes dimension pass_id
    res = mls("calib", "georef", b, "--out", tmp_path / "laz")
    assert res.exit_code == 0, res.output
    text = " ".join(res.output.split())
    assert f"passes {BIG + 1}, {BIG + 2}" in text and "exceed LAS's 16-bit point_source_id: 0 there" in text
    las = laspy.read(tmp_path / "laz" / f"pass-{BIG + 3}.laz")
    assert las.header.file_source_id == 0 and not las.point_source_id.any()
    assert las.pass_id.dtype == np.int64 and set(las.pass_id.tolist()) == {BIG + 3}
    assert len(las.points) == int(np.sum(read_bundle(b).points.pass_id == BIG + 3))


def test_small_pass_ids_stay_in_point_source_id_too(tmp_path, example_bundle):
    res = mls("calib", "georef", example_bundle, "--out", tmp_path)
    assert res.exit_code == 0, res.output
    las = laspy.read(tmp_path / "pass-2.laz")
    assert las.header.file_source_id == 2 and set(las.point_source_id.tolist()) == {2}
    assert set(las.pass_id.tolist()) == {2}


# -- the plan against the points ----------------------------------------------------------------


def test_calib_run_warns_of_planned_passes_without_points_and_points_of_unplanned_passes(tmp_path, sim):
    b = copy_bundle(
        sim,
        tmp_path / "plan",
        site_passes=lambda passes: (
            [replace(p, id=16) if p.id == 6 else p for p in passes] + [PassSpec(7, 0.0)]
        ),
    )
    res = mls("calib", "run", b, "--out", tmp_path / "out", "--no-history", "--no-plots")
    assert res.exit_code == 0, res.output
    site, points = b / "site.yaml", b / "points.csv"
    n6 = int(np.sum(read_bundle(b).points.pass_id == 6))
    expected = [
        f"passes 16, 7 planned in {site} have no points in {points}",
        f"{points} holds points of pass 6 ({n6:,} points) not planned in {site}",
    ]
    assert [" ".join(w.split()) for w in warnings_of(res)] == [f"warning: {w}" for w in expected]
    assert "warning" not in res.stdout
    report = (tmp_path / "out" / "report.md").read_text()
    assert all(f"- ⚠ {w}" in report for w in expected)
    assert json.loads((tmp_path / "out" / "result.json").read_text())["warnings"][:2] == expected


# -- --skip-uncovered ---------------------------------------------------------------------------


def test_calib_run_skip_uncovered_drops_and_counts_per_pass(tmp_path, sim):
    b = copy_bundle(sim, tmp_path / "short")
    pts = read_bundle(b).points
    t_cut = float(np.median(pts.t_gps_s[pts.pass_id == 6]))  # the trajectory ends mid pass 6
    lines = (b / "trajectory.csv").read_text().splitlines(keepends=True)
    kept = [lines[0]] + [row for row in lines[1:] if float(row.split(",", 1)[0]) <= t_cut]
    (b / "trajectory.csv").write_text("".join(kept))
    line = one_line_error(mls("calib", "run", b, "--no-history", "--no-plots"))
    assert "the trajectory does not cover the points" in line and "pass 6:" in line
    assert "or drop these points with --skip-uncovered" in line
    assert not (b / "calib").exists()
    res = mls("calib", "run", b, "--no-history", "--no-plots", "--skip-uncovered")
    assert res.exit_code == 0, res.output
    bundle = read_bundle(b)
    bad = bundle.trajectory.uncovered(bundle.points.t_gps_s)
    n6 = int(np.sum(bundle.points.pass_id == 6))
    assert bad.sum() == np.sum(bad & (bundle.points.pass_id == 6)) > 100
    warning = f"pass 6: dropped {int(bad.sum()):,} of {n6:,} points outside the trajectory's coverage"
    assert any(warning in " ".join(w.split()) for w in warnings_of(res)), res.stderr
    assert warning in (b / "calib" / "report.md").read_text()
    doc = json.loads((b / "calib" / "result.json").read_text())
    assert doc["passes"][-1]["id"] == 6 and any(w.startswith(warning) for w in doc["warnings"])
    # outliers still name rows of points.csv: every listed row is a covered point
    assert not bad[np.asarray(doc["outlier_point_ids"], int)].any()


# -- --force ------------------------------------------------------------------------------------


def test_writers_refuse_a_directory_that_holds_data_unless_forced(tmp_path, sim, example_bundle):
    out = tmp_path / "sim"
    args = ("sim", "dataset", "--scenario", "montreal", "--point-rate-scale", "0.05", "--out", out)
    assert mls(*args).exit_code == 0
    before = (out / "points.csv").read_bytes()
    line = one_line_error(mls(*args, "--seed", "1"), 2)
    assert line == (
        f"error: {out}: --out is not empty (points.csv, site.yaml, trajectory.csv, … (4 entries)); "
        f"add --force to write into it anyway (files of the same names are replaced), or choose a "
        f"new directory"
    )
    assert (out / "points.csv").read_bytes() == before
    assert mls(*args, "--seed", "1", "--force").exit_code == 0
    assert (out / "points.csv").read_bytes() != before
    # calib run: --out, and the default BUNDLE/calib of a second run
    b = copy_bundle(example_bundle, tmp_path / "mini")
    (tmp_path / "used").mkdir()
    (tmp_path / "used" / "result.json").write_text("{}")
    line = one_line_error(mls("calib", "run", b, "--out", tmp_path / "used", "--no-history"), 2)
    assert f"{tmp_path / 'used'}: --out is not empty (result.json); add --force" in line
    assert (tmp_path / "used" / "result.json").read_text() == "{}"
    (b / "calib").mkdir()
    (b / "calib" / "report.md").write_text("an earlier run")
    line = one_line_error(mls("calib", "run", b, "--no-history"), 2)
    assert f"{b / 'calib'}: the output directory (--out) is not empty (report.md); add --force" in line
    # calib georef, calib assess, design
    line = one_line_error(mls("calib", "georef", b, "--out", tmp_path / "used"))
    assert f"{tmp_path / 'used'}: --out is not empty (result.json); add --force" in line
    assert mls("calib", "georef", b, "--out", tmp_path / "used", "--force").exit_code == 0
    assert (tmp_path / "used" / "pass-1.laz").is_file()
    line = one_line_error(
        mls("calib", "assess", b, "--result", tmp_path / "x.json", "--out", tmp_path / "used")
    )
    assert "--out is not empty (pass-1.laz, pass-2.laz, result.json); add --force" in line
    line = one_line_error(mls("design", "--site", b / "site.yaml", "--out", tmp_path / "used"), 2)
    assert "--out is not empty" in line and "--force" in line


# -- mls export -----------------------------------------------------------------------------------


def _session(tmp_path, marks, site_text):
    from tests.office.jobs.test_export import _write_session

    session = _write_session(tmp_path, marks)[0]
    (tmp_path / "site.yaml").write_text(site_text)
    return session


def test_export_keeps_survey_line_ids_and_warns_of_passes_the_plan_does_not_match(tmp_path):
    from tests.office.jobs.test_export import SITE

    # passes from the plan: survey line ids, and one planned line never sailed
    site = (
        SITE.replace("{id: 1,", f"{{id: {BIG + 1},").replace("{id: 2,", f"{{id: {BIG + 2},")
        + f"  - {{id: {BIG + 3}, relative_heading_deg: 45.0, length_m: 40.0, speed_mps: 2.0}}\n"
    )
    session = _session(tmp_path, False, site)
    res = mls("export", session, "--bundle", tmp_path / "b", "--site", tmp_path / "site.yaml")
    assert res.exit_code == 0, res.output
    assert read_bundle(tmp_path / "b").points.pass_ids() == [BIG + 1, BIG + 2]
    expected = (
        f"pass {BIG + 3} planned in {tmp_path / 'site.yaml'} has no points in {tmp_path / 'b' / 'points.csv'}"
    )
    assert f"warning: {expected}" in [" ".join(w.split()) for w in warnings_of(res)]
    assert "(stderr)" in res.stdout and "warning:" not in res.stdout
    # passes from the marks (1 and 2) against a plan of passes 1 and 3
    session = _session(tmp_path / "m", True, SITE.replace("{id: 2,", "{id: 3,"))
    res = mls("export", session, "--bundle", tmp_path / "m" / "b", "--site", tmp_path / "m" / "site.yaml")
    assert res.exit_code == 0, res.output
    got = [" ".join(w.split()) for w in warnings_of(res)]
    site_path, points = tmp_path / "m" / "site.yaml", tmp_path / "m" / "b" / "points.csv"
    assert f"warning: pass 3 planned in {site_path} has no points in {points}" in got
    assert any(
        w.startswith(f"warning: {points} holds points of pass 2 (") and str(site_path) in w for w in got
    )


def test_export_refuses_to_overwrite_unless_forced(tmp_path):
    from tests.office.jobs.test_export import SITE

    session = _session(tmp_path, True, SITE)
    site = ("--site", tmp_path / "site.yaml")
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "points.csv").write_text("someone's data")
    line = one_line_error(mls("export", session, "--bundle", tmp_path / "b", *site))
    assert line.startswith(f"error: {tmp_path / 'b'}: --bundle is not empty (points.csv); add --force")
    assert (tmp_path / "b" / "points.csv").read_text() == "someone's data"
    (tmp_path / "t.sbet").write_bytes(b"an old trajectory")
    line = one_line_error(
        mls("export", session, "--bundle", tmp_path / "c", "--sbet", tmp_path / "t.sbet", *site)
    )
    assert f"{tmp_path / 't.sbet'}: --sbet: the file exists; add --force to replace it" in line
    assert not (tmp_path / "c").exists()
    res = mls("export", session, "--bundle", tmp_path / "b", "--sbet", tmp_path / "t.sbet", "--force", *site)
    assert res.exit_code == 0, res.output
    assert len(read_bundle(tmp_path / "b").points) > 0 and (tmp_path / "t.sbet").stat().st_size > 100


# -- a directory where a file belongs, a file where a directory belongs, hostile YAML -------------


def test_paths_of_the_wrong_kind_are_one_line(tmp_path, example_bundle):
    afile = tmp_path / "afile"
    afile.write_text("x")
    line = one_line_error(mls("calib", "georef", example_bundle, "--out", afile))
    assert line == f"error: {afile}: --out names a directory, but this is a file"
    line = one_line_error(mls("calib", "run", example_bundle, "--out", afile, "--no-history"), 2)
    assert line == f"error: {afile}: --out names a directory, but this is a file"
    line = one_line_error(mls("sim", "dataset", "--scenario", "montreal", "--out", afile), 2)
    assert line == f"error: {afile}: --out names a directory, but this is a file"
    for name, message in (
        ("site.yaml", "is a directory, expected a YAML file"),
        ("points.csv.gz", "is a directory, expected a file"),
    ):
        b = copy_bundle(example_bundle, tmp_path / f"with-{name}")
        (b / name).unlink()
        (b / name).mkdir()
        for args in (
            ("calib", "georef", b, "--out", tmp_path / f"o-{name}"),
            ("calib", "run", b, "--no-history"),
        ):
            assert one_line_error(mls(*args)) == f"error: {b / name}: {message}"
    line = one_line_error(mls("export", afile, "--bundle", tmp_path / "e"))
    assert line == f"error: {afile}: not a directory (a session is the directory the daemon recorded)"
    session = tmp_path / "session"
    session.mkdir()
    line = one_line_error(mls("export", session, "--bundle", tmp_path / "e", "--sbet", tmp_path))
    assert line == f"error: {tmp_path}: --sbet names a file, but this is a directory"
    line = one_line_error(mls("plan", example_bundle / "site.yaml", "--out", tmp_path))
    assert line == f"error: {tmp_path}: --out names a file, but this is a directory"
    line = one_line_error(mls("sim", "devices", "--scenario", "montreal", "--run-dir", afile), 2)
    assert line == f"error: {afile}: --run-dir names a directory, but this is a file"
    line = one_line_error(mls("calib", "c2c", tmp_path, afile), 2)
    assert line == f"error: {tmp_path}: is a directory, expected a point-cloud file"
    res = mls("demo", "--out", afile)
    assert res.exit_code == 1 and isinstance(res.exception, SystemExit)  # no traceback
    assert (
        f"mls demo failed at step preparing the run directory: {afile}: --out names a directory, "
        f"but this is a file" in res.output
    )


def test_a_billion_laughs_site_yaml_is_one_line_within_a_second(tmp_path, example_bundle):
    b = copy_bundle(example_bundle, tmp_path / "lol")
    (b / "site.yaml").write_text(billion_laughs())
    t0 = time.thread_time()  # CPU time of this thread: the loader's work, not the machine's load
    line = one_line_error(mls("calib", "run", b, "--no-history"))
    assert time.thread_time() - t0 < 1.0
    assert line == (
        f"error: {b / 'site.yaml'}: more than 100,000 values once its aliases are expanded "
        f"(aliases nested in aliases, a 'billion laughs'?): refused"
    )


def test_every_yaml_file_of_the_project_is_read_within_the_bounds(tmp_path):
    """The bound protects a YAML file only if it is read by calib/io/configfile.py: no other
    module parses YAML (git grep), and each loader (site, vessel config, scenario, faults)
    refuses a billion laughs at once."""
    from acquire.daemon.config import load_vessel_config
    from calib.io.configfile import ConfigError
    from calib.sim.scenariofile import load_scenario
    from sim_devices.faults import load_faults
    from tests.conftest import PROJECT_ROOT

    out = subprocess.run(
        ["git", "grep", "-n", "-E", r"yaml\.((safe_|full_|unsafe_)?load(_all)?|compose(_all)?|parse|scan)\("],
        cwd=PROJECT_ROOT,
        capture_output=True,
        text=True,
        check=False,
    ).stdout.splitlines()
    assert out, "git grep found nothing: is this a git checkout?"
    assert [line for line in out if not line.startswith(("calib/io/configfile.py:", "tests/"))] == []
    path = tmp_path / "laughs.yaml"
    path.write_text(billion_laughs())
    for load in (load_site, load_vessel_config, load_scenario, load_faults):
        t0 = time.thread_time()  # CPU time of this thread: the loader's work, not the machine's load
        with pytest.raises(ConfigError, match=r"laughs\.yaml: more than 100,000 values once its aliases"):
            load(path)
        assert time.thread_time() - t0 < 1.0, load
