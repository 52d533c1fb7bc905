"""``mls watch BUNDLE``: a production survey whose mount moved mid-way gives the alarm on the
angle that moved, after the event, with the report (markdown, JSON, plot) and exit status 3; the
same survey against the mount it really had says steady; a non-empty report directory is
refused without --force; a session without pass marks is cut into lines by its heading."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from typer.testing import CliRunner

from calib.boresight.result import write_result
from calib.core.frames import LocalFrame
from calib.core.trajectory import Trajectory
from calib.sim.production import MountEvent, ProductionSpec, simulate_production
from cli.app import app
from office.deliver.surveylines import lines_from_heading

#: one worker computes the module's costly fixtures once (spread over two, each computed them)
pytestmark = pytest.mark.xdist_group("cli-watch")

ENV = {"COLUMNS": "250"}


def result_doc(boresight_deg) -> dict:
    r, p, y = (float(x) for x in boresight_deg)
    return {
        "boresight_deg": {"roll": r, "pitch": p, "yaw": y},
        "sigma_deg": {"roll": 0.003, "pitch": 0.003, "yaw": 0.01},
        "sigma_scaled_deg": {"roll": 0.003, "pitch": 0.003, "yaw": 0.01},
        "sigma0_squared": 1.0,
        "n_points": 1000,
        "sigma_realistic_deg": {"roll": 0.003, "pitch": 0.003, "yaw": 0.01},
        "correlation": np.eye(3).tolist(),
        "software_version": "marine-mls test",
        "extras": {},
    }


@pytest.fixture(scope="module")
def moved(tmp_path_factory):
    root = tmp_path_factory.mktemp("watch")
    # a 0.2° roll step during line 3 (lines of 250 m at 1.5–3.5 m/s take 70–170 s)
    ev = MountEvent(t_s=300.0, step_rad=np.radians([0.2, 0.0, 0.0]))
    sim = simulate_production(
        "montreal", ProductionSpec(n_lines=6, line_length_m=250.0, mount_event=ev), seed=5
    )
    bundle = sim.write(root / "bundle")
    write_result(root / "calibrated.json", result_doc(sim.truth["mount_calibrated"]))
    after = np.asarray(sim.truth["mount_calibrated"]) + [0.2, 0.0, 0.0]
    write_result(root / "after.json", result_doc(after))
    return root, bundle, sim


def test_a_moved_mount_is_reported_with_its_angle_and_time(moved):
    root, bundle, sim = moved
    out = root / "report"
    res = CliRunner().invoke(
        app,
        ["watch", str(bundle), "--calibration", str(root / "calibrated.json"), "--out", str(out)],
        env=ENV,
    )
    assert res.exit_code == 3, res.output
    assert "MOUNT SHIFT" in res.output and "roll" in res.output
    doc = json.loads((out / "watch.json").read_text())
    alarm = doc["alarm"]
    assert alarm["angles"] == ["roll"]
    t_ev = sim.truth["mount_event"]["t_gps_s"]
    assert alarm["t_gps_s"] > t_ev
    assert abs(alarm["size_deg"][0] - 0.2) < 4 * alarm["sigma_deg"][0] + 0.01
    assert (out / "watch.png").stat().st_size > 10_000
    md = (out / "watch.md").read_text()
    assert "MOUNT SHIFT" in md and "Where the information came from" in md
    assert "| block | family | lines |" in md and {b["family"] for b in doc["blocks"]} == {0, 1}
    # the report exists: not replaced without --force
    again = CliRunner().invoke(app, ["watch", str(bundle), "--out", str(out)], env=ENV)
    assert again.exit_code == 1 and "--force" in again.output


def test_against_the_mount_it_had_after_the_event_the_last_lines_are_steady(moved):
    root, bundle, sim = moved
    out = root / "after"
    res = CliRunner().invoke(
        app, ["watch", str(bundle), "-c", str(root / "after.json"), "--out", str(out), "--no-plot"], env=ENV
    )
    doc = json.loads((out / "watch.json").read_text())
    t_ev = sim.truth["mount_event"]["t_gps_s"]
    late = [b for b in doc["blocks"] if b["status"] == "ok" and b["t_start_gps_s"] > t_ev]
    assert late, doc["blocks"]
    for b in late:  # measured against the mount it really had: roll steady within 4σ
        assert abs(b["delta_deg"][0]) < 4 * b["sigma_deg"][0] + 0.005
    assert not (out / "watch.png").exists()
    assert res.exit_code in (0, 3)  # the lines before the event moved the other way


def test_a_survey_without_marks_is_cut_into_lines_by_its_heading():
    # 100 s north at 2 m/s, a 40-s turn, 120 s south, a 40-s turn, 100 s north; 10-Hz epochs
    t = np.arange(0.0, 400.0, 0.1)
    h = np.interp(t, [0, 100, 140, 260, 300, 400], [0, 0, math.pi, math.pi, 2 * math.pi, 2 * math.pi])
    h = (h + np.random.default_rng(0).normal(0, math.radians(1.0), h.size)) % (2 * math.pi)
    step = 2.0 * 0.1 * np.column_stack([np.cos(h), np.sin(h), np.zeros_like(h)])
    traj = Trajectory(
        1e9 + t,
        np.cumsum(step, axis=0),
        np.column_stack([np.zeros((t.size, 2)), h]),
        LocalFrame(45.5, -73.5, 0.0),
    )
    lines = lines_from_heading(traj, min_line_s=20.0)
    assert [i for i, _, _ in lines] == [1, 2, 3]
    for (_, a, b), (a0, b0) in zip(lines, [(0, 100), (140, 260), (300, 399.9)]):
        assert abs(a / 1e9 - 1e9 - a0) <= 6 and abs(b / 1e9 - 1e9 - b0) <= 6, lines
