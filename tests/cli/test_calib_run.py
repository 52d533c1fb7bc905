"""``mls calib run`` as users run it: bundles written by ``mls sim dataset``, read back from
the files; the realistic σ under Gauss–Markov POS errors, the outputs, the history, and one
clear line for every error."""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from calib.assess.history import list_results
from calib.boresight.pipeline import CalibrationOptions, run_bundle
from calib.io.bundle import read_truth
from calib.sim.simulate import simulate
from cli.app import app

runner = CliRunner()
WIDE = {"COLUMNS": "250"}
ANGLES = ("roll", "pitch", "yaw")
#: First-order Gauss–Markov POS errors, attitude σ 0.012° with τ = 30 s, position as
#: the scenario gives (2 cm, τ = 20 s).
GAUSS_MARKOV = (
    "noise.pos.model=gauss_markov",
    "noise.pos.sigma_attitude_deg=[0.012,0.012,0.012]",
    "noise.pos.tau_attitude_s=[30,30,30]",
)


def sim_dataset(out, seed=0, *sets):
    args = ["sim", "dataset", "--scenario", "montreal", "--seed", str(seed), "--out", str(out)]
    for s in sets:
        args += ["--set", s]
    res = runner.invoke(app, args, env=WIDE)
    assert res.exit_code == 0, res.output
    return out


def calib_run(bundle, *args):
    return runner.invoke(app, ["calib", "run", str(bundle), *args], env=WIDE)


def one_line_error(res, code=1) -> str:
    assert res.exit_code == code, (res.exit_code, res.output)
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), res.stderr
    return lines[0]


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    return sim_dataset(tmp_path_factory.mktemp("b") / "montreal", 0, *GAUSS_MARKOV)


@pytest.mark.slow
def test_realistic_sigma_covers_the_truth_through_the_files(tmp_path):
    """The thesis estimator's realistic σ: 20 simulated bundles with Gauss–Markov POS errors, calibrated from the files
    (seed 0 by the command itself, the others by the function it calls, without plots):
    sigma_realistic_deg covers the truth at 2σ for ≥ 90 % of the 60 angles, while the formal σ
    is optimistic by an order of magnitude, and the report says by how much."""
    db = tmp_path / "history.sqlite"
    z, z_formal = [], []
    for seed in range(20):
        b = sim_dataset(tmp_path / f"s{seed}", seed, *GAUSS_MARKOV)
        if seed == 0:
            res = calib_run(b, "--db", str(db), "--mount", "mc", "--estimator", "thesis")
            assert res.exit_code == 0, res.output
        else:
            run_bundle(b, options=CalibrationOptions(estimator="thesis"), plots=False)
        doc = json.loads((b / "calib" / "result.json").read_text())
        truth = read_truth(b)["boresight_deg"]
        err = np.array([doc["boresight_deg"][a] - truth[a] for a in ANGLES])
        z.append(err / np.array([doc["sigma_realistic_deg"][a] for a in ANGLES]))
        z_formal.append(err / np.array([doc["sigma_deg"][a] for a in ANGLES]))
    z, z_formal = np.array(z), np.array(z_formal)
    assert np.mean(np.abs(z) <= 2.0) >= 0.90, z
    assert np.mean(np.abs(z_formal) <= 2.0) < 0.5  # the formal σ would mislead
    assert 0.6 < np.sqrt(np.mean(z**2)) < 1.4  # and the realistic one is not inflated
    # seed 0, written by the command: the report states the ratio realistic / formal
    doc = json.loads((tmp_path / "s0" / "calib" / "result.json").read_text())
    report = (tmp_path / "s0" / "calib" / "report.md").read_text()
    ratio = doc["sigma_realistic_over_formal"]
    assert min(ratio.values()) > 5
    assert (
        f"optimistic by a factor of {ratio['roll']:.1f} for roll, {ratio['pitch']:.1f} for "
        f"pitch and {ratio['yaw']:.1f} for yaw"
    ) in report
    assert [r.mount_id for r in list_results(db=db)] == ["mc"]


def test_run_writes_the_result_report_and_plots_and_records_history(tmp_path, bundle):
    db = tmp_path / "h.sqlite"
    out = tmp_path / "out"
    res = calib_run(bundle, "--out", str(out), "--db", str(db), "--vessel", "test-boat", "--mount", "m1")
    assert res.exit_code == 0, res.output
    doc = json.loads((out / "result.json").read_text())
    for key in (
        "boresight_deg",
        "sigma_deg",
        "sigma_scaled_deg",
        "sigma_realistic_deg",
        "correlation",
        "sigma0_squared",
        "chi2_test",
        "iterations",
        "converged",
        "planes",
        "passes",
        "n_points",
        "n_outliers",
        "runtime_s",
        "apriori_deg",
        "software_version",
    ):
        assert key in doc, key
    # the terse table: one row per angle with estimate, σ formal and σ realistic
    for a in ANGLES:
        row = re.search(rf"│ {a}\s*│\s*(\S+)\s*│\s*(\S+)\s*│\s*(\S+)\s*│", res.output)
        assert row, res.output
        est, formal, real = (float(x) for x in row.groups())
        assert est == pytest.approx(doc["boresight_deg"][a], abs=5e-5)
        assert formal == pytest.approx(doc["sigma_deg"][a], abs=5e-5)
        assert real == pytest.approx(doc["sigma_realistic_deg"][a], abs=5e-5)
    pngs = sorted(p.name for p in out.glob("*.png"))
    assert pngs == [
        "residuals_by_pass.png",
        "residuals_by_plane.png",
        "residuals_time.png",
        "target_T1.png",
        "target_T2.png",
        "tie_patches.png",  # the default GLS adds tie patches of the scene
    ]
    assert all((out / p).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in pngs)
    assert "![target_T2](target_T2.png)" in (out / "report.md").read_text()
    recs = list_results(db=db)
    assert [(r.vessel, r.mount_id) for r in recs] == [("test-boat", "m1")]
    assert "recorded in the calibration history as #" in res.output
    # default output directory, no history, no plots
    res = calib_run(bundle, "--no-history", "--no-plots", "--apriori-deg", "0.2,1.2,0.15")
    assert res.exit_code == 0, res.output
    doc2 = json.loads((bundle / "calib" / "result.json").read_text())
    assert doc2["apriori_deg"] == pytest.approx({"roll": 0.2, "pitch": 1.2, "yaw": 0.15})
    assert not list((bundle / "calib").glob("*.png")) and len(list_results(db=db)) == 1


def test_a_target_missing_from_one_pass_warns_and_the_run_continues(tmp_path):
    r = simulate("montreal", 1)
    keep = ~((r.target_index == 1) & (r.points.pass_id == 3))
    b = replace(r, points=r.points.select(keep)).write(tmp_path / "b")
    res = calib_run(b, "--no-history")
    assert res.exit_code == 0, res.output
    assert "warning: target T2 is missing from pass 3" in res.output
    doc = json.loads((b / "calib" / "result.json").read_text())
    # a pass's n_points are its targets' points (its tie-patch points are counted apart)
    assert doc["extraction"]["points_per_pass"]["3"] == {"T1": doc["passes"][2]["n_points"], "T2": 0}
    assert doc["passes"][2]["n_tie_patch_points"] > 0


@pytest.mark.parametrize(
    ("sets", "pattern"),
    [
        (
            ("site.passes=[{id: 1, relative_heading_deg: 0}, {id: 2, relative_heading_deg: 180}]",),
            r"boresight pitch and yaw are not observable with passes 1 \(0°\), 2 \(180°\).*for pitch "
            r"sail a side-looking reciprocal pair 45°/225° or 315°/135°; for yaw sail a crossing pair",
        ),
        (("scene.targets.1.size_m=[0.08, 0.08]",), r"target\(s\) with fewer than 10 points: T2 \(0 points\)"),
        (
            ("scene.targets=[{name: T1, along_m: -1.75, out_m: 0.03, up_m: 5.0, size_m: [1.23, 1.22]}]",),
            r"only one target \(T1\) has points",
        ),
    ],
)
def test_adjustment_errors_are_one_clear_line(tmp_path, sets, pattern):
    b = sim_dataset(tmp_path / "b", 0, *sets)
    line = one_line_error(calib_run(b, "--no-history"))
    assert re.search(pattern, line), line
    assert not (b / "calib" / "result.json").exists()


def _edit_points(src, dst, edit):
    import shutil

    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("calib"))
    lines = (dst / "points.csv").read_text().splitlines()
    edit(lines)
    (dst / "points.csv").write_text("\n".join(lines) + "\n")
    return dst


def test_bad_times_and_an_uncovering_trajectory_are_one_clear_line(tmp_path, bundle):
    def nan_time(lines):
        f = lines[6].split(",")
        lines[6] = ",".join([f[0], "nan", *f[2:]])

    def swap(lines):
        lines[9], lines[10] = lines[10], lines[9]

    line = one_line_error(calib_run(_edit_points(bundle, tmp_path / "nan", nan_time)))
    assert re.search(r"points\.csv:7:2: column 'gps_time' is 'nan', expected a finite number", line)
    line = one_line_error(calib_run(_edit_points(bundle, tmp_path / "swap", swap)))
    assert re.search(r"points\.csv:11:2: gps_time .* times must not decrease within a pass", line)
    cut = _edit_points(bundle, tmp_path / "cut", lambda lines: None)
    traj = (cut / "trajectory.csv").read_text().splitlines()
    (cut / "trajectory.csv").write_text("\n".join(traj[: len(traj) // 2]) + "\n")
    line = one_line_error(calib_run(cut, "--no-history"))
    assert "the trajectory does not cover the points" in line and "pass 6:" in line


@pytest.mark.parametrize(
    ("args", "code", "pattern"),
    [
        (["--apriori-deg", "1,2"], 2, r"--apriori-deg: got '1,2', expected three numbers"),
        (["--estimate", "scan_angle_offset"], 2, r"scan_angle_offset cannot be estimated"),
        (["--estimate", "lever_arm_z"], 2, r"unknown extra unknown\(s\) lever_arm_z"),
        (["--error-model", "pink"], 2, r"error model 'pink': expected one of gauss_markov"),
        (
            ["--estimator", "kalman"],
            2,
            r"estimator 'kalman' \(--estimator\): expected one of gls, thesis, pass_offsets",
        ),
        (["--tie-patches", "maybe"], 2, r"tie patches 'maybe' \(--tie-patches\): expected 'auto' or 'off'"),
        # the GLS default refuses a non-Gauss–Markov error model and says which estimator takes it
        (["--error-model", "white"], 2, r"error model 'white' goes with --estimator thesis or pass_offsets"),
        (["--subsample", "-0.1"], 2, r"--subsample -0.1: expected a positive voxel size"),
        (["--extraction", "manual"], 2, r"extraction mode 'manual'"),
        (["--correlation-time-s", "0"], 2, r"--correlation-time-s 0.0: expected a positive"),
    ],
)
def test_bad_options_are_one_clear_line(bundle, args, code, pattern):
    line = one_line_error(calib_run(bundle, *args), code)
    assert re.search(pattern, line), line


def test_a_session_is_exported_then_calibrated(tmp_path, monkeypatch, bundle):
    """A session directory goes through the export (office.jobs.export.export_session, replaced
    here by a copy of a simulated bundle) into SESSION/calib/bundle, then is calibrated."""
    import shutil

    import office.jobs.export
    from office.jobs.export import ExportResult

    session = tmp_path / "20190709T140000Z_boat"
    session.mkdir()
    (session / "seg-000001.mcap").write_bytes(b"")
    (session / "site.yaml").write_text("")  # the daemon's copy of the site file
    line = one_line_error(calib_run(session))  # the real export: an empty session
    assert line.startswith(f"error: {session} is a recorded session and could not be exported")
    assert f"run 'mls export {session} --bundle DIR' with its options" in line
    calls = []

    def fake_export(src, dst, options=None, progress=None):
        calls.append((Path(src), Path(dst)))
        shutil.copytree(bundle, dst, ignore=shutil.ignore_patterns("calib"))
        return ExportResult(
            bundle=Path(dst),
            epochs=100,
            epochs_from_clock=0,
            points=1000,
            points_per_pass={1: 1000},
            returns_outside_passes=0,
            packets=10,
            packets_unsynced=0,
            pass_source="events",
            passes=[],
        )

    monkeypatch.setattr(office.jobs.export, "export_session", fake_export)
    res = calib_run(session, "--no-history", "--no-plots")
    assert res.exit_code == 0, res.output
    assert calls == [(session, session / "calib" / "bundle")]
    assert "exported the session to" in res.output
    doc = json.loads((session / "calib" / "result.json").read_text())
    assert doc["source"] == str(session / "calib" / "bundle")


def test_a_missing_directory_is_one_clear_line(tmp_path):
    line = one_line_error(calib_run(tmp_path / "nowhere"))
    assert "not a directory" in line


def test_a_refused_result_exits_4_is_not_recorded_and_accept_refused_marks_it(tmp_path, bundle):
    """The trajectory claims a POS ten times better than the simulated one (per-epoch sigmas
    divided by 10) and the thesis estimator weighs by them: σ̂0² far beyond 2, the verdict is
    refused, the command says why, exits 4 and records nothing; with --accept-refused it records
    the result, still marked refused in the history."""
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(bundle, bad, ignore=shutil.ignore_patterns("calib"))
    lines = (bad / "trajectory.csv").read_text().splitlines()
    sigma_cols = [i for i, c in enumerate(lines[0].split(",")) if c.startswith("sigma_")]
    assert len(sigma_cols) == 6
    rows = [lines[0]]
    for line in lines[1:]:
        f = line.split(",")
        for i in sigma_cols:
            f[i] = repr(float(f[i]) / 10)
        rows.append(",".join(f))
    (bad / "trajectory.csv").write_text("\n".join(rows) + "\n")
    db = tmp_path / "h.sqlite"
    res = calib_run(bad, "--no-plots", "--estimator", "thesis", "--db", str(db), "--mount", "m1")
    assert res.exit_code == 4, res.output
    assert "verdict: refused" in res.output and "do not fit the error model" in res.output
    assert "verdict refused" in res.stderr and "not recorded" in res.stderr
    doc = json.loads((bad / "calib" / "result.json").read_text())
    assert doc["verdict"] == "refused" and doc["sigma0_squared"] > 2.0
    assert "## Verdict\n\n**refused**: do not use this result." in (bad / "calib" / "report.md").read_text()
    assert list_results(db=db) == []
    res = calib_run(
        bad,
        "--no-plots",
        "--estimator",
        "thesis",
        "--force",
        "--db",
        str(db),
        "--mount",
        "m1",
        "--accept-refused",
    )
    assert res.exit_code == 0, res.output
    [rec] = list_results(db=db)
    assert rec.verdict == "refused"
    hist = runner.invoke(app, ["calib", "history", "--db", str(db)], env=WIDE)
    assert hist.exit_code == 0 and "refused" in hist.output
