"""The pre-survey checks (docs/architecture.md §8), pure: :func:`prechecks`, each check passed, failed
(with the reason) or unknown (no data yet), and the disk the planned passes need
(:func:`disk_needed_bytes`)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from calib.survey.passplan import PassPlan
from drivers.hydrins.nav import NavRecord

#: Z+F Profiler 9012: 1.016 Mpts/s of (range u32, intensity u16) in ZFP1 packets, plus packet
#: and log framing (~10 %), plus the INS at 200 Hz (~300 B per epoch in NMEA).
DEFAULT_LOG_RATE_BYTES_S = 1.016e6 * 6 * 1.1 + 200 * 300


@dataclass(frozen=True)
class Check:
    name: str
    label: str
    ok: bool | None  # None: no data yet
    detail: str

    def as_dict(self) -> dict:
        return {"name": self.name, "label": self.label, "ok": self.ok, "detail": self.detail}


def disk_needed_bytes(
    plan: PassPlan, rate_bytes_s: float = DEFAULT_LOG_RATE_BYTES_S, turn_s: float = 120.0, margin: float = 2.0
) -> int:
    """Disk the planned passes need: their sailing time plus a turn between passes, at the
    log's data rate, times a margin (resails, the export and the calibration's outputs)."""
    t = sum(p.duration_s for p in plan.passes) + turn_s * max(len(plan.passes) - 1, 0)
    return int(math.ceil(t * rate_bytes_s * margin))


def _fmt_bytes(n: float) -> str:
    for unit, scale in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            v = n / scale
            return f"{v:.0f} {unit}" if v >= 10 else f"{v:.1f} {unit}"
    return f"{n:.0f} B"


def prechecks(
    nav: NavRecord | None,
    clock: Mapping | None,
    latency: Mapping[str, Mapping] | None = None,
    bands_ms: Mapping[str, tuple[float, float]] | None = None,
    free_bytes: int | None = None,
    needed_bytes: int | None = None,
    mount_configured: bool = False,
    n_targets: int = 0,
    devices: Mapping[str, str | None] | None = None,
) -> list[Check]:
    """The pre-survey checks, each with pass/fail and the reason.

    ``nav``: the latest INS record; ``clock``: the clock model's status
    (:meth:`acquire.timing.clock.ClockStatus.as_dict`); ``latency``: device → latency statistics
    (:meth:`acquire.timing.latency.LatencyStats.as_dict`) and ``bands_ms`` device → expected band;
    ``free_bytes`` on the session's file system and ``needed_bytes`` for the planned passes
    (:func:`disk_needed_bytes`); ``devices``: device → why it is not connected (the OS error
    text, e.g. ``[Errno 98] Address already in use``), None when it is.
    """
    out = []
    if devices is not None:
        down = {name: error for name, error in devices.items() if error is not None}
        out.append(
            Check(
                "devices_connected",
                "Devices",
                not down,
                "; ".join(f"{n}: {e}" for n, e in down.items()) or f"{len(devices)} connected",
            )
        )
    if nav is None:
        out.append(Check("ins_navigating", "INS nav+fine", None, "no INS data"))
        out.append(Check("gnss_fix", "GNSS fix", None, "no INS data"))
    else:
        flags = {"navigating": nav.navigation, "fine-aligned": nav.fine_alignment}
        missing = [k for k, v in flags.items() if v is None]
        bad = [k for k, v in flags.items() if v is False]
        if missing:
            out.append(Check("ins_navigating", "INS nav+fine", False, "status not received"))
        elif bad:
            why = "aligning" if nav.alignment else "not " + " / ".join(bad)
            out.append(Check("ins_navigating", "INS nav+fine", False, why))
        elif nav.dead_reckoning:
            out.append(Check("ins_navigating", "INS nav+fine", False, "dead reckoning"))
        else:
            out.append(Check("ins_navigating", "INS nav+fine", True, "navigating, fine"))
        if nav.gps_valid is None:
            out.append(Check("gnss_fix", "GNSS fix", False, "status not received"))
        elif not nav.gps_valid:
            out.append(
                Check(
                    "gnss_fix",
                    "GNSS fix",
                    False,
                    "no GNSS data" if not nav.gps_received else "GNSS not valid",
                )
            )
        elif nav.utc_detected is False:
            out.append(Check("gnss_fix", "GNSS fix", False, "fix, INS not on UTC"))
        else:
            sig = math.hypot(nav.sigma_north_m, nav.sigma_east_m)
            out.append(
                Check("gnss_fix", "GNSS fix", True, f"fix, σh {sig:.2f} m" if math.isfinite(sig) else "fix")
            )
    # PPS: the INS sees it, the clock model has recent edges, the profiler reports it
    pps_bad = []
    if nav is not None and nav.pps_detected is not True:
        pps_bad.append("INS" + (" ?" if nav.pps_detected is None else ""))
    age = None if clock is None else clock.get("last_edge_age_s")
    if clock is not None and (age is None or age > 1.5):
        pps_bad.append("no edges" if age is None else f"last edge {age:.1f} s ago")
    for dev, st in (latency or {}).items():
        if st.get("pps_flag") is False:
            pps_bad.append(dev)
    if nav is None and clock is None:
        out.append(Check("pps_locked", "PPS locked", None, "no data"))
    elif pps_bad:
        out.append(Check("pps_locked", "PPS locked", False, "no PPS: " + ", ".join(pps_bad)))
    else:
        devs = sum(bool(st.get("pps_flag")) for st in (latency or {}).values())
        out.append(
            Check(
                "pps_locked",
                "PPS locked",
                True,
                "INS, clock" + (f", {devs} device{'s' if devs > 1 else ''}" if devs else ""),
            )
        )
    if clock is None:
        out.append(Check("clock_locked", "Clock LOCKED", None, "no clock status"))
    else:
        state = clock.get("state")
        jit = clock.get("jitter_rms_us")
        if state == "LOCKED":
            out.append(
                Check(
                    "clock_locked",
                    "Clock LOCKED",
                    True,
                    "LOCKED" + (f", jitter {jit:.1f} µs" if jit is not None else ""),
                )
            )
        else:
            bound = clock.get("error_bound_us")
            out.append(
                Check(
                    "clock_locked",
                    "Clock LOCKED",
                    False,
                    f"{state}" + (f", ±{bound:.0f} µs" if bound is not None else ""),
                )
            )
    # latency in band
    if not latency:
        out.append(Check("latency_in_band", "Latency", None, "no statistics yet"))
    else:
        bad, worst = [], -math.inf
        for dev, st in sorted(latency.items()):
            mean, p99 = st.get("latency_mean_ms"), st.get("latency_p99_ms")
            lo, hi = (bands_ms or {}).get(dev, (0.0, 100.0))
            if mean is None:
                bad.append(f"{dev} no data")
            elif max(mean, p99 if p99 is not None else mean) > hi:
                bad.append(f"{dev} {max(mean, p99 or mean):.1f}>{hi:g} ms")
            elif mean < lo:
                bad.append(f"{dev} {mean:.1f}<{lo:g} ms")
            else:
                worst = max(worst, mean)
        out.append(
            Check(
                "latency_in_band",
                "Latency",
                not bad,
                ", ".join(bad) if bad else f"in band, max {worst:.1f} ms",
            )
        )
    if free_bytes is None:
        out.append(Check("disk_space", "Disk space", None, "unknown"))
    else:
        need = needed_bytes or 0
        ok = free_bytes >= need
        out.append(
            Check(
                "disk_space",
                "Disk space",
                ok,
                f"{_fmt_bytes(free_bytes)} free {'≥' if ok else '<'} {_fmt_bytes(need)}",
            )
        )
    cfg_bad = []
    if not mount_configured:
        cfg_bad.append("no mount")
    if n_targets < 2:
        cfg_bad.append(f"{n_targets} target{'s' if n_targets != 1 else ''} (need 2)")
    out.append(
        Check(
            "mount_targets",
            "Mount+targets",
            not cfg_bad,
            ", ".join(cfg_bad) if cfg_bad else f"mount, {n_targets} targets",
        )
    )
    return out
