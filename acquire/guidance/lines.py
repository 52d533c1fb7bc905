"""Line geometry for the calibration passes (docs/architecture.md §8), as pure functions over numpy
arrays (vectorized over samples): where the vessel is relative to the planned line —
cross-track error and progress along a line (:func:`line_offsets`), heading error with wrap
(:func:`heading_error`), speed and course over ground, the capture window — and the guidance's
settings (:class:`GuidanceSettings`). The daemon's state that uses them is
:mod:`acquire.guidance.state`.

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
from dataclasses import dataclass

import numpy as np

from calib.core import frames
from calib.survey.passplan import PlannedPass


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
