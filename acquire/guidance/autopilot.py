"""Autopilot output for the active calibration line: NMEA 0183 ``$--XTE`` and ``$--APB``.

The line runs from its start (the origin waypoint) to its end (the destination waypoint,
id ``L<pass id>``). From the vessel's position:

- **cross-track error** (:func:`acquire.guidance.lines.line_offsets`): ``xte_m`` + to starboard of the
  line. NMEA sends its magnitude in nautical miles and the **direction to steer**: ``L`` when the
  vessel is to starboard (``xte_m > 0``), ``R`` when it is to port (NMEA 0183 "direction to
  steer, L/R");
- **heading to steer**: a look-ahead law, the line's heading corrected by
  ``−atan(xte / look-ahead)`` (with the default 20 m look-ahead a 2 m offset asks for 5.7°
  toward the line);
- arrival circle (within ``arrival_radius_m`` of the end) and perpendicular passed (progress
  past the end);
- bearings true (``T``); status ``A`` with mode ``A`` (autonomous) when the position is valid,
  else ``V`` and mode ``N``.

Sentences (NMEA 0183 v2.3 and later, with the mode indicator)::

    $--XTE,A,A,x.x,a,N,a*hh
    $--APB,A,A,x.x,a,N,A,A,x.x,T,c--c,x.x,T,x.x,T,a*hh
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from acquire.guidance.lines import line_offsets
from calib.core import frames
from calib.survey.passplan import PlannedPass
from drivers.hydrins.nmea_encode import encode_sentence

NM_M = 1852.0
DEFAULT_LOOKAHEAD_M = 20.0
DEFAULT_ARRIVAL_RADIUS_M = 5.0


@dataclass(frozen=True)
class Steering:
    """What an autopilot needs to follow ``pass_id``'s line from the vessel's position."""

    pass_id: int
    valid: bool
    xte_m: float  # + starboard of the line
    along_m: float
    line_heading_rad: float  # bearing origin → destination
    bearing_to_end_rad: float  # bearing present position → destination
    heading_to_steer_rad: float
    distance_to_end_m: float
    arrived: bool  # inside the arrival circle
    passed: bool  # past the perpendicular at the destination

    @property
    def steer(self) -> str:
        """NMEA direction to steer: L when the vessel is to starboard of the line."""
        return "L" if self.xte_m > 0 else "R"

    @property
    def waypoint_id(self) -> str:
        return f"L{self.pass_id}"


def steering(
    p_lgf_m,
    line: PlannedPass,
    *,
    lookahead_m: float = DEFAULT_LOOKAHEAD_M,
    arrival_radius_m: float = DEFAULT_ARRIVAL_RADIUS_M,
    valid: bool = True,
) -> Steering:
    """Steering toward ``line`` from the LGF position ``p_lgf_m`` (3,)."""
    p = np.asarray(p_lgf_m, float).reshape(3)
    along, xte = line_offsets(p, line)
    a, x = float(along[0]), float(xte[0])
    d = line.end_lgf_m[:2] - p[:2]
    dist = float(np.hypot(*d))
    steer = frames.wrap_2pi(line.heading_rad - math.atan2(x, lookahead_m))
    return Steering(
        line.id,
        bool(valid) and math.isfinite(x),
        x,
        a,
        float(line.heading_rad),
        float(frames.wrap_2pi(math.atan2(d[1], d[0]))),
        float(steer),
        dist,
        dist <= arrival_radius_m,
        a >= line.length_m,
    )


def _deg(rad: float) -> str:
    return f"{math.degrees(rad) % 360.0:.1f}"


def xte_sentence(s: Steering, talker: str = "GP") -> bytes:
    """``$--XTE``: cross-track error, direction to steer, nautical miles."""
    st, mode = ("A", "A") if s.valid else ("V", "N")
    mag = f"{abs(s.xte_m) / NM_M:.4f}" if s.valid else ""
    return encode_sentence(f"{talker}XTE,{st},{st},{mag},{s.steer if s.valid else ''},N,{mode}")


def apb_sentence(s: Steering, talker: str = "GP") -> bytes:
    """``$--APB``: autopilot sentence B (bearings true)."""
    st, mode = ("A", "A") if s.valid else ("V", "N")
    mag = f"{abs(s.xte_m) / NM_M:.4f}" if s.valid else ""
    fields = [
        st,
        st,
        mag,
        s.steer if s.valid else "",
        "N",
        "A" if s.arrived else "V",
        "A" if s.passed else "V",
        _deg(s.line_heading_rad),
        "T",
        s.waypoint_id,
        _deg(s.bearing_to_end_rad),
        "T",
        _deg(s.heading_to_steer_rad),
        "T",
        mode,
    ]
    return encode_sentence(f"{talker}APB," + ",".join(fields))


def autopilot_sentences(
    p_lgf_m,
    line: PlannedPass,
    *,
    talker: str = "GP",
    lookahead_m: float = DEFAULT_LOOKAHEAD_M,
    arrival_radius_m: float = DEFAULT_ARRIVAL_RADIUS_M,
    valid: bool = True,
) -> list[bytes]:
    """The XTE and APB sentences for an autopilot following ``line`` from ``p_lgf_m``."""
    s = steering(p_lgf_m, line, lookahead_m=lookahead_m, arrival_radius_m=arrival_radius_m, valid=valid)
    return [xte_sentence(s, talker), apb_sentence(s, talker)]
