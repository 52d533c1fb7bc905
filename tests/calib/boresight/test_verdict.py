"""The calibration's verdict (calib.boresight.checks.verdict): each check's threshold moves the verdict
and names its reason; the users of a result (georef, the watch) are told when it is not trusted."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from calib.boresight.checks.verdict import (
    MAX_SIGMA_RAD,
    QUESTION_SIGMA0_SQUARED,
    REFUSE_SIGMA0_SQUARED,
    Evidence,
    judge,
    untrusted_warning,
)

GOOD = Evidence(
    converged=True,
    sigma0_squared=1.0,
    chi2_lower=0.97,
    sigma_realistic_rad=np.radians([0.005, 0.006, 0.02]),
    sigma_jackknife_rad=np.radians([0.006, 0.006, 0.03]),
)


def test_a_clean_run_is_trusted():
    v = judge(GOOD)
    assert v.status == "trusted" and v.reasons == []


@pytest.mark.parametrize(
    ("change", "status", "words"),
    [
        ({"converged": False}, "refused", "did not converge"),
        ({"sigma0_squared": REFUSE_SIGMA0_SQUARED + 0.1}, "refused", "do not fit the error model"),
        ({"sigma0_squared": QUESTION_SIGMA0_SQUARED + 0.1}, "questionable", "fit the error model poorly"),
        (
            {"sigma_realistic_rad": np.array([0.0001, 0.0001, 1.5 * MAX_SIGMA_RAD])},
            "questionable",
            "yaw is determined",
        ),
        ({"sigma_realistic_rad": np.radians([0.005, 0.9, 0.02])}, "refused", "pitch is not calibrated"),
        ({"sigma_jackknife_rad": np.radians([0.005, 0.006, 0.07])}, "questionable", "one pass disagrees"),
        ({"lost_passes": {"T1": [4, 6]}}, "questionable", "T1 lost in 2 passes (4, 6)"),
        (
            {"patch_check": {"agree": False, "chi2": 40.0, "dof": 3, "p_value": 1e-8}},
            "questionable",
            "disagree",
        ),
        (
            {"removed_groups": [{"removed": True, "reason": "T1 in pass 3: off"}]},
            "questionable",
            "gross error removed: T1 in pass 3",
        ),
        (
            {"removed_groups": [{"removed": False, "reason": "T2 in pass 1: kept"}]},
            "refused",
            "found but kept: T2 in pass 1",
        ),
    ],
)
def test_each_check_moves_the_verdict_and_names_its_reason(change, status, words):
    v = judge(replace(GOOD, **change))
    assert v.status == status
    assert any(words in r for r in v.reasons), v.reasons


def test_a_target_lost_in_one_pass_only_and_a_mild_variance_factor_stay_trusted():
    v = judge(replace(GOOD, lost_passes={"T2": [5]}, sigma0_squared=1.2))
    assert v.status == "trusted"
    assert any("scaled by σ̂0" in n for n in v.notes)


def test_tau_sensitivity_beyond_one_and_a_half_sigma_is_questionable():
    def rows(shift_deg):
        mid = {"tau_s": 20.0, "boresight_deg": [0.1, 0.2, 0.3], "sigma_deg": [0.01, 0.01, 0.02]}
        return [
            {"tau_s": 6.7, "boresight_deg": [0.1, 0.2, 0.3 + shift_deg], "sigma_deg": [0.01, 0.01, 0.02]},
            mid,
            {"tau_s": 60.0, "boresight_deg": [0.1, 0.2, 0.3], "sigma_deg": [0.01, 0.01, 0.02]},
        ]

    assert judge(replace(GOOD, tau_rows=rows(0.02))).status == "trusted"
    v = judge(replace(GOOD, tau_rows=rows(0.04)))
    assert v.status == "questionable" and "yaw moves by 2.0 σ" in v.reasons[0]


def test_users_of_a_result_are_warned_unless_it_is_trusted():
    assert untrusted_warning({"verdict": "trusted"}, "#3") is None
    w = untrusted_warning({"verdict": "questionable", "verdict_reasons": ["T1 lost in 2 passes"]}, "#3")
    assert w == "calibration #3 is QUESTIONABLE: T1 lost in 2 passes"
    assert "no verdict" in untrusted_warning({}, "r.json")
