"""Line guidance for the calibration passes (docs/architecture.md §8), as pure functions over numpy arrays
(vectorized over samples or points): where the vessel is relative to the planned line, which
targets the profiler is hitting, whether the system is ready, and whether a pass is good
enough. The daemon's state that uses them is :mod:`acquire.guidance.state`.

- cross-track error and progress along a line (:func:`line_offsets`), heading error with wrap
  (:func:`heading_error`), speed and course over ground, the capture window;
- live target hits (:func:`target_hits`: gate returns by range and scan angle around each
  target first, then georeference only those);
- the pre-survey checks (:func:`prechecks`) and the acceptance of a pass
  (:func:`evaluate_pass`, every failed condition a reason).

Signs and conventions:

- **Cross-track error** ``xte_m`` is **positive when the vessel is to starboard of the line**
  (right of the line's direction), negative to port. The autopilot output (NMEA ``XTE``/``APB``,
  :mod:`acquire.guidance.autopilot`) gives the *direction to steer*: ``L`` when ``xte_m > 0``, ``R`` when
  ``xte_m < 0`` (NMEA 0183: "direction to steer").
- **Heading error** = vessel heading − line heading, wrapped to (−180°, 180°]: positive when the
  bow points to starboard of the line.
- **Progress** ``along_m``: distance along the line from its start (negative before it).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np

from calib.core import frames
from calib.core.georef import Mount, georeference
from calib.core.trajectory import Trajectory
from calib.sim.scene import Scene
from calib.survey.passplan import PassPlan, PlannedPass
from drivers.hydrins.nav import NavRecord

#: Z+F Profiler 9012: 1.016 Mpts/s of (range u32, intensity u16) in ZFP1 packets, plus packet
#: and log framing (~10 %), plus the INS at 200 Hz (~300 B per epoch in NMEA).
DEFAULT_LOG_RATE_BYTES_S = 1.016e6 * 6 * 1.1 + 200 * 300


# =============================================================================================
# Settings
# =============================================================================================


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
class GuidanceSettings:
    """How the vessel is matched to a line and how target hits are found."""

    match_xte_m: float = 10.0  # entering a capture window counts within this |XTE| …
    match_heading_rad: float = math.radians(25.0)  # … and this |heading error|
    abort_xte_m: float = 10.0  # leaving the line this far ends the capture early
    abort_heading_rad: float = math.radians(45.0)
    approach_m: float = 150.0  # how far before a line's start a vessel counts as on it
    settle_s: float = 1.0  # wait this long after a window for late profiles
    hit_plane_tolerance_m: float = 0.15  # a hit lies this close to the target's plane …
    hit_edge_margin_m: float = 0.0  # … and inside its rectangle grown by this
    gate_grow_m: float = 0.5  # the range/angle gate grows each target by this
    gate_pad_rad: float = math.radians(0.5)  # and widens its angle sector by this each side
    min_intensity: float | None = None  # optional intensity floor for target hits
    max_pending_profiles: int = 2000  # profiles waiting for navigation (oldest dropped)
    nav_history_s: float = 300.0  # navigation kept in memory
    prediction_gap_s: float = 60.0  # a candidate pass is assumed sailed this long after the last


# =============================================================================================
# Line geometry (pure)
# =============================================================================================


def line_offsets(p_lgf_m, line: PlannedPass) -> tuple[np.ndarray, np.ndarray]:
    """(along_m, xte_m) of points (n, 3) or (3,) relative to ``line``: distance along the line
    from its start, and cross-track error, + to starboard of the line's direction."""
    p = np.atleast_2d(np.asarray(p_lgf_m, float))
    h = line.heading_rad
    d = p[:, :2] - line.start_lgf_m[:2]
    along = d[:, 0] * math.cos(h) + d[:, 1] * math.sin(h)
    xte = -d[:, 0] * math.sin(h) + d[:, 1] * math.cos(h)  # starboard unit = (−sin ψ, cos ψ)
    return along, xte


def heading_error(heading_rad, line_heading_rad) -> np.ndarray:
    """Vessel heading − line heading, wrapped to (−π, π] (+: bow to starboard of the line)."""
    return frames.wrap_pi(np.asarray(heading_rad, float) - line_heading_rad)


def speed_over_ground(v_north_m_s, v_east_m_s) -> np.ndarray:
    return np.hypot(v_north_m_s, v_east_m_s)


def course_over_ground(v_north_m_s, v_east_m_s) -> np.ndarray:
    """Course over ground, clockwise from north in [0, 2π)."""
    return frames.wrap_2pi(np.arctan2(v_east_m_s, v_north_m_s))


def in_capture(along_m, line: PlannedPass) -> np.ndarray:
    a = np.asarray(along_m, float)
    return (a >= line.capture_start_m) & (a <= line.capture_end_m)


@dataclass(frozen=True)
class LineState:
    """Where the vessel is relative to one line (scalars, from one navigation sample)."""

    pass_id: int
    along_m: float
    xte_m: float
    heading_error_rad: float
    speed_mps: float
    in_capture: bool
    to_capture_m: float  # distance to the capture window's start (negative once past it)
    range_to_targets_m: float  # 3D distance from the vessel to the nearest target centre

    def as_dict(self) -> dict:
        return {
            "pass_id": self.pass_id,
            "along_m": round(self.along_m, 3),
            "xte_m": round(self.xte_m, 3),
            "heading_error_deg": round(math.degrees(self.heading_error_rad), 3),
            "speed_mps": round(self.speed_mps, 3),
            "in_capture": self.in_capture,
            "to_capture_m": round(self.to_capture_m, 2),
            "range_to_targets_m": round(self.range_to_targets_m, 2),
        }


def line_state(
    p_lgf_m, heading_rad: float, speed_mps: float, line: PlannedPass, target_centers_lgf_m: np.ndarray
) -> LineState:
    along, xte = line_offsets(p_lgf_m, line)
    a = float(along[0])
    rng = np.linalg.norm(np.atleast_2d(target_centers_lgf_m) - np.asarray(p_lgf_m, float), axis=1)
    return LineState(
        line.id,
        a,
        float(xte[0]),
        float(heading_error(heading_rad, line.heading_rad)),
        float(speed_mps),
        bool(in_capture(a, line)),
        line.capture_start_m - a,
        float(rng.min()) if rng.size else math.nan,
    )


# =============================================================================================
# Live target hits (pure)
# =============================================================================================


@dataclass(frozen=True)
class TargetHits:
    """Returns found on the targets, and how many points the gate let through."""

    t_gps_s: np.ndarray
    range_m: np.ndarray
    scan_angle_rad: np.ndarray
    target_index: np.ndarray  # into the scene's rectangles
    n_points: int  # returns looked at
    n_gated: int  # returns georeferenced (inside some target's range/angle gate)
    n_uncovered: int = 0  # gated returns the trajectory could not place

    def counts(self, n_targets: int) -> np.ndarray:
        return np.bincount(self.target_index, minlength=n_targets)

    @staticmethod
    def empty(n_points: int = 0) -> TargetHits:
        e = np.empty(0)
        return TargetHits(e, e, e, np.empty(0, np.int64), n_points, 0)


def target_hits(
    t_gps_s,
    range_m,
    scan_angle_rad,
    profile_of_point,
    t_profile_gps_s,
    traj: Trajectory,
    mount: Mount,
    scene: Scene,
    *,
    settings: GuidanceSettings = GuidanceSettings(),
    intensity=None,
) -> TargetHits:
    """Which returns of a batch of profiles lie on the targets (the scene's rectangles).

    ``profile_of_point`` (n,) indexes ``t_profile_gps_s`` (P,), each profile's mid time. Per
    profile the scan plane is placed with the pose at that time, and each target gives a
    sector of beam angles (:meth:`calib.sim.scene.Scene.scan_sectors`, the target grown by
    ``gate_grow_m``, widened by ``gate_pad_rad``) and a range band (distance to its centre ±
    half its diagonal ± the growth). Only the returns inside some gate are georeferenced (with
    their own time's pose); a hit lies within ``hit_plane_tolerance_m`` of the target's plane
    and inside the rectangle grown by ``hit_edge_margin_m``. NaN ranges (no return) never pass.
    """
    s = settings
    t = np.asarray(t_gps_s, float)
    rho = np.asarray(range_m, float)
    alpha = np.asarray(scan_angle_rad, float)
    pi = np.asarray(profile_of_point, np.int64)
    n = t.size
    if n == 0 or len(scene) == 0:
        return TargetHits.empty(n)
    tp = np.asarray(t_profile_gps_s, float)
    poses = traj.interpolate(tp + mount.time_offset_s)
    M = poses.r_b_n @ mount.r_s_b
    origin = poses.p_lgf_m + poses.r_b_n @ mount.lever_arm_m
    sec = scene.scan_sectors(origin, M[:, :, 0], M[:, :, 1], M[:, :, 2], s.gate_grow_m)
    centers = np.array([r.center_m for r in scene.rectangles])
    half_diag = np.array([0.5 * math.hypot(r.width_m, r.height_m) for r in scene.rectangles])
    dist = np.linalg.norm(centers[None, :, :] - origin[:, None, :], axis=2)  # (P, R)
    # returns only (most of a profile over water has none), then the gates on those
    ret = np.flatnonzero(~np.isnan(rho))
    rho_r = rho[ret] + mount.range_offset_m
    keep = rho_r > 0
    if s.min_intensity is not None and intensity is not None:
        keep &= np.asarray(intensity)[ret] >= s.min_intensity
    if not keep.all():
        ret, rho_r = ret[keep], rho_r[keep]
    beam = alpha[ret] + (mount.scan_angle_offset_rad + s.gate_pad_rad)
    pr = pi[ret]
    two_pi = 2.0 * math.pi
    gated = np.zeros(ret.size, bool)
    for r in range(len(scene)):
        if not sec.hit[:, r].any():
            continue
        ok = sec.hit[:, r].take(pr)
        ok &= np.mod(beam - sec.start_rad[:, r].take(pr), two_pi) <= (
            sec.width_rad[:, r] + 2 * s.gate_pad_rad
        ).take(pr)
        ok &= np.abs(rho_r - dist[:, r].take(pr)) <= half_diag[r] + s.gate_grow_m
        gated |= ok
    idx = ret[gated]
    if idx.size == 0:
        return TargetHits.empty(n)
    uncovered = traj.uncovered(t[idx] + mount.time_offset_s)
    n_uncovered = int(uncovered.sum())
    idx = idx[~uncovered]
    if idx.size == 0:
        return replace(TargetHits.empty(n), n_gated=int(gated.sum()), n_uncovered=n_uncovered)
    p = georeference(t[idx], rho[idx], alpha[idx], traj, mount)
    best = np.full(idx.size, np.inf)
    which = np.full(idx.size, -1, np.int64)
    for r, rect in enumerate(scene.rectangles):
        dd = np.abs(rect.signed_distance(p))
        ok = (dd <= s.hit_plane_tolerance_m) & rect.contains(p, s.hit_edge_margin_m) & (dd < best)
        best[ok] = dd[ok]
        which[ok] = r
    on = which >= 0
    k = idx[on]
    return TargetHits(t[k], rho[k], alpha[k], which[on], n, int(gated.sum()), n_uncovered)


# =============================================================================================
# Pre-survey checks (pure)
# =============================================================================================


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
) -> list[Check]:
    """The pre-survey checks, each with pass/fail and the reason.

    ``nav``: the latest INS record; ``clock``: the clock model's status
    (:meth:`acquire.timing.clock.ClockStatus.as_dict`); ``latency``: device → latency statistics
    (:meth:`acquire.timing.latency.LatencyStats.as_dict`) and ``bands_ms`` device → expected band;
    ``free_bytes`` on the session's file system and ``needed_bytes`` for the planned passes
    (:func:`disk_needed_bytes`).
    """
    out = []
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


# =============================================================================================
# Pass acceptance (pure)
# =============================================================================================


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
        xte = float(np.max(np.abs(w.xte_m)))
        herr = float(np.max(np.abs(w.heading_error_rad)))
        v = w.speed_mps[np.isfinite(w.speed_mps)]
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
        if v.size:
            stats.update(
                speed_min_mps=round(float(v.min()), 3),
                speed_max_mps=round(float(v.max()), 3),
                speed_mean_mps=round(float(v.mean()), 3),
            )
            dev = float(np.max(np.abs(v - w.planned_speed_mps)))
            if dev > tol.max_speed_error_mps:
                reasons.append(
                    f"speed {v.min():.2f}–{v.max():.2f} m/s, planned "
                    f"{w.planned_speed_mps:g} ± {tol.max_speed_error_mps:g} m/s"
                )
        else:
            reasons.append("no speed over ground from the INS")
        # INS health over the window
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
    else:
        reasons.append("no INS records in the window")
    prof_gap = _max_gap(w.profile_t_gps_s, w.t_enter_gps_s, w.t_exit_gps_s)
    stats["max_profile_gap_s"] = round(prof_gap, 3)
    if prof_gap > tol.max_gap_s:
        reasons.append(f"profiler data gap of {prof_gap:.2f} s (limit {tol.max_gap_s:g} s)")
    if w.profiles_incomplete:
        reasons.append(f"{w.profiles_incomplete} profile(s) incomplete (packets lost)")
    if w.profiles_pps_unlocked:
        reasons.append(f"profiler PPS not locked in {w.profiles_pps_unlocked} profile(s)")
    unlocked = sorted({s for s in w.clock_states if s != "LOCKED"})
    if unlocked or not w.clock_states:
        reasons.append(
            "clock "
            + (", ".join(unlocked) if unlocked else "state unknown")
            + " during the window (must stay LOCKED)"
        )
    few = [
        f"{name}: {n} point{'s' if n != 1 else ''}"
        for name, n in w.hits.items()
        if n < tol.min_points_per_target
    ]
    if few:
        reasons.append(f"too few target points ({', '.join(few)}; need {tol.min_points_per_target})")
    return PassVerdict(w.pass_id, not reasons, tuple(reasons), stats, attempt)
