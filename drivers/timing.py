"""Device time tags against host receive stamps: clock drift, offset and jitter.

Given pairs (host receive stamp, device time tag) for one device — e.g. pcapng capture stamps
and STDBIN validity times — :func:`fit_clock` fits the host − device offset as a straight line
of device time, ``host − device = offset + drift·(device − device₀)``, by least squares with
outlier gating. It reports:

- ``drift_ppm``: the slope in ppm, i.e. ``(d host / d device − 1)·1e6``: how fast the host clock
  runs against the device clock. −35 ppm (the iXblue pcapng captures) means the capture host
  loses 35 µs per INS second — equivalently the INS runs 35 ppm fast on the host's time scale;
- ``offset_s``: host − device at the first sample (clock offset plus transport latency);
- the residual jitter of the host stamps around the line (RMS, max |r|, peak-to-peak).

This is the estimator behind ``mls decode --timing`` and the reference for the clock model.

Host clocks: every host stamp is ``CLOCK_MONOTONIC``; kernel ``CLOCK_REALTIME`` stamps are moved
to it through a :class:`HostClock` (the real one unless told otherwise), whose
:meth:`~HostClock.realtime_minus_monotonic_ns` reads also count the steps of the realtime clock
(its own :class:`HostClockSteps`: an NTP step, ``date -s``), and a transport converts its stamps
through :class:`RealtimeStamps`, which keeps a step from shifting the stamps taken before it.
:class:`FakeHostClock` stands in for a step in the simulated devices' runs: it is chosen
explicitly (``mls acquire --sim-host-clock FILE``, a test's constructor argument), never by the
environment, and handed to whoever reads the clock.
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass

import numpy as np

DAY_NS = 86_400 * 1_000_000_000


#: realtime − monotonic moving more than this between two reads is a step of CLOCK_REALTIME
#: (an NTP/chrony step or a manual ``date -s``; a slew moves both clocks alike)
STEP_THRESHOLD_NS = 1_000_000
#: a step at least this large is worth the operator's attention (``host_clock_step``); smaller
#: ones are a virtual machine's or PTP's clock discipline — handled and counted alike, no alarm
STEP_ALARM_NS = 10_000_000
_REALTIME = time.CLOCK_REALTIME


def _kernel_offset_ns(tries: int) -> int:
    best_width, best = None, 0
    for _ in range(tries):
        a = time.monotonic_ns()
        real = time.clock_gettime_ns(time.CLOCK_REALTIME)
        b = time.monotonic_ns()
        if best_width is None or b - a < best_width:
            best_width, best = b - a, real - (a + b) // 2
    return best


class HostClockSteps:
    """The steps of ``CLOCK_REALTIME`` one :class:`HostClock` has seen (through its
    :meth:`~HostClock.realtime_minus_monotonic_ns` reads): ``count`` (every step > :data:`STEP_THRESHOLD_NS`),
    ``large`` (those of at least :data:`STEP_ALARM_NS`), and the latest as
    ``(host monotonic ns, step ns)`` in ``last``. The daemon raises ``host_clock_step`` when
    ``large`` grows and refreshes its system-clock seed when ``count`` does; the host's own
    stamps are monotonic and never move."""

    def __init__(self) -> None:
        self.offset_ns: int | None = None
        self.count = 0
        self.large = 0
        self.last: tuple[int, int] | None = None
        self._lock = threading.Lock()

    def observe(self, offset_ns: int) -> None:
        with self._lock:  # one read's compare and store at a time (reads come from any thread)
            last = self.offset_ns
            self.offset_ns = offset_ns
            if last is not None and abs(offset_ns - last) > STEP_THRESHOLD_NS:
                self.count += 1
                self.large += abs(offset_ns - last) >= STEP_ALARM_NS
                self.last = (time.monotonic_ns(), offset_ns - last)


class HostClock:
    """The host's clock as a process reads it: ``CLOCK_REALTIME − CLOCK_MONOTONIC``
    (:meth:`realtime_minus_monotonic_ns`) and the steps of the realtime clock those reads have
    seen (:attr:`steps_seen`, this clock's own counter: whoever needs the counts gets the clock). This
    class is the real clock; :class:`FakeHostClock` the simulated devices' one, given explicitly
    where it is wanted."""

    #: kernel realtime stamps are moved by this clock's steps (:meth:`kernel_stamp`): a fake
    fake = False

    def __init__(self) -> None:
        self.steps_seen = HostClockSteps()

    def offset_ns(self, tries: int = 3) -> int:
        """realtime − monotonic now, not shown to :attr:`steps_seen` (a transport's receive path)."""
        return _kernel_offset_ns(tries)

    def kernel_stamp(self, realtime_ns: int) -> int:
        """A real kernel realtime stamp as this clock would have stamped it (the real clock: as is)."""
        return realtime_ns

    def realtime_minus_monotonic_ns(self, tries: int = 3) -> int:
        """``CLOCK_REALTIME − CLOCK_MONOTONIC`` now, to move a kernel's realtime stamp (a socket's
        ``SO_TIMESTAMPNS``, a PPS fetch) to monotonic time. Each try brackets the realtime read by
        two monotonic reads; the narrowest bracket wins, so a preemption between the reads (a busy
        machine) does not shift the offset — and with it the order of stamps taken moments apart.

        Every read is also shown to :attr:`steps_seen`, which counts the steps of the realtime clock.
        On a :class:`FakeHostClock` (the simulated devices' runs only) the offset is the faked one."""
        offset = self.offset_ns(tries)
        self.steps_seen.observe(offset)
        return offset


class RealtimeStamps:
    """A transport's kernel ``CLOCK_REALTIME`` stamps → ``CLOCK_MONOTONIC``, across a step.

    :meth:`begin` samples the offset for a read. While the offset is the one of the previous
    read (:attr:`exact`), ``stamp − offset`` is exact and the caller does it inline (keeping
    :attr:`last_ns`, the latest stamp, for the order check below). After a
    step, the stamps of one read may lie on either side of it (stamped before the step, read
    after): for ``hold_ns`` after the step :meth:`convert` converts each with both offsets and
    keeps the later of those that put it no later than now and not before the previous stamp
    (a socket's stamps come in order) — the wrong one is a step away: in the future, or a step
    earlier. A stamp that fits neither is replaced by the read time and counted (``unknown``);
    stamps kept on the old offset are counted (``repaired``).

    ``clock``: the host clock read (default: the real one, read inline); a
    :class:`FakeHostClock` moves the offset and the stamps by its steps."""

    def __init__(
        self, hold_ns: int = 2_000_000_000, tolerance_ns: int = 1_000_000, clock: HostClock | None = None
    ) -> None:
        self._fake = clock if clock is not None and clock.fake else None
        self.hold_ns = hold_ns
        self.tolerance_ns = tolerance_ns
        self.offset: int | None = None
        self.exact = True
        self.steps = self.repaired = self.unknown = 0
        self._old: int | None = None  # the offset before the latest step
        self._until = 0  # host ns until which stamps may still be of the old offset
        self.last_ns = -(2**62)  # the latest monotonic stamp given out (the caller's, when exact)

    def begin(self) -> int:
        """The offset for this read (and :attr:`exact`). (The host clock's step counter is left
        to the daemon's periodic read: this is the receive path.)"""
        fake = self._fake
        if fake is None:  # _kernel_offset_ns(3), inline: once per read of a busy socket
            mono, real, width, offset = time.monotonic_ns, time.clock_gettime_ns, None, 0
            for _ in range(3):
                a = mono()
                r = real(_REALTIME)
                b = mono()
                if width is None or b - a < width:
                    width, offset = b - a, r - (a + b) // 2
        else:
            offset = fake.offset_ns(3)
        prev, self.offset = self.offset, offset
        if prev is not None and not -STEP_THRESHOLD_NS <= offset - prev <= STEP_THRESHOLD_NS:
            self.steps += 1
            self._old, self._until = prev, time.monotonic_ns() + self.hold_ns
        if self._old is None:
            self.exact = fake is None
        else:
            if time.monotonic_ns() > self._until:
                self._old = None
            self.exact = False
        return offset

    def convert(self, realtime_ns: int, read_ns: int) -> int:
        """One stamp when not :attr:`exact` (see the class docstring)."""
        if self._fake is not None:
            realtime_ns = self._fake.kernel_stamp(realtime_ns)
        assert self.offset is not None
        hi = time.monotonic_ns() + self.tolerance_ns
        lo = self.last_ns - self.tolerance_ns
        m = realtime_ns - self.offset
        if self._old is not None:
            m_old = realtime_ns - self._old
            # the true stamp is in the past; the other candidate is a step away from it: in the
            # future (rejected) or a step earlier (the later one wins)
            fits = [c for c in (m, m_old) if lo <= c <= hi]
            if not fits:
                self.unknown += 1
                m = read_ns
            elif max(fits) != m:
                self.repaired += 1
                m = m_old
        self.last_ns = max(self.last_ns, m)
        return m


class FakeHostClock(HostClock):
    """The host clock as the simulated devices' ``host_clock_step`` fault makes it look: the
    emulators cannot step this machine's ``CLOCK_REALTIME``, so they write the steps they would
    make to a file (``<run dir>/host_clock``: lines ``<host monotonic ns> <step ns>``) and a
    daemon given that file (``mls acquire --sim-host-clock FILE``) reads realtime − monotonic
    through this class: the real offset plus every step whose instant has passed, and kernel
    realtime stamps (:meth:`kernel_stamp`) moved alike when they were taken after a step — what
    a real step does to both. Never used on a vessel. The file is looked at (``stat``) at most
    every ``poll_ns``."""

    fake = True

    def __init__(self, path: str, poll_ns: int = 100_000_000) -> None:
        super().__init__()
        self.path = path
        self.poll_ns = poll_ns
        self.steps: list[tuple[int, int]] = []  # (host monotonic ns, step ns), sorted
        self._mtime: int | None = None
        self._next_poll = 0

    def _poll(self) -> None:
        now = time.monotonic_ns()
        if now < self._next_poll:
            return
        self._next_poll = now + self.poll_ns
        try:
            mtime = os.stat(self.path).st_mtime_ns
            if mtime == self._mtime:
                return
            with open(self.path, encoding="utf-8") as f:
                rows = [line.split() for line in f if line.strip() and not line.startswith("#")]
            self.steps = sorted((int(a), int(b)) for a, b in rows)
            self._mtime = mtime
        except (OSError, ValueError):
            pass

    def step_at(self, monotonic_ns: int) -> int:
        """The sum of the steps made by ``monotonic_ns``."""
        return sum(step for t, step in self.steps if t <= monotonic_ns)

    def offset_ns(self, tries: int = 3) -> int:
        """The real realtime − monotonic plus the steps made by now (not shown to :attr:`steps_seen`)."""
        self._poll()
        return _kernel_offset_ns(tries) + self.step_at(time.monotonic_ns())

    def kernel_stamp(self, realtime_ns: int) -> int:
        """A real kernel realtime stamp as the faked clock would have stamped it."""
        if not self.steps:
            return realtime_ns
        return realtime_ns + self.step_at(realtime_ns - _kernel_offset_ns(1))


@dataclass(frozen=True)
class ClockFit:
    n: int  # samples used
    n_outliers: int  # samples gated out
    span_s: float  # device time covered
    drift_ppm: float  # (d host / d device − 1)·1e6
    offset_s: float  # host − device at the first sample (clock offset + latency)
    jitter_rms_s: float  # RMS of the residuals
    jitter_max_s: float  # largest |residual|
    jitter_p2p_s: float  # max − min residual


def unwrap_time_of_day_ns(tod_ns) -> np.ndarray:
    """Time-of-day tags (ns since midnight) → monotonic ns across midnight rollovers."""
    t = np.asarray(tod_ns, dtype=np.int64)
    steps = np.diff(t)
    wraps = np.concatenate([[0], np.cumsum(steps < -DAY_NS // 2)])
    return t + wraps.astype(np.int64) * DAY_NS


def fit_clock(host_ns, device_ns, gate: float = 5.0, max_iter: int = 5) -> ClockFit:
    """Fit host − device against device time (both int64 ns, same length, at least 3 samples).

    Samples whose residual exceeds ``gate`` × 1.4826 × MAD of the residuals (a robust σ; the RMS
    when the MAD is 0), but never closer than two quanta of the stamps' resolution (1 ms stamps
    are common), are dropped and the fit repeated, so a few late datagrams do not bias the drift.
    """
    h = np.asarray(host_ns, dtype=np.int64)
    d = np.asarray(device_ns, dtype=np.int64)
    if h.shape != d.shape or h.ndim != 1 or h.size < 3:
        raise ValueError(f"fit_clock: need two 1-D arrays of equal length >= 3, got {h.shape} and {d.shape}")
    x = (d - d[0]).astype(np.float64) * 1e-9
    y = (h - h[0]).astype(np.float64) * 1e-9 - x  # host − device, relative to the first sample
    # stamps written with a coarse resolution (ms in many loggers) quantize the residuals: never
    # gate closer than two quanta
    quantum_ns = next((10**k for k in range(9, 0, -1) if np.all(h % 10**k == 0)), 1)
    floor_s = 2e-9 * quantum_ns
    keep = np.ones(x.size, dtype=bool)
    for _ in range(max_iter):
        slope, intercept = np.polyfit(x[keep], y[keep], 1)
        r = y - (intercept + slope * x)
        mad = np.median(np.abs(r[keep] - np.median(r[keep])))
        # robust σ; on coarsely quantized stamps (ms) the MAD can be 0, then the RMS stands in
        sigma = 1.4826 * mad if mad > 0 else float(np.sqrt(np.mean(r[keep] ** 2)))
        new_keep = np.abs(r) <= max(gate * sigma, floor_s)
        if new_keep.sum() < 3 or np.array_equal(new_keep, keep):
            break
        keep = new_keep
    slope, intercept = np.polyfit(x[keep], y[keep], 1)
    r = (y - (intercept + slope * x))[keep]
    return ClockFit(
        n=int(keep.sum()),
        n_outliers=int((~keep).sum()),
        span_s=float(x[-1] - x[0]),
        drift_ppm=float(slope * 1e6),
        offset_s=float((h[0] - d[0]) * 1e-9 + intercept),
        jitter_rms_s=float(np.sqrt(np.mean(r**2))),
        jitter_max_s=float(np.max(np.abs(r))),
        jitter_p2p_s=float(np.ptp(r)),
    )


def signed_time_of_day_offset_s(offset_s: float) -> float:
    """An offset of a full time scale against a time of day (a capture's UTC stamp − the
    device's time-of-day tag: the date plus latency and clock offset) without the date: folded
    into [−12 h, +12 h), so a device tag 6.6 ms *ahead* of the stamp gives −0.0066 s, not
    86399.9934 s as ``offset_s % 86400`` does."""
    half_day = DAY_NS // 2_000_000_000
    return (offset_s + half_day) % (2 * half_day) - half_day
