"""Lines for yaw (calib.design.yawlines): what piles and lines farther out buy the boresight yaw,
predicted as the GLS σ (the Cramér–Rao bound of the model) from one noise-free simulation."""

from __future__ import annotations

import csv
from dataclasses import replace

import numpy as np
import pytest
from typer.testing import CliRunner

from calib.boresight.covariance import predict_covariance
from calib.boresight.errormodel import ErrorModel
from calib.boresight.oracle import MAX_POINTS, dense_gls
from calib.design.layouts import default_spec
from calib.design.passpredict import (
    ObservationModel,
    predict_pass,
    predict_sigma,
    rank_candidates,
    weakest_angle,
)
from calib.design.prediction import DesignError, Sigmas, feature_observations, select_passes
from calib.design.study import run_study
from calib.design.whatif import site_as_scenario, what_if
from calib.design.yawlines import best_for_yaw, predict_yaw_lines, yaw_lines_markdown, yaw_scenario
from calib.io.site import PassSpec, load_site
from calib.sim.scenariofile import load_scenario
from calib.sim.simulate import simulate
from calib.survey.passplan import plan_site
from cli.app import app


@pytest.fixture(scope="module")
def piles():
    return load_scenario("montreal_piles")


@pytest.fixture(scope="module")
def rows(piles):
    return predict_yaw_lines(piles, Sigmas.of_scenario(piles), (20.0, 60.0))


def _row(rows, lines_prefix, features):
    return next(r for r in rows if r["lines"].startswith(lines_prefix) and r["features"] == features)


def test_the_added_lines_are_parallel_pairs_at_their_own_standoff(piles):
    sc, sets = yaw_scenario(piles, (20.0, 60.0))
    plan = sc.pass_plan()
    added = [p for p in plan.passes if p.id > 6]
    assert [round(np.degrees(p.relative_heading_rad)) for p in added] == [0, 180, 0, 180]
    assert [p.standoff_m for p in added] == pytest.approx([35.0, 35.0, 75.0, 75.0])
    assert [len(s.pass_ids) for s in sets] == [6, 8, 8, 10]
    assert sets[-1].added_time_s == pytest.approx(4 * 60.0 / 2.0)
    assert sc.surfaces and all(s.kind == "target" for s in sc.surfaces) and len(sc.piles) == 5
    with pytest.raises(DesignError, match="offsets"):
        yaw_scenario(piles, (20.0, -5.0))


def test_piles_and_farther_lines_sharpen_yaw_and_never_blur_an_angle(rows):
    angles = ("roll", "pitch", "yaw")
    for lines in ("own", "+ 2 lines at 35", "+ 2 lines at 75", "+ 4"):
        t, p = _row(rows, lines, "targets"), _row(rows, lines, "targets+piles")
        assert p["n_piles"] == 5 and t["n_piles"] == 0 and p["n_points"] > t["n_points"]
        # more data under the same model: the bound can only shrink
        assert all(p[f"sigma_{a}_deg"] <= t[f"sigma_{a}_deg"] * (1 + 1e-9) for a in angles)
    own, near, far, both = (
        _row(rows, x, "targets+piles")["sigma_yaw_deg"]
        for x in ("own", "+ 2 lines at 35", "+ 2 lines at 75", "+ 4")
    )
    # a pile moves by range × δψ: the farther the second standoff, the sharper the yaw
    assert own > near > far >= both
    assert far < 0.7 * own
    assert _row(rows, "own", "targets")["yaw_gain"] == pytest.approx(1.0)
    assert best_for_yaw(rows)["features"] == "targets+piles"


def test_the_prediction_is_the_dense_oracles_bound(piles):
    """The σ of a line set equals the dense (unstructured) oracle's Cramér–Rao bound of the same
    observations: the banded GLS loses nothing (every k-th point, to keep the oracle small)."""
    sc, sets = yaw_scenario(piles, (40.0,))
    sigmas = Sigmas.of_scenario(piles)
    sim = simulate(sc, 0)
    obs, features = feature_observations(sim, sigmas, 0.005)
    o, f = select_passes(obs, features, sets[1].pass_ids)
    o = o.select(np.arange(len(o)) % (len(o) // (MAX_POINTS - 500) + 1) == 0)
    assert len(set(o.plane_index)) == len(f) == 7
    model = ErrorModel("gauss_markov", tuple(sigmas.correlation_time_s))
    gls = predict_covariance(o, sim.mount_true, f, (), model, estimator="gls")["realistic"]
    oracle = dense_gls(o, sim.mount_true, f, model)
    np.testing.assert_allclose(np.sqrt(np.diag(gls)), oracle.crlb_sigma_rad, rtol=1e-5)


def test_a_scene_without_piles_predicts_the_targets_alone_and_says_so():
    base = load_scenario("montreal")
    rows = predict_yaw_lines(base, Sigmas.of_scenario(base), (30.0,))
    assert {r["features"] for r in rows} == {"targets"} and len(rows) == 2
    text = "\n".join(yaw_lines_markdown(rows))
    assert "no pile the passes see" in text and "| + 2 lines at 45 m | 2 (60 s) | targets |" in text
    assert yaw_lines_markdown([], "pass 7: its closest approach is only 2.00 m")[-1].startswith(
        "Not predicted: pass 7"
    )


def test_mls_design_writes_the_yaw_lines_table_and_refuses_bad_offsets(tmp_path):
    out = tmp_path / "study"
    args = [
        "design",
        "--scenario",
        "montreal_piles",
        "--group",
        "yaw_lines",
        "--error",
        "none",
        "--no-figures",
    ]
    res = CliRunner().invoke(app, [*args, "--yaw-line-offsets", "20,60", "--out", str(out)])
    assert res.exit_code == 0, res.output
    with open(out / "yaw_lines.csv", encoding="utf-8") as fh:
        table = list(csv.DictReader(fh))
    assert len(table) == 8 and {r["features"] for r in table} == {"targets", "targets+piles"}
    assert "## Lines for yaw" in (out / "summary.md").read_text(encoding="utf-8")
    assert "for yaw: sail" in res.output
    bad = CliRunner().invoke(app, [*args, "--yaw-line-offsets", "20,far", "--out", str(tmp_path / "x")])
    assert bad.exit_code == 2 and "--yaw-line-offsets" in bad.output


def test_the_study_runs_the_yaw_lines_group_only_when_asked(piles):
    res = run_study(piles, default_spec(piles, groups=(), errors=()))
    assert res.yaw_lines == [] and res.yaw_lines_note == ""


def test_a_site_configs_piles_give_the_what_if_its_lines_for_yaw(piles, rows, tmp_path):
    """A simulated bundle's site.yaml lists the scene's piles; the what-if reads them back to
    the same piles and predicts the same lines for yaw as the scenario (same sigmas, motion)."""
    site_file = tmp_path / "site.yaml"
    piles.site().dump(site_file)
    site = load_site(site_file)
    assert [p.name for p in site.piles] == ["P1", "P2", "P3", "P4", "P5"]
    sc = site_as_scenario(site, piles)
    for got, want in zip(sc.piles, piles.piles, strict=True):
        for attr in ("along_m", "out_m", "bottom_up_m", "top_up_m", "diameter_m"):
            assert getattr(got, attr) == pytest.approx(getattr(want, attr), abs=1e-6), attr
    w = what_if(site, piles)
    assert w.yaw_lines and w.yaw_lines_note == ""
    want = predict_yaw_lines(piles, Sigmas.of_scenario(piles))
    np.testing.assert_allclose(
        [r["sigma_yaw_deg"] for r in w.yaw_lines], [r["sigma_yaw_deg"] for r in want], rtol=0.02
    )
    no_piles = what_if(load_scenario("montreal").site(), "montreal")
    assert no_piles.yaw_lines == [] and "no piles" in no_piles.yaw_lines_note


def test_the_live_prediction_counts_the_sites_piles_and_names_the_far_line_for_yaw(piles):
    """The guidance's σ prediction (calib.design.passpredict) with the piles of site.yaml: they
    sharpen yaw, and once the six-fold is sailed the line that helps the weakest angle (yaw) most
    is the far one, not another line at the standoff."""
    extra = (
        PassSpec(7, 0.0, 60.0, 2.0, 75.0),
        PassSpec(8, np.pi, 60.0, 2.0, 75.0),
        PassSpec(9, 0.0, 60.0, 2.0),
    )
    site = replace(piles.site(), passes=piles.site().passes + extra)
    frame = site.reference
    plan = plan_site(site, track_down_m=1.65, capture_margin_m=6.0)
    rects = site.target_rectangles(frame)
    cyls = [p.cylinder(frame) for p in site.piles]
    model = ObservationModel.from_site(site)
    geo = {
        pp.id: predict_pass(
            pp, rects, site.mount, piles.scanner, frame, t_start_gps_s=200.0 * pp.order, piles=cyls
        )
        for pp in plan.passes
    }
    sailed = [geo[i] for i in range(1, 7)]
    assert any(np.any(g.target_index >= len(rects)) for g in sailed)  # the piles' returns
    targets_only = [replace(g, **_only_targets(g, len(rects))) for g in sailed]
    with_piles = predict_sigma(sailed, [*rects, *cyls], site.mount, model)
    without = predict_sigma(targets_only, rects, site.mount, model)
    assert with_piles.observable.all() and without.observable.all()
    assert with_piles.realistic_rad[2] < 0.85 * without.realistic_rad[2]
    assert np.all(with_piles.realistic_rad <= without.realistic_rad * (1 + 1e-9))
    ranking = rank_candidates(sailed, {i: geo[i] for i in (7, 8, 9)}, [*rects, *cyls], site.mount, model)
    weak = weakest_angle(with_piles, ranking)
    assert weak["angle"] == "yaw" and weak["best_pass"] in (7, 8), (weak, ranking)


def _only_targets(g, n_targets: int) -> dict:
    keep = g.target_index < n_targets
    return {
        "t_gps_s": g.t_gps_s[keep],
        "range_m": g.range_m[keep],
        "scan_angle_rad": g.scan_angle_rad[keep],
        "target_index": g.target_index[keep],
    }
