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
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

DAY_NS = 86_400 * 1_000_000_000


def realtime_minus_monotonic_ns(tries: int = 3) -> int:
    """``CLOCK_REALTIME − CLOCK_MONOTONIC`` now, to move a kernel's realtime stamp (a socket's
    ``SO_TIMESTAMPNS``, a PPS fetch) to monotonic time. Each try brackets the realtime read by
    two monotonic reads; the narrowest bracket wins, so a preemption between the reads (a busy
    machine) does not shift the offset — and with it the order of stamps taken moments apart."""
    best_width, best = None, 0
    for _ in range(tries):
        a = time.monotonic_ns()
        real = time.clock_gettime_ns(time.CLOCK_REALTIME)
        b = time.monotonic_ns()
        if best_width is None or b - a < best_width:
            best_width, best = b - a, real - (a + b) // 2
    return best


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
