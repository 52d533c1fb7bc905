"""The six-fold pass plan (thesis Fig. 3.3, §4.4.1): straight lines around a group of targets.

Every pass is a straight segment sailed at a constant heading ``wall azimuth + relative
heading`` (0°, 180°, 45°, 225°, 315°, 135° in the default order). Its closest approach (CPA) to
the target group's centre is the standoff distance, on the side the targets face (the water).
A 2D profiler scans the plane across the track, so each target is swept near the CPA; the
*capture window* is the stretch of the line where the scan plane can meet a target (its
along-track extent plus a margin). Parallel passes are centred on the CPA. Oblique passes head
toward or away from the wall: the segment is slid back along the line so that it stays at
least ``safe_wall_distance_m`` from the wall; the plan is refused when the capture window no
longer fits.

All geometry is in the LGF (NED); lines are horizontal at ``track_down_m``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from calib.core import frames
from calib.core.errors import CalibError
from calib.core.geometry import Rectangle
from calib.io.site import PassSpec, Site

#: Below this |cos| a heading counts as parallel to the wall.
_PARALLEL_TOL = 1e-9


class PassPlanError(CalibError, ValueError):
    """The requested plan cannot be built (the message says which pass and why)."""


@dataclass(frozen=True)
class PlannedPass:
    """One line of the plan. Distances along the line are measured from ``start_lgf_m``."""

    id: int
    order: int  # 1-based position in the sailing order
    relative_heading_rad: float
    heading_rad: float  # absolute, clockwise from north, [0, 2π)
    start_lgf_m: np.ndarray  # (3,) NED
    end_lgf_m: np.ndarray  # (3,)
    closest_approach_lgf_m: np.ndarray  # (3,) point of the line nearest the target group
    speed_mps: float
    capture_start_m: float  # capture window along the line, from the start
    capture_end_m: float
    targets_side: str  # "starboard" or "port": where the targets are seen from the vessel
    end_wall_distance_m: float  # horizontal distance from the wall at the end nearest to it
    standoff_m: float | None = None  # horizontal distance of the closest approach from the aim

    @property
    def direction(self) -> np.ndarray:
        h = self.heading_rad
        return np.array([np.cos(h), np.sin(h), 0.0])

    @property
    def length_m(self) -> float:
        return float(np.linalg.norm(self.end_lgf_m - self.start_lgf_m))

    @property
    def duration_s(self) -> float:
        return self.length_m / self.speed_mps

    @property
    def capture_window_s(self) -> tuple[float, float]:
        """The capture window in seconds after the start of the line."""
        return self.capture_start_m / self.speed_mps, self.capture_end_m / self.speed_mps

    def position_at(self, distance_m) -> np.ndarray:
        """(n, 3) points at the given distances along the line from its start."""
        s = np.atleast_1d(np.asarray(distance_m, float))
        return self.start_lgf_m + s[:, None] * self.direction


@dataclass(frozen=True)
class PassPlan:
    passes: tuple[PlannedPass, ...]
    aim_lgf_m: np.ndarray  # centre of the target group (the CPA reference)
    water_azimuth_rad: float  # direction from the wall toward the water
    wall_azimuth_rad: float
    standoff_m: float
    safe_wall_distance_m: float
    wall_offset_m: float  # the wall line's signed distance from the aim point toward the water

    def by_id(self, pass_id: int) -> PlannedPass:
        for p in self.passes:
            if p.id == pass_id:
                return p
        raise KeyError(f"pass {pass_id} is not in the plan")

    def wall_distance(self, p_lgf_m) -> np.ndarray:
        """Horizontal distance of points (n, 3) from the wall line (positive on the water)."""
        w = _unit(self.water_azimuth_rad)
        return (np.atleast_2d(p_lgf_m) - self.aim_lgf_m) @ w - self.wall_offset_m


def _unit(azimuth_rad: float) -> np.ndarray:
    return np.array([np.cos(azimuth_rad), np.sin(azimuth_rad), 0.0])


def water_azimuth(targets: Sequence[Rectangle], wall_azimuth_rad: float) -> float:
    """The side of the wall the targets face: of the two horizontal normals to the wall line,
    the one closest to the targets' mean horizontal normal; a group without a horizontal
    normal (horizontal targets) takes the site convention, water to the left of the wall
    direction (pass 0° sees the wall to starboard)."""
    left = wall_azimuth_rad - np.pi / 2
    if targets:
        m = np.mean([r.normal for r in targets], axis=0)
        if np.hypot(m[0], m[1]) > 1e-6 and m @ _unit(left) < 0:
            return float(frames.wrap_2pi(wall_azimuth_rad + np.pi / 2))
    return float(frames.wrap_2pi(left))


@dataclass(frozen=True, kw_only=True)
class _Layout:
    """What every line of a plan is laid out from."""

    corners: np.ndarray  # (k, 3) the targets' corners (LGF)
    aim: np.ndarray  # the targets' mean centre at the track's depth
    water: np.ndarray  # unit vector toward the water
    wall_offset_m: float  # the wall face along ``water`` from the aim (the targets' back)
    extra: np.ndarray | None  # the corners of the further rectangles to capture
    wall_azimuth_rad: float
    standoff_m: float
    safe_wall_distance_m: float
    capture_margin_m: float


def _line_extent(spec: PassSpec, d0: float, approach: float, safe_m: float) -> tuple[float, float]:
    """The line's ends (m along it from the closest approach): centred on it, shifted so that
    the end toward the wall keeps ``safe_m`` from it."""
    L = spec.length_m
    s_a, s_b = -L / 2, L / 2
    if approach < -_PARALLEL_TOL:  # heading toward the wall: limit the far end
        s_b = min(s_b, (d0 - safe_m) / -approach)
        s_a = s_b - L
    elif approach > _PARALLEL_TOL:  # heading away: limit the near (start) end
        s_a = max(s_a, -(d0 - safe_m) / approach)
        s_b = s_a + L
    return s_a, s_b


def _capture_window(spec: PassSpec, lay: _Layout, cpa, h, s_a: float, s_b: float) -> tuple[float, float]:
    """Where the line must record (m along it): the targets with a margin (refused when it does
    not fit the line), widened to the further rectangles within the line."""
    s_t = (lay.corners - cpa) @ h
    cap_a, cap_b = float(s_t.min() - lay.capture_margin_m), float(s_t.max() + lay.capture_margin_m)
    if cap_a < s_a or cap_b > s_b:
        raise PassPlanError(
            f"pass {spec.id} (relative heading {np.degrees(spec.relative_heading_rad):g}°): "
            f"the capture window [{cap_a:.1f}, {cap_b:.1f}] m around the closest approach "
            f"does not fit the {spec.length_m:g} m line [{s_a:.1f}, {s_b:.1f}] m that keeps "
            f"{lay.safe_wall_distance_m:g} m from the wall; increase standoff_m or length_m"
        )
    if lay.extra is not None:
        s_e = (lay.extra - cpa) @ h
        cap_a = max(s_a, min(cap_a, float(s_e.min() - lay.capture_margin_m)))
        cap_b = min(s_b, max(cap_b, float(s_e.max() + lay.capture_margin_m)))
    return cap_a, cap_b


def _planned_pass(order: int, spec: PassSpec, lay: _Layout) -> PlannedPass:
    """One line: at its heading, its closest approach ``standoff_m`` (the line's own, else the
    plan's) from the aim on the water side, as long as asked and clear of the wall."""
    heading = float(frames.wrap_2pi(lay.wall_azimuth_rad + spec.relative_heading_rad))
    h = _unit(heading)
    perp = np.array([-h[1], h[0], 0.0])
    toward_water = float(perp @ lay.water)
    if abs(toward_water) < 1e-6:
        raise PassPlanError(
            f"pass {spec.id}: relative heading {np.degrees(spec.relative_heading_rad):g}° "
            f"points straight at the wall; no line at that heading keeps a standoff"
        )
    if toward_water < 0:
        perp = -perp
    standoff = lay.standoff_m if spec.standoff_m is None else spec.standoff_m
    cpa = lay.aim + standoff * perp
    approach = float(h @ lay.water)  # change of the wall distance per metre along the line
    d0 = float((cpa - lay.aim) @ lay.water) - lay.wall_offset_m  # wall distance at the CPA
    if d0 < lay.safe_wall_distance_m:
        raise PassPlanError(
            f"pass {spec.id}: its closest approach is only {d0:.2f} m from the wall, less "
            f"than the safe distance {lay.safe_wall_distance_m:g} m; increase standoff_m"
        )
    s_a, s_b = _line_extent(spec, d0, approach, lay.safe_wall_distance_m)
    cap_a, cap_b = _capture_window(spec, lay, cpa, h, s_a, s_b)
    starboard = np.array([-np.sin(heading), np.cos(heading), 0.0])
    side = "starboard" if float(-perp @ starboard) > 0 else "port"
    end_wall = min(d0 + s_a * approach, d0 + s_b * approach)
    return PlannedPass(
        id=spec.id,
        order=order,
        relative_heading_rad=float(spec.relative_heading_rad),
        heading_rad=heading,
        start_lgf_m=cpa + s_a * h,
        end_lgf_m=cpa + s_b * h,
        closest_approach_lgf_m=cpa,
        speed_mps=float(spec.speed_mps),
        capture_start_m=cap_a - s_a,
        capture_end_m=cap_b - s_a,
        targets_side=side,
        end_wall_distance_m=float(end_wall),
        standoff_m=float(standoff),
    )


def plan_passes(
    targets: Sequence[Rectangle],
    wall_azimuth_rad: float,
    standoff_m: float,
    passes: Sequence[PassSpec],
    *,
    track_down_m: float = 0.0,
    safe_wall_distance_m: float = 5.0,
    capture_margin_m: float = 3.0,
    also_capture: Sequence[Rectangle] = (),
) -> PassPlan:
    """Plan the lines around ``targets`` (LGF rectangles).

    ``also_capture``: further rectangles (validation planes) whose along-track extent widens
    the capture window where the line reaches them (clipped to the line, never refused).
    """
    if not targets:
        raise PassPlanError("a pass plan needs at least one target")
    if not passes:
        raise PassPlanError("a pass plan needs at least one pass")
    if standoff_m <= 0:
        raise PassPlanError(f"standoff_m is {standoff_m!r}, expected > 0")
    corners = np.concatenate([r.corners() for r in targets])
    aim = np.mean([r.center_m for r in targets], axis=0)
    aim = np.array([aim[0], aim[1], track_down_m])
    water = water_azimuth(targets, wall_azimuth_rad)
    w = _unit(water)
    lay = _Layout(
        corners=corners,
        aim=aim,
        water=w,
        # the wall face: the back of the target group
        wall_offset_m=float(np.min((corners - aim) @ w)),
        extra=np.concatenate([r.corners() for r in also_capture]) if also_capture else None,
        wall_azimuth_rad=wall_azimuth_rad,
        standoff_m=standoff_m,
        safe_wall_distance_m=safe_wall_distance_m,
        capture_margin_m=capture_margin_m,
    )
    out = [_planned_pass(order, spec, lay) for order, spec in enumerate(passes, start=1)]
    return PassPlan(
        tuple(out),
        aim,
        water,
        float(wall_azimuth_rad),
        float(standoff_m),
        float(safe_wall_distance_m),
        lay.wall_offset_m,
    )


def plan_site(site: Site, frame: frames.LocalFrame | None = None, **kwargs) -> PassPlan:
    """The plan of a site config: its targets, wall azimuth, standoff and passes (in the site's
    LGF unless ``frame`` is given). Keyword arguments go to :func:`plan_passes`."""
    frame = site.frame(frame)
    return plan_passes(
        site.target_rectangles(frame), site.wall_azimuth_rad, site.standoff_m, site.passes, **kwargs
    )
