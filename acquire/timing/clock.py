"""Clock model: host monotonic ns → GPS ns, fitted over labelled PPS edges (docs/architecture.md §6).

``gps = a + b·(host − t0)``, fitted by least squares over a sliding window of labelled PPS edges
``(host_ns, gps_second)`` (the host stamp of the pulse and the GPS second a time message gave it,
gpsd's rule, applied by the drivers' ``PpsLabeler``). Each new edge is first *gated* against the
current fit: an edge whose residual exceeds ``max(gate_floor, gate_sigmas·σ)`` is rejected as an
outlier (a late interrupt, a mislabelled second); when ``max_consecutive_rejects`` edges in a row
disagree with the fit, the fit is wrong (the labels stepped, e.g. by 1 s) and the model restarts
from the new edges, counting a *step*.

States (:class:`ClockState`), evaluated at any host time:

- ``LOCKED``: at least ``min_edges`` edges in the window and the last one at most
  ``loss_timeout`` ago;
- ``HOLDOVER``: PPS lost, the fit is extrapolated; the error bound grows with the fit's own
  uncertainty (offset and drift covariance) plus an assumed oscillator frequency wander
  (``holdover_wander_ppm``) times the time since the last edge;
- ``UNLOCKED``: no usable fit yet, or the holdover bound exceeded ``holdover_limit``. Estimates
  are still returned (extrapolated, or host time + a coarse offset from the system clock) but
  are flagged.

Arithmetic: times stay int64 ns; the fit works on small differences (``host − t0`` and
``(gps − host) − offset_ref``, both exact in float64), so nothing loses resolution at GPS-epoch
magnitudes (1.4e18 ns). ``drift_ppm`` = (GPS ns per host ns − 1)·1e6: positive when the host
clock runs slow against GPS.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from dataclasses import dataclass
from enum import Enum

NS_PER_S = 1_000_000_000


class ClockState(str, Enum):
    LOCKED = "LOCKED"
    HOLDOVER = "HOLDOVER"
    UNLOCKED = "UNLOCKED"


@dataclass(frozen=True)
class ClockParams:
    window_edges: int = 60  # edges in the sliding fit window (one per second)
    min_edges: int = 4  # edges needed to lock
    loss_timeout_ns: int = 1_500_000_000  # no edge for this long → HOLDOVER
    gate_floor_ns: int = 250_000  # outlier gate, at least this wide
    gate_sigmas: float = 6.0  # outlier gate in residual σ
    bootstrap_gate_ns: int = 2_000_000  # gate before min_edges edges (σ not known yet)
    max_consecutive_rejects: int = 4  # this many rejected edges in a row → restart (a step)
    prior_jitter_ns: int = 100_000  # edge σ assumed while fewer than 3 edges
    holdover_wander_ppm: float = 0.1  # assumed frequency wander in holdover (bound growth)
    holdover_limit_ns: int = 200_000  # holdover bound above this → UNLOCKED
    bound_sigmas: float = 3.0  # the error bound is this many σ of the prediction
    # the host's system clock off GPS time by more than this once the PPS gives GPS time: the
    # alarm host_clock_offset (acquire.timing.timekeeper); 1 s, chrony's usual `makestep 1.0`
    host_offset_alarm_ns: int = NS_PER_S

    def __post_init__(self) -> None:
        if self.window_edges < 2 or self.min_edges < 2 or self.min_edges > self.window_edges:
            raise ValueError(
                f"clock window_edges={self.window_edges}, min_edges={self.min_edges}: "
                "expected 2 ≤ min_edges ≤ window_edges"
            )
        if self.host_offset_alarm_ns <= 0:
            raise ValueError(f"clock host_offset_alarm_ns={self.host_offset_alarm_ns}: expected > 0")


#: the clock state of a record stamped before any PPS fit: UNLOCKED, its ``log_time`` the host's
#: system clock (the coarse seed), not GPS — the session log marks it (acquire.log.schema)
HOST_TIME_STATE = "UNLOCKED_HOST_TIME"


@dataclass(frozen=True)
class GpsEstimate:
    gps_ns: int
    state: ClockState
    error_bound_ns: int | None  # None when there is no PPS fit at all

    @property
    def record_state(self) -> str:
        """The clock state a record stamped with this estimate carries: the state's name, or
        :data:`HOST_TIME_STATE` when there is no PPS fit (the time is the host's)."""
        if self.error_bound_ns is None and self.state == ClockState.UNLOCKED:
            return HOST_TIME_STATE
        return self.state.value


@dataclass(frozen=True)
class EdgeResult:
    accepted: bool
    reason: str  # "accepted", "restart", "outlier", "duplicate", "out_of_order", "stale_restart"
    residual_ns: int | None = None  # edge GPS − prediction, when there was a prediction
    step_ns: int | None = None  # on "restart" after rejects: the size of the step


@dataclass(frozen=True)
class ClockStatus:
    state: ClockState
    offset_ns: int | None  # GPS − host at the status time
    drift_ppm: float | None
    jitter_rms_ns: float | None  # residual RMS of the edges in the window
    jitter_max_ns: float | None
    error_bound_ns: int | None  # prediction bound now (grows in holdover)
    edges_in_window: int
    edges_accepted: int
    edges_rejected: dict[str, int]
    steps: int
    last_edge_age_ns: int | None

    def as_dict(self) -> dict:
        """JSON-friendly (µs for the small quantities, as the operator reads them)."""

        def us(v):
            return None if v is None else round(v / 1000.0, 3)

        return {
            "state": self.state.value,
            "offset_ns": self.offset_ns,
            "drift_ppm": None if self.drift_ppm is None else round(self.drift_ppm, 4),
            "jitter_rms_us": us(self.jitter_rms_ns),
            "jitter_max_us": us(self.jitter_max_ns),
            "error_bound_us": us(self.error_bound_ns),
            "edges_in_window": self.edges_in_window,
            "edges_accepted": self.edges_accepted,
            "edges_rejected": dict(self.edges_rejected),
            "steps": self.steps,
            "last_edge_age_s": None
            if self.last_edge_age_ns is None
            else round(self.last_edge_age_ns / NS_PER_S, 3),
        }


@dataclass(frozen=True)
class _Fit:
    """``gps(host) = host + off_ref + c + d·(host − t0)`` with c, d fitted on small numbers."""

    t0: int
    off_ref: int
    c: float
    d: float
    n: int
    xbar: float  # mean of host − t0 over the window (ns)
    sxx: float  # Σ (x − xbar)² (ns²); 0 when n == 1
    sigma_ns: float  # edge residual σ (estimated, or the prior for n < 3)
    rms_ns: float
    max_ns: float

    def predict(self, host_ns: int) -> int:
        return host_ns + self.off_ref + round(self.c + self.d * (host_ns - self.t0))

    def sigma_at(self, host_ns: int) -> float:
        """σ of the prediction of the line at ``host_ns`` (offset and drift uncertainty)."""
        if self.n < 2 or self.sxx <= 0.0:
            return self.sigma_ns
        dx = (host_ns - self.t0) - self.xbar
        return self.sigma_ns * math.sqrt(1.0 / self.n + dx * dx / self.sxx)


def _fit(edges: deque[tuple[int, int]], prior_jitter_ns: float) -> _Fit:
    t0 = edges[-1][0]
    off_ref = edges[-1][1] - edges[-1][0]
    xs = [float(h - t0) for h, _ in edges]
    ys = [float((g - h) - off_ref) for h, g in edges]
    n = len(xs)
    xbar = sum(xs) / n
    ybar = sum(ys) / n
    sxx = sum((x - xbar) ** 2 for x in xs)
    if n >= 2 and sxx > 0.0:
        d = sum((x - xbar) * (y - ybar) for x, y in zip(xs, ys, strict=True)) / sxx
    else:
        d = 0.0
    c = ybar - d * xbar
    res = [y - (c + d * x) for x, y in zip(xs, ys, strict=True)]
    rms = math.sqrt(sum(r * r for r in res) / n)
    max_abs = max(abs(r) for r in res)
    sigma = math.sqrt(sum(r * r for r in res) / (n - 2)) if n >= 3 else float(prior_jitter_ns)
    return _Fit(t0, off_ref, c, d, n, xbar, sxx, max(sigma, 1.0), rms, max_abs)


class ClockModel:
    """Host monotonic → GPS time from labelled PPS edges. Feed edges in host-time order."""

    def __init__(self, params: ClockParams | None = None, coarse_offset_ns: int | None = None):
        """``coarse_offset_ns``: GPS − host monotonic from the system clock (UTC + leap
        seconds), used for estimates before the first PPS edge (flagged UNLOCKED)."""
        self.params = params or ClockParams()
        self.coarse_offset_ns = coarse_offset_ns
        self._edges: deque[tuple[int, int]] = deque(maxlen=self.params.window_edges)
        self._fit: _Fit | None = None
        self._rejects: list[tuple[int, int]] = []  # consecutive rejected edges
        self._last_host: int | None = None
        self.edges_accepted = 0
        self.edges_rejected: Counter[str] = Counter()
        self.steps = 0

    # -- edges ------------------------------------------------------------------------------

    def add_edge(self, host_ns: int, gps_second: int) -> EdgeResult:
        """A PPS edge stamped at ``host_ns`` and labelled with GPS second ``gps_second``."""
        p = self.params
        host_ns, gps_ns = int(host_ns), int(gps_second) * NS_PER_S
        if self._last_host is not None and host_ns <= self._last_host:
            self.edges_rejected["out_of_order"] += 1
            return EdgeResult(False, "out_of_order")
        if self._edges and gps_ns == self._edges[-1][1]:
            self.edges_rejected["duplicate"] += 1
            return EdgeResult(False, "duplicate")
        fit = self._fit
        if fit is None:
            return self._accept(host_ns, gps_ns, None)
        dt = host_ns - self._edges[-1][0]
        if self._bound(fit, host_ns, dt) > p.holdover_limit_ns and dt > p.loss_timeout_ns:
            # holdover exhausted: the old window says nothing reliable about this edge
            self._restart()
            self._accept(host_ns, gps_ns, None)
            return EdgeResult(True, "stale_restart")
        residual = gps_ns - fit.predict(host_ns)
        gate: float
        if len(self._edges) < p.min_edges:
            gate = p.bootstrap_gate_ns
        else:
            gate = max(p.gate_floor_ns, p.gate_sigmas * fit.sigma_at(host_ns))
        gate += p.holdover_wander_ppm * 1e-6 * max(dt, 0)
        if abs(residual) <= gate and gps_ns > self._edges[-1][1]:
            return self._accept(host_ns, gps_ns, residual)
        self._last_host = host_ns
        self._rejects.append((host_ns, gps_ns))
        if len(self._rejects) < p.max_consecutive_rejects:
            self.edges_rejected["outlier"] += 1
            return EdgeResult(False, "outlier", residual_ns=residual)
        # the fit disagrees with several edges in a row: the time labels stepped. Restart from
        # the rejected edges when they agree with each other, else from this edge alone.
        rejects = deque(self._rejects, maxlen=p.window_edges)
        if _fit(rejects, p.prior_jitter_ns).max_ns > p.bootstrap_gate_ns:
            rejects = deque([(host_ns, gps_ns)], maxlen=p.window_edges)
        self._restart()
        self.steps += 1
        self._edges.extend(rejects)
        self.edges_accepted += len(rejects)
        self.edges_rejected["outlier"] -= len(rejects) - 1  # counted again as accepted
        self._fit = _fit(self._edges, p.prior_jitter_ns)
        return EdgeResult(True, "restart", residual_ns=residual, step_ns=residual)

    def _accept(self, host_ns: int, gps_ns: int, residual: int | None) -> EdgeResult:
        self._edges.append((host_ns, gps_ns))
        self._last_host = host_ns
        self._rejects = []
        self.edges_accepted += 1
        self._fit = _fit(self._edges, self.params.prior_jitter_ns)
        return EdgeResult(True, "accepted", residual_ns=residual)

    def _restart(self) -> None:
        self._edges.clear()
        self._fit = None
        self._rejects = []

    # -- estimates --------------------------------------------------------------------------

    def _bound(self, fit: _Fit, host_ns: int, dt_ns: int) -> float:
        p = self.params
        return p.bound_sigmas * fit.sigma_at(host_ns) + p.holdover_wander_ppm * 1e-6 * max(dt_ns, 0)

    def _state(self, fit: _Fit | None, host_ns: int) -> tuple[ClockState, float | None]:
        if fit is None:
            return ClockState.UNLOCKED, None
        p = self.params
        dt = host_ns - self._edges[-1][0]
        bound = self._bound(fit, host_ns, dt)
        if len(self._edges) < p.min_edges:
            return ClockState.UNLOCKED, bound
        if dt <= p.loss_timeout_ns:
            return ClockState.LOCKED, bound
        if bound <= p.holdover_limit_ns:
            return ClockState.HOLDOVER, bound
        return ClockState.UNLOCKED, bound

    def to_gps(self, host_ns: int) -> GpsEstimate:
        """GPS ns for a host monotonic stamp, with the state and error bound at that time."""
        fit = self._fit
        if fit is None:
            offset = self.coarse_offset_ns or 0
            return GpsEstimate(int(host_ns) + offset, ClockState.UNLOCKED, None)
        state, bound = self._state(fit, host_ns)
        return GpsEstimate(fit.predict(int(host_ns)), state, None if bound is None else round(bound))

    def gps_ns(self, host_ns: int) -> int:
        """Just the GPS ns (for :class:`acquire.alarms.AlarmBook`'s ``to_gps``)."""
        return self.to_gps(host_ns).gps_ns

    def state_at(self, host_ns: int) -> ClockState:
        return self._state(self._fit, host_ns)[0]

    def status(self, now_host_ns: int) -> ClockStatus:
        fit = self._fit
        state, bound = self._state(fit, now_host_ns)
        est = self.to_gps(now_host_ns)
        return ClockStatus(
            state=state,
            offset_ns=est.gps_ns - int(now_host_ns)
            if fit is not None or self.coarse_offset_ns is not None
            else None,
            drift_ppm=None if fit is None or fit.n < 2 else fit.d * 1e6,
            jitter_rms_ns=None if fit is None or fit.n < 3 else fit.rms_ns,
            jitter_max_ns=None if fit is None or fit.n < 3 else fit.max_ns,
            error_bound_ns=None if bound is None else round(bound),
            edges_in_window=len(self._edges),
            edges_accepted=self.edges_accepted,
            edges_rejected=dict(self.edges_rejected),
            steps=self.steps,
            last_edge_age_ns=None if not self._edges else int(now_host_ns) - self._edges[-1][0],
        )
