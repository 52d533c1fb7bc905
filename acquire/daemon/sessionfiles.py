"""What the daemon writes around a session at start-up: the salvage report of the unfinished
sessions it found under the log directory, and the vessel config, site file and summary
(``vessel.yaml``, ``site.yaml``, ``session.json``) it puts into the new session."""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import shutil
from pathlib import Path

from acquire.daemon.configschema import VesselConfig


def salvage_report(root: Path) -> dict:
    """Salvage every unfinished session under ``root`` (:func:`acquire.log.recover.salvage_root`):
    what was recovered, by session (the ``salvaged`` entry of ``session_start``)."""
    from acquire.log.recover import salvage_root

    reports = salvage_root(root)
    return {
        name: [
            {"segment": r.segment, "messages": r.messages, "torn_bytes": r.torn_bytes, "problem": r.problem}
            for r in rs
        ]
        for name, rs in reports.items()
    }


def write_session_files(cfg: VesselConfig, session_dir: Path, started_utc: _dt.datetime) -> None:
    """vessel.yaml (verbatim), site.yaml (the site file) and session.json in the session."""
    with contextlib.suppress(OSError):
        shutil.copyfile(cfg.source, session_dir / "vessel.yaml")
    if cfg.site_file is not None:
        with contextlib.suppress(OSError):
            shutil.copyfile(cfg.site_file, session_dir / "site.yaml")
    m = cfg.mount
    summary = {
        "format": "marine-mls session v1",
        "vessel": cfg.vessel,
        "session": session_dir.name,
        "started_utc": started_utc.isoformat(timespec="seconds"),
        "config_file": str(cfg.source),
        "site_file": str(cfg.site_file) if cfg.site_file else None,
        "mount": None
        if m is None
        else {
            "lever_arm_m": list(m.lever_arm_m),
            "nominal_deg": list(m.nominal_deg),
            "boresight_apriori_deg": list(m.boresight_apriori_deg),
        },
        "devices": [{"name": d.name, "kind": d.kind, "protocol": d.protocol} for d in cfg.devices],
    }
    tmp = session_dir / "session.json.tmp"
    tmp.write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    tmp.replace(session_dir / "session.json")
