"""The mount watch's sequential test on synthetic block estimates: its false-alarm rate against
Lorden's bound, its delay, the angle it names, and what is not evidence."""

from __future__ import annotations

import math

import numpy as np
import pytest

from calib.watch.block import BlockEstimate
from calib.watch.sequential import FAMILIES, MountTest
from calib.watch.sequential import WatchDesign as Design

DEG = math.pi / 180.0


def block(k: int, delta_deg, sigma_deg, status: str = "ok", block_s: float = 300.0) -> BlockEstimate:
    sig = np.asarray(sigma_deg, float) * DEG
    return BlockEstimate(
        t_start_gps_s=k * block_s,
        t_end_gps_s=(k + 1) * block_s,
        pass_ids=(2 * k + 1, 2 * k + 2),
        headings_deg=(0.0, 180.0),
        status=status,
        delta_rad=None if status != "ok" else np.asarray(delta_deg, float) * DEG,
        cov_rad2=None if status != "ok" else np.diag(sig**2),
    )


def test_the_threshold_follows_the_stated_rate():
    d = Design(false_alarms_per_hour=0.01, max_blocks_per_hour=60.0)
    # six one-sided statistics per family, each with mean run length ≥ e^h blocks
    assert 6 * FAMILIES * 60.0 * math.exp(-d.threshold) == pytest.approx(0.01)


def test_false_alarms_stay_within_lordens_bound():
    # a design loose enough that false alarms happen at all: at most 6·e^−h per block of a family
    d = Design(false_alarms_per_hour=3.0, max_blocks_per_hour=30.0)  # h = ln 120
    bound_per_block = 6.0 * math.exp(-d.threshold)
    rng = np.random.default_rng(1)
    sigma = np.array([0.01, 0.03, 0.05])
    alarms, blocks = 0, 0
    for _ in range(40):
        t = MountTest(d)
        for k in range(500):
            blocks += 1
            if t.update(block(k, rng.normal(0.0, sigma), sigma)) is not None:
                alarms += 1
                t = MountTest(d)  # restart after an alarm: count renewals
    rate = alarms / blocks
    assert rate <= bound_per_block
    assert alarms > 0  # the test is not vacuous: the rate is measurable at this design


@pytest.mark.parametrize("angle", [0, 1, 2])
def test_a_step_is_detected_on_its_angle_within_two_blocks(angle):
    """Over many runs, as often as the two blocks' log-likelihood ratios reach the threshold
    (their sum is normal: the oracle), always on the angle that moved and since the step."""
    rng = np.random.default_rng(7 + angle)
    sigma = np.array([0.01, 0.02, 0.025])
    design = Design()
    step = np.zeros(3)
    step[angle] = 0.1
    runs, found = 200, 0
    for _ in range(runs):
        t = MountTest(design)
        for k in range(10):  # a steady mount first
            assert t.update(block(k, rng.normal(0.0, sigma), sigma)) is None
        alarm = None
        for k in range(10, 12):
            alarm = alarm or t.update(block(k, step + rng.normal(0.0, sigma), sigma))
        if alarm is None:
            continue
        found += 1
        assert alarm.angles == (("roll", "pitch", "yaw")[angle],)
        # the CUSUM's change time: where its run began, within a block of the step
        assert alarm.since_gps_s in (9 * 300.0, 10 * 300.0, 11 * 300.0)
        assert abs(alarm.size_rad[angle] / DEG - 0.1) < 4 * alarm.sigma_rad[angle] / DEG
    # the oracle: Λ = (μ/σ²)(δ − μ/2) per block, δ ~ N(μ, σ²); two blocks' sum reach h
    mu, sig = 0.1, sigma[angle]
    mean, sd = 2 * (mu / sig**2) * (mu / 2), math.sqrt(2) * mu / sig
    p = 0.5 * math.erfc((design.threshold - mean) / (sd * math.sqrt(2)))
    assert found / runs >= p - 3 * math.sqrt(p * (1 - p) / runs), (found, p)
    t = MountTest(design)
    t.update(block(30, [0.3, 0.0, 0.0], sigma))
    assert "since 1980-01-06 02:30:00 UTC" in t.alarm.message()  # GPS 9000 s


def test_each_family_has_its_own_statistics_and_the_alarm_is_sized_in_its_family():
    sigma = np.array([0.01, 0.01, 0.01])
    t = MountTest(Design())
    # family 1's blocks see roll +0.2°, family 0's see nothing: only family 1's CUSUM rises
    t.update(block(0, [0.0, 0.0, 0.0], sigma), 0)
    t.update(block(1, [0.2, 0.0, 0.0], sigma), 1)
    assert t.S[0].max() == 0.0 and t.S[1][0, 0] == pytest.approx((0.1 / 0.01**2) * (0.2 - 0.05))
    assert t.alarm is not None and t.alarm.first_block == 1
    for k in range(2, 8):
        t.update(block(k, [0.0, 0.0, 0.0] if k % 2 == 0 else [0.2, 0.0, 0.0], sigma), k % 2)
    # the size: family 1's blocks after its first, not family 0's zeros
    assert t.alarm.size_rad[0] / DEG == pytest.approx(0.2) and t.alarm.blocks_after == 3
    assert t.alarm.sigma_rad[0] / DEG == pytest.approx(0.01 / math.sqrt(3))
    # the running estimate weighs each block at half (every line is in two blocks)
    one = MountTest(Design())
    one.update(block(0, [0.2, 0.0, 0.0], sigma))
    p0 = math.radians(1.0) ** 2
    r = FAMILIES * (0.01 * DEG) ** 2
    assert one.estimate_rad[0] == pytest.approx(0.2 * DEG * p0 / (p0 + r))
    with pytest.raises(ValueError, match="family 2"):
        one.update(block(1, [0.0, 0.0, 0.0], sigma), 2)


def test_a_negative_step_and_the_running_estimate():
    sigma = np.array([0.01, 0.01, 0.01])
    t = MountTest(Design())
    for k in range(10):
        t.update(block(k, [0.0, -0.15, 0.0], sigma))
    assert t.alarm is not None and t.alarm.angles == ("pitch",)
    assert t.estimate_rad[1] / DEG == pytest.approx(-0.15, abs=0.01)
    assert t.state()["alarm"]["angles"] == ["pitch"]


def test_blocks_without_evidence_move_nothing():
    t = MountTest(Design())
    for k in range(20):
        # no estimate at all, or an angle resolved only to 0.5° that claims a 1° change
        t.update(block(k, None, None, status="no tie patch seen from two headings"))
        t.update(block(k, [0.0, 0.0, 1.0], [0.01, 0.01, 0.5]))
    assert t.alarm is None
    assert t.statistic[2] == 0.0
    assert t.estimate_rad[2] == 0.0
    assert t.state()["blocks"] == 40 and t.state()["blocks_ok"] == 20


def test_the_alarm_is_raised_once():
    sigma = np.array([0.01, 0.01, 0.01])
    t = MountTest(Design())
    raised = [t.update(block(k, [0.3, 0.0, 0.0], sigma)) for k in range(5)]
    assert sum(a is not None for a in raised) == 1
    assert raised[0] is not None  # 30 σ in one block


def test_the_alarms_size_is_refined_by_the_blocks_after_the_change():
    sigma = np.array([0.01, 0.01, 0.01])
    t = MountTest(Design())
    for k in range(5):
        t.update(block(k, [0.0, 0.0, 0.0], sigma))
    t.update(block(5, [0.12, 0.0, 0.0], sigma))  # the change happened during this block
    alarm = t.alarm
    assert alarm is not None and alarm.blocks_after == 0 and "a part of it" in alarm.message()
    for k in range(6, 9):
        t.update(block(k, [0.2, 0.0, 0.0], sigma))
    assert t.alarm.blocks_after == 3 and t.alarm.t_gps_s == alarm.t_gps_s
    assert t.alarm.size_rad[0] / DEG == pytest.approx(0.2, abs=1e-9)
    assert t.alarm.sigma_rad[0] / DEG == pytest.approx(0.01 / math.sqrt(3))
    assert "a part of it" not in t.alarm.message()
