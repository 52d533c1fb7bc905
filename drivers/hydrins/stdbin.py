"""iXblue STDBIN protocol versions 2–5, sans-I/O decoder and encoder (DESIGN §5).

Wire format (big-endian). Navigation frame (``'IX'``)::

    'IX' | version u8 | navigation mask u32 | extended navigation mask u32 (V3+)
         | external data mask u32 | navigation size u16 (V4+) | telegram size u16
         | validity time u32 (100 µs, time of day in the INS time base) | counter u32
         | blocks, in ascending bit order: navigation, extended navigation, external data
         | checksum u32 = sum of all preceding bytes (mod 2**32)

Header sizes: 21 (V2), 25 (V3), 27 (V4, V5); the V4+ navigation size counts the navigation and
extended-navigation blocks. Answer frame (``'AN'``, V3+): ``'AN' | version | telegram size u16 |
payload | checksum``. Block sizes and field layouts are tabulated in :data:`NAVIGATION_BLOCKS`,
:data:`EXTENDED_NAVIGATION_BLOCKS` and :data:`EXTERNAL_DATA_BLOCKS` (bit → name, struct
format, field names); the iXblue ``ixblue_stdbin_decoder`` sources and the real captures in
``tests/data/real/ixblue-stdbin`` are the reference.

:class:`StdbinDecoder` turns bytes into :class:`StdbinFrame` / :class:`StdbinAnswer` records:
frames split across reads are reassembled, garbage before or between frames is skipped, and a
frame with a bad checksum, an unknown version or a size that does not match its masks is
rejected and counted (``stats.rejected``) — the decoder never raises. A frame still incomplete
while a later header's whole frame is already buffered and valid (a frame cut short, or a damaged
size field) is dropped at once as ``truncated`` and decoding resumes at that later frame, so a
good frame is never held back behind a bogus one; ``flush()`` does the same search before
dropping what is left. A mask bit this table does
not know (``stats.events['unknown_block']``) stops decoding of that mask at that bit; the frame
is still delivered with the blocks before it (V4+: the external data too, found through the
navigation size).

A :class:`StdbinFrame` holds the native decoded fields (degrees, iXblue signs, longitude 0–360):
``frame.blocks['attitude_heading']['pitch_deg']`` etc., plus the shortcuts the ``mls decode``
output names (``heading_deg``, ``roll_deg``, ``pitch_deg``, ``latitude_deg``, ``longitude_deg``,
``altitude_m``, ``system_date``, the status words and flags). :meth:`StdbinFrame.to_nav` gives
the canonical :class:`~drivers.hydrins.nav.NavRecord` (time of day from the validity time, date
from the system-date block: ``date_source='system_date'``), and :class:`StdbinNavDecoder` feeds
bytes straight to NavRecords, so the daemon treats STDBIN and NMEA alike.

Encoders for the emulators: :func:`encode_frame` (a StdbinFrame → bytes, masks derived from the
blocks present), :func:`frame_from_nav` and :func:`encode_nav` (canonical NavRecord → frame).
"""

from __future__ import annotations

import math
import struct
import time
from bisect import bisect_right
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from calib.core.frames import attitude_from_ixblue, attitude_to_ixblue, gps_ns_to_utc, utc_fields_to_gps_ns
from drivers.base import DecoderStats, DriverError
from drivers.hydrins.nav import NavRecord, wrap_heading_rad, wrap_lon_deg
from drivers.hydrins.timeofday import DAY_NS, resolve_gps_ns, utc_time_of_day_ns

NAN = math.nan
HEADER_SIZES = {2: 21, 3: 25, 4: 27, 5: 27}
ANSWER_HEADER_SIZE = 5
CHECKSUM_SIZE = 4
MAX_TELEGRAM = 4096
MAX_ANSWER = 2048
NS_PER_100US = 100_000

_F3 = "fff"
_VEC = ("xv1", "xv2", "xv3")


def _v(suffix: str) -> tuple[str, ...]:
    return tuple(f"{a}_{suffix}" for a in _VEC)


#: bit → (block name, struct format, field names). Units are in the names.
NAVIGATION_BLOCKS: dict[int, tuple[str, str, tuple[str, ...]]] = {
    0: ("attitude_heading", _F3, ("heading_deg", "roll_deg", "pitch_deg")),
    1: ("attitude_heading_deviation", _F3, ("heading_sd_deg", "roll_sd_deg", "pitch_sd_deg")),
    2: ("realtime_heave_surge_sway", "ffff", ("heave_no_lever_arm_m", "heave_m", "surge_m", "sway_m")),
    3: ("smart_heave", "If", ("validity_time_100us", "smart_heave_m")),
    4: ("heading_roll_pitch_rate", _F3, ("heading_rate_deg_s", "roll_rate_deg_s", "pitch_rate_deg_s")),
    5: ("rotation_rate_vessel_frame", _F3, _v("deg_s")),
    6: ("acceleration_vessel_frame", _F3, _v("m_s2")),
    7: ("position", "ddBf", ("latitude_deg", "longitude_deg", "altitude_ref", "altitude_m")),
    8: ("position_deviation", "ffff", ("north_sd_m", "east_sd_m", "north_east_corr", "altitude_sd_m")),
    9: ("speed_geographic_frame", _F3, ("north_m_s", "east_m_s", "up_m_s")),
    10: ("speed_geographic_frame_deviation", _F3, ("north_sd_m_s", "east_sd_m_s", "up_sd_m_s")),
    11: ("current_geographic_frame", "ff", ("north_m_s", "east_m_s")),
    12: ("current_geographic_frame_deviation", "ff", ("north_sd_m_s", "east_sd_m_s")),
    13: ("system_date", "BBH", ("day", "month", "year")),
    14: ("sensor_status", "II", ("status1", "status2")),
    15: ("ins_algorithm_status", "IIII", ("status1", "status2", "status3", "status4")),
    16: ("ins_system_status", "III", ("status1", "status2", "status3")),
    17: ("ins_user_status", "I", ("status",)),
    18: ("ahrs_algorithm_status", "I", ("status",)),
    19: ("ahrs_system_status", "III", ("status1", "status2", "status3")),
    20: ("ahrs_user_status", "I", ("status",)),
    21: ("heave_surge_sway_speed", _F3, ("heave_speed_m_s", "surge_speed_m_s", "sway_speed_m_s")),
    22: ("speed_vessel_frame", _F3, _v("m_s")),
    23: ("acceleration_geographic_frame", _F3, ("north_m_s2", "east_m_s2", "up_m_s2")),
    24: ("course_speed_over_ground", "ff", ("course_deg", "speed_m_s")),
    25: ("temperatures", _F3, ("fog_temperature_degc", "accelerometer_temperature_degc", "board_temperature_degc")),
    26: ("attitude_quaternion", "ffff", ("q0", "q1", "q2", "q3")),
    27: ("attitude_quaternion_deviation", _F3, ("xi1_sd_rad", "xi2_sd_rad", "xi3_sd_rad")),
    28: ("raw_acceleration_vessel_frame", _F3, _v("m_s2")),
    29: ("acceleration_vessel_frame_deviation", _F3, _v("sd_m_s2")),
    30: ("rotation_rate_vessel_frame_deviation", _F3, _v("sd_deg_s")),
}  # fmt: skip

EXTENDED_NAVIGATION_BLOCKS: dict[int, tuple[str, str, tuple[str, ...]]] = {
    0: ("rotation_acceleration_vessel_frame", _F3, _v("deg_s2")),
    1: ("rotation_acceleration_vessel_frame_deviation", _F3, _v("sd_deg_s2")),
    2: ("raw_rotation_rate_vessel_frame", _F3, _v("deg_s")),
    3: ("vehicle_attitude_heading", _F3, ("heading_deg", "roll_deg", "pitch_deg")),
    4: ("vehicle_attitude_heading_deviation", _F3, ("heading_sd_deg", "roll_sd_deg", "pitch_sd_deg")),
    5: ("vehicle_position", "ddBf", ("latitude_deg", "longitude_deg", "altitude_ref", "altitude_m")),
    6: ("vehicle_position_deviation", "ffff", ("north_sd_m", "east_sd_m", "north_east_corr", "altitude_sd_m")),
}  # fmt: skip

_GNSS = ("IBBddffffff", ("validity_time_100us", "gnss_id", "gnss_quality", "latitude_deg", "longitude_deg",
         "altitude_m", "latitude_sd_m", "longitude_sd_m", "altitude_sd_m", "lat_lon_cov_m2", "geoidal_separation_m"))
_EMLOG = ("IBff", ("validity_time_100us", "emlog_id", "xv1_water_speed_m_s", "xv1_speed_sd_m_s"))
_USBL = ("IB8sddfffff", ("validity_time_100us", "usbl_id", "beacon_id", "latitude_deg", "longitude_deg",
         "altitude_m", "north_sd_m", "east_sd_m", "lat_lon_cov_m2", "altitude_sd_m"))
_DVL_GROUND = ("IBffffffff", ("validity_time_100us", "dvl_id", *_v("ground_speed_m_s"), "speed_of_sound_m_s",
               "dvl_altitude_m", *_v("speed_sd_m_s")))
_DVL_WATER = ("IBfffffff", ("validity_time_100us", "dvl_id", *_v("water_speed_m_s"), "speed_of_sound_m_s",
              *_v("speed_sd_m_s")))
_LBL = ("IB8sddfff", ("validity_time_100us", "rfu", "beacon_id", "beacon_latitude_deg", "beacon_longitude_deg",
        "beacon_altitude_m", "range_m", "range_sd_m"))
_EVENT = ("IBI", ("validity_time_100us", "event_id", "event_count"))
_VTG = ("IBfff", ("validity_time_100us", "vtg_id", "true_course_deg", "magnetic_course_deg", "speed_over_ground_m_s"))

EXTERNAL_DATA_BLOCKS: dict[int, tuple[str, str, tuple[str, ...]]] = {
    0: ("utc", "IB", ("validity_time_100us", "source")),
    1: ("gnss1", *_GNSS),
    2: ("gnss2", *_GNSS),
    3: ("gnss_manual", *_GNSS),
    4: ("emlog1", *_EMLOG),
    5: ("emlog2", *_EMLOG),
    6: ("usbl1", *_USBL),
    7: ("usbl2", *_USBL),
    8: ("usbl3", *_USBL),
    9: ("depth", "Iff", ("validity_time_100us", "depth_m", "depth_sd_m")),
    10: ("dvl_ground_speed1", *_DVL_GROUND),
    11: ("dvl_water_speed1", *_DVL_WATER),
    12: ("sound_velocity", "If", ("validity_time_100us", "speed_of_sound_m_s")),
    13: ("dmi", "Ii", ("validity_time_100us", "pulse_count")),
    14: ("lbl1", *_LBL),
    15: ("lbl2", *_LBL),
    16: ("lbl3", *_LBL),
    17: ("lbl4", *_LBL),
    18: ("event_marker_a", *_EVENT),
    19: ("event_marker_b", *_EVENT),
    20: ("event_marker_c", *_EVENT),
    21: ("dvl_ground_speed2", *_DVL_GROUND),
    22: ("dvl_water_speed2", *_DVL_WATER),
    24: ("turret_angles", "Ifff", ("validity_time_100us", "heading_bearing_drift_deg", "roll_deg", "elevation_pitch_deg")),
    25: ("vtg1", *_VTG),
    26: ("vtg2", *_VTG),
    27: ("logbook", "II32s", ("validity_time_100us", "log_id", "custom_text")),
}  # fmt: skip

_TABLES = (NAVIGATION_BLOCKS, EXTENDED_NAVIGATION_BLOCKS, EXTERNAL_DATA_BLOCKS)
#: block name → (mask index 0/1/2, bit, fmt, names)
BLOCKS_BY_NAME = {
    spec[0]: (i, bit, spec[1], spec[2]) for i, table in enumerate(_TABLES) for bit, spec in table.items()
}
BLOCK_SIZES = {name: struct.calcsize(">" + fmt) for name, (_, _, fmt, _) in BLOCKS_BY_NAME.items()}


def _sum32(data) -> int:
    return sum(data) & 0xFFFFFFFF


# ---------------------------------------------------------------------------------------------
# Records.
# ---------------------------------------------------------------------------------------------


@dataclass(slots=True)
class StdbinAnswer:
    protocol_version: int
    payload: bytes
    host_ns: int | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"type": "answer", "protocol_version": self.protocol_version, "payload_hex": self.payload.hex()}


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

        The date comes from the system-date block, else from ``utc_hint_ns`` (host UTC, ns since
        the Unix epoch, nearest day within ±12 h); ``gps_ns`` stays None when the INS says it is
        not on UTC.
        """
        nav = NavRecord("stdbin", host_ns=self.host_ns)
        b = self.blocks
        if "attitude_heading" in b:
            a = b["attitude_heading"]
            roll, pitch, heading = attitude_from_ixblue(
                math.radians(a["roll_deg"]), math.radians(a["pitch_deg"]), math.radians(a["heading_deg"])
            )
            nav.roll_rad, nav.pitch_rad, nav.heading_rad = float(roll), float(pitch), wrap_heading_rad(float(heading))
        if "attitude_heading_deviation" in b:
            a = b["attitude_heading_deviation"]
            nav.sigma_heading_rad = math.radians(a["heading_sd_deg"])
            nav.sigma_roll_rad = math.radians(a["roll_sd_deg"])
            nav.sigma_pitch_rad = math.radians(a["pitch_sd_deg"])
        if "position" in b:
            p = b["position"]
            nav.lat_deg, nav.lon_deg, nav.height_m = p["latitude_deg"], wrap_lon_deg(p["longitude_deg"]), p["altitude_m"]
            nav.height_ref = {0: "geoid", 1: "ellipsoid"}.get(p["altitude_ref"])
        if "position_deviation" in b:
            p = b["position_deviation"]
            nav.sigma_north_m, nav.sigma_east_m, nav.sigma_down_m = p["north_sd_m"], p["east_sd_m"], p["altitude_sd_m"]
        if "speed_geographic_frame" in b:
            v = b["speed_geographic_frame"]
            nav.v_north_m_s, nav.v_east_m_s, nav.v_down_m_s = v["north_m_s"], v["east_m_s"], -v["up_m_s"]
        if "speed_geographic_frame_deviation" in b:
            v = b["speed_geographic_frame_deviation"]
            nav.sigma_v_north_m_s, nav.sigma_v_east_m_s, nav.sigma_v_down_m_s = (
                v["north_sd_m_s"], v["east_sd_m_s"], v["up_sd_m_s"])  # fmt: skip
        if "realtime_heave_surge_sway" in b:
            h = b["realtime_heave_surge_sway"]
            nav.surge_m, nav.sway_m, nav.heave_m = h["surge_m"], -h["sway_m"], -h["heave_m"]
        nav.algorithm_status = self._words("ins_algorithm_status")
        nav.system_status = self._words("ins_system_status")
        if "ins_user_status" in b:
            nav.user_status = b["ins_user_status"]["status"]
        tod = (self.validity_time_100us * NS_PER_100US) % DAY_NS
        nav.time_of_day_ns = tod
        if nav.utc_detected is not False:
            date = self.system_date
            if date is not None:
                try:
                    nav.gps_ns = utc_fields_to_gps_ns(date["year"], date["month"], date["day"], tod)
                    nav.date_source = "system_date"
                except ValueError:  # an impossible date in a checksum-valid frame: leave unresolved
                    pass
            elif utc_hint_ns is not None:
                nav.gps_ns, nav.date_source = resolve_gps_ns(tod, utc_hint_ns), "host"
        return nav

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
        for name in ("navigation", "alignment", "fine_alignment", "dead_reckoning", "utc_detected", "pps_detected"):
            out[name] = getattr(nav_flags, name)
        out["blocks"] = {name: {k: _json(v) for k, v in blk.items()} for name, blk in self.blocks.items()}
        return out


def _json(v):
    if isinstance(v, float) and v != v:
        return None
    if isinstance(v, bytes):
        return v.rstrip(b"\0").decode("latin-1")
    return v


def _hexwords(words):
    return None if words is None else [f"0x{w:08x}" for w in words]


# ---------------------------------------------------------------------------------------------
# Layouts: one compiled struct per (version, masks), cached.
# ---------------------------------------------------------------------------------------------


@dataclass(slots=True)
class _Layout:
    segments: list  # [(offset, struct.Struct, [(block name, names, n_values)])]
    size: int | None  # exact telegram size when every bit is known, else None
    min_size: int
    unknown: int  # number of masks cut short by an unknown bit
    index: dict = field(default_factory=dict)  # block name → (segment, first value, field names)


class _Blocks(Mapping):
    """The decoded blocks of one frame, each dict built on first access (most frames are only
    partly read: the nav view touches ten blocks of forty)."""

    __slots__ = ("_index", "_values", "_cache")

    def __init__(self, index: dict, values: list) -> None:
        self._index, self._values, self._cache = index, values, {}

    def __getitem__(self, name: str) -> dict[str, Any]:
        blk = self._cache.get(name)
        if blk is None:
            seg, k, names = self._index[name]
            blk = self._cache[name] = dict(zip(names, self._values[seg][k : k + len(names)]))
        return blk

    def __contains__(self, name: object) -> bool:
        return name in self._index

    def __iter__(self):
        return iter(self._index)

    def __len__(self) -> int:
        return len(self._index)

    def __repr__(self) -> str:
        return repr(dict(self))


def _blocks_of(mask: int, table) -> tuple[list, int, bool]:
    """Known blocks of a mask in bit order up to the first unknown bit: (specs, size, cut)."""
    specs, size = [], 0
    for bit in range(32):
        if mask >> bit & 1:
            spec = table.get(bit)
            if spec is None:
                return specs, size, True
            specs.append(spec)
            size += BLOCK_SIZES[spec[0]]
    return specs, size, False


def _segment(offset: int, specs: list):
    fmt = ">" + "".join(s[1] for s in specs)
    return offset, struct.Struct(fmt), [(s[0], s[2], len(s[2])) for s in specs]


_LAYOUTS: dict[tuple, _Layout] = {}


def _layout(version: int, nav_mask: int, ext_nav_mask: int | None, ext_mask: int, nav_size: int | None) -> _Layout:
    key = (version, nav_mask, ext_nav_mask, ext_mask, nav_size)
    lay = _LAYOUTS.get(key)
    if lay is not None:
        return lay
    header = HEADER_SIZES[version]
    nav, nav_bytes, nav_cut = _blocks_of(nav_mask, NAVIGATION_BLOCKS)
    ext_nav, ext_nav_bytes, ext_nav_cut = ([], 0, False)
    if ext_nav_mask is not None and not nav_cut:
        ext_nav, ext_nav_bytes, ext_nav_cut = _blocks_of(ext_nav_mask, EXTENDED_NAVIGATION_BLOCKS)
    ext, ext_bytes, ext_cut = _blocks_of(ext_mask, EXTERNAL_DATA_BLOCKS)
    unknown = int(nav_cut) + int(ext_nav_cut) + int(ext_cut)
    segments = [_segment(header, nav + ext_nav)]
    size: int | None
    if not nav_cut and not ext_nav_cut:
        segments.append(_segment(header + nav_bytes + ext_nav_bytes, ext))
        size = None if ext_cut else header + nav_bytes + ext_nav_bytes + ext_bytes + CHECKSUM_SIZE
        min_size = header + nav_bytes + ext_nav_bytes + ext_bytes + CHECKSUM_SIZE
    elif nav_size is not None:  # V4+: the navigation size tells where external data starts
        segments.append(_segment(header + nav_size, ext))
        size, min_size = None, header + nav_size + ext_bytes + CHECKSUM_SIZE
    else:
        size, min_size = None, header + nav_bytes + ext_nav_bytes + CHECKSUM_SIZE
    lay = _Layout([s for s in segments if s[2]], size, min_size, unknown)
    for seg, (_, _, specs) in enumerate(lay.segments):
        k = 0
        for name, names, count in specs:
            lay.index[name] = (seg, k, names)
            k += count
    if len(_LAYOUTS) < 1024:
        _LAYOUTS[key] = lay
    return lay


# ---------------------------------------------------------------------------------------------
# Decoder.
# ---------------------------------------------------------------------------------------------

_H_V2 = struct.Struct(">IIHII")
_H_V3 = struct.Struct(">IIIHII")
_H_V4 = struct.Struct(">IIIHHII")
_U16 = struct.Struct(">H")
_U32 = struct.Struct(">I")


class _Headers:
    """The next ``'IX'`` / ``'AN'`` at or after a position of ``buf`` (-1: none), for positions
    that only grow: each magic is searched again only once the position has passed it."""

    __slots__ = ("buf", "ix", "an")

    def __init__(self, buf: bytes) -> None:
        self.buf, self.ix, self.an = buf, -2, -2

    def next(self, pos: int) -> int:
        if -1 != self.ix < pos:
            self.ix = self.buf.find(b"IX", pos)
        if -1 != self.an < pos:
            self.an = self.buf.find(b"AN", pos)
        i, j = self.ix, self.an
        return i if j < 0 or 0 <= i < j else j


def _nav_header(buf: bytes, pos: int, version: int):
    """The header fields of the navigation frame at ``pos`` (``version`` known, header complete):
    ``(nav_mask, ext_nav, ext_mask, size, validity, counter, layout)``, or None when the telegram
    size does not match what the masks say."""
    nav_size = ext_nav = None
    if version == 2:
        nav_mask, ext_mask, size, validity, counter = _H_V2.unpack_from(buf, pos + 3)
    elif version == 3:
        nav_mask, ext_nav, ext_mask, size, validity, counter = _H_V3.unpack_from(buf, pos + 3)
    else:
        nav_mask, ext_nav, ext_mask, nav_size, size, validity, counter = _H_V4.unpack_from(buf, pos + 3)
    lay = _layout(version, nav_mask, ext_nav, ext_mask, nav_size)
    if (lay.size is not None and size != lay.size) or size < lay.min_size or size > MAX_TELEGRAM:
        return None
    return nav_mask, ext_nav, ext_mask, size, validity, counter, lay


class StdbinDecoder:
    """Bytes → :class:`StdbinFrame` / :class:`StdbinAnswer` (see the module docstring)."""

    def __init__(self) -> None:
        self.stats = DecoderStats()
        self._buf = b""
        # chunk starts inside _buf (offsets, ascending, first 0) and their host stamps
        self._mark_off: list[int] = []
        self._mark_ns: list[int | None] = []
        # while the candidate at _buf[0] is incomplete: (next offset to look for a header from,
        # pending later candidates, bytes the candidate needs); see _later_frame
        self._scan: tuple[int, list[int], int] | None = None
        self._scan_state: tuple[int, list[int]] | None = None

    def feed(self, data: bytes, host_ns: int | None = None) -> list:
        """Decode what ``data`` completes; a frame's ``host_ns`` is the stamp of the chunk that
        brought its first byte."""
        self.stats.bytes_in += len(data)
        old = len(self._buf)
        if not old:
            self._mark_off, self._mark_ns = [0], [host_ns]
            return self._decode(bytes(data), 0, host_ns)
        if not data:
            return []
        self._mark_off.append(old)
        self._mark_ns.append(host_ns)
        buf = self._buf + bytes(data)
        scan = self._scan
        if (
            scan is not None
            and len(buf) < scan[2]
            and not scan[1]
            and buf.find(b"IX", scan[0]) < 0
            and buf.find(b"AN", scan[0]) < 0
        ):  # the frame at _buf[0] is still short and no other header came: just buffer
            self._buf = buf
            self._scan = (len(buf) - 1, scan[1], scan[2])
            return []
        return self._decode(buf, old, host_ns)

    def _stamp(self, pos: int):
        return self._mark_ns[bisect_right(self._mark_off, pos) - 1]

    def _decode(self, buf: bytes, old: int, host_ns) -> list:
        """Decode ``buf`` (``old`` bytes of it buffered before, the rest stamped ``host_ns``)."""
        out: list = []
        pos, n = 0, len(buf)
        stats = self.stats
        scan = self._scan
        self._scan = None
        waiting = False
        headers = _Headers(buf)
        while True:
            start = headers.next(pos)
            if start < 0:
                # a lone trailing "I"/"A" may start the next frame (only if not yet consumed)
                keep = n - 1 if n > pos and buf[-1:] in (b"I", b"A") else n
                stats.skipped_bytes += keep - pos
                pos = keep
                break
            stats.skipped_bytes += start - pos
            pos = start
            if n - pos < 3:
                break
            version = buf[pos + 2]
            stamp = host_ns if pos >= old else self._stamp(pos)
            if buf[pos] == 0x49:  # 'I'
                status = self._frame(buf, pos, version, stamp, out)
            else:
                status = self._answer(buf, pos, version, stamp, out)
            if status == 0:  # incomplete: a later complete, valid frame proves this one bogus
                q = self._later_frame(buf, pos, scan if pos == 0 else None)
                scan = None
                if q < 0:
                    waiting = True
                    break
                stats.rejected["truncated"] += 1
                stats.skipped_bytes += q - pos
                pos = q
            elif status < 0:  # rejected: resynchronize one byte further
                stats.skipped_bytes += 1
                pos += 1
            else:
                pos += status
        if waiting:  # remember the look-ahead and the size the frame at pos needs
            have = n - pos
            if buf[pos] == 0x49:
                header = HEADER_SIZES[buf[pos + 2]]
                need = header if have < header else _U16.unpack_from(buf, pos + header - 10)[0]
            else:
                need = ANSWER_HEADER_SIZE if have < ANSWER_HEADER_SIZE else _U16.unpack_from(buf, pos + 3)[0]
            self._scan = (*self._scan_state, need)
        self._keep(buf, pos, old, host_ns)
        stats.records += len(out)
        return out

    def _keep(self, buf: bytes, pos: int, old: int, host_ns) -> None:
        """Buffer ``buf[pos:]`` with the stamps of the chunks it came in."""
        self._buf = buf[pos:]
        if not self._buf:
            self._mark_off, self._mark_ns = [], []
        elif pos >= old:
            self._mark_off, self._mark_ns = [0], [host_ns]
        elif pos:
            k = bisect_right(self._mark_off, pos) - 1
            self._mark_off = [0] + [o - pos for o in self._mark_off[k + 1 :]]
            self._mark_ns = self._mark_ns[k:]

    def _later_frame(self, buf: bytes, pos: int, state) -> int:
        """Offset of the first header after ``pos`` whose whole frame is buffered and valid, else -1.

        Candidates still incomplete are remembered (``state``: next offset to search from and the
        pending candidates, relative to ``pos``) so a frame arriving in many reads is not rescanned
        from its start at every read.
        """
        n = len(buf)
        if state is None:
            scan, pending = pos + 1, []
        elif not state[1]:  # common case: nothing pending, and no new header in the new bytes
            scan, pending = state[0] + pos, []
            if buf.find(b"IX", scan) < 0 and buf.find(b"AN", scan) < 0:
                self._scan_state = (max(scan, n - 1) - pos, pending)
                return -1
        else:
            scan, pending = state[0] + pos, [q + pos for q in state[1]]
        still = []
        for q in pending:
            r = self._check(buf, q)
            if r > 0:
                return q
            if r == 0:
                still.append(q)
        headers = _Headers(buf)
        while True:
            q = headers.next(scan)
            if q < 0:
                break
            r = self._check(buf, q)
            if r > 0:
                return q
            if r == 0:
                still.append(q)
            scan = q + 1
        scan = max(scan, n - 1)
        self._scan_state = (scan - pos, [q - pos for q in still])
        return -1

    @staticmethod
    def _check(buf: bytes, q: int) -> int:
        """Size of the complete, valid frame at ``q``; 0 if it may still become one; -1 if not."""
        have = len(buf) - q
        if have < 3:
            return 0
        version = buf[q + 2]
        if buf[q] == 0x49:  # 'I'
            header = HEADER_SIZES.get(version)
            if header is None:
                return -1
            if have < header:
                return 0
            h = _nav_header(buf, q, version)
            if h is None:
                return -1
            size = h[3]
        else:
            if not 3 <= version <= 5:
                return -1
            if have < ANSWER_HEADER_SIZE:
                return 0
            size = _U16.unpack_from(buf, q + 3)[0]
            if not ANSWER_HEADER_SIZE + CHECKSUM_SIZE <= size <= MAX_ANSWER:
                return -1
        if have < size:
            return 0
        end = q + size - CHECKSUM_SIZE
        return size if _U32.unpack_from(buf, end)[0] == _sum32(buf[q:end]) else -1

    def flush(self) -> list:
        """End of stream: frames still in the buffer behind an incomplete one are decoded; what
        is left is counted (``truncated``) and dropped."""
        out: list = []
        self._scan = None
        while len(self._buf) >= 3:
            q = self._later_frame(self._buf, 0, None)
            if q < 0:
                break
            self.stats.rejected["truncated"] += 1
            self.stats.skipped_bytes += q
            self._keep(self._buf, q, len(self._buf), None)
            out += self._decode(self._buf, len(self._buf), None)  # every byte buffered: own stamps
            self._scan = None
        if self._buf:
            self.stats.skipped_bytes += len(self._buf)
            if len(self._buf) >= 3:
                self.stats.rejected["truncated"] += 1
        self._buf, self._mark_off, self._mark_ns, self._scan = b"", [], [], None
        return out

    def _frame(self, buf: bytes, pos: int, version: int, host_ns, out: list) -> int:
        header = HEADER_SIZES.get(version)
        if header is None:
            self.stats.rejected["unknown_version"] += 1
            return -1
        if len(buf) - pos < header:
            return 0
        h = _nav_header(buf, pos, version)
        if h is None:
            self.stats.rejected["size_mismatch"] += 1
            return -1
        nav_mask, ext_nav, ext_mask, size, validity, counter, lay = h
        if len(buf) - pos < size:
            return 0
        end = pos + size - CHECKSUM_SIZE
        if _U32.unpack_from(buf, end)[0] != _sum32(buf[pos:end]):
            self.stats.rejected["bad_checksum"] += 1
            return -1
        blocks = _Blocks(lay.index, [st.unpack_from(buf, pos + offset) for offset, st, _ in lay.segments])
        if lay.unknown:
            self.stats.events["unknown_block"] += lay.unknown
        out.append(StdbinFrame(version, counter, validity, blocks, nav_mask, ext_nav, ext_mask, size, host_ns))
        return size

    def _answer(self, buf: bytes, pos: int, version: int, host_ns, out: list) -> int:
        if not 3 <= version <= 5:
            self.stats.rejected["unknown_version"] += 1
            return -1
        if len(buf) - pos < ANSWER_HEADER_SIZE:
            return 0
        size = _U16.unpack_from(buf, pos + 3)[0]
        if not ANSWER_HEADER_SIZE + CHECKSUM_SIZE <= size <= MAX_ANSWER:
            self.stats.rejected["size_mismatch"] += 1
            return -1
        if len(buf) - pos < size:
            return 0
        end = pos + size - CHECKSUM_SIZE
        if _U32.unpack_from(buf, end)[0] != _sum32(buf[pos:end]):
            self.stats.rejected["bad_checksum"] += 1
            return -1
        out.append(StdbinAnswer(version, buf[pos + ANSWER_HEADER_SIZE : end], host_ns))
        return size


class StdbinNavDecoder:
    """Bytes → canonical :class:`NavRecord` per navigation frame (answers are counted, not returned).

    ``utc_clock`` (host UTC ns since the Unix epoch) dates frames without a system-date block;
    None never dates them from the host.
    """

    def __init__(self, utc_clock: Callable[[], int] | None = time.time_ns) -> None:
        self.decoder = StdbinDecoder()
        self.utc_clock = utc_clock

    @property
    def stats(self) -> DecoderStats:
        return self.decoder.stats

    def feed(self, data: bytes, host_ns: int | None = None, utc_hint_ns: int | None = None) -> list[NavRecord]:
        return self._navs(self.decoder.feed(data, host_ns), utc_hint_ns)

    def _navs(self, records: list, utc_hint_ns: int | None) -> list[NavRecord]:
        out = []
        for rec in records:
            if isinstance(rec, StdbinFrame):
                hint = utc_hint_ns
                if hint is None and self.utc_clock is not None and "system_date" not in rec.blocks:
                    hint = self.utc_clock()
                out.append(rec.to_nav(hint))
            else:
                self.stats.events["answers"] += 1
        return out

    def flush(self, utc_hint_ns: int | None = None) -> list[NavRecord]:
        return self._navs(self.decoder.flush(), utc_hint_ns)


# ---------------------------------------------------------------------------------------------
# Encoders.
# ---------------------------------------------------------------------------------------------


def encode_frame(frame: StdbinFrame) -> bytes:
    """A :class:`StdbinFrame` → wire bytes. Masks come from the blocks present (the frame's own
    mask fields are ignored); every field of each block must be given.

    Raises :class:`DriverError` naming the block/field for an unknown block, a missing field or
    a block that the version cannot carry.
    """
    version = frame.protocol_version
    if version not in HEADER_SIZES:
        raise DriverError(f"STDBIN version {version!r}: expected 2, 3, 4 or 5")
    masks = [0, 0, 0]
    for name in frame.blocks:
        spec = BLOCKS_BY_NAME.get(name)
        if spec is None:
            raise DriverError(f"STDBIN block {name!r} is unknown; known: {sorted(BLOCKS_BY_NAME)}")
        if spec[0] == 1 and version < 3:
            raise DriverError(f"STDBIN block {name!r} (extended navigation) needs version >= 3, got {version}")
        masks[spec[0]] |= 1 << spec[1]
    parts: list[bytes] = []
    sizes = [0, 0, 0]
    for index, table in enumerate(_TABLES):
        for bit in range(32):
            if masks[index] >> bit & 1:
                name, fmt, names = table[bit]
                blk = frame.blocks[name]
                missing = [n for n in names if n not in blk]
                if missing:
                    raise DriverError(f"STDBIN block {name!r}: missing field(s) {missing}")
                try:
                    parts.append(struct.pack(">" + fmt, *(blk[n] for n in names)))
                except struct.error as exc:
                    raise DriverError(f"STDBIN block {name!r}: {exc}") from exc
                sizes[index] += BLOCK_SIZES[name]
    header_size = HEADER_SIZES[version]
    size = header_size + sum(sizes) + CHECKSUM_SIZE
    if size > MAX_TELEGRAM:
        raise DriverError(f"STDBIN telegram of {size} bytes exceeds {MAX_TELEGRAM}")
    validity, counter = frame.validity_time_100us & 0xFFFFFFFF, frame.counter & 0xFFFFFFFF
    if version == 2:
        header = b"IX\x02" + _H_V2.pack(masks[0], masks[2], size, validity, counter)
    elif version == 3:
        header = b"IX\x03" + _H_V3.pack(masks[0], masks[1], masks[2], size, validity, counter)
    else:
        header = bytes((0x49, 0x58, version)) + _H_V4.pack(
            masks[0], masks[1], masks[2], sizes[0] + sizes[1], size, validity, counter
        )
    body = header + b"".join(parts)
    return body + _U32.pack(_sum32(body))


def encode_answer(payload: bytes, version: int = 5) -> bytes:
    if not 3 <= version <= 5:
        raise DriverError(f"STDBIN answer version {version!r}: expected 3, 4 or 5")
    size = ANSWER_HEADER_SIZE + len(payload) + CHECKSUM_SIZE
    body = b"AN" + bytes((version,)) + _U16.pack(size) + payload
    return body + _U32.pack(_sum32(body))


def frame_from_nav(nav: NavRecord, version: int = 3, counter: int = 0) -> StdbinFrame:
    """A canonical NavRecord → a native frame (iXblue signs, degrees, longitude 0–360).

    Blocks written: attitude/heading (+ deviation), real-time heave/surge/sway, position
    (+ deviation), geographic speed (+ deviation), system date and the UTC external block when
    ``gps_ns`` is set, and the INS status words when present. Missing values are sent as NaN.
    """
    blocks: dict[str, dict[str, Any]] = {}
    roll, pitch, heading = attitude_to_ixblue(nav.roll_rad, nav.pitch_rad, nav.heading_rad)
    blocks["attitude_heading"] = {
        "heading_deg": math.degrees(float(heading)),
        "roll_deg": math.degrees(float(roll)),
        "pitch_deg": math.degrees(float(pitch)),
    }
    blocks["attitude_heading_deviation"] = {
        "heading_sd_deg": math.degrees(nav.sigma_heading_rad),
        "roll_sd_deg": math.degrees(nav.sigma_roll_rad),
        "pitch_sd_deg": math.degrees(nav.sigma_pitch_rad),
    }
    blocks["realtime_heave_surge_sway"] = {
        "heave_no_lever_arm_m": -nav.heave_m,
        "heave_m": -nav.heave_m,
        "surge_m": nav.surge_m,
        "sway_m": -nav.sway_m,
    }
    blocks["position"] = {
        "latitude_deg": nav.lat_deg,
        "longitude_deg": nav.lon_deg % 360.0 if nav.lon_deg == nav.lon_deg else NAN,
        "altitude_ref": 1 if nav.height_ref == "ellipsoid" else 0,
        "altitude_m": nav.height_m,
    }
    blocks["position_deviation"] = {
        "north_sd_m": nav.sigma_north_m,
        "east_sd_m": nav.sigma_east_m,
        "north_east_corr": 0.0,
        "altitude_sd_m": nav.sigma_down_m,
    }
    blocks["speed_geographic_frame"] = {"north_m_s": nav.v_north_m_s, "east_m_s": nav.v_east_m_s, "up_m_s": -nav.v_down_m_s}
    blocks["speed_geographic_frame_deviation"] = {
        "north_sd_m_s": nav.sigma_v_north_m_s,
        "east_sd_m_s": nav.sigma_v_east_m_s,
        "up_sd_m_s": nav.sigma_v_down_m_s,
    }
    if nav.gps_ns is not None:
        utc = gps_ns_to_utc(nav.gps_ns)
        tod = utc_time_of_day_ns(nav.gps_ns)
        blocks["system_date"] = {"day": utc.day, "month": utc.month, "year": utc.year}
    else:
        tod = nav.time_of_day_ns or 0
    if nav.algorithm_status is not None:
        words = (tuple(nav.algorithm_status) + (0, 0, 0, 0))[:4]
        blocks["ins_algorithm_status"] = dict(zip(("status1", "status2", "status3", "status4"), words))
    if nav.system_status is not None:
        words = (tuple(nav.system_status) + (0, 0, 0))[:3]
        blocks["ins_system_status"] = dict(zip(("status1", "status2", "status3"), words))
    if nav.user_status is not None:
        blocks["ins_user_status"] = {"status": nav.user_status}
    validity = tod // NS_PER_100US
    if nav.gps_ns is not None:
        blocks["utc"] = {"validity_time_100us": validity, "source": 0}
    return StdbinFrame(version, counter, validity, blocks)


def encode_nav(nav: NavRecord, version: int = 3, counter: int = 0) -> bytes:
    """Canonical NavRecord → one STDBIN navigation frame."""
    return encode_frame(frame_from_nav(nav, version, counter))
