"""The vessel config for a run of the emulators (``mls sim devices|replay --write-config``).

:func:`vessel_config` returns the YAML mapping that ``acquire.daemon.config`` validates (the keys of
``systemd/vessel.example.yaml``): the devices where the emulators are (the INS on the stable
``<run dir>/ins`` link at 921600 baud — a pty ignores the rate, and the PHINS block at 100 Hz
needs ~600 kbit/s on a real line; the profiler and PPS UDP addresses; the CAN event markers on
``udp_multicast``), latency thresholds matched to the emulated latencies, the session
directory ``<run dir>/sessions``, the status socket ``<run dir>/status.sock`` (the default
``/run/mls`` needs root) and, for a scenario, its a-priori mount, its site file (written
beside the config as ``<stem>.site.yaml``) and the ``guidance`` section matched to the emulated
profiler: its profile rate and points per 360° (what the σ prediction of the passes still to
sail assumes) and a minimum of target points per pass scaled from the full Z+F rate's 100 (at
least :data:`MIN_TARGET_POINTS`). The PPS device is written only with an INS (its pulses are
labelled by the INS's time messages). Rates are per host second (× ``speed``).
"""

from __future__ import annotations

import datetime as _dt
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from sim_devices.canbus import DEFAULT_PORT
from sim_devices.ins import InsSettings

if TYPE_CHECKING:
    from calib.io.site import Site

FULL_RATE_PTS_S = 200.0 * 5080  # the Z+F Profiler 9012 at its full rate
MIN_TARGET_POINTS = 20  # the guidance's floor of hits per target and pass


def vessel_config(
    *,
    vessel: str,
    run_dir: Path,
    locations: dict[str, dict],
    speed: float = 1.0,
    ins: InsSettings | None = None,
    profiler_rate_hz: float = 200.0,
    profiler_latency_s: float = 0.0005,
    profiler_points_per_360: int | None = None,
    site: Site | None = None,
    site_file: str | None = None,
) -> dict:
    """The vessel config of the emulators at ``locations`` (module docstring)."""
    run_dir = Path(run_dir)
    ins = ins or InsSettings(protocol=locations.get("ins", {}).get("protocol") or "nmea")
    devices = []
    if "ins" in locations:
        devices.append(_ins_device(locations["ins"]["link"], ins, speed))
    if "profiler" in locations:
        host, port = locations["profiler"]["address"]
        devices.append(_profiler_device(host, int(port), profiler_rate_hz, profiler_latency_s, speed))
    if "pps" in locations and "ins" in locations:
        host, port = locations["pps"]["address"]
        devices.append(_pps_device(host, int(port), ins))
    if "can" in locations:
        c = locations["can"]
        devices.append(
            {
                "name": "marks",
                "kind": "can",
                "transport": {"type": "can", "interface": c["interface"], "channel": c["channel"]},
            }
        )
    cfg: dict = {
        "vessel": vessel,
        "devices": devices,
        "session": {"directory": str(run_dir / "sessions")},
        "status": {"socket": str(run_dir / "status.sock")},
    }
    if site is not None:
        m = site.mount
        cfg["mount"] = {
            "lever_arm_m": [float(x) for x in m.lever_arm_m],
            "nominal_deg": [float(x) for x in np.degrees(m.nominal_rad)],
            "boresight_apriori_deg": [float(x) for x in np.degrees(m.boresight_rad)],
        }
    if site_file is not None:
        cfg["site_file"] = site_file
        if profiler_points_per_360 is not None:
            cfg["guidance"] = _guidance(profiler_rate_hz, profiler_points_per_360)
    return cfg


def _ins_device(link: str, ins: InsSettings, speed: float) -> dict:
    """The INS on the emulator's pty link; its latency band covers the emulated latency and jitter."""
    return {
        "name": "ins",
        "kind": "ins",
        "protocol": ins.protocol,
        "transport": {"type": "serial", "port": link, "baud": 921600},
        "latency": {
            "band_ms": [0.0, round(max(30.0, 1.5e3 * (ins.latency_s + ins.jitter_s) + 10.0), 1)],
            "jump_ms": 5.0,
            "rate_hz": float(ins.rate_hz * speed),
            "gap_s": 0.5,
            "expect_pps_flag": True,
        },
    }


def _profiler_device(host: str, port: int, rate_hz: float, latency_s: float, speed: float) -> dict:
    """The profiler on UDP; its latency band covers a profile period and the emulated latency."""
    band = 1.5 * (1e3 / rate_hz + 1e3 * latency_s) + 10.0
    return {
        "name": "profiler",
        "kind": "profiler",
        "protocol": "zfp1",
        "transport": {"type": "udp", "host": host, "port": port},
        "latency": {
            "band_ms": [0.0, round(band, 1)],
            "jump_ms": 5.0,
            "rate_hz": float(rate_hz * speed),
            "gap_s": 0.5,
        },
    }


def _pps_device(host: str, port: int, ins: InsSettings) -> dict:
    """The PPS on UDP, its pulses labelled by the INS's time messages."""
    return {
        "name": "pps",
        "kind": "pps",
        "source": {"type": "udp", "host": host, "port": port},
        "time_device": "ins",
        "time_messages": ["ZDA"] if ins.protocol == "nmea" else ["validity_time"],
    }


def _guidance(profiler_rate_hz: float, points_per_360: int) -> dict:
    """The guidance section matched to the emulated profiler (module docstring)."""
    pts_s = profiler_rate_hz * points_per_360
    return {
        "min_points_per_target": max(MIN_TARGET_POINTS, round(100 * pts_s / FULL_RATE_PTS_S)),
        "profile_rate_hz": round(float(profiler_rate_hz), 4),
        "points_per_360": int(points_per_360),
    }


def write_vessel_config(path: str | Path, *, what: str, site: Site | None = None, **kwargs: Any) -> Path:
    """Write :func:`vessel_config` (``kwargs``) to ``path``, with the site file beside it when
    ``site`` (a :class:`calib.io.site.Site`) is given; ``what`` names the run in the header."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    site_file = None
    if site is not None:
        site_path = path.with_name(f"{path.stem}.site.yaml")
        site.dump(site_path)
        site_file = site_path.name
    cfg = vessel_config(site=site, site_file=site_file, **kwargs)
    notes = [
        f"# marine-mls vessel config written on {_dt.datetime.now(_dt.UTC):%Y-%m-%dT%H:%M:%SZ} for",
        f"# {what}, run directory {kwargs['run_dir']}:",
        "# its devices are those emulators; `mls acquire --config` this file while they run.",
    ]
    can = kwargs["locations"].get("can")
    if can is not None and can.get("port", DEFAULT_PORT) != DEFAULT_PORT:
        notes.append(
            f"# NOTE: the CAN emulator uses UDP port {can['port']}; a vessel config cannot set "
            f"the port (python-can uses {DEFAULT_PORT}), so the daemon will not see the markers."
        )
    path.write_text(
        "\n".join(notes) + "\n" + yaml.safe_dump(cfg, sort_keys=False, default_flow_style=None),
        encoding="utf-8",
    )
    return path
