"""iXblue STDBIN versions 2–5: the wire format — sizes, header layouts, block tables, checksum.

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
"""

from __future__ import annotations

import struct

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
    25: (
        "temperatures",
        _F3,
        ("fog_temperature_degc", "accelerometer_temperature_degc", "board_temperature_degc"),
    ),
    26: ("attitude_quaternion", "ffff", ("q0", "q1", "q2", "q3")),
    27: ("attitude_quaternion_deviation", _F3, ("xi1_sd_rad", "xi2_sd_rad", "xi3_sd_rad")),
    28: ("raw_acceleration_vessel_frame", _F3, _v("m_s2")),
    29: ("acceleration_vessel_frame_deviation", _F3, _v("sd_m_s2")),
    30: ("rotation_rate_vessel_frame_deviation", _F3, _v("sd_deg_s")),
}

EXTENDED_NAVIGATION_BLOCKS: dict[int, tuple[str, str, tuple[str, ...]]] = {
    0: ("rotation_acceleration_vessel_frame", _F3, _v("deg_s2")),
    1: ("rotation_acceleration_vessel_frame_deviation", _F3, _v("sd_deg_s2")),
    2: ("raw_rotation_rate_vessel_frame", _F3, _v("deg_s")),
    3: ("vehicle_attitude_heading", _F3, ("heading_deg", "roll_deg", "pitch_deg")),
    4: ("vehicle_attitude_heading_deviation", _F3, ("heading_sd_deg", "roll_sd_deg", "pitch_sd_deg")),
    5: ("vehicle_position", "ddBf", ("latitude_deg", "longitude_deg", "altitude_ref", "altitude_m")),
    6: (
        "vehicle_position_deviation",
        "ffff",
        ("north_sd_m", "east_sd_m", "north_east_corr", "altitude_sd_m"),
    ),
}

_GNSS = (
    "IBBddffffff",
    (
        "validity_time_100us",
        "gnss_id",
        "gnss_quality",
        "latitude_deg",
        "longitude_deg",
        "altitude_m",
        "latitude_sd_m",
        "longitude_sd_m",
        "altitude_sd_m",
        "lat_lon_cov_m2",
        "geoidal_separation_m",
    ),
)
_EMLOG = ("IBff", ("validity_time_100us", "emlog_id", "xv1_water_speed_m_s", "xv1_speed_sd_m_s"))
_USBL = (
    "IB8sddfffff",
    (
        "validity_time_100us",
        "usbl_id",
        "beacon_id",
        "latitude_deg",
        "longitude_deg",
        "altitude_m",
        "north_sd_m",
        "east_sd_m",
        "lat_lon_cov_m2",
        "altitude_sd_m",
    ),
)
_DVL_GROUND = (
    "IBffffffff",
    (
        "validity_time_100us",
        "dvl_id",
        *_v("ground_speed_m_s"),
        "speed_of_sound_m_s",
        "dvl_altitude_m",
        *_v("speed_sd_m_s"),
    ),
)
_DVL_WATER = (
    "IBfffffff",
    ("validity_time_100us", "dvl_id", *_v("water_speed_m_s"), "speed_of_sound_m_s", *_v("speed_sd_m_s")),
)
_LBL = (
    "IB8sddfff",
    (
        "validity_time_100us",
        "rfu",
        "beacon_id",
        "beacon_latitude_deg",
        "beacon_longitude_deg",
        "beacon_altitude_m",
        "range_m",
        "range_sd_m",
    ),
)
_EVENT = ("IBI", ("validity_time_100us", "event_id", "event_count"))
_VTG = (
    "IBfff",
    ("validity_time_100us", "vtg_id", "true_course_deg", "magnetic_course_deg", "speed_over_ground_m_s"),
)

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
    24: (
        "turret_angles",
        "Ifff",
        ("validity_time_100us", "heading_bearing_drift_deg", "roll_deg", "elevation_pitch_deg"),
    ),
    25: ("vtg1", *_VTG),
    26: ("vtg2", *_VTG),
    27: ("logbook", "II32s", ("validity_time_100us", "log_id", "custom_text")),
}

BLOCK_TABLES = (NAVIGATION_BLOCKS, EXTENDED_NAVIGATION_BLOCKS, EXTERNAL_DATA_BLOCKS)
#: block name → (mask index 0/1/2, bit, fmt, names)
BLOCKS_BY_NAME = {
    spec[0]: (i, bit, spec[1], spec[2]) for i, table in enumerate(BLOCK_TABLES) for bit, spec in table.items()
}
BLOCK_SIZES = {name: struct.calcsize(">" + fmt) for name, (_, _, fmt, _) in BLOCKS_BY_NAME.items()}


def sum32(data) -> int:
    """The STDBIN checksum: the sum of the bytes, mod 2**32."""
    return sum(data) & 0xFFFFFFFF


# the navigation header after 'IX' | version (V2, V3, V4+), and the u16 / u32 fields of frames
HEADER_V2 = struct.Struct(">IIHII")
HEADER_V3 = struct.Struct(">IIIHII")
HEADER_V4 = struct.Struct(">IIIHHII")
U16 = struct.Struct(">H")
U32 = struct.Struct(">I")
