"""The calibration report (calib.boresight.report): what report.md says matches the result, the
edge-on views show the passes' copies of a target merging, and the plots are written."""

from __future__ import annotations

import struct
from dataclasses import replace

import numpy as np
import pytest

from calib.boresight.pipeline import CalibrationOptions, calibrate
from calib.boresight.report import edge_on, report_markdown, write_report
from calib.sim.simulate import simulate


@pytest.fixture(scope="module")
def misaligned():
    """Montreal with a 1.5° boresight error in every angle and Gauss–Markov POS errors."""
    r = simulate("montreal", 5, overrides={"truth.boresight_deg": [1.5, -1.5, 1.5]})
    return r, calibrate(
        r.site, r.trajectory_observed, r.points, CalibrationOptions(), source="simulated montreal seed 5"
    )


def _row(md: str, first_cell: str) -> list[str]:
    line = next(x for x in md.splitlines() if x.startswith(f"| {first_cell} |"))
    return [c.strip().strip("*") for c in line.strip("|").split("|")]


def test_the_narrative_states_the_numbers_of_the_result(misaligned):
    _, run = misaligned
    res, doc = run.result, run.doc
    md = report_markdown(run)
    for a in ("roll", "pitch", "yaw"):
        cells = _row(md, a)
        assert float(cells[1]) == pytest.approx(doc["boresight_deg"][a], abs=5e-5)
        assert float(cells[2]) == pytest.approx(doc["boresight_thesis_convention_deg"][a], abs=5e-5)
        assert float(cells[3]) == pytest.approx(doc["sigma_deg"][a], rel=5e-3)
        assert float(cells[5]) == pytest.approx(doc["sigma_realistic_deg"][a], rel=5e-3)
        assert float(cells[6]) == pytest.approx(doc["sigma_jackknife_deg"][a], rel=5e-3)
        assert float(cells[7]) == pytest.approx(doc["sigma_realistic_over_formal"][a], abs=0.05)
    # the default GLS: its formal σ is its realistic σ, nothing to call optimistic
    assert doc["estimator"] == "gls"
    assert all(v == pytest.approx(1.0, abs=0.05) for v in doc["sigma_realistic_over_formal"].values())
    assert "optimistic by a factor" not in md
    assert "correlation time 20/20/20/10/10/10 s (N/E/D/roll/pitch/heading) (from site.yaml" in md
    c = res.chi2_test()
    assert f"σ̂0² = {res.sigma0_squared:.3f} with {c['df']} degrees of freedom" in md
    assert ("**passed**" in md) == c["passed"]
    assert f"converged in {res.iterations} iterations" in md
    corr_row = next(x for x in md.split("## Correlations")[1].splitlines() if x.startswith("| pitch"))
    assert [float(x) for x in corr_row.strip("|").split("|")[1:]] == pytest.approx(
        res.correlation[1], abs=5e-4
    )
    assert "- roll: observed best by the reciprocal parallel pair 0°/180°; sailed: 0°/180°." in md
    assert "sailed: 45°/135°, 315°/225°." in md
    for p in res.plane_stats:
        assert int(_row(md, p["name"])[1]) == p["n_points"]
    counts = run.extraction.counts()
    for p in res.pass_stats:
        cells = _row(md, str(p["id"]))
        assert [int(x) for x in cells[2:4]] == [counts[p["id"]]["T1"], counts[p["id"]]["T2"]]
    assert "No point failed the data-snooping test" in md
    assert "POS σ per point from the trajectory's per-epoch sigmas" in md


def test_edge_on_views_show_the_passes_merging(misaligned):
    """Before the calibration the six copies of each target are centimetres to decimetres
    apart; after it they lie on one plane to within the POS errors."""
    r, run = misaligned
    for name, e in edge_on(run).items():
        k = e["pass_index"]
        offsets_before = [np.mean(e["before_m"][k == i]) for i in np.unique(k)]
        offsets_after = [np.mean(e["after_m"][k == i]) for i in np.unique(k)]
        assert np.ptp(offsets_before) > 0.1, name
        assert np.ptp(offsets_after) < 0.06, name
        assert np.sqrt(np.mean(e["after_m"] ** 2)) < 0.2 * np.sqrt(np.mean(e["before_m"] ** 2))
        width = next(t.width_m for t in r.site.targets if t.name == name)
        assert np.ptp(e["along_after_m"]) == pytest.approx(width, abs=0.1)
        assert np.ptp(e["along_before_m"]) > width + 0.2  # the copies also slid along it


def _png_size(path) -> tuple[int, int]:
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", head[16:24])


def test_plots_are_written_and_linked(tmp_path, misaligned):
    _, run = misaligned
    paths = write_report(run, tmp_path)
    assert [p.name for p in paths] == [
        "report.md",
        "residuals_by_plane.png",
        "residuals_by_pass.png",
        "residuals_time.png",
        "tie_patches.png",
        "target_T1.png",
        "target_T2.png",
    ]
    assert _png_size(tmp_path / "target_T1.png") == (1100, int(round(3.8 * 110)))  # 2 panels
    assert _png_size(tmp_path / "residuals_by_pass.png")[0] == int(round(3 * 4.2 * 110))
    md = (tmp_path / "report.md").read_text()
    assert md.count("](") == 6 and "![residuals_time](residuals_time.png)" in md
    assert write_report(run, tmp_path / "bare", plots=False) == [tmp_path / "bare" / "report.md"]


def test_white_model_default_tau_and_outliers_are_stated():
    r = simulate("montreal", 6, overrides={"noise.pos.model": "per_point"})
    ranges = r.points.range_m.copy()
    blunders = np.flatnonzero(r.target_index == 0)[[50, 700, 1500]]
    ranges[blunders] += 0.5
    pts = replace(r.points, range_m=ranges)
    site = replace(r.site, pos_correlation_time_s=None)
    # labelled points: the extraction's plane band would already drop such blunders
    run = calibrate(
        site,
        r.trajectory_observed,
        pts,
        CalibrationOptions(estimator="thesis", error_model="white"),
        poses=r.observed_poses(),
        labels=r.target_index,
    )
    md = report_markdown(run)
    assert "here it equals the formal σ, because the white error model was chosen" in md
    assert set(blunders) <= set(run.result.outlier_point_ids.tolist())
    assert "failed the data-snooping test on normalized residuals and were removed" in md
    assert all(str(int(i)) in md.split("## Outliers")[1] for i in blunders)
    gm = calibrate(
        site,
        r.trajectory_observed,
        pts,
        CalibrationOptions(estimator="thesis", jackknife=False),
        poses=r.observed_poses(),
    )
    assert "sigma_realistic assumes 60 s" in report_markdown(gm)
