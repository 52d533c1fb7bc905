"""A production survey: the harbour front (:mod:`calib.sim.harbour`) surveyed the way crews do it,
for an hour or two, with an optional mount event — the scanner's boresight changing during the
survey, at once or creeping — that the mount watch must detect from the data alone.

    base scenario (mount a priori, true = *calibrated* boresight, scanner and POS noise, motion)
        ──► the harbour's surfaces, the profiler recording its full circle up to 119 m
        ──► lines along the wall at the offsets: there and back at one offset, then the next
            (consecutive lines always on opposite headings), each at its own speed, Dubins turns
        ──► each line scanned in pieces, each with one true mount and one scene:
            ≤ 10 s; cut where a step takes effect; ≤ 5 s during a creep (the mount of a piece
            is the calibrated one + the event's change at its middle); ≤ 1 s with moving hulls
            (the hulls moved to their pose at its middle, plus the line's drift)
        ──► the observations and the truth as for any simulation (:func:`calib.sim.result.observe`)

A line's pieces continue one profile grid (every piece starts a whole number of profile periods
after the line's first profile), as the device feed needs. A step takes effect at the first
profile that starts at or after its time (``truth["mount_event"]["effective_t_gps_s"]``): every
return before that time was measured with the calibrated mount, every one from it on with the
stepped mount. Every point's ``pass_id`` is its line's id (1, 2, 3 …).

No mid-line speed change: a line is one constant speed (:func:`calib.sim.motion.sail`); the
speed changes from line to line.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from calib.core import frames
from calib.core.georef import Mount
from calib.io.site import PassSpec
from calib.sim.harbour import (
    QUAY_REACH_M,
    HullSwell,
    harbour_scenario,
    hull_groups,
    moved_hulls,
)
from calib.sim.motion import VesselRun, dubins_path, sail, sample_path
from calib.sim.result import SimResult, SimulationError, observe
from calib.sim.scanning import ScanReturns, covering, scan_batches
from calib.sim.scenario import MountEvent, ProductionSpec, Scenario
from calib.sim.scenariofile import load_scenario
from calib.sim.scene import Scene
from calib.survey.passplan import PassPlan, PlannedPass

__all__ = [
    "MountEvent",
    "ProductionSpec",
    "line_layout",
    "sail_production",
    "scenario_of",
    "simulate_production",
]

#: Longest piece of a line scanned with one mount and one scene (s): in general, during a
#: creep, and with moving hulls.
PIECE_S, CREEP_PIECE_S, HULL_PIECE_S = 10.0, 5.0, 1.0
#: Turns keep at least this close to the nearer of the two lines' offsets (m).
_TURN_MARGIN_M = 0.5
#: A line back at the offset of the line before lies this much off it (m): see line_layout.
LINE_NUDGE_M = 0.1
#: How far a moving hull's surfaces may stray from rest (m): swell, drift (3σ), travel in 0.2 s.
_HULL_REACH_M = 3.0


# -- the lines ------------------------------------------------------------------------------------


def _turn(a_m: float, b_m: float, stagger_m: float, radius_m: float) -> tuple[float, float]:
    """The Dubins turn from the end of a line along the wall (+along) at offset ``a_m`` to the
    start of a line back at ``b_m`` that starts ``stagger_m`` short of the first one's end
    (< 0: beyond it): (length, least offset), in the (along, out) plane. A turn from a line back
    to one along the wall is this turn mirrored (the same length and offsets)."""
    q0, q1 = np.array([0.0, a_m]), np.array([-stagger_m, b_m])
    segs = dubins_path(q0, 0.0, q1, np.pi, radius_m)
    length = sum(s[1] for s in segs)
    xy, _ = sample_path(q0, 0.0, segs, radius_m, np.linspace(0.0, length, 200))
    return float(length), float(xy[:, 1].min())


@functools.lru_cache(maxsize=256)
def _staggers(a_m: float, b_m: float, radius_m: float) -> list[float]:
    """The smallest stagger of each sign (2.5 m steps) whose turn stays between the two lines
    (never nearer the wall): a U-turn between offsets less than two turn radii apart needs
    room to swing out — outward, the next line starts short of the last one's end; inward,
    beyond it. A turn fits when it still does with the next line a step further on and a
    little to either side (the sailed line ends up to an epoch past its end; two lines at
    one offset have two shortest turns, mirror images, one of them toward the wall)."""

    def fits(g: float) -> bool:
        return all(
            _turn(a_m, b_m + e, g + d, radius_m)[1] >= min(a_m, b_m) - _TURN_MARGIN_M
            for e in (-0.02, 0.0, 0.02)
            for d in (-2.5, 0.0, 2.5)
        )

    out = []
    for sign in (1.0, -1.0):
        for g in np.arange(2.5, 8.0 * radius_m + 2.5, 2.5):
            if fits(sign * g):
                out.append(float(sign * g))
                break
    return out


def line_layout(spec: ProductionSpec, radius_m: float, rng: np.random.Generator) -> list[dict]:
    """The lines in sailing order (site frame): ``{id, offset_m, direction (+1 along the wall,
    −1 back), along0_m, along1_m, speed_mps}``. Line ``i`` (from 0) lies at offset
    ``offsets_m[(i // 2) % n]`` (there and back at each offset in turn; a line back at the
    offset of the line before lies :data:`LINE_NUDGE_M` off it, so that the turn between has one
    shortest way round), ``line_length_m`` long; each next line is staggered along the wall so
    that the turn stays between the two lines (:func:`_staggers`), of the staggers the one that
    keeps the lines nearest along = 0. Lines are added until ``duration_s`` is reached (turns
    included, the line under way finished), or ``n_lines`` of them."""
    offs, L = spec.offsets_m, spec.line_length_m
    n_max = spec.n_lines if spec.n_lines is not None else 100_000
    lines: list[dict] = []
    t_s, centre = 0.0, 0.0
    while len(lines) < n_max:
        i = len(lines)
        o = offs[(i // 2) % len(offs)]
        sign = 1 if i % 2 == 0 else -1
        if i:
            prev = lines[-1]
            a = prev["offset_m"]
            near = abs(o - a) < LINE_NUDGE_M
            # along → back: the next line's centre is centre − g; back → along: centre + g
            options = [
                (abs(centre + sign * g), abs(g), b, g)
                for b in ((o + LINE_NUDGE_M, o - LINE_NUDGE_M) if near else (o,))
                for g in _staggers(a, b, radius_m)
            ]
            if not options:
                raise SimulationError(
                    f"no turn of radius {radius_m:g} m joins lines at {a:g} and {o:g} m from the "
                    f"wall without nearing it: use a smaller motion.turn_radius_m"
                )
            _, _, o, g = min(options)
            centre += sign * g
            t_s += _turn(a, o, g, radius_m)[0] / prev["speed_mps"]
            if spec.n_lines is None and t_s >= spec.duration_s:
                break
        speed = float(rng.uniform(*spec.speeds_mps))
        lines.append(
            {
                "id": i + 1,
                "offset_m": float(o),
                "direction": sign,
                "along0_m": centre - sign * 0.5 * L,
                "along1_m": centre + sign * 0.5 * L,
                "speed_mps": speed,
            }
        )
        t_s += L / speed
        if spec.n_lines is None and t_s >= spec.duration_s:
            break
    return lines


def _plan(sc: Scenario, lines: list[dict]) -> PassPlan:
    """The lines as a pass plan in the LGF (the POS reference point's track, the scanner at
    up = 0 on a level vessel), each captured from end to end."""
    down = -float(sc.mount.lever_arm_m[2])

    def lgf(along, out):
        p = sc.site_to_lgf(along, out, 0.0)[0]
        return np.array([p[0], p[1], down])

    passes = []
    for k, ln in enumerate(lines):
        rel = 0.0 if ln["direction"] > 0 else float(np.pi)
        start, end = lgf(ln["along0_m"], ln["offset_m"]), lgf(ln["along1_m"], ln["offset_m"])
        length = float(np.linalg.norm(end - start))
        passes.append(
            PlannedPass(
                id=ln["id"],
                order=k + 1,
                relative_heading_rad=rel,
                heading_rad=float(frames.wrap_2pi(sc.wall_azimuth_rad + rel)),
                start_lgf_m=start,
                end_lgf_m=end,
                closest_approach_lgf_m=0.5 * (start + end),
                speed_mps=ln["speed_mps"],
                capture_start_m=0.0,
                capture_end_m=length,
                targets_side="starboard" if ln["direction"] > 0 else "port",
                end_wall_distance_m=ln["offset_m"],
            )
        )
    return PassPlan(
        tuple(passes),
        np.array([0.0, 0.0, down]),
        sc.water_azimuth_rad,
        sc.wall_azimuth_rad,
        float(lines[0]["offset_m"]),
        sc.safe_wall_distance_m,
        0.0,
    )


def _check_inside(sc: Scenario, spec: ProductionSpec, run: VesselRun, lines: list[dict]) -> None:
    """The vessel keeps off the wall (turns included) and its lines lie along the quay."""
    p = run.trajectory.p_lgf_m
    w = sc.water_azimuth_rad
    out = p[:, 0] * np.cos(w) + p[:, 1] * np.sin(w)
    reach = 0.5 * spec.line_length_m + QUAY_REACH_M - 10.0
    ends = max(max(abs(ln["along0_m"]), abs(ln["along1_m"])) for ln in lines)
    if ends > reach or out.min() < min(spec.offsets_m) - 1.0:
        raise SimulationError(
            f"turns of radius {sc.motion.turn_radius_m:g} m do not fit the harbour (lines reach "
            f"{ends:.0f} m along the {reach:.0f} m of quay, the vessel {out.min():.1f} m from the "
            f"wall): use a smaller motion.turn_radius_m"
        )


# -- scanning -------------------------------------------------------------------------------------


def _line_grid(sc: Scenario, run: VesselRun, line_id: int, mount: Mount) -> tuple[float, int]:
    """(t_org, n): a line's profile ``k < n`` fires at ``t_org + k / rate`` (as :func:`simulate`
    scans a pass: from its line start to its end, a guard inside both)."""
    rate = sc.scanner.effective_profile_rate_hz
    guard = abs(mount.time_offset_s) + 1e-3
    l0, l1 = run.line_times[line_id]
    return l0 + guard, int(np.floor((l1 - 2.0 * guard - l0) * rate))


def _cut(t_gps_s: float, t_org: float, rate: float) -> int:
    """The first profile of a grid that starts at or after ``t_gps_s``."""
    return math.ceil((t_gps_s - t_org) * rate - 1e-6)


def _pieces(n_total: int, cuts: tuple[int, int] | None, rate: float, fine: np.ndarray | None):
    """Profile ranges [n, m) of a line with the event's phase: 0 before it, 1 creeping, 2 after
    (module docstring); ``cuts``: the event's first and end profile (:func:`_cut`); ``fine``:
    whether a moving hull may be in view in each second of the line (pieces of ≤ 1 s there)."""
    n = 0
    while n < n_total:
        phase = 0 if cuts is None or n < cuts[0] else (2 if n >= cuts[1] else 1)
        piece_s = CREEP_PIECE_S if phase == 1 else PIECE_S
        ends = list(cuts or ())
        if fine is not None:
            b = min(int(n / rate / HULL_PIECE_S), fine.size - 1)
            if fine[b]:
                piece_s = HULL_PIECE_S
            else:  # a coarse piece stops where a hull may come into view
                later = np.flatnonzero(fine[b + 1 :])
                if later.size:
                    ends.append(math.ceil((b + 1 + later[0]) * HULL_PIECE_S * rate))
        m = min(n + max(int(piece_s * rate), 1), n_total)
        for c in ends:
            if n < c < m:
                m = c
        yield n, m, phase
        n = m


def _hull_seconds(
    sc: Scenario, run: VesselRun, mount: Mount, hulls: Scene, t_org: float, n_total: int
) -> np.ndarray:
    """For each second of a line's profile grid: whether a scan plane may meet a hull then
    (its rectangles at rest grown by what the swell and the drift move them, and by the
    vessel's travel between the poses sampled every 0.2 s)."""
    rate = sc.scanner.effective_profile_rate_hz
    span_s = n_total / rate
    t = t_org + np.arange(0.0, span_s + 0.2, 0.2)
    t = np.minimum(t, t_org + span_s)
    poses = run.trajectory.interpolate(t + mount.time_offset_s)
    m = poses.r_b_n @ mount.r_s_b
    origin = poses.p_lgf_m + poses.r_b_n @ mount.lever_arm_m
    sec = hulls.scan_sectors(origin, m[:, :, 0], m[:, :, 1], m[:, :, 2], grow_m=_HULL_REACH_M)
    seen = np.flatnonzero(sec.hit.any(axis=1))
    fine = np.zeros(int(np.ceil(span_s / HULL_PIECE_S)) + 1, bool)
    for d in (-1, 0, 1):  # and the seconds on either side
        fine[np.clip(((t[seen] - t_org) / HULL_PIECE_S).astype(int) + d, 0, fine.size - 1)] = True
    return fine


def _scan_line(
    sc: Scenario,
    spec: ProductionSpec,
    run: VesselRun,
    line_id: int,
    mount: Mount,
    scene_at: Callable[[float], Scene],
    hulls: Scene | None,
) -> Iterator[ScanReturns]:
    """The returns of one line, piece by piece (module docstring); ``hulls``: the moving hulls'
    surfaces at rest (None: the hulls do not move)."""
    rate = sc.scanner.effective_profile_rate_hz
    t_org, n_total = _line_grid(sc, run, line_id, mount)
    ev, t0 = spec.mount_event, sc.start_gps_s
    cuts = None
    if ev is not None:
        cuts = (_cut(t0 + ev.t_s, t_org, rate), _cut(t0 + ev.t_s + ev.creep_s, t_org, rate))
    fine = None if hulls is None else _hull_seconds(sc, run, mount, hulls, t_org, n_total)
    off = mount.time_offset_s
    for n, m, phase in _pieces(n_total, cuts, rate, fine):
        ta, tb = t_org + n / rate, t_org + m / rate
        t_mid = 0.5 * (ta + tb)
        piece_mount = mount
        if ev is not None and phase:
            delta = ev.step_rad if phase == 2 else ev.delta_rad(t_mid - t0)[0]
            piece_mount = replace(mount, boresight_rad=mount.boresight_rad + delta)
        sub = covering(run.trajectory, ta + off - 0.05, tb + off + 0.05)
        yield from scan_batches(
            sc.scanner, scene_at(t_mid - t0), sub, piece_mount, ta, ta + (m - n + 0.5) / rate
        )


def _effective_event_time(sc: Scenario, run: VesselRun, mount: Mount, t_ev_gps: float) -> float:
    """When a step is first in the data: the first profile of its line that starts at or after
    it (its own time when it falls between lines)."""
    rate = sc.scanner.effective_profile_rate_hz
    for line_id in run.line_times:
        t_org, n_total = _line_grid(sc, run, line_id, mount)
        c = _cut(t_ev_gps, t_org, rate)
        if 0 < c < n_total:
            return t_org + c / rate
    return t_ev_gps


def _scene_at(
    scene: Scene, groups: tuple, swell: HullSwell, phases_rad: np.ndarray, drift: np.ndarray
) -> Callable[[float], Scene]:
    """The scene at ``tau_s`` seconds into the survey during a line with this ``drift`` of the
    hulls (the scene itself when they do not move)."""
    if not groups:
        return lambda tau_s: scene
    return lambda tau_s: moved_hulls(scene, groups, swell, tau_s, phases_rad, drift)


# -- the survey -----------------------------------------------------------------------------------


def _production_scenario(scenario: Scenario, spec: ProductionSpec, rng_lines) -> tuple[Scenario, list[dict]]:
    """The harbour scenario of ``spec`` with its survey lines (drawn with ``rng_lines``) as
    its passes."""
    sc = harbour_scenario(scenario, spec)
    lines = line_layout(spec, sc.motion.turn_radius_m, rng_lines)
    sc = replace(
        sc,
        passes=tuple(
            PassSpec(
                ln["id"], 0.0 if ln["direction"] > 0 else float(np.pi), spec.line_length_m, ln["speed_mps"]
            )
            for ln in lines
        ),
    )
    return sc, lines


@dataclass(frozen=True, kw_only=True)
class _Hulls:
    """The moored hulls that move in the swell: their groups, their surfaces alone, the swell,
    each group's phases and each line's drift of each group."""

    groups: tuple
    scene: Scene | None  # the hulls' surfaces (None: no hull moves)
    swell: HullSwell
    phases_rad: np.ndarray  # (groups, 3)
    drift: np.ndarray  # (lines, groups, 3)


def _moving_hulls(sc: Scenario, scene: Scene, spec: ProductionSpec, n_lines: int, rng_hulls) -> _Hulls:
    groups = hull_groups(sc, scene) if spec.moving_hulls else ()
    idx = [j for g in groups for j in g.indices]
    swell = HullSwell()
    return _Hulls(
        groups=groups,
        scene=scene.subset(idx) if idx else None,
        swell=swell,
        phases_rad=rng_hulls.uniform(0.0, 2.0 * np.pi, (len(groups), 3)),
        drift=rng_hulls.standard_normal((n_lines, len(groups), 3)) * np.asarray(swell.drift_sigma),
    )


def _scan_lines(sc, spec, run, lines, mount, scene, hulls: _Hulls, progress):
    """Every line scanned: the returns and each return's line id."""
    parts, pass_ids = [], []
    for k, ln in enumerate(lines):
        scene_at = _scene_at(scene, hulls.groups, hulls.swell, hulls.phases_rad, hulls.drift[k])
        for part in _scan_line(sc, spec, run, ln["id"], mount, scene_at, hulls.scene):
            parts.append(part)
            pass_ids.append(np.full(part.t_gps_s.size, ln["id"], np.int64))
        if progress is not None:
            progress(k + 1, len(lines))
    if not parts:
        raise SimulationError(f"scenario {sc.name!r}: the production survey has no return")
    return ScanReturns.concatenate(parts), np.concatenate(pass_ids)


def _event_truth(sc: Scenario, spec: ProductionSpec, run, mount: Mount) -> dict | None:
    """truth.json's ``mount_event`` (None: the mount does not move)."""
    ev = spec.mount_event
    if ev is None:
        return None
    t_ev = sc.start_gps_s + ev.t_s
    return {
        "t_gps_s": t_ev,
        "t_s": ev.t_s,
        "step_deg": [float(x) for x in np.degrees(ev.step_rad)],
        "creep_s": ev.creep_s,
        "effective_t_gps_s": float(_effective_event_time(sc, run, mount, t_ev) if ev.creep_s == 0 else t_ev),
    }


def _hulls_truth(scene: Scene, hulls: _Hulls, lines: list[dict]) -> dict:
    """truth.json's ``hulls``: which surfaces move together, the swell, phases and drifts."""
    groups, drift = hulls.groups, hulls.drift
    return {
        "surfaces": {g.name: [scene.names[j] for j in g.indices] for g in groups},
        "swell": hulls.swell.to_dict(),
        "phases_deg": {
            g.name: [float(x) for x in np.degrees(hulls.phases_rad[h])] for h, g in enumerate(groups)
        },
        "drift": [
            {
                "line": ln["id"],
                **{
                    g.name: {
                        "along_m": float(drift[k, h, 0]),
                        "out_m": float(drift[k, h, 1]),
                        "yaw_deg": float(np.degrees(drift[k, h, 2])),
                    }
                    for h, g in enumerate(groups)
                },
            }
            for k, ln in enumerate(lines)
        ],
    }


def sail_production(
    scenario: Scenario,
    spec: ProductionSpec,
    seed: int,
    overrides: Sequence[str] = (),
    progress: Callable[[int, int], None] | None = None,
) -> SimResult:
    """The production survey ``spec`` with the base ``scenario``'s mount, noise and motion
    (module docstring); ``overrides`` are recorded in the truth."""
    # the first four streams are simulate()'s (motion, POS, scanner, per point)
    rng_motion, rng_pos, rng_scan, rng_point, rng_lines, rng_hulls = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(6)
    )
    sc, lines = _production_scenario(scenario, spec, rng_lines)
    plan = _plan(sc, lines)
    run = sail(plan, sc.motion, sc.start_gps_s, sc.reference, rng_motion)
    _check_inside(sc, spec, run, lines)
    scene = sc.scene()
    mount = sc.truth.true_mount(sc.mount)  # the calibrated mount: the truth before the event
    hulls = _moving_hulls(sc, scene, spec, len(lines), rng_hulls)
    ret, pass_ids = _scan_lines(sc, spec, run, lines, mount, scene, hulls, progress)
    result = observe(
        sc, seed, list(overrides), scene, plan, run, mount, ret, pass_ids, (rng_pos, rng_scan, rng_point)
    )
    truth = dict(result.truth)
    truth["production"] = spec.to_dict()
    truth["mount_calibrated"] = [float(x) for x in np.degrees(mount.boresight_rad)]
    truth["mount_event"] = _event_truth(sc, spec, run, mount)
    truth["lines"] = [
        {
            "id": ln["id"],
            "t_start_gps_s": float(run.line_times[ln["id"]][0]),
            "t_end_gps_s": float(run.line_times[ln["id"]][1]),
            "heading_deg": float(np.degrees(plan.passes[k].heading_rad)),
            "offset_m": ln["offset_m"],
            "speed_mps": ln["speed_mps"],
        }
        for k, ln in enumerate(lines)
    ]
    if hulls.groups:
        truth["hulls"] = _hulls_truth(scene, hulls, lines)
    return replace(result, truth=truth)


def scenario_of(
    scenario: Scenario | str | Path, overrides: Sequence[str] | Mapping[str, Any] = ()
) -> tuple[Scenario, list[str]]:
    """A :class:`Scenario` as given, or a shipped name / YAML path loaded with ``overrides``; and
    the overrides applied as truth.json lists them."""
    if not isinstance(scenario, Scenario):
        scenario = load_scenario(scenario, overrides)
    elif overrides:
        raise SimulationError("overrides apply when the scenario is loaded by name or path")
    applied = (
        [f"{k}={v!r}" for k, v in overrides.items()]
        if isinstance(overrides, Mapping)
        else [str(o) for o in overrides]
    )
    return scenario, applied


def simulate_production(
    scenario: Scenario | str | Path = "montreal",
    spec: ProductionSpec | None = None,
    seed: int = 0,
    progress: Callable[[int, int], None] | None = None,
    *,
    overrides: Sequence[str] | Mapping[str, Any] = (),
) -> SimResult:
    """Simulate a production survey of the harbour front with the mount, noise and motion of
    ``scenario`` (a :class:`Scenario`, or a shipped name / YAML path loaded with ``overrides``):
    ``spec``, else the scenario's own ``production`` section, else the defaults.
    ``progress(done, total)`` is called after each line."""
    scenario, applied = scenario_of(scenario, overrides)
    spec = spec or scenario.production or ProductionSpec()
    return sail_production(scenario, spec, seed, applied, progress)
