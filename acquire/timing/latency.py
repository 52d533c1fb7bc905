"""Latency monitor and sync check (docs/architecture.md §6): device time tags against the PPS clock model.

For each record of a device, ``latency = GPS(host receive) − device time tag``, with GPS(host
receive) from the clock model. A device whose time tags are synchronized to the same GPS time
(INS with UTC + PPS, profiler with its PPS flag) has a small, steady latency; anything else is an
alarm with a reason (:mod:`acquire.alarms`), keyed ``(name, device)``:

- ``time_step`` (critical): the latency moved by ≥ 0.5 s from its baseline, or sits ≥ 0.5 s
  outside the band — a whole-second step of the device's time tags (a 1 s offset);
- ``latency_jump`` (warning): the short-term median left the baseline by ≥ ``jump`` (clears when
  it returns within ``jump/2``, or once the new level has been stable for ``relearn``);
- ``clock_drift`` (warning): the latency drifts (the device clock runs at another rate than GPS)
  faster than ``max_drift_ppm`` (beyond 2σ), from a line through the 1-s medians of up to
  ``drift_window`` since the last discontinuity;
- ``pps_flag_lost`` (critical): the device says it no longer sees the PPS / UTC sync;
- ``data_gap`` (critical): no record for ``gap`` — also a device that has delivered nothing
  for ``gap`` since the monitor first looked at it (its first :meth:`LatencyMonitor.tick` or
  record: the daemon's start);
- ``rate_drop`` (warning): the record rate over 2 s fell below 80 % of the nominal rate;
- ``latency_out_of_band`` / ``latency_jitter`` (warning): mean or p99 outside the band; σ above
  ``max_sigma``.

While a step or jump is active the baseline is frozen, so the alarm lasts as long as the
condition. Statistics (mean, σ, p99, max) cover the last ``stats_window`` after the last
discontinuity. The monitor is pure: it sees only the stamps it is given (stream time = host
monotonic ns of the observations, or of :meth:`LatencyMonitor.tick`); evaluation runs every
``eval_period`` of stream time, vectorized, so ``observe`` is O(1).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from acquire.alarms import CRITICAL, WARNING, AlarmBook, AlarmEvent
from acquire.timing.clock import ClockState, GpsEstimate

NS_PER_S = 1_000_000_000
MS = 1_000_000
STEP_NS = NS_PER_S // 2  # a latency change this large is a time step, not a jump
#: (raise after, clear after) in seconds of each alarm: its condition must hold (or be over) for
#: this long of stream time before the alarm is raised (or cleared)
ALARM_DELAYS_S: dict[str, tuple[float, float]] = {
    "data_gap": (0.0, 0.0),
    "rate_drop": (1.0, 2.0),
    "pps_flag_lost": (0.0, 2.0),
    "time_step": (0.0, 3.0),
    "latency_jump": (0.0, 2.0),
    "latency_out_of_band": (1.0, 3.0),
    "latency_jitter": (2.0, 5.0),
    "clock_drift": (5.0, 5.0),
}


class Clock(Protocol):
    def to_gps(self, host_ns: int) -> GpsEstimate: ...


@dataclass(frozen=True)
class LatencyLimits:
    """Thresholds of one device (config: ``devices[].latency``)."""

    band_ns: tuple[int, int] = (0, 100 * MS)  # expected latency range
    jump_ns: int = 5 * MS  # a change of the short-term median this large is a jump
    max_sigma_ns: int = 5 * MS
    max_drift_ppm: float = 10.0
    rate_hz: float | None = None  # nominal record rate; None: no rate check
    gap_ns: int = NS_PER_S  # no record for this long is a gap
    expect_pps_flag: bool = True  # a device reporting pps_flag=False raises pps_flag_lost


@dataclass(frozen=True)
class MonitorParams:
    window_ns: int = 30 * NS_PER_S  # baseline and drift window
    stats_window_ns: int = 10 * NS_PER_S  # mean, σ, p99, max
    short_ns: int = NS_PER_S // 2  # short-term median (at least 3 samples)
    guard_ns: int = 2 * NS_PER_S  # the baseline ignores the newest samples
    eval_period_ns: int = NS_PER_S // 4
    rate_window_ns: int = 2 * NS_PER_S
    drift_window_ns: int = 120 * NS_PER_S  # drift: a line through the 1-s medians of this long
    # a rate is judged over a minute at least: at the 10-ppm limit the latency moves 0.6 ms in it,
    # above the 1-s medians' wander on a loaded host (CI: a 20-s span read −94 ± 22 ppm into the
    # INS stamps of a run under load, from an emulator whose clock is the truth)
    drift_min_span_ns: int = 60 * NS_PER_S
    relearn_ns: int = 60 * NS_PER_S  # a jump to a level stable this long becomes the baseline


@dataclass(frozen=True, kw_only=True)
class LatencyStats:
    device: str
    sync: str  # "ok", "waiting" (not enough samples), "no_clock" (clock UNLOCKED), "no_time_tag"
    n: int  # latency samples in the statistics window
    mean_ns: float | None
    sigma_ns: float | None
    p99_ns: float | None
    max_ns: float | None
    baseline_ns: float | None
    drift_ppm: float | None  # rate of the latency change (device clock slow: +)
    drift_sigma_ppm: float | None
    rate_hz: float | None
    last_age_ns: int | None  # stream time since the last record
    pps_flag: bool | None
    records: int  # all records observed

    def as_dict(self) -> dict:
        def ms(v):
            return None if v is None else round(v / MS, 4)

        return {
            "device": self.device,
            "sync": self.sync,
            "n": self.n,
            "latency_mean_ms": ms(self.mean_ns),
            "latency_sigma_ms": ms(self.sigma_ns),
            "latency_p99_ms": ms(self.p99_ns),
            "latency_max_ms": ms(self.max_ns),
            "baseline_ms": ms(self.baseline_ns),
            "drift_ppm": None if self.drift_ppm is None else round(self.drift_ppm, 3),
            "drift_sigma_ppm": None if self.drift_sigma_ppm is None else round(self.drift_sigma_ppm, 3),
            "rate_hz": None if self.rate_hz is None else round(self.rate_hz, 2),
            "last_age_s": None if self.last_age_ns is None else round(self.last_age_ns / NS_PER_S, 3),
            "pps_flag": self.pps_flag,
            "records": self.records,
        }


def _fmt_ms(ns: float) -> str:
    return f"{ns / MS:+.3f} ms" if abs(ns) < 100 * MS else f"{ns / NS_PER_S:+.3f} s"


def _step_message(is_step: bool, short_med: float, baseline: float | None, band_ns: tuple[int, int]) -> str:
    """The ``time_step`` message: the stepped latency against baseline and band, or its return."""
    if not is_step:
        return f"latency back at {_fmt_ms(short_med)}"
    lo, hi = band_ns
    return (
        f"time tags stepped: latency {_fmt_ms(short_med)}"
        + (f", baseline {_fmt_ms(baseline)}" if baseline is not None else "")
        + f", band [{lo / MS:g}, {hi / MS:g}] ms"
    )


@dataclass
class _Device:
    name: str
    limits: LatencyLimits
    pend_t: list[int] = field(default_factory=list)
    pend_lat: list[int] = field(default_factory=list)
    win_t: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    win_lat: np.ndarray = field(default_factory=lambda: np.empty(0, np.float64))
    recent: deque = field(default_factory=deque)  # host stamps of records (rate)
    records: int = 0
    unsynced: int = 0  # records whose latency could not be formed (clock not usable)
    untagged: int = 0  # records without a device time tag
    first_host: int | None = None
    last_host: int | None = None
    since: int | None = None  # stream time the monitor first looked at the device (silence from it)
    last_eval: int | None = None
    pps_flag: bool | None = None
    baseline: float | None = None
    level: tuple[bool, bool] = (False, False)  # (step, jump) at the last evaluation
    level_since: int | None = None  # when the current jump alarm was raised
    discontinuity: int | None = None  # stream time of the last step/jump onset
    bins: deque = field(default_factory=deque)  # (t_ns, median latency) per second (drift)
    bin_next: int | None = None  # start of the next second to close
    resumed: int | None = None  # when records resumed after the last gap
    last_gap_ns: int = 0
    stats: LatencyStats | None = None


@dataclass
class _Evaluation:
    """One evaluation of one device at stream time ``now``: its alarm updates, in order."""

    alarms: AlarmBook
    d: _Device
    now: int
    events: list[AlarmEvent] = field(default_factory=list)

    def update(self, name: str, cond: bool, message: str, severity: str = WARNING) -> AlarmEvent | None:
        """Feed alarm ``name`` of the device with its delays (:data:`ALARM_DELAYS_S`)."""
        raise_s, clear_s = ALARM_DELAYS_S[name]
        ev = self.alarms.update(
            name,
            self.d.name,
            bool(cond),
            self.now,
            message=message,
            severity=severity,
            raise_after_ns=int(raise_s * NS_PER_S),
            clear_after_ns=int(clear_s * NS_PER_S),
        )
        if ev is not None:
            self.events.append(ev)
        return ev

    def active(self, name: str) -> bool:
        return self.alarms.is_active(name, self.d.name)


@dataclass(frozen=True)
class _Window:
    """The latency samples one evaluation judges."""

    t: np.ndarray  # host ns of the window's samples
    lat: np.ndarray  # their latencies (ns)
    sync: str  # LatencyStats.sync before the count of samples is judged
    st: np.ndarray  # the statistics window's latencies (since the last discontinuity)
    short_med: float | None  # the short-term (lower) median; None without samples


@dataclass(frozen=True)
class _Spread:
    """The statistics window's mean, σ, p99 and max (ns); None with fewer than 3 samples."""

    mean_ns: float | None = None
    sigma_ns: float | None = None
    p99_ns: float | None = None
    max_ns: float | None = None


class LatencyMonitor:
    """Per-device latency statistics and sync alarms against a clock model."""

    def __init__(self, clock: Clock, alarms: AlarmBook | None = None, params: MonitorParams | None = None):
        self.clock = clock
        self.alarms = alarms if alarms is not None else AlarmBook()
        self.params = params or MonitorParams()
        self._devices: dict[str, _Device] = {}

    def add_device(self, name: str, limits: LatencyLimits | None = None) -> None:
        self._devices[name] = _Device(name, limits or LatencyLimits())

    @property
    def devices(self) -> list[str]:
        return list(self._devices)

    def observe(
        self, device: str, host_ns: int, device_ns: int | None = None, *, pps_flag: bool | None = None
    ) -> list[AlarmEvent]:
        """One record: its host receive stamp, its device time tag as GPS ns (None when the
        device has no valid time tag), and the device's PPS/sync flag when it reports one."""
        d = self._devices[device]
        host_ns = int(host_ns)
        d.records += 1
        quiet_since = d.last_host if d.last_host is not None else d.since
        resumed = False
        if quiet_since is not None and host_ns - quiet_since > d.limits.gap_ns:
            resumed = True
            d.resumed, d.last_gap_ns = host_ns, host_ns - quiet_since
        if d.since is None:
            d.since = host_ns
        if d.first_host is None:
            d.first_host = host_ns
        d.last_host = host_ns
        d.recent.append(host_ns)
        if pps_flag is not None:
            d.pps_flag = bool(pps_flag)
        if device_ns is None:
            d.untagged += 1
        else:
            est = self.clock.to_gps(host_ns)
            if est.state == ClockState.UNLOCKED:
                d.unsynced += 1
            else:
                d.pend_t.append(host_ns)
                d.pend_lat.append(est.gps_ns - int(device_ns))
        if resumed or d.last_eval is None or host_ns - d.last_eval >= self.params.eval_period_ns:
            return self._evaluate(d, host_ns)
        return []

    def tick(self, now_host_ns: int) -> list[AlarmEvent]:
        """Evaluate every device at stream time ``now_host_ns`` (gaps need this without data)."""
        events: list[AlarmEvent] = []
        for d in self._devices.values():
            events += self._evaluate(d, int(now_host_ns))
        return events

    def stats(self, device: str) -> LatencyStats:
        d = self._devices[device]
        if d.stats is None:
            return LatencyStats(
                device=device,
                sync="waiting",
                n=0,
                mean_ns=None,
                sigma_ns=None,
                p99_ns=None,
                max_ns=None,
                baseline_ns=None,
                drift_ppm=None,
                drift_sigma_ppm=None,
                rate_hz=None,
                last_age_ns=None,
                pps_flag=d.pps_flag,
                records=d.records,
            )
        return d.stats

    def snapshot(self) -> dict[str, dict]:
        return {name: self.stats(name).as_dict() for name in self._devices}

    # -- evaluation -------------------------------------------------------------------------

    def _evaluate(self, d: _Device, now: int) -> list[AlarmEvent]:
        """Bring the device's window to ``now``, update its alarms (in this order: data flow,
        level, spread, drift) and its statistics; returns the alarm transitions."""
        d.last_eval = now
        if d.since is None:
            d.since = now
        self._take_pending(d, now)
        ev = _Evaluation(self.alarms, d, now)
        age, rate = self._flow_alarms(ev)
        w = self._window(d, now)
        step_on, jump_on = ev.active("time_step"), ev.active("latency_jump")
        if not (step_on or jump_on):
            self._learn_baseline(d, w, now)
        if w.short_med is not None:
            self._level_alarms(ev, w, w.short_med, jump_on)
        spread = self._spread_alarms(ev, w.st)
        self._close_bins(d, now)
        drift, drift_sigma = self._drift_alarm(ev)
        d.stats = LatencyStats(
            device=d.name,
            sync=w.sync if w.st.size >= 3 or w.sync != "ok" else "waiting",
            n=int(w.st.size),
            mean_ns=spread.mean_ns,
            sigma_ns=spread.sigma_ns,
            p99_ns=spread.p99_ns,
            max_ns=spread.max_ns,
            baseline_ns=d.baseline,
            drift_ppm=drift,
            drift_sigma_ppm=drift_sigma,
            rate_hz=rate,
            last_age_ns=age,
            pps_flag=d.pps_flag,
            records=d.records,
        )
        return ev.events

    def _take_pending(self, d: _Device, now: int) -> None:
        """The samples observed since the last evaluation into the window; the window and the
        rate's stamps cut to their lengths before ``now``."""
        p = self.params
        if d.pend_t:
            d.win_t = np.concatenate([d.win_t, np.asarray(d.pend_t, np.int64)])
            d.win_lat = np.concatenate([d.win_lat, np.asarray(d.pend_lat, np.float64)])
            d.pend_t.clear()
            d.pend_lat.clear()
        keep = int(np.searchsorted(d.win_t, now - p.window_ns, side="left"))
        if keep:
            d.win_t, d.win_lat = d.win_t[keep:], d.win_lat[keep:]
        while d.recent and d.recent[0] <= now - p.rate_window_ns:
            d.recent.popleft()

    def _flow_alarms(self, ev: _Evaluation) -> tuple[int | None, float | None]:
        """The data flow: ``data_gap``, ``rate_drop``, ``pps_flag_lost``; returns (stream time
        since the last record, the record rate over the rate window), each None when unknown."""
        d, p, lim, now = ev.d, self.params, ev.d.limits, ev.now
        age = None if d.last_host is None else now - d.last_host
        quiet_from = d.last_host if d.last_host is not None else d.since
        assert quiet_from is not None, "the evaluation sets since"
        silent = now - quiet_from
        gap = silent > lim.gap_ns
        if gap:
            msg = f"no record for {silent / NS_PER_S:.2f} s" + (" (none since start)" if age is None else "")
        else:
            first = d.first_host is not None and d.first_host == d.resumed
            msg = f"{'first record' if first else 'records again'} after {d.last_gap_ns / NS_PER_S:.2f} s"
        ev.update("data_gap", gap, msg, CRITICAL)
        rate = None
        if d.first_host is not None and now - d.first_host >= p.rate_window_ns:
            rate = len(d.recent) * NS_PER_S / p.rate_window_ns
        if lim.rate_hz:
            low = 0.8 if not ev.active("rate_drop") else 0.9
            settled = d.resumed is None or now - d.resumed >= p.rate_window_ns  # not the gap again
            drop = rate is not None and rate < low * lim.rate_hz and not gap and settled
            ev.update(
                "rate_drop",
                drop,
                f"{rate:.1f} records/s, nominal {lim.rate_hz:g}/s" if rate is not None else "",
                WARNING,
            )
        if lim.expect_pps_flag and d.pps_flag is not None:
            ev.update(
                "pps_flag_lost",
                not d.pps_flag,
                "device reports no PPS/UTC sync" if not d.pps_flag else "device PPS flag back",
                CRITICAL,
            )
        return age, rate

    def _window(self, d: _Device, now: int) -> _Window:
        """The latency samples of the sync check (before this evaluation's level change)."""
        p = self.params
        t, lat = d.win_t, d.win_lat
        sync = "ok"
        if t.size == 0:
            sync = "no_clock" if d.unsynced else ("no_time_tag" if d.untagged else "waiting")
        stats_mask = t > now - p.stats_window_ns
        if d.discontinuity is not None:
            stats_mask &= t >= d.discontinuity
        i_short = int(np.searchsorted(t, now - p.short_ns, side="right"))
        short = lat[min(i_short, max(t.size - 3, 0)) :]
        # the lower median is always one of the samples: never a value between two levels
        short_med = (
            float(np.partition(short, (short.size - 1) // 2)[(short.size - 1) // 2]) if short.size else None
        )
        return _Window(t=t, lat=lat, sync=sync, st=lat[stats_mask], short_med=short_med)

    def _learn_baseline(self, d: _Device, w: _Window, now: int) -> None:
        """The baseline: the median since the last discontinuity, but for the newest samples
        (the guard); kept while fewer than 3 samples give it."""
        base_mask = w.t <= now - self.params.guard_ns
        if d.discontinuity is not None:
            base_mask &= w.t >= d.discontinuity
        if np.count_nonzero(base_mask) >= 3:
            d.baseline = float(np.median(w.lat[base_mask]))

    def _level_alarms(self, ev: _Evaluation, w: _Window, short_med: float, jump_on: bool) -> None:
        """``time_step`` and ``latency_jump`` from the short-term median against the baseline
        and the band; a change of level restarts statistics, baseline and drift from ``now``."""
        d, lim = ev.d, ev.d.limits
        lo, hi = lim.band_ns
        dev = short_med - d.baseline if d.baseline is not None else 0.0
        outside = max(lo - short_med, short_med - hi, 0.0)
        is_step = abs(dev) >= STEP_NS or outside >= STEP_NS
        ev.update("time_step", is_step, _step_message(is_step, short_med, d.baseline, lim.band_ns), CRITICAL)
        is_jump = self._jump_alarm(ev, w, short_med, dev, jump_on, is_step)
        if (is_step, is_jump) != d.level:  # the latency changed level: statistics,
            d.level = (is_step, is_jump)  # baseline and drift restart from here
            d.discontinuity = ev.now  # (older samples may mix both levels)

    def _jump_alarm(
        self, ev: _Evaluation, w: _Window, short_med: float, dev: float, jump_on: bool, is_step: bool
    ) -> bool:
        """``latency_jump`` (a hysteresis of half the jump; a jump to a level stable for
        ``relearn`` becomes the baseline); returns whether the latency sits at a jumped level."""
        d, p, lim, now = ev.d, self.params, ev.d.limits, ev.now
        threshold = lim.jump_ns if not jump_on else lim.jump_ns / 2
        is_jump = d.baseline is not None and threshold <= abs(dev) < STEP_NS
        relearned = False
        if jump_on and is_jump and d.level_since is not None and now - d.level_since >= p.relearn_ns:
            recent = w.lat[w.t > now - p.stats_window_ns]
            if recent.size >= 3 and abs(float(np.median(recent)) - short_med) < lim.jump_ns / 2:
                d.baseline, dev, is_jump, relearned = short_med, 0.0, False, True
        if is_jump:
            assert d.baseline is not None, "a jump is judged against a baseline"
            msg = (
                f"latency {_fmt_ms(short_med)}, baseline {_fmt_ms(d.baseline)} "
                f"({_fmt_ms(dev)}, threshold {lim.jump_ns / MS:g} ms)"
            )
        elif relearned:
            msg = f"latency settled at {_fmt_ms(short_med)}: new baseline"
        else:
            msg = f"latency {_fmt_ms(short_med)}, within {lim.jump_ns / MS:g} ms of baseline"
        event = ev.update("latency_jump", is_jump and not is_step, msg, WARNING)
        if event is not None:
            d.level_since = now if event.action == "raise" else None
        return is_jump

    def _spread_alarms(self, ev: _Evaluation, st: np.ndarray) -> _Spread:
        """``latency_out_of_band`` and ``latency_jitter`` on the statistics window (3 samples at
        least; not while a time step is active); returns its mean, σ, p99 and max."""
        if st.size < 3:
            return _Spread()
        lim = ev.d.limits
        lo, hi = lim.band_ns
        mean, sigma = float(st.mean()), float(st.std(ddof=1))
        p99, mx = float(np.percentile(st, 99)), float(st.max())
        step_now = ev.active("time_step")
        oob = not step_now and (mean < lo or mean > hi or p99 > hi)
        ev.update(
            "latency_out_of_band",
            oob,
            f"mean {_fmt_ms(mean)}, p99 {_fmt_ms(p99)}, band [{lo / MS:g}, {hi / MS:g}] ms",
            WARNING,
        )
        jit_lim = lim.max_sigma_ns if not ev.active("latency_jitter") else 0.8 * lim.max_sigma_ns
        ev.update(
            "latency_jitter",
            not step_now and sigma > jit_lim,
            f"σ {sigma / MS:.3f} ms, limit {lim.max_sigma_ns / MS:g} ms",
            WARNING,
        )
        return _Spread(mean_ns=mean, sigma_ns=sigma, p99_ns=p99, max_ns=mx)

    def _drift_alarm(self, ev: _Evaluation) -> tuple[float | None, float | None]:
        """``clock_drift``: only a drift that exceeds the limit by more than 2σ of its own
        estimate; returns the drift and its σ (ppm), None while there is none."""
        fit = self._drift_ppm(ev.d)
        if fit is None:
            return None, None
        drift, drift_sigma = fit
        lim = ev.d.limits
        drift_lim = lim.max_drift_ppm if not ev.active("clock_drift") else 0.7 * lim.max_drift_ppm
        ev.update(
            "clock_drift",
            abs(drift) - 2.0 * drift_sigma > drift_lim,
            f"device time tags drift {drift:+.2f} ± {drift_sigma:.2f} ppm against the PPS "
            f"clock (limit {lim.max_drift_ppm:g} ppm)",
            WARNING,
        )
        return drift, drift_sigma

    def _close_bins(self, d: _Device, now: int) -> None:
        """Append the median of each completed second of latency samples to ``d.bins``."""
        t, lat = d.win_t, d.win_lat
        if d.bin_next is None:
            if not t.size:
                return
            d.bin_next = int(t[0])
        while d.bin_next + NS_PER_S <= now:
            a = int(np.searchsorted(t, d.bin_next, side="left"))
            if a == t.size:
                break  # nothing newer yet
            if t[a] >= d.bin_next + NS_PER_S:  # skip empty seconds at once
                d.bin_next += int((t[a] - d.bin_next) // NS_PER_S) * NS_PER_S
                continue
            b = int(np.searchsorted(t, d.bin_next + NS_PER_S, side="left"))
            d.bins.append((int(np.median(t[a:b])), float(np.median(lat[a:b]))))
            d.bin_next += NS_PER_S
        while d.bins and d.bins[0][0] < now - self.params.drift_window_ns:
            d.bins.popleft()

    def _drift_ppm(self, d: _Device) -> tuple[float, float] | None:
        """Slope of the latency and its σ (ppm): a line through the 1-s medians since the last
        discontinuity. The σ is widened for correlated residuals (quantized or wandering tags).
        None while a step or jump is active, or the medians are too few or too short a span."""
        if self.alarms.is_active("time_step", d.name) or self.alarms.is_active("latency_jump", d.name):
            return None
        bins = [b for b in d.bins if d.discontinuity is None or b[0] >= d.discontinuity]
        if len(bins) < 5 or bins[-1][0] - bins[0][0] < self.params.drift_min_span_ns:
            return None
        tb = np.array([b[0] - bins[0][0] for b in bins], dtype=np.float64)
        lb = np.array([b[1] for b in bins])
        tb -= tb.mean()
        sxx = float(tb @ tb)
        slope = float(tb @ (lb - lb.mean())) / sxx
        res = lb - lb.mean() - slope * tb
        ss = float(res @ res)
        rho = min(max(float(res[1:] @ res[:-1]) / ss, 0.0), 0.9) if ss > 0 else 0.0
        sigma = np.sqrt(ss / (tb.size - 2) / sxx * (1 + rho) / (1 - rho))
        return slope * 1e6, float(sigma) * 1e6
