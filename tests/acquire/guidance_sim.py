"""A simulated survey for the guidance tests (not a test module): the ``montreal`` scenario
simulated in memory, turned into the INS records and profiles the daemon would hand to
:class:`acquire.guidance.state.Guidance`, fed in time order with an update every 0.2 s, with the
``checklist`` messages kept at the moments the checklist test shows."""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace

import numpy as np

from acquire.guidance.acceptance import AcceptanceTolerances
from acquire.guidance.prechecks import prechecks
from acquire.guidance.state import Guidance
from calib.boresight.adjust import AdjustmentResult, adjust
from calib.boresight.errormodel import ErrorModel
from calib.boresight.observations import AdjustOptions, build_observations
from calib.core import frames
from calib.sim.simulate import SimResult, simulate
from calib.survey.passplan import plan_site
from drivers.hydrins.nav import NavRecord, status_words
from drivers.zf.codec import Profile

SCENARIO = "montreal"
UPDATE_PERIOD_S = 0.2


def nav_records(sim: SimResult) -> list[NavRecord]:
    """INS epochs from the observed trajectory, velocities from the true one."""
    obs, true = sim.trajectory_observed, sim.trajectory_true
    lat, lon, h = obs.frame.to_geodetic(obs.p_lgf_m)
    v = np.gradient(true.p_lgf_m, true.t_gps_s, axis=0)
    alg, sys_ = status_words(
        navigation=True,
        fine_alignment=True,
        gps_received=True,
        gps_valid=True,
        utc_detected=True,
        pps_detected=True,
    )
    out = []
    for i, t in enumerate(obs.t_gps_s):
        r, p, y = obs.rpy_rad[i]
        out.append(
            NavRecord(
                "nmea",
                gps_ns=int(frames.seconds_to_gps_ns(t)),
                lat_deg=float(lat[i]),
                lon_deg=float(lon[i]),
                height_m=float(h[i]),
                roll_rad=float(r),
                pitch_rad=float(p),
                heading_rad=float(y),
                v_north_m_s=float(v[i, 0]),
                v_east_m_s=float(v[i, 1]),
                v_down_m_s=float(v[i, 2]),
                algorithm_status=alg,
                system_status=sys_,
            )
        )
    return out


def profiles(sim: SimResult) -> list[Profile]:
    """Every profile along every line: the simulated returns binned by profile period, and a
    single no-return point (NaN range) for a profile without returns, as the profiler would
    send (it sends every profile)."""
    sc = sim.scenario.scanner
    rate = sc.effective_profile_rate_hz
    pts = sim.points
    out = []
    counter = 0
    for p in sim.plan.passes:
        l0, l1 = sim.truth["passes"][p.order - 1]["line_gps_s"]
        n_prof = int((l1 - l0) * rate)
        sel = np.flatnonzero(pts.pass_id == p.id)
        k = np.floor((pts.t_gps_s[sel] - l0) * rate).astype(np.int64)
        bounds = np.searchsorted(k, np.arange(n_prof + 1))
        for j in range(n_prof):
            idx = sel[bounds[j] : bounds[j + 1]]
            if idx.size:
                t = pts.t_gps_s[idx]
                prof = Profile(
                    counter,
                    frames.seconds_to_gps_ns(t).astype(np.int64),
                    pts.scan_angle_rad[idx],
                    pts.range_m[idx],
                    np.round(pts.intensity[idx] * 65535).astype(np.uint16),
                    packets_received=1,
                    packet_count=1,
                )
            else:
                t_mid = l0 + (j + 0.5) / rate
                prof = Profile(
                    counter,
                    np.array([frames.seconds_to_gps_ns(t_mid)], np.int64),
                    np.array([np.pi]),
                    np.array([np.nan]),
                    np.zeros(1, np.uint16),
                    packets_received=1,
                    packet_count=1,
                )
            out.append(prof)
            counter += 1
    return out


def adjust_simulated(sim: SimResult, beam: bool = False, roughness: str = "all") -> AdjustmentResult:
    """The adjustment of the simulated returns on the targets (the simulator's own labels),
    with the site's sigmas (``beam``: its range-per-metre σ and beam divergence too) and its
    Gauss–Markov correlation times; ``roughness`` as AdjustOptions."""
    site, pts = sim.site, sim.points
    sel = sim.target_index >= 0
    obs = build_observations(
        sim.trajectory_observed,
        pts.t_gps_s[sel],
        pts.range_m[sel],
        pts.scan_angle_rad[sel],
        sim.target_index[sel],
        pts.pass_id[sel],
        [t.name for t in site.targets],
        site.sigma_range_m,
        site.sigma_scan_angle_rad,
        site.sigma_position_m,
        site.sigma_attitude_rad,
        sigma_range_per_m=site.sigma_range_per_m if beam else 0.0,
        beam_divergence_rad=site.beam_divergence_rad if beam else 0.0,
    )
    rects = site.target_rectangles(site.frame())
    model = ErrorModel("gauss_markov", tuple(site.pos_correlation_time_s))
    options = AdjustOptions(jackknife=False, error_model=model, roughness=roughness)
    return adjust(obs, site.mount, [(r.normal, r.d) for r in rects], options)


@dataclass
class SimulatedSurvey:
    sim: SimResult
    guidance: Guidance
    verdicts: list  # PassVerdict in the order they finished
    stages: list[tuple[str, dict]]  # (stage name, checklist message)


def green_checks(g: Guidance, nav: NavRecord):
    return prechecks(
        nav,
        {"state": "LOCKED", "last_edge_age_s": 0.4, "jitter_rms_us": 2.1},
        {
            "ins": {"latency_mean_ms": 12.0, "latency_p99_ms": 14.0, "pps_flag": True},
            "profiler": {"latency_mean_ms": 3.0, "latency_p99_ms": 4.5, "pps_flag": True},
        },
        {"ins": (0.0, 30.0), "profiler": (0.0, 20.0)},
        free_bytes=80 * 10**9,
        needed_bytes=10 * 10**9,
        mount_configured=True,
        n_targets=len(g.target_names),
    )


@functools.lru_cache(maxsize=2)
def run_survey(seed: int = 3, holdover_pass: int | None = None) -> SimulatedSurvey:
    """Sail the simulated survey through the guidance (cached: several tests look at it).

    With ``holdover_pass``, the clock model drops to HOLDOVER for an instant in the middle of
    that pass's capture window (the pass is rejected), and the pass is sailed again after the
    last one (its records replayed 60 s after the end of the survey)."""
    sim = simulate(SCENARIO, seed)
    sc = sim.scenario
    plan = plan_site(
        sim.site,
        track_down_m=-float(sc.mount.lever_arm_m[2]),
        safe_wall_distance_m=sc.safe_wall_distance_m,
        capture_margin_m=sc.capture_margin_m,
    )
    # the scenario thins the profiler to 1/10 of its point rate (point_rate_scale 0.1): ~120
    # points on the 45° target per oblique pass instead of ~1200, so ask for 50 rather than 100
    g = Guidance(
        sim.site, plan, scanner=sc.scanner, tolerances=AcceptanceTolerances(min_points_per_target=50)
    )
    g.on_clock("LOCKED")
    g.refresh_prediction()
    items = sorted(
        [(r.gps_ns, 0, r) for r in nav_records(sim)] + [(int(p.gps_ns[-1]), 1, p) for p in profiles(sim)],
        key=lambda x: x[:2],
    )
    if holdover_pass is not None:
        l0, l1 = sim.truth["passes"][plan.by_id(holdover_pass).order - 1]["line_gps_s"]
        again = [it for it in items if l0 - 1 <= it[0] * 1e-9 <= l1 + 1]
        dt_ns = items[-1][0] + 60 * 10**9 - again[0][0]
        items += [(t + dt_ns, k, replace(r, gps_ns=r.gps_ns + dt_ns)) for t, k, r in again]
    stages: list[tuple[str, dict]] = []
    verdicts = []
    i = 0
    t = items[0][0] * 1e-9
    mid_taken: set[tuple[int, int]] = set()
    holdover_done = False
    while i < len(items):
        t += UPDATE_PERIOD_S
        while i < len(items) and items[i][0] * 1e-9 <= t:
            _, kind, rec = items[i]
            (g.on_nav if kind == 0 else g.on_profile)(rec)
            i += 1
        g.on_clock("LOCKED")
        done = g.update()
        checks = green_checks(g, g.last_nav)
        verdicts += done
        if not stages:
            stages.append(("start", g.message(checks)))
        for v in done:
            stages.append((f"pass-{v.pass_id}-{'accepted' if v.accepted else 'rejected'}", g.message(checks)))
        msg = g.message(checks)
        a = msg["active"]
        if a and a.get("state") == "capture":
            key = (a["pass_id"], len(g.passes[a["pass_id"]].verdicts))
            cap = a["capture_m"]
            if key not in mid_taken and a["along_m"] >= 0.5 * (cap[0] + cap[1]):
                mid_taken.add(key)
                stages.append((f"pass-{a['pass_id']}-capture", msg))
                if a["pass_id"] == holdover_pass and not holdover_done:
                    g.on_clock("HOLDOVER")  # back to LOCKED at the next update
                    holdover_done = True
    return SimulatedSurvey(sim, g, verdicts, stages)
