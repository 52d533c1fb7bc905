"""Vessel motion along a pass plan → the true trajectory.

Along each line the POS reference point moves at the planned speed; the vessel rolls, pitches
and heaves on sinusoidal waves (amplitude, period, seeded phase) and its heading oscillates
slightly about the line's heading (yaw). Between lines the log either stops (a gap of
``pass_gap_s`` in the trajectory) or, with ``turns``, the vessel sails the shortest constant-
radius turn (a Dubins curve: arc, straight, arc) from the end of one line to the start of the
next, so that the trajectory is continuous (what a real-time INS stream needs).

Epochs lie on one grid ``t_start + k / rate_hz``; a line's epochs run from its start until the
first epoch at or past its end.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calib.core import frames
from calib.core.trajectory import Trajectory
from calib.survey.passplan import PassPlan


@dataclass(frozen=True)
class Wave:
    """``amplitude · sin(2π (t − t_start) / period + phase)``; amplitude in rad or m."""

    amplitude: float = 0.0
    period_s: float = 10.0

    def __post_init__(self):
        if not self.period_s > 0:
            raise ValueError(f"Wave.period_s must be > 0, got {self.period_s!r}")

    def __call__(self, tau_s: np.ndarray, phase_rad: float) -> np.ndarray:
        return self.amplitude * np.sin(2.0 * np.pi * tau_s / self.period_s + phase_rad)


@dataclass(frozen=True)
class MotionModel:
    rate_hz: float = 50.0  # trajectory epochs per second
    roll: Wave = field(default_factory=Wave)
    pitch: Wave = field(default_factory=Wave)
    heave: Wave = field(default_factory=Wave)  # metres, + up
    yaw: Wave = field(default_factory=Wave)
    turns: bool = False
    turn_radius_m: float = 15.0
    pass_gap_s: float = 30.0  # without turns: time between the end of a line and the next

    def to_dict(self) -> dict:
        def deg(w):
            return {"amplitude_deg": float(np.degrees(w.amplitude)), "period_s": w.period_s}

        return {
            "rate_hz": self.rate_hz,
            "roll": deg(self.roll),
            "pitch": deg(self.pitch),
            "heave": {"amplitude_m": self.heave.amplitude, "period_s": self.heave.period_s},
            "yaw": deg(self.yaw),
            "turns": self.turns,
            "turn_radius_m": self.turn_radius_m,
            "pass_gap_s": self.pass_gap_s,
        }


@dataclass(frozen=True)
class VesselRun:
    trajectory: Trajectory  # the true trajectory
    line_times: dict[int, tuple[float, float]]  # pass id → GPS s at the line's start and end
    capture_times: dict[int, tuple[float, float]]  # pass id → GPS s of the capture window
    phases_rad: dict[str, float]  # wave phases drawn from the seed


# -- Dubins turns (shortest path with bounded curvature: arc–straight–arc) -------------------
# Worked in a mathematical frame: x east, y north, θ counter-clockwise from east; a left turn
# turns counter-clockwise.


def _centre(p, theta, R, left):
    s = 1.0 if left else -1.0
    return p + s * R * np.array([-np.sin(theta), np.cos(theta)])


def dubins_path(p0, theta0, p1, theta1, R) -> list[tuple[str, float]]:
    """The shortest of the LSL, RSR, LSR and RSL paths from (p0, θ0) to (p1, θ1) as a list of
    (kind, length_m), kind in L, S, R."""
    two_pi = 2.0 * np.pi
    best = None
    for first, second in (("L", "L"), ("R", "R"), ("L", "R"), ("R", "L")):
        c0 = _centre(p0, theta0, R, first == "L")
        c1 = _centre(p1, theta1, R, second == "L")
        d = c1 - c0
        D = float(np.hypot(*d))
        psi = float(np.arctan2(d[1], d[0]))
        if first == second:
            phi, straight = psi, D
        else:
            if D < 2 * R:
                continue
            phi = psi + (1.0 if first == "L" else -1.0) * np.arcsin(2 * R / D)
            straight = float(np.sqrt(D * D - 4 * R * R))
        a1 = np.mod(phi - theta0, two_pi) if first == "L" else np.mod(theta0 - phi, two_pi)
        a2 = np.mod(theta1 - phi, two_pi) if second == "L" else np.mod(phi - theta1, two_pi)
        segs = [(first, R * a1), ("S", straight), (second, R * a2)]
        total = sum(s[1] for s in segs)
        if best is None or total < best[0]:
            best = (total, segs)
    assert best is not None  # LSL and RSR always exist
    return best[1]


def sample_path(p0, theta0, segments, R, s_m) -> tuple[np.ndarray, np.ndarray]:
    """Positions (n, 2) and θ (n,) at arc lengths ``s_m`` along ``segments`` from (p0, θ0)."""
    s_m = np.asarray(s_m, float)
    pos = np.empty((s_m.size, 2))
    theta = np.empty(s_m.size)
    p, th, s0 = np.asarray(p0, float), float(theta0), 0.0
    for i, (kind, length) in enumerate(segments):
        last = i == len(segments) - 1
        sel = (s_m >= s0) & ((s_m <= s0 + length) if last else (s_m < s0 + length))
        ds = s_m[sel] - s0
        if kind == "S":
            pos[sel] = p + ds[:, None] * [np.cos(th), np.sin(th)]
            theta[sel] = th
            p = p + length * np.array([np.cos(th), np.sin(th)])
        else:
            left = kind == "L"
            sgn = 1.0 if left else -1.0
            c = _centre(p, th, R, left)
            t_sel = th + sgn * ds / R
            pos[sel] = c + sgn * R * np.stack([np.sin(t_sel), -np.cos(t_sel)], axis=-1)
            theta[sel] = t_sel
            th = th + sgn * length / R
            p = c + sgn * R * np.array([np.sin(th), -np.cos(th)])
        s0 += length
    return pos, theta


def _to_math(p_ne, heading_rad):
    return np.array([p_ne[1], p_ne[0]]), np.pi / 2 - heading_rad


# -- the run --------------------------------------------------------------------------------


def sail(
    plan: PassPlan,
    motion: MotionModel,
    t_start_gps_s: float,
    frame: frames.LocalFrame,
    rng: np.random.Generator,
) -> VesselRun:
    """Sail the plan's lines in order from ``t_start_gps_s``; returns the true trajectory."""
    rate = float(motion.rate_hz)
    if not rate >= 2.0 or (not motion.turns and motion.pass_gap_s <= 1.0):
        raise ValueError(
            f"MotionModel: rate_hz must be ≥ 2 (got {rate!r}) and pass_gap_s > 1 s "
            f"(got {motion.pass_gap_s!r}): the trajectory interpolates steps up to "
            f"1 s and no more"
        )
    phases = {name: float(rng.uniform(0.0, 2.0 * np.pi)) for name in ("roll", "pitch", "heave", "yaw")}
    k_parts, ne_parts, track_parts = [], [], []
    line_times, capture_times = {}, {}
    k0 = 0
    for i, p in enumerate(plan.passes):
        n_steps = int(np.ceil(p.duration_s * rate - 1e-9))
        k = np.arange(k0, k0 + n_steps + 1)
        s = (k - k0) / rate * p.speed_mps
        k_parts.append(k)
        ne_parts.append(p.start_lgf_m[:2] + s[:, None] * p.direction[:2])
        track_parts.append(np.full(k.size, p.heading_rad))
        t_line = t_start_gps_s + k0 / rate
        line_times[p.id] = (t_line, t_line + p.duration_s)
        cw = p.capture_window_s
        capture_times[p.id] = (t_line + cw[0], t_line + cw[1])
        k_end = k[-1]
        if i + 1 == len(plan.passes):
            break
        nxt = plan.passes[i + 1]
        if motion.turns:
            q0, th0 = _to_math(ne_parts[-1][-1], p.heading_rad)
            q1, th1 = _to_math(nxt.start_lgf_m[:2], nxt.heading_rad)
            segs = dubins_path(q0, th0, q1, th1, motion.turn_radius_m)
            length = sum(sg[1] for sg in segs)
            n_turn = max(int(np.ceil(length / p.speed_mps * rate - 1e-9)), 1)
            kt = np.arange(k_end + 1, k_end + n_turn)
            xy, th = sample_path(q0, th0, segs, motion.turn_radius_m, (kt - k_end) * (length / n_turn))
            k_parts.append(kt)
            ne_parts.append(xy[:, ::-1])
            track_parts.append(np.pi / 2 - th)
            k0 = k_end + n_turn
        else:
            k0 = k_end + max(int(round(motion.pass_gap_s * rate)), 1)
    k = np.concatenate(k_parts)
    ne = np.concatenate(ne_parts)
    track = np.concatenate(track_parts)
    t = t_start_gps_s + k / rate
    tau = k / rate
    down = plan.aim_lgf_m[2] - motion.heave(tau, phases["heave"])
    p_lgf = np.column_stack([ne, down])
    rpy = np.column_stack(
        [
            motion.roll(tau, phases["roll"]),
            motion.pitch(tau, phases["pitch"]),
            frames.wrap_2pi(track + motion.yaw(tau, phases["yaw"])),
        ]
    )
    traj = Trajectory(t, p_lgf, rpy, frame, name="true trajectory")
    return VesselRun(traj, line_times, capture_times, phases)
