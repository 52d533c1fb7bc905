"""Emitting at scheduled instants: sleep until shortly before, spin the rest; measure the error.

:class:`Pacer` waits for a host ``CLOCK_MONOTONIC`` instant: ``time.sleep`` until ``spin_ns``
before it (never longer than ``poll_s`` at a time, so a stop request is seen), then a busy loop.
A high-rate emitter (the profiler, thousands of datagrams per second) uses ``spin_ns=0`` and
relies on the sleep alone; the process's timer slack is lowered to 1 µs
(:func:`tune_process`), which brings Linux's sleep overshoot from ~50–100 µs to ~10–30 µs.

:class:`TimingLog` keeps ``emitted − scheduled`` of every emission (ns) and summarizes it
(median, p99, max) with the CPU the emitter used (process time / wall time).
"""

from __future__ import annotations

import ctypes
import os
import signal
import time
from array import array

import numpy as np

_PR_SET_PDEATHSIG = 1
_PR_SET_TIMERSLACK = 29


class Pacer:
    """Wait until host instants; ``stopped()`` (a callable) ends a wait early."""

    def __init__(self, stopped=lambda: False, spin_ns: int = 200_000, poll_s: float = 0.05) -> None:
        self.stopped = stopped
        self.spin_ns = int(spin_ns)
        self.poll_s = poll_s

    def wait_until(self, t_ns: int) -> bool:
        """Return True at ``t_ns`` (or at once if it has passed), False if stopped first."""
        mono = time.monotonic_ns
        while True:
            rem = t_ns - mono()
            if rem <= 0:
                return True
            if self.stopped():
                return False
            if rem > self.spin_ns:
                time.sleep(min((rem - self.spin_ns) * 1e-9, self.poll_s))
            else:
                while mono() < t_ns:
                    pass
                return True


class TimingLog:
    """``emitted − scheduled`` per emission (ns), and the emitter's CPU use."""

    def __init__(self) -> None:
        self.errors_ns = array("q")
        self._cpu0 = time.process_time()
        self._wall0 = time.monotonic()

    def record(self, scheduled_ns: int, emitted_ns: int) -> None:
        self.errors_ns.append(emitted_ns - scheduled_ns)

    def summary(self) -> dict:
        wall = time.monotonic() - self._wall0
        cpu = time.process_time() - self._cpu0
        e = np.frombuffer(self.errors_ns, dtype=np.int64) if len(self.errors_ns) else np.zeros(0, np.int64)
        out = {
            "emissions": int(e.size),
            "wall_s": wall,
            "cpu_s": cpu,
            "cpu_fraction": cpu / wall if wall > 0 else 0.0,
        }
        if e.size:
            out.update(
                error_median_us=float(np.median(e)) / 1e3,
                error_p99_us=float(np.percentile(e, 99)) / 1e3,
                error_max_us=float(e.max()) / 1e3,
                error_min_us=float(e.min()) / 1e3,
            )
        return out


def tune_process(parent_death_signal: int | None = signal.SIGTERM, realtime: bool = False) -> str:
    """For an emulator process (Linux): 1 µs timer slack, ``parent_death_signal`` delivered when
    the parent dies (so no emulator outlives ``mls sim devices``, even after a ``kill -9``), and
    with ``realtime`` the SCHED_FIFO policy (priority 10) when the system permits it: the
    emulator then preempts ordinary processes at each emission instant (it sleeps in between, so
    it cannot starve the machine). Returns the scheduling policy in effect, for the stats."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_TIMERSLACK, 1000, 0, 0, 0)
        if parent_death_signal is not None:
            libc.prctl(_PR_SET_PDEATHSIG, int(parent_death_signal), 0, 0, 0)
    except (OSError, AttributeError):  # not Linux: keep the defaults
        pass
    if not realtime:
        return "SCHED_OTHER"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
        return "SCHED_FIFO 10"
    except (OSError, AttributeError) as e:
        return f"SCHED_OTHER (SCHED_FIFO refused: {getattr(e, 'strerror', None) or e})"
