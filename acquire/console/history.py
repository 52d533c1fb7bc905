"""The last calibration of this vessel from the calibration history (``mls calib history``,
:mod:`calib.assess.history`), as the console shows it: pushed to the pages as the console-only
topic ``calibration`` at start and whenever a new result is recorded (read every
:data:`HISTORY_PERIOD_S`, in a worker thread: SQLite is not read in the daemon's loop).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from pathlib import Path

from calib.assess.history import HistoryError, ResultFormatError, list_results, validate_result

HISTORY_PERIOD_S = 30.0
TOPIC = "calibration"

log = logging.getLogger("mls.acquire")


def last_calibration(vessel: str, db: Path | None = None) -> dict:
    """``{"recorded": False}`` when the history holds no result of ``vessel``; else its latest:
    id, date, mount, verdict (None for an older result), boresight and σ in degrees (the realistic
    σ when the result has one, else the scaled σ, ``sigma_kind`` says which)."""
    records = list_results(vessel=vessel, db=db)
    if not records:
        return {"recorded": False, "vessel": vessel}
    r = records[-1]
    fields = validate_result(r.result, f"history #{r.id}")
    realistic = fields["sigma_realistic_deg"]
    return {
        "recorded": True,
        "vessel": vessel,
        "id": r.id,
        "date_utc": r.date_utc,
        "mount_id": r.mount_id,
        "verdict": r.verdict,
        "boresight_deg": fields["boresight_deg"],
        "sigma_deg": realistic if realistic is not None else fields["sigma_scaled_deg"],
        "sigma_kind": "realistic" if realistic is not None else "scaled",
        "n_points": fields["n_points"],
    }


def read_safely(vessel: str, db: Path | None) -> dict:
    """:func:`last_calibration`, or ``{"error": …}`` naming why the history cannot be read (the
    console shows it; the acquisition never depends on the history)."""
    try:
        return last_calibration(vessel, db)
    except (HistoryError, ResultFormatError) as e:
        return {"recorded": False, "vessel": vessel, "error": str(e)}


async def follow_history(
    vessel: str, push: Callable[[str, dict], None], db: Path | None = None, period_s: float = HISTORY_PERIOD_S
) -> None:
    """Push the vessel's last calibration now and each time it changes, until cancelled."""
    last: dict | None = None
    while True:
        doc = await asyncio.to_thread(read_safely, vessel, db)
        if doc != last:
            push(TOPIC, doc)
            if "error" in doc:
                log.warning("console: %s", doc["error"])
            last = doc
        await asyncio.sleep(period_s)
