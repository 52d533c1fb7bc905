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
        out.append(_devices_check(devices))
    out.append(_ins_check(nav))
    out.append(_gnss_check(nav))
    out.append(_pps_check(nav, clock, latency))
    out.append(_clock_check(clock))
    out.append(_latency_check(latency, bands_ms))
    out.append(_disk_check(free_bytes, needed_bytes))
    out.append(_config_check(mount_configured, n_targets))
    return out


def _devices_check(devices: Mapping[str, str | None]) -> Check:
    """Every device connected (else each one's error)."""
    down = {name: error for name, error in devices.items() if error is not None}
    detail = "; ".join(f"{n}: {e}" for n, e in down.items()) or f"{len(devices)} connected"
    return Check(name="devices_connected", label="Devices", ok=not down, detail=detail)


def _ins_check(nav: NavRecord | None) -> Check:
    """The INS navigating, fine-aligned, not dead reckoning."""

    def check(ok: bool | None, detail: str) -> Check:
        return Check(name="ins_navigating", label="INS nav+fine", ok=ok, detail=detail)

    if nav is None:
        return check(None, "no INS data")
    flags = {"navigating": nav.navigation, "fine-aligned": nav.fine_alignment}
    missing = [k for k, v in flags.items() if v is None]
    bad = [k for k, v in flags.items() if v is False]
    if missing:
        return check(False, "status not received")
    if bad:
        return check(False, "aligning" if nav.alignment else "not " + " / ".join(bad))
    if nav.dead_reckoning:
        return check(False, "dead reckoning")
    return check(True, "navigating, fine")


def _gnss_check(nav: NavRecord | None) -> Check:
    """A valid GNSS fix, the INS on UTC time (the horizontal σ when known)."""

    def check(ok: bool | None, detail: str) -> Check:
        return Check(name="gnss_fix", label="GNSS fix", ok=ok, detail=detail)

    if nav is None:
        return check(None, "no INS data")
    if nav.gps_valid is None:
        return check(False, "status not received")
    if not nav.gps_valid:
        return check(False, "no GNSS data" if not nav.gps_received else "GNSS not valid")
    if nav.utc_detected is False:
        return check(False, "fix, INS not on UTC")
    sig = math.hypot(nav.sigma_north_m, nav.sigma_east_m)
    return check(True, f"fix, σh {sig:.2f} m" if math.isfinite(sig) else "fix")


def _pps_check(nav: NavRecord | None, clock: Mapping | None, latency: Mapping[str, Mapping] | None) -> Check:
    """PPS: the INS sees it, the clock model has recent edges, the profiler reports it."""
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
        return Check(name="pps_locked", label="PPS locked", ok=None, detail="no data")
    if pps_bad:
        return Check(name="pps_locked", label="PPS locked", ok=False, detail="no PPS: " + ", ".join(pps_bad))
    devs = sum(bool(st.get("pps_flag")) for st in (latency or {}).values())
    detail = "INS, clock" + (f", {devs} device{'s' if devs > 1 else ''}" if devs else "")
    return Check(name="pps_locked", label="PPS locked", ok=True, detail=detail)


def _clock_check(clock: Mapping | None) -> Check:
    """The clock model LOCKED (its jitter; else its state and error bound)."""
    if clock is None:
        return Check(name="clock_locked", label="Clock LOCKED", ok=None, detail="no clock status")
    state = clock.get("state")
    if state == "LOCKED":
        jit = clock.get("jitter_rms_us")
        detail = "LOCKED" + (f", jitter {jit:.1f} µs" if jit is not None else "")
        return Check(name="clock_locked", label="Clock LOCKED", ok=True, detail=detail)
    bound = clock.get("error_bound_us")
    detail = f"{state}" + (f", ±{bound:.0f} µs" if bound is not None else "")
    return Check(name="clock_locked", label="Clock LOCKED", ok=False, detail=detail)


def _latency_check(
    latency: Mapping[str, Mapping] | None, bands_ms: Mapping[str, tuple[float, float]] | None
) -> Check:
    """Every device's latency (mean and 99th percentile) in its expected band."""
    if not latency:
        return Check(name="latency_in_band", label="Latency", ok=None, detail="no statistics yet")
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
    detail = ", ".join(bad) if bad else f"in band, max {worst:.1f} ms"
    return Check(name="latency_in_band", label="Latency", ok=not bad, detail=detail)


def _disk_check(free_bytes: int | None, needed_bytes: int | None) -> Check:
    """Free space for the planned passes on the session's file system."""
    if free_bytes is None:
        return Check(name="disk_space", label="Disk space", ok=None, detail="unknown")
    need = needed_bytes or 0
    ok = free_bytes >= need
    detail = f"{_fmt_bytes(free_bytes)} free {'≥' if ok else '<'} {_fmt_bytes(need)}"
    return Check(name="disk_space", label="Disk space", ok=ok, detail=detail)


def _config_check(mount_configured: bool, n_targets: int) -> Check:
    """A mount configured and at least two targets."""
    cfg_bad = []
    if not mount_configured:
        cfg_bad.append("no mount")
    if n_targets < 2:
        cfg_bad.append(f"{n_targets} target{'s' if n_targets != 1 else ''} (need 2)")
    detail = ", ".join(cfg_bad) if cfg_bad else f"mount, {n_targets} targets"
    return Check(name="mount_targets", label="Mount+targets", ok=not cfg_bad, detail=detail)
