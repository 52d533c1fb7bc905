"""The canonical INS navigation record, shared by the Hydrins NMEA and STDBIN drivers.

One :class:`NavRecord` per INS epoch, whatever the wire format, so the daemon treats NMEA and
STDBIN alike. Everything in it is **canonical** (docs/architecture.md §3), converted at the edge:

- attitude in radians, ``R_b^n = Rz(heading)·Ry(pitch)·Rx(roll)``; roll + starboard down, pitch +
  bow up (iXblue pitch is bow-down positive and is negated through
  :func:`calib.core.frames.attitude_from_ixblue`), heading clockwise from true north in [0, 2π);
- position WGS84: ``lat_deg``, ``lon_deg`` in [−180, 180) (iXblue sends 0–360), ``height_m``
  with ``height_ref`` ('ellipsoid', 'geoid' or None when the wire does not say);
- velocity NED (``v_north_m_s``, ``v_east_m_s``, ``v_down_m_s``; iXblue sends east/north/up);
- surge/sway/heave in the body FRD frame: surge + bow, sway + starboard, heave + down
  (iXblue native: sway + port, heave + up — both negated here);
- 1σ: ``sigma_roll_rad``…, ``sigma_north_m``…, ``sigma_v_north_m_s``…;
- time: ``time_of_day_ns`` is the INS time tag (ns since midnight; UTC when ``utc_detected``,
  otherwise the INS system time), ``gps_ns`` the full GPS time (ns since 1980-01-06) when it can
  be resolved, and ``date_source`` says where the date came from: ``'zda'`` (a ZDA sentence),
  ``'host'`` (the host's UTC date, nearest day within ±12 h), ``'system_date'`` (the STDBIN
  system-date block). ``host_ns`` is the host monotonic receive stamp of the epoch's first bytes.
- status: the raw words (``algorithm_status``, ``system_status``, ``user_status``) and boolean
  properties decoded from them (``navigation``, ``alignment``, ``fine_alignment``,
  ``dead_reckoning``, ``gps_received``, ``gps_valid``, ``gps_detected``, ``utc_detected``,
  ``pps_detected``, ``internal_time_used``); a flag is None when its word was not received.

Missing values are NaN (floats) or None (ints, bools, strings), never 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

NAN = math.nan
TWO_PI = 2.0 * math.pi

# (word list name, word index, bit) of each decoded flag. Word indices count from 0, so
# "algorithm status 1" is index 0 (NMEA ALGSTS first field, STDBIN INS algorithm status word 1).
STATUS_BITS: dict[str, tuple[str, int, int]] = {
    "navigation": ("algorithm_status", 0, 0),
    "alignment": ("algorithm_status", 0, 1),
    "fine_alignment": ("algorithm_status", 0, 2),
    "dead_reckoning": ("algorithm_status", 0, 3),
    "gps_received": ("algorithm_status", 0, 12),
    "gps_valid": ("algorithm_status", 0, 13),
    "internal_time_used": ("system_status", 0, 24),
    "gps_detected": ("system_status", 1, 2),
    "utc_detected": ("system_status", 1, 9),
    "pps_detected": ("system_status", 1, 11),
}


def _flag(name: str):
    words_attr, index, bit = STATUS_BITS[name]

    def get(self) -> bool | None:
        words = getattr(self, words_attr)
        if words is None or len(words) <= index:
            return None
        return bool((words[index] >> bit) & 1)

    get.__name__ = name
    get.__doc__ = f"Bit {bit} of {words_attr.replace('_', ' ')} word {index + 1} (None if absent)."
    return property(get)


@dataclass(slots=True, eq=True)
class NavRecord:
    """One INS epoch in canonical conventions (see the module docstring)."""

    source: str  # 'nmea' | 'stdbin'
    host_ns: int | None = None
    time_of_day_ns: int | None = None
    gps_ns: int | None = None
    date_source: str | None = None
    lat_deg: float = NAN
    lon_deg: float = NAN
    height_m: float = NAN
    height_ref: str | None = None
    roll_rad: float = NAN
    pitch_rad: float = NAN
    heading_rad: float = NAN
    v_north_m_s: float = NAN
    v_east_m_s: float = NAN
    v_down_m_s: float = NAN
    surge_m: float = NAN
    sway_m: float = NAN
    heave_m: float = NAN
    sigma_roll_rad: float = NAN
    sigma_pitch_rad: float = NAN
    sigma_heading_rad: float = NAN
    sigma_north_m: float = NAN
    sigma_east_m: float = NAN
    sigma_down_m: float = NAN
    sigma_v_north_m_s: float = NAN
    sigma_v_east_m_s: float = NAN
    sigma_v_down_m_s: float = NAN
    algorithm_status: tuple[int, ...] | None = None
    system_status: tuple[int, ...] | None = None
    user_status: int | None = None

    navigation = _flag("navigation")
    alignment = _flag("alignment")
    fine_alignment = _flag("fine_alignment")
    dead_reckoning = _flag("dead_reckoning")
    gps_received = _flag("gps_received")
    gps_valid = _flag("gps_valid")
    internal_time_used = _flag("internal_time_used")
    gps_detected = _flag("gps_detected")
    utc_detected = _flag("utc_detected")
    pps_detected = _flag("pps_detected")

    def __eq__(self, other: object) -> bool:  # NaN == NaN for records
        if not isinstance(other, NavRecord):
            return NotImplemented
        for f in fields(self):
            a, b = getattr(self, f.name), getattr(other, f.name)
            if a != b and not (isinstance(a, float) and isinstance(b, float) and a != a and b != b):
                return False
        return True

    def to_dict(self, degrees: bool = True) -> dict[str, Any]:
        """Plain dict for JSON: NaN → None; with ``degrees`` the ``*_rad`` fields become ``*_deg``."""
        out: dict[str, Any] = {}
        for name, deg_name in _FIELD_NAMES:
            value = getattr(self, name)
            if isinstance(value, float):
                if degrees and deg_name:
                    name, value = deg_name, math.degrees(value)
                if value != value:
                    value = None
            elif isinstance(value, tuple):
                value = list(value)
            out[name] = value
        for name in STATUS_BITS:
            out[name] = getattr(self, name)
        return out


def status_words(
    *,
    navigation: bool = False,
    alignment: bool = False,
    fine_alignment: bool = False,
    dead_reckoning: bool = False,
    gps_received: bool = False,
    gps_valid: bool = False,
    internal_time_used: bool = False,
    gps_detected: bool = False,
    utc_detected: bool = False,
    pps_detected: bool = False,
) -> tuple[tuple[int, int], tuple[int, int]]:
    """Build (algorithm_status, system_status) word pairs from flags (for emulators)."""
    flags = dict(locals())
    words = {"algorithm_status": [0, 0], "system_status": [0, 0]}
    for name, value in flags.items():
        if value:
            attr, index, bit = STATUS_BITS[name]
            words[attr][index] |= 1 << bit
    alg, sys_ = words["algorithm_status"], words["system_status"]
    return (alg[0], alg[1]), (sys_[0], sys_[1])


def wrap_lon_deg(lon_deg: float) -> float:
    """Longitude to [−180, 180) (iXblue sends 0–360)."""
    if lon_deg != lon_deg or -180.0 <= lon_deg < 180.0:
        return lon_deg
    return (lon_deg + 180.0) % 360.0 - 180.0


def wrap_heading_rad(heading_rad: float) -> float:
    if heading_rad != heading_rad:
        return heading_rad
    return heading_rad % TWO_PI


# (field, its name in degrees for a ``*_rad`` field else None), in declaration order
_FIELD_NAMES = tuple(
    (f.name, f.name[:-4] + "_deg" if f.name.endswith("_rad") else None) for f in fields(NavRecord)
)
