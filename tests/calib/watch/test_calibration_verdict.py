"""``mls watch`` says when the calibration it tests against is not trusted (result.json's
``verdict``; an older result has none)."""

from __future__ import annotations

import json

from calib.watch.report import OLDER_CALIBRATION, add_calibration_verdict, calibration_verdict


def test_a_trusted_calibration_is_named_without_a_warning():
    line, warning = calibration_verdict({"verdict": "trusted", "verdict_reasons": []})
    assert line == "calibration verdict: trusted" and warning is None


def test_a_questionable_or_refused_calibration_warns_with_its_reasons():
    line, warning = calibration_verdict({"verdict": "refused", "verdict_reasons": ["χ² 3.1", "lost T2"]})
    assert line == "calibration verdict: refused (χ² 3.1; lost T2)"
    assert warning is not None and warning.startswith("the calibration is refused (χ² 3.1; lost T2)")


def test_an_older_result_has_no_verdict_and_no_calibration_has_no_line():
    line, warning = calibration_verdict({"boresight_deg": {}})
    assert line == f"calibration verdict: {OLDER_CALIBRATION}" and "older calibration" in str(warning)
    assert calibration_verdict(None) == (None, None)


def test_the_verdict_goes_under_the_watchs_own_in_watch_md_and_into_watch_json(tmp_path):
    (tmp_path / "watch.md").write_text("# Mount watch\n\n**mount steady**\n\n- source: `x`\n")
    (tmp_path / "watch.json").write_text(json.dumps({"verdict": "mount steady"}))
    add_calibration_verdict(
        tmp_path, "calibration verdict: questionable (x)", "the calibration is questionable"
    )
    md = (tmp_path / "watch.md").read_text().split("\n")
    assert md[:7] == [
        "# Mount watch",
        "",
        "**mount steady**",
        "",
        "> **Warning:** the calibration is questionable",
        "",
        "- calibration verdict: questionable (x)",
    ]
    doc = json.loads((tmp_path / "watch.json").read_text())
    assert doc["calibration_verdict"] == "calibration verdict: questionable (x)"
    assert doc["calibration_warning"] == "the calibration is questionable"
