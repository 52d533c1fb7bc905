"""``mls calib assess`` end to end (typer runner): ``mls sim dataset`` → ``mls calib run`` →
``mls calib assess``, all through the CLI; the result.json assessed is the one ``mls calib run``
wrote for the simulated tower bundle (1° boresight error on each angle)."""

from __future__ import annotations

import json
import re

import pytest
from typer.testing import CliRunner

from calib.assess.summary import fmt_length
from cli.app import app

ENV = {"COLUMNS": "200", "MLS_HISTORY_DB": "/nonexistent/never-used.sqlite"}


def run(*args):
    return CliRunner().invoke(app, [str(a) for a in args], env=ENV)


def table_row(output: str, label: str) -> list[str]:
    line = next(l for l in output.splitlines() if l.strip("│ ").startswith(label + " "))
    return [c.strip() for c in line.strip().strip("│").split("│")]


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    bundle, calib = d / "tower", d / "calib"
    r = run(
        "sim",
        "dataset",
        "--scenario",
        "tower",
        "--seed",
        5,
        "--out",
        bundle,
        "--set",
        "truth.boresight_deg=[1.0, 1.0, 1.0]",
    )
    assert r.exit_code == 0, r.output
    r = run("calib", "run", bundle, "--out", calib, "--no-history", "--no-plots")
    assert r.exit_code == 0, r.output
    assert (calib / "result.json").exists()
    return bundle, calib / "result.json"


def test_assess_prints_tables_and_writes_the_report(calibrated, tmp_path):
    bundle, result = calibrated
    out = tmp_path / "assess"
    r = run("calib", "assess", bundle, "--result", result, "--out", out, "--pairs", "1:2", "--knn", 12)
    assert r.exit_code == 0, r.output
    assert "passes 1 (215°) ↔ 2 (35°): median C2C (mm), local LS planes k = 12" in r.output
    v3 = table_row(r.output, "V3")  # surface, height, returns, before, after, ×, …
    height, before_mm, after_mm = float(v3[1]), float(v3[3]), float(v3[4])
    assert 37.0 < height < 39.5
    assert 1200 < before_mm < 1450 and after_mm < 100  # 2·h·tan(1°) = 1.33 m before
    assert table_row(r.output, "overlap")[0] == "overlap"
    fit = table_row(r.output, "1:2")
    assert float(fit[1]) > 25.0 and abs(float(fit[2])) < 2.0  # mm per metre of height
    assert re.search(r"median C2C on V3 \(38 m\) went from 1\.\d\d m to \d+(\.\d)? mm", r.output)
    doc = json.loads((out / "assessment.json").read_text())
    c = next(c for c in doc["comparisons"] if c["name"] == "V3")
    assert c["before"]["median_m"] * 1e3 == pytest.approx(before_mm, abs=0.5)
    assert doc["k"] == 12 and doc["pairs"] == [[1, 2]]
    md = (out / "assessment.md").read_text()
    assert "## Passes 1 (215°) ↔ 2 (35°)" in md and "went from" in md
    # the per-plane table: count, mean, median, RMS and 95th percentile, before and after
    head = next(line for line in md.splitlines() if line.startswith("| surface |"))
    md_v3 = next(line for line in md.splitlines() if line.startswith("| V3 |"))
    cells = dict(zip([h.strip() for h in head.split("|")], [x.strip() for x in md_v3.split("|")]))
    for when in ("before", "after"):
        for stat in ("mean", "median", "RMS", "p95"):
            key = {"RMS": "rms_m", "p95": "p95_m"}.get(stat, f"{stat}_m")
            assert cells[f"{when} {stat}"] == fmt_length(c[when][key]), (when, stat)
    assert cells["returns"] == f"{c['after']['count']:,}"
    compared = {c["name"] for c in doc["comparisons"]}
    assert {"V1", "V2", "V3", "V5", "overlap"} <= compared
    figures = {p.name for p in out.glob("*.png")}
    assert figures == {"height_1-2.png"} | {f"hist_1-2_{n}.png" for n in compared}
    for name in compared - {"overlap"}:
        assert f"![hist_1-2_{name}](hist_1-2_{name}.png)" in md
    if "V4" not in compared:  # its two patches overlap too little with the 1° error: said so
        assert "note: V4: passes 1:2 overlap on" in r.output
    assert r.output.rstrip().endswith("figures")  # the tables end the output, with what was written


def test_assess_errors_are_one_clear_line(calibrated, tmp_path):
    bundle, result = calibrated
    r = run("calib", "assess", bundle, "--result", result, "--out", tmp_path, "--pairs", "1-2")
    assert r.exit_code == 2 and "pair '1-2': expected two pass ids A:B" in r.output
    r = run("calib", "assess", bundle, "--result", tmp_path / "none.json", "--out", tmp_path)
    assert r.exit_code == 1 and "none.json: file not found" in r.output
    r = run("calib", "assess", bundle, "--result", result, "--out", tmp_path, "--pairs", "1:8")
    assert r.exit_code == 1 and "pass 8 (pair 1:8) has no returns" in r.output
    r = run("calib", "assess", tmp_path / "nowhere", "--result", result, "--out", tmp_path)
    assert r.exit_code == 1 and "nowhere: not a directory" in r.output
    assert not (tmp_path / "assessment.md").exists()
