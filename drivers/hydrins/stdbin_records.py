"""iXblue STDBIN records: a decoded navigation frame (:class:`StdbinFrame`) and answer
(:class:`StdbinAnswer`), with the frame's canonical NavRecord and JSON views.

A :class:`StdbinFrame` holds the native decoded fields (degrees, iXblue signs, longitude 0–360):
``frame.blocks['attitude_heading']['pitch_deg']`` etc., plus the shortcuts the ``mls decode``
output names (``heading_deg``, ``roll_deg``, ``pitch_deg``, ``latitude_deg``, ``longitude_deg``,
``altitude_m``, ``system_date``, the status words and flags). :meth:`StdbinFrame.to_nav` gives
the canonical :class:`~drivers.hydrins.nav.NavRecord` (time of day from the validity time, date
from the system-date block: ``date_source='system_date'``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from calib.core.frames import attitude_from_ixblue
from drivers.hydrins.nav import NavRecord, wrap_heading_rad, wrap_lon_deg
from drivers.hydrins.stdbin_format import NS_PER_100US
from drivers.hydrins.timeofday import DAY_NS, NS_PER_S, device_fields_to_gps_ns, resolve_gps_ns

NAN = math.nan


@dataclass(slots=True)
class StdbinAnswer:
    protocol_version: int
    payload: bytes
    host_ns: int | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "type": "answer",
            "protocol_version": self.protocol_version,
            "payload_hex": self.payload.hex(),
        }


def _shortcut(block: str, name: str, doc: str | None = None) -> property:
    def get(self) -> float:
        b = self.blocks.get(block)
        return NAN if b is None else b[name]

    return property(get, doc=doc or f"``blocks[{block!r}][{name!r}]``, NaN when the block is absent.")


@dataclass(slots=True)
class StdbinFrame:
    """One ``'IX'`` navigation frame with its native decoded blocks (see the module docstring)."""

    protocol_version: int
    counter: int
    validity_time_100us: int
    blocks: Mapping[str, dict[str, Any]] = field(default_factory=dict)  # name → {field: value}
    navigation_mask: int = 0
    extended_navigation_mask: int | None = None
    external_data_mask: int = 0
    telegram_size: int = 0
    host_ns: int | None = None

    heading_deg = _shortcut("attitude_heading", "heading_deg")
    roll_deg = _shortcut("attitude_heading", "roll_deg")
    pitch_deg = _shortcut("attitude_heading", "pitch_deg", "iXblue native pitch: + bow down.")
    latitude_deg = _shortcut("position", "latitude_deg")
    longitude_deg = _shortcut("position", "longitude_deg", "As sent, 0–360.")
    altitude_m = _shortcut("position", "altitude_m")

    @property
    def system_date(self) -> dict[str, int] | None:
        d = self.blocks.get("system_date")
        return None if d is None else {"day": d["day"], "month": d["month"], "year": d["year"]}

    def _words(self, block: str) -> tuple[int, ...] | None:
        b = self.blocks.get(block)
        return None if b is None else tuple(b.values())

    def to_nav(self, utc_hint_ns: int | None = None) -> NavRecord:
        """The canonical NavRecord of this frame (radians, NED, FRD; see :mod:`drivers.hydrins.nav`).

        The date comes from the system-date block (moved by whole 1024-week eras when it is a GPS
        week rollover more than 9.8 years from ``utc_hint_ns``), else from ``utc_hint_ns`` (host
        UTC, ns since the Unix epoch, nearest day within ±12 h); ``gps_ns`` stays None when the
        INS says it is not on UTC. A validity time of 86 400 s or more is 23:59:60.x.
        """
        nav = NavRecord("stdbin", host_ns=self.host_ns)
        b = self.blocks
        _put_attitude(nav, b)
        _put_position(nav, b)
        _put_speed_and_heave(nav, b)
        nav.algorithm_status = self._words("ins_algorithm_status")
        nav.system_status = self._words("ins_system_status")
        if "ins_user_status" in b:
            nav.user_status = b["ins_user_status"]["status"]
        tod = self.validity_time_100us * NS_PER_100US
        if not DAY_NS <= tod < DAY_NS + NS_PER_S:  # [24 h, 24 h + 1 s): an inserted 23:59:60
            tod %= DAY_NS
        nav.time_of_day_ns = tod
        if nav.utc_detected is not False:
            self._put_date(nav, tod, utc_hint_ns)
        return nav

    def _put_date(self, nav: NavRecord, tod: int, utc_hint_ns: int | None) -> None:
        """``nav.gps_ns`` and its ``date_source`` for the time of day ``tod``: dated by the
        system-date block, else by ``utc_hint_ns``; left unresolved for an impossible date."""
        date = self.system_date
        if date is not None:
            try:
                nav.gps_ns, _ = device_fields_to_gps_ns(
                    date["year"], date["month"], date["day"], tod, utc_hint_ns
                )
                nav.date_source = "system_date"
            except ValueError:  # an impossible date in a checksum-valid frame: leave unresolved
                pass
        elif utc_hint_ns is not None:
            nav.gps_ns, nav.date_source = resolve_gps_ns(tod, utc_hint_ns), "host"

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: header, the shortcut fields, status words and flags, and every block."""
        nav_flags = self.to_nav()
        out: dict[str, Any] = {
            "type": "navigation",
            "protocol_version": self.protocol_version,
            "counter": self.counter,
            "validity_time_100us": self.validity_time_100us,
            "telegram_size": self.telegram_size,
            "navigation_mask": f"0x{self.navigation_mask:08x}",
            "extended_navigation_mask": None
            if self.extended_navigation_mask is None
            else f"0x{self.extended_navigation_mask:08x}",
            "external_data_mask": f"0x{self.external_data_mask:08x}",
            "heading_deg": _json(self.heading_deg),
            "roll_deg": _json(self.roll_deg),
            "pitch_deg": _json(self.pitch_deg),
            "latitude_deg": _json(self.latitude_deg),
            "longitude_deg": _json(self.longitude_deg),
            "altitude_m": _json(self.altitude_m),
            "system_date": self.system_date,
            "ins_algorithm_status": _hexwords(self._words("ins_algorithm_status")),
            "ins_system_status": _hexwords(self._words("ins_system_status")),
            "ins_user_status": _hexwords(self._words("ins_user_status")),
        }
        for name in (
            "navigation",
            "alignment",
            "fine_alignment",
            "dead_reckoning",
            "utc_detected",
            "pps_detected",
        ):
            out[name] = getattr(nav_flags, name)
        out["blocks"] = {name: {k: _json(v) for k, v in blk.items()} for name, blk in self.blocks.items()}
        return out


def _put_attitude(nav: NavRecord, b: Mapping[str, dict[str, Any]]) -> None:
    """Roll, pitch, heading (canonical) and their standard deviations, from their blocks."""
    if "attitude_heading" in b:
        a = b["attitude_heading"]
        roll, pitch, heading = attitude_from_ixblue(
            math.radians(a["roll_deg"]), math.radians(a["pitch_deg"]), math.radians(a["heading_deg"])
        )
        nav.roll_rad, nav.pitch_rad, nav.heading_rad = (
            float(roll),
            float(pitch),
            wrap_heading_rad(float(heading)),
        )
    if "attitude_heading_deviation" in b:
        a = b["attitude_heading_deviation"]
        nav.sigma_heading_rad = math.radians(a["heading_sd_deg"])
        nav.sigma_roll_rad = math.radians(a["roll_sd_deg"])
        nav.sigma_pitch_rad = math.radians(a["pitch_sd_deg"])


def _put_position(nav: NavRecord, b: Mapping[str, dict[str, Any]]) -> None:
    """Latitude, longitude (wrapped to ±180°), height and its reference, and their standard
    deviations (NED), from their blocks."""
    if "position" in b:
        p = b["position"]
        nav.lat_deg, nav.lon_deg, nav.height_m = (
            p["latitude_deg"],
            wrap_lon_deg(p["longitude_deg"]),
            p["altitude_m"],
        )
        nav.height_ref = {0: "geoid", 1: "ellipsoid"}.get(p["altitude_ref"])
    if "position_deviation" in b:
        p = b["position_deviation"]
        nav.sigma_north_m, nav.sigma_east_m, nav.sigma_down_m = (
            p["north_sd_m"],
            p["east_sd_m"],
            p["altitude_sd_m"],
        )


def _put_speed_and_heave(nav: NavRecord, b: Mapping[str, dict[str, Any]]) -> None:
    """Velocity (NED) and its standard deviations, and the real-time heave, surge and sway
    (FRD), from their blocks."""
    if "speed_geographic_frame" in b:
        v = b["speed_geographic_frame"]
        nav.v_north_m_s, nav.v_east_m_s, nav.v_down_m_s = v["north_m_s"], v["east_m_s"], -v["up_m_s"]
    if "speed_geographic_frame_deviation" in b:
        v = b["speed_geographic_frame_deviation"]
        nav.sigma_v_north_m_s, nav.sigma_v_east_m_s, nav.sigma_v_down_m_s = (
            v["north_sd_m_s"],
            v["east_sd_m_s"],
            v["up_sd_m_s"],
        )
    if "realtime_heave_surge_sway" in b:
        h = b["realtime_heave_surge_sway"]
        nav.surge_m, nav.sway_m, nav.heave_m = h["surge_m"], -h["sway_m"], -h["heave_m"]


def _json(v):
    if isinstance(v, float) and v != v:
        return None
    if isinstance(v, bytes):
        return v.rstrip(b"\0").decode("latin-1")
    return v


def _hexwords(words):
    return None if words is None else [f"0x{w:08x}" for w in words]
