"""``mls watch`` says when the calibration it tests against is not trusted (result.json's
``verdict``; an older result has none): the verdict line from the calibration's provenance,
written by the report itself under the watch's own verdict."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from calib.io.site import load_site
from calib.watch.report import OLDER_CALIBRATION, _calibration_lines, calibration_verdict
from office.deliver.calibration import load_calibration

SITE = Path(__file__).resolve().parents[3] / "examples" / "montreal-mini" / "site.yaml"


def provenance(tmp_path, **result) -> tuple[dict, str | None]:
    """The provenance and untrusted warning of a result.json with these fields."""
    sigma = {"roll": 0.01, "pitch": 0.01, "yaw": 0.02}
    doc = {
        "boresight_deg": {"roll": 0.1, "pitch": 0.2, "yaw": 0.3},
        **{k: sigma for k in ("sigma_deg", "sigma_scaled_deg", "sigma_realistic_deg")},
        "correlation": np.eye(3).tolist(),
        "sigma0_squared": 1.0,
        "n_points": 1000,
        "software_version": "test",
        **result,
    }
    (tmp_path / "result.json").write_text(json.dumps(doc))
    cal = load_calibration(load_site(SITE), str(tmp_path / "result.json"), "test")
    return cal.provenance, cal.untrusted


def test_a_trusted_calibration_is_named_without_a_warning(tmp_path):
    prov, warning = provenance(tmp_path, verdict="trusted", verdict_reasons=[])
    assert calibration_verdict(prov) == "calibration verdict: trusted" and warning is None


def test_a_questionable_or_refused_calibration_warns_with_its_reasons(tmp_path):
    prov, warning = provenance(tmp_path, verdict="refused", verdict_reasons=["χ² 3.1", "lost T2"])
    assert calibration_verdict(prov) == "calibration verdict: refused (χ² 3.1; lost T2)"
    assert warning is not None and "REFUSED: χ² 3.1; lost T2" in warning


def test_an_older_result_has_no_verdict_and_no_calibration_has_no_line(tmp_path):
    prov, warning = provenance(tmp_path)
    assert calibration_verdict(prov) == f"calibration verdict: {OLDER_CALIBRATION}"
    assert "no verdict" in str(warning)
    assert calibration_verdict({"calibration": None}) is None


def test_the_verdict_goes_under_the_watchs_own_with_its_warning_first():
    meta = {"calibration_verdict": "calibration verdict: questionable (x)", "calibration_warning": "w"}
    assert _calibration_lines(meta) == ["> **Warning:** w", "", "- calibration verdict: questionable (x)"]
    assert _calibration_lines({"calibration_verdict": None, "calibration_warning": None}) == []
