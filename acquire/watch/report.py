"""What the mount watch tells the operator (pure functions of its state): the ``mount``
checklist section and the summary of a block for ``/events``. The one-line verdict is
:func:`calib.watch.report.verdict` (the same offline and live)::

    waiting for a pair of opposite lines (1 line so far)
    mount steady: roll +0.003 ± 0.004°, pitch -0.001 ± 0.003°, yaw not observed (4 blocks)
    MOUNT SHIFT: roll +0.301° ± 0.021° since 2019-07-09 14:05:12 UTC — recalibrate the mount
"""

from __future__ import annotations

import math

from calib.watch.block import BlockEstimate


def checklist_section(state: dict, text: str) -> dict:
    """The ``mount`` section of the ``checklist`` topic: ``ok`` is None while waiting, False
    once the alarm is raised."""
    alarm = state.get("alarm")
    ok = False if alarm else (True if state.get("blocks_ok") else None)
    stat = state.get("statistic") or [0.0, 0.0, 0.0]
    return {
        "ok": ok,
        "verdict": text,
        "blocks": state.get("blocks", 0),
        "blocks_ok": state.get("blocks_ok", 0),
        "statistic": round(max(stat), 3),  # of the threshold: the alarm at 1
        "alarm": alarm["message"] if alarm else None,
    }


def block_summary(block: BlockEstimate) -> dict:
    """A block in a few fields (``/events``, the ``mount`` topic's ``last_block_status``)."""
    d = {
        "lines": list(block.pass_ids),
        "t_start_gps_s": block.t_start_gps_s,
        "t_end_gps_s": block.t_end_gps_s,
        "headings_deg": [round(h, 2) for h in block.headings_deg],
        "status": block.status,
        "n_points": block.n_points,
        "patches": len(block.patches),
        "moved_patches": len(block.moved_patches),
        "runtime_s": round(block.runtime_s, 3),
    }
    if block.ok and block.delta_rad is not None:
        d["delta_deg"] = [math.degrees(x) for x in block.delta_rad]
        d["sigma_deg"] = [math.degrees(x) for x in block.sigma_rad]
    return d
