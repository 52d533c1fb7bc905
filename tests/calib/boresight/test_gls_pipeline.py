"""The calibration pipeline with its default estimator (GLS with tie patches) on the
simulator's Montreal site, in memory: what result.json and the report say, and the
``--tie-patches off`` and ``--estimator thesis`` routes."""

from __future__ import annotations

import numpy as np
import pytest

from calib.boresight.pipeline import CalibrationOptions, calibrate
from calib.boresight.report import report_markdown
from calib.boresight.report_gls import tie_patch_plot
from calib.sim.simulate import simulate


@pytest.fixture(scope="module")
def sim():
    return simulate("montreal", 3)


def _run(r, **kw):
    return calibrate(r.site, r.trajectory_observed, r.points, CalibrationOptions(jackknife=False, **kw))


@pytest.fixture(scope="module")
def default_run(sim):
    return _run(sim)


def test_the_default_is_gls_with_tie_patches_seen_from_two_passes(sim, default_run):
    run = default_run
    doc, res = run.doc, run.result
    assert doc["estimator"] == "gls" and doc["tie_patches_mode"] == "auto"
    assert res.converged
    patches = doc["tie_patches"]
    assert patches, doc.get("tie_patch_candidates")
    assert all(len(set(p["passes"])) >= 2 for p in patches)
    assert doc["tie_patch_candidates"]["found"] >= len(patches)
    kinds = {p["name"]: p["kind"] for p in doc["planes"]}
    assert {p["name"] for p in patches} == {n for n, k in kinds.items() if k == "tie patch"}
    assert {n for n, k in kinds.items() if k == "target"} == {"T1", "T2"}
    assert all(p["roughness_m"] is not None and p["roughness_m"] >= 0 for p in doc["planes"])
    # the thesis estimator and the targets-only GLS are stated beside it
    assert set(doc["thesis_estimator"]) == {"boresight_deg", "sigma_realistic_deg"}
    assert set(doc["targets_only"]) == {"boresight_deg", "sigma_realistic_deg"}
    # the estimate covers the simulator's truth (σ realistic is the GLS σ)
    err = np.abs(res.boresight_rad - sim.mount_true.boresight_rad)
    assert np.all(err <= 3 * res.sigma_realistic_rad), (err, res.sigma_realistic_rad)


def test_the_report_has_the_estimator_section_and_the_tie_patch_plot(tmp_path, default_run):
    md = report_markdown(default_run)
    assert "## Estimator" in md
    section = md.split("## Estimator")[1]
    assert "| **GLS (default)** |" in section
    thesis = next(x for x in section.splitlines() if x.startswith("| thesis (white weights) |"))
    cells = [c.strip() for c in thesis.strip("|").split("|")][1:]
    for cell, b, s in zip(
        cells,
        default_run.doc["thesis_estimator"]["boresight_deg"],
        default_run.doc["thesis_estimator"]["sigma_realistic_deg"],
    ):
        est, sig = (float(x) for x in cell.split("±"))
        assert est == pytest.approx(b, abs=5e-5) and sig == pytest.approx(s, abs=5e-5)
    for p in default_run.doc["tie_patches"]:
        assert f"| {p['name']} |" in section
    # the plot of where the patches are (write_report writes it among the others)
    assert tie_patch_plot(default_run, tmp_path) == tmp_path / "tie_patches.png"
    assert (tmp_path / "tie_patches.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "![tie_patches](tie_patches.png)" in report_markdown(default_run, ["tie_patches.png"])


def test_tie_patches_off_gives_targets_only(sim, default_run):
    run = _run(sim, tie_patches="off")
    doc = run.doc
    assert doc["estimator"] == "gls" and doc["tie_patches_mode"] == "off"
    assert "tie_patches" not in doc and "targets_only" not in doc
    assert [p["kind"] for p in doc["planes"]] == ["target", "target"]
    assert not run.observations.patch_planes
    # the same as the default run's solution before its patches
    np.testing.assert_allclose(
        doc["boresight_deg"]["roll"], default_run.doc["targets_only"]["boresight_deg"][0], atol=1e-6
    )
    assert "Tie patches: off" in report_markdown(run)


def test_the_thesis_estimator_is_the_old_behaviour(sim, default_run):
    """--estimator thesis: white weights, no tie patches, no comparison, and the realistic σ
    larger than the formal one under the scenario's Gauss–Markov POS errors; its estimate is
    the comparison row of the default run."""
    run = _run(sim, estimator="thesis")
    doc, res = run.doc, run.result
    assert doc["estimator"] == "thesis"
    assert "tie_patches" not in doc and "thesis_estimator" not in doc
    assert [p["kind"] for p in doc["planes"]] == ["target", "target"]
    assert np.all(res.sigma_realistic_rad > 3 * res.sigma_formal_rad)
    np.testing.assert_allclose(
        np.degrees(res.boresight_rad), default_run.doc["thesis_estimator"]["boresight_deg"], atol=1e-7
    )
    np.testing.assert_allclose(
        np.degrees(res.sigma_realistic_rad),
        default_run.doc["thesis_estimator"]["sigma_realistic_deg"],
        rtol=1e-6,
    )
    md = report_markdown(run)
    assert "Estimator: thesis" in md
