"""The acceptance of a pass (docs/architecture.md §8), pure: :func:`evaluate_pass` accepts or rejects
what was recorded over a capture window (:class:`PassWindow`) against the
:class:`AcceptanceTolerances`, every failed condition a reason that names the value and the limit."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class AcceptanceTolerances:
    """What a pass must meet over its capture window to be accepted."""

    max_xte_m: float = 2.0  # |cross-track error| at every sample
    max_heading_error_rad: float = math.radians(5.0)  # |heading − line heading|
    max_speed_error_mps: float = 0.5  # |speed over ground − planned speed|
    min_points_per_target: int = 100  # live hits on every target
    max_gap_s: float = 0.5  # longest gap in the INS records or between profiles

    def as_dict(self) -> dict:
        return {
            "max_xte_m": self.max_xte_m,
            "max_heading_error_deg": math.degrees(self.max_heading_error_rad),
            "max_speed_error_mps": self.max_speed_error_mps,
            "min_points_per_target": self.min_points_per_target,
            "max_gap_s": self.max_gap_s,
        }


@dataclass(frozen=True)
class PassWindow:
    """Everything recorded while the vessel sailed one capture window."""

    pass_id: int
    planned_speed_mps: float
    capture_m: tuple[float, float]  # the window along the line
    completed: bool  # sailed through to the window's end
    exit_reason: str  # why it ended early ("" when completed)
    t_enter_gps_s: float
    t_exit_gps_s: float
    # navigation samples inside the window
    t_gps_s: np.ndarray
    along_m: np.ndarray
    xte_m: np.ndarray
    heading_error_rad: np.ndarray
    speed_mps: np.ndarray
    navigation: np.ndarray  # 1 / 0 / NaN (not reported)
    dead_reckoning: np.ndarray
    ins_pps: np.ndarray
    utc: np.ndarray
    # profiler
    profile_t_gps_s: np.ndarray  # mid time of every profile in the window
    profiles_incomplete: int
    profiles_pps_unlocked: int
    hits: dict[str, int]  # target name → hits
    clock_states: tuple[str, ...] = ()  # every clock state seen during the window


@dataclass(frozen=True)
class PassVerdict:
    pass_id: int
    accepted: bool
    reasons: tuple[str, ...]
    stats: dict
    attempt: int = 1

    def as_dict(self) -> dict:
        return {
            "pass_id": self.pass_id,
            "accepted": self.accepted,
            "reasons": list(self.reasons),
            "stats": self.stats,
            "attempt": self.attempt,
        }


def _flag_seconds(t: np.ndarray, bad: np.ndarray) -> float:
    """Seconds (sample-weighted) during which ``bad`` holds."""
    if t.size < 2:
        return float(bad.any())
    dt = np.diff(t, append=t[-1])
    return float(np.sum(dt[bad]))


def _max_gap(t: np.ndarray, t0: float, t1: float) -> float:
    edges = np.concatenate([[t0], np.sort(t), [t1]])
    return float(np.max(np.diff(edges))) if edges.size > 1 else 0.0


def evaluate_pass(
    w: PassWindow, tol: AcceptanceTolerances = AcceptanceTolerances(), attempt: int = 1
) -> PassVerdict:
    """Accept or reject a sailed window; every failed condition is a reason that names the
    value and the tolerance."""
    reasons: list[str] = []
    stats: dict = {
        "t_enter_gps_s": w.t_enter_gps_s,
        "t_exit_gps_s": w.t_exit_gps_s,
        "duration_s": round(w.t_exit_gps_s - w.t_enter_gps_s, 3),
        "n_nav": int(w.t_gps_s.size),
        "n_profiles": int(w.profile_t_gps_s.size),
        "hits": dict(w.hits),
    }
    if not w.completed:
        reached = float(np.max(w.along_m)) if w.along_m.size else w.capture_m[0]
        reasons.append(
            f"capture window not completed: {w.exit_reason} at "
            f"{reached - w.capture_m[0]:.1f} of "
            f"{w.capture_m[1] - w.capture_m[0]:.1f} m"
        )
    if w.t_gps_s.size:
        reasons += _track_reasons(w, tol, stats)
        reasons += _speed_reasons(w, tol, stats)
        reasons += _ins_health_reasons(w, tol, stats)
    else:
        reasons.append("no INS records in the window")
    reasons += _profiler_reasons(w, tol, stats)
    reasons += _clock_reasons(w)
    reasons += _target_reasons(w, tol)
    return PassVerdict(
        pass_id=w.pass_id, accepted=not reasons, reasons=tuple(reasons), stats=stats, attempt=attempt
    )


def _track_reasons(w: PassWindow, tol: AcceptanceTolerances, stats: dict) -> list[str]:
    """The line kept: cross-track and heading error over the window's INS records (into
    ``stats``: their maxima and the RMS cross-track error)."""
    reasons = []
    xte = float(np.max(np.abs(w.xte_m)))
    herr = float(np.max(np.abs(w.heading_error_rad)))
    stats.update(
        max_xte_m=round(xte, 3),
        rms_xte_m=round(float(np.sqrt(np.mean(w.xte_m**2))), 3),
        max_heading_error_deg=round(math.degrees(herr), 3),
    )
    if xte > tol.max_xte_m:
        reasons.append(f"cross-track error up to {xte:.2f} m (tolerance {tol.max_xte_m:g} m)")
    if herr > tol.max_heading_error_rad:
        reasons.append(
            f"heading error up to {math.degrees(herr):.1f}° (tolerance "
            f"{math.degrees(tol.max_heading_error_rad):g}°)"
        )
    return reasons


def _speed_reasons(w: PassWindow, tol: AcceptanceTolerances, stats: dict) -> list[str]:
    """The planned speed kept: speed over ground within tolerance of it (into ``stats``: its
    minimum, maximum and mean)."""
    v = w.speed_mps[np.isfinite(w.speed_mps)]
    if not v.size:
        return ["no speed over ground from the INS"]
    stats.update(
        speed_min_mps=round(float(v.min()), 3),
        speed_max_mps=round(float(v.max()), 3),
        speed_mean_mps=round(float(v.mean()), 3),
    )
    dev = float(np.max(np.abs(v - w.planned_speed_mps)))
    if dev > tol.max_speed_error_mps:
        return [
            f"speed {v.min():.2f}–{v.max():.2f} m/s, planned "
            f"{w.planned_speed_mps:g} ± {tol.max_speed_error_mps:g} m/s"
        ]
    return []


def _ins_health_reasons(w: PassWindow, tol: AcceptanceTolerances, stats: dict) -> list[str]:
    """The INS healthy over the window: navigating, on UTC time, with PPS, not dead
    reckoning, no gap in its records (into ``stats``: the longest gap)."""
    reasons = []
    t = w.t_gps_s
    for arr, item, what in (
        (w.navigation, "navigation", "not navigating"),
        (w.utc, "UTC time", "not on UTC time"),
        (w.ins_pps, "PPS", "without PPS"),
    ):
        if np.isnan(arr).any():
            reasons.append(f"INS status ({item}) not reported")
        elif (arr == 0).any():
            reasons.append(f"INS {what} for {_flag_seconds(t, arr == 0):.1f} s of the window")
    dr = w.dead_reckoning == 1
    if dr.any():
        reasons.append(f"INS in dead reckoning for {_flag_seconds(t, dr):.1f} s")
    nav_gap = _max_gap(t, w.t_enter_gps_s, w.t_exit_gps_s)
    stats["max_nav_gap_s"] = round(nav_gap, 3)
    if nav_gap > tol.max_gap_s:
        reasons.append(f"INS data gap of {nav_gap:.2f} s (limit {tol.max_gap_s:g} s)")
    return reasons


def _profiler_reasons(w: PassWindow, tol: AcceptanceTolerances, stats: dict) -> list[str]:
    """The profiler's data whole: no gap between profiles, none incomplete, all PPS-locked
    (into ``stats``: the longest gap)."""
    reasons = []
    prof_gap = _max_gap(w.profile_t_gps_s, w.t_enter_gps_s, w.t_exit_gps_s)
    stats["max_profile_gap_s"] = round(prof_gap, 3)
    if prof_gap > tol.max_gap_s:
        reasons.append(f"profiler data gap of {prof_gap:.2f} s (limit {tol.max_gap_s:g} s)")
    if w.profiles_incomplete:
        reasons.append(f"{w.profiles_incomplete} profile(s) incomplete (packets lost)")
    if w.profiles_pps_unlocked:
        reasons.append(f"profiler PPS not locked in {w.profiles_pps_unlocked} profile(s)")
    return reasons


def _clock_reasons(w: PassWindow) -> list[str]:
    """The clock LOCKED throughout the window (and its state known)."""
    unlocked = sorted({s for s in w.clock_states if s != "LOCKED"})
    if unlocked or not w.clock_states:
        return [
            "clock "
            + (", ".join(unlocked) if unlocked else "state unknown")
            + " during the window (must stay LOCKED)"
        ]
    return []


def _target_reasons(w: PassWindow, tol: AcceptanceTolerances) -> list[str]:
    """Enough live hits on every target."""
    few = [
        f"{name}: {n} point{'s' if n != 1 else ''}"
        for name, n in w.hits.items()
        if n < tol.min_points_per_target
    ]
    if few:
        return [f"too few target points ({', '.join(few)}; need {tol.min_points_per_target})"]
    return []
