"""What the operator reads of the mount watch: the verdict's forms, the ``mount`` checklist
section, and its row in ``mls checklist``'s checks."""

from __future__ import annotations

import numpy as np

from acquire.ui.panels import ChecklistState, render_prechecks
from acquire.watch.report import checklist_section
from calib.watch.block import BlockEstimate
from calib.watch.report import WAITING, verdict
from calib.watch.sequential import MountAlarm, MountTest


def _block(delta_deg, sigma_deg, t0=1000.0) -> BlockEstimate:
    return BlockEstimate(
        t0,
        t0 + 100.0,
        (1, 2),
        (0.0, 180.0),
        "ok",
        np.radians(delta_deg),
        np.diag(np.radians(sigma_deg) ** 2),
    )


def test_the_verdict_waits_then_says_steady_then_shift():
    test = MountTest()
    assert verdict(test.state(), None, 0, None) == WAITING
    assert verdict(test.state(), None, 1, None) == f"{WAITING} (1 line so far)"
    empty = BlockEstimate(0.0, 1.0, (1, 2), (), "no tie patch seen from two headings")
    test.update(empty)
    assert verdict(test.state(), None, 0, empty) == (
        f"{WAITING} with tie patches (last block: no tie patch seen from two headings)"
    )
    blk = _block([0.003, -0.001, 0.0], [0.004, 0.003, 2.0])  # yaw not resolved
    test.update(blk)
    text = verdict(test.state(), None, 0, blk)
    assert text.startswith("mount steady: roll +0.003 ± 0.00") and "pitch -0.001 ± 0.00" in text
    assert text.endswith("yaw not observed (1 block)")
    section = checklist_section(test.state(), text)
    assert section["ok"] is True and section["alarm"] is None and section["blocks_ok"] == 1
    alarm = MountAlarm(2000.0, 1500.0, ("roll",), np.radians([0.301, 0, 0]), np.radians([0.021, 1, 1]), 40.0)
    text = verdict(test.state(), alarm, 0, blk)
    assert text == f"MOUNT SHIFT: {alarm.message().removeprefix('mount shift: ')} — recalibrate the mount"
    assert "roll +0.301° ± 0.021°" in text


def test_mls_checklist_shows_the_mount_section_as_a_check():
    st = ChecklistState()
    st.apply(
        "checklist",
        {
            "presurvey": {"clock_locked": {"ok": True, "detail": "LOCKED"}},
            "mount": {"ok": False, "verdict": "MOUNT SHIFT: roll +0.301° ± 0.021° since GPS 1500 s"},
        },
    )
    checks = {c["name"]: c for c in st.checks()}
    assert checks["mount_watch"] == {
        "name": "mount_watch",
        "label": "Mount watch",
        "ok": False,
        "detail": "MOUNT SHIFT: roll +0.301° ± 0.021° since GPS 1500 s",
    }
    text = render_prechecks(st, width=60, rows=7).plain
    assert text.splitlines()[0].startswith("✘ Mount watch") and "MOUNT SHIFT" in text
    st.apply("checklist", {"mount": {"ok": None, "verdict": WAITING}})
    assert render_prechecks(st, width=60).plain == f"… Mount watch {WAITING}"
