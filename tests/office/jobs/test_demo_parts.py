"""The pure parts of ``mls demo``: the run directory, the demo's scenario, the lines printed while
the survey runs and the comparison with the truth (the demo end to end: ``test_demo.py``)."""

from __future__ import annotations

import math

import pytest

from office.jobs.demo import DemoError, DemoSettings, prepare_out, scenario_overrides
from office.jobs.demo_compare import AngleComparison, comparison_rows
from office.jobs.demo_progress import pass_events, progress_line, sigma_covers_accepted, sigma_events

RELATIVE_HEADINGS = [0, 180, 45, 225, 315, 135]


def test_prepare_out_empties_a_previous_demo_and_refuses_anything_else(tmp_path):
    out = tmp_path / "demo-out"
    prepare_out(out)
    (out / "run" / "sessions").mkdir(parents=True)
    (out / "vessel.yaml").write_text("x")
    prepare_out(out)
    assert [p.name for p in out.iterdir()] == [".mls-demo"]
    other = tmp_path / "thesis"
    other.mkdir()
    (other / "chapter1.tex").write_text("x")
    with pytest.raises(
        DemoError,
        match=r"thesis is not a previous demo's run directory \(no "
        r"\.mls-demo in it, and it holds chapter1\.tex\): choose "
        r"another --out",
    ):
        prepare_out(other)
    assert (other / "chapter1.tex").read_text() == "x"
    old = tmp_path / "old-demo"  # what the earlier mls demo left: LAZ files
    (old / "laz").mkdir(parents=True)
    (old / "laz" / "pass_1.laz").write_bytes(b"x")
    prepare_out(old)
    assert [p.name for p in old.iterdir()] == [".mls-demo"]


def test_the_demo_scenario_keeps_the_six_fold_pattern_and_both_targets():
    from calib.sim.scenariofile import load_scenario
    from calib.sim.simulate import simulate

    overrides = scenario_overrides(DemoSettings())
    sc = load_scenario("montreal", overrides)
    assert [round(math.degrees(p.relative_heading_rad)) for p in sc.passes] == RELATIVE_HEADINGS
    assert [p.length_m for p in sc.passes] == [44.0] + [18.0] * 5
    sim = simulate(sc, 0)
    counts = sim.point_counts()
    assert all(counts[i]["T1"] > 300 and counts[i]["T2"] > 60 for i in range(1, 7)), counts
    t = [p["line_gps_s"] for p in sim.truth["passes"]]
    assert t[-1][1] - t[0][0] == pytest.approx(22 + 5 * 9 + 5 * 3)


def test_progress_line_and_pass_events():
    plan = [
        {"id": i + 1, "relative_heading_deg": h, "status": "pending", "attempts": 0}
        for i, h in enumerate(RELATIVE_HEADINGS)
    ]
    before = {"passes": plan, "accepted": 0, "active": {"pass_id": 1, "state": "approach"}}
    assert progress_line({}, None, 3.2) == "00:03 waiting for the guidance · clock —"
    assert progress_line(before, "UNLOCKED", 61.0) == "01:01 pass 1 approach · 0/6 accepted · clock UNLOCKED"
    capture = {
        **before,
        "active": {
            "pass_id": 1,
            "state": "capture",
            "along_m": 19.0,
            "capture_m": [14.6, 25.4],
            "xte_m": -0.042,
        },
    }
    assert progress_line(capture, "LOCKED", 9.9) == "00:09 pass 1 capture 4/11 m · XTE -0.04 m · 0/6 accepted"
    full = {
        **capture,
        "active": {**capture["active"], "pass_id": 6, "along_m": 25.4, "xte_m": -9.99},
        "accepted": 5,
        "sigma": {
            "current": {
                "passes": [1, 2, 3, 4, 5],
                "realistic_deg": {"roll": 0.0424, "pitch": 0.2039, "yaw": 0.0481},
            }
        },
    }
    line = progress_line(full, "LOCKED", 3599.0)
    assert line == "59:59 pass 6 capture 11/11 m · XTE -9.99 m · 5/6 accepted · σ° 0.042 0.204 0.048"
    assert len(line) <= 80
    done = [
        {
            **plan[0],
            "status": "accepted",
            "attempts": 1,
            "hits": {"T1": 700, "T2": 150},
            "stats": {"max_xte_m": 0.05},
        },
        {**plan[1], "status": "rejected", "attempts": 1, "reasons": ["clock HOLDOVER during the window"]},
        *plan[2:],
    ]
    after = {
        "passes": done,
        "accepted": 1,
        "active": None,
        "sigma": {"current": {"passes": [1], "realistic_deg": {"roll": 0.05, "pitch": None, "yaw": None}}},
    }
    assert pass_events(before, after) == [
        "✔ pass 1 (0°) accepted: hits T1 700, T2 150; max XTE 0.05 m",
        "✘ pass 2 (180°) rejected: clock HOLDOVER during the window",
    ]
    assert pass_events(after, after) == []
    assert sigma_events(before, after) == ["  predicted σ roll 0.050° pitch n/o yaw n/o with passes 1"]
    assert sigma_events(after, after) == [] and sigma_covers_accepted(after)
    worse = {
        **after,
        "sigma": {
            "current": {
                "passes": [1, 3],
                "rose": ["roll"],
                "realistic_deg": {"roll": 0.062, "pitch": None, "yaw": None},
            }
        },
    }
    assert sigma_events(after, worse) == [
        "  predicted σ roll 0.062° pitch n/o yaw n/o with passes 1, 3 (roll σ rose: the pass's "
        "POS bias outweighs its geometry)"
    ]
    assert not sigma_covers_accepted({**after, "sigma": None})


def test_comparison_rows_in_both_conventions():
    result = {
        "boresight_deg": {"roll": 0.2, "pitch": 1.3, "yaw": 0.1},
        "sigma_deg": {"roll": 0.002, "pitch": 0.007, "yaw": 0.002},
        "sigma_realistic_deg": {"roll": 0.04, "pitch": 0.1, "yaw": 0.05},
    }
    truth = {"boresight_deg": {"roll": 0.208, "pitch": 1.245, "yaw": 0.149}}
    rows = comparison_rows(result, truth)
    assert [(r.angle, r.convention) for r in rows] == [
        (a, c) for c in ("canonical", "thesis") for a in ("roll", "pitch", "yaw")
    ]
    pitch, thesis_pitch = rows[1], rows[4]
    assert (thesis_pitch.truth_deg, thesis_pitch.recovered_deg) == (-1.245, -1.3)
    assert pitch.error_sigmas == pytest.approx(0.55) and thesis_pitch.error_sigmas == pytest.approx(-0.55)
    assert rows[2].error_sigmas == pytest.approx(-0.98)
    assert AngleComparison("roll", "canonical", 0.0, 0.1, 0.0, 0.0).error_sigmas == math.inf
