"""iXblue STDBIN encoders for the emulators: frames, answers and canonical NavRecords → bytes.

:func:`encode_frame` (a StdbinFrame → bytes, masks derived from the blocks present),
:func:`encode_answer`, :func:`frame_from_nav` and :func:`encode_nav` (canonical NavRecord →
frame).
"""

from __future__ import annotations

import math
import struct
from typing import Any

from calib.core.frames import attitude_to_ixblue, gps_ns_to_utc_fields
from drivers.base import DriverError
from drivers.hydrins.nav import NavRecord
from drivers.hydrins.stdbin_format import (
    ANSWER_HEADER_SIZE,
    BLOCK_SIZES,
    BLOCK_TABLES,
    BLOCKS_BY_NAME,
    CHECKSUM_SIZE,
    HEADER_SIZES,
    HEADER_V2,
    HEADER_V3,
    HEADER_V4,
    MAX_TELEGRAM,
    NS_PER_100US,
    U16,
    U32,
    sum32,
)
from drivers.hydrins.stdbin_records import NAN, StdbinFrame


def encode_frame(frame: StdbinFrame) -> bytes:
    """A :class:`StdbinFrame` → wire bytes. Masks come from the blocks present (the frame's own
    mask fields are ignored); every field of each block must be given.

    Raises :class:`DriverError` naming the block/field for an unknown block, a missing field or
    a block that the version cannot carry.
    """
    version = frame.protocol_version
    if version not in HEADER_SIZES:
        raise DriverError(f"STDBIN version {version!r}: expected 2, 3, 4 or 5")
    masks = _block_masks(frame, version)
    parts, sizes = _packed_blocks(frame, masks)
    header_size = HEADER_SIZES[version]
    size = header_size + sum(sizes) + CHECKSUM_SIZE
    if size > MAX_TELEGRAM:
        raise DriverError(f"STDBIN telegram of {size} bytes exceeds {MAX_TELEGRAM}")
    validity, counter = frame.validity_time_100us & 0xFFFFFFFF, frame.counter & 0xFFFFFFFF
    if version == 2:
        header = b"IX\x02" + HEADER_V2.pack(masks[0], masks[2], size, validity, counter)
    elif version == 3:
        header = b"IX\x03" + HEADER_V3.pack(masks[0], masks[1], masks[2], size, validity, counter)
    else:
        header = bytes((0x49, 0x58, version)) + HEADER_V4.pack(
            masks[0], masks[1], masks[2], sizes[0] + sizes[1], size, validity, counter
        )
    body = header + b"".join(parts)
    return body + U32.pack(sum32(body))


def _block_masks(frame: StdbinFrame, version: int) -> list[int]:
    """The navigation, extended navigation and external data masks of the frame's blocks
    (:class:`DriverError` for an unknown block or one ``version`` cannot carry)."""
    masks = [0, 0, 0]
    for name in frame.blocks:
        spec = BLOCKS_BY_NAME.get(name)
        if spec is None:
            raise DriverError(f"STDBIN block {name!r} is unknown; known: {sorted(BLOCKS_BY_NAME)}")
        if spec[0] == 1 and version < 3:
            raise DriverError(
                f"STDBIN block {name!r} (extended navigation) needs version >= 3, got {version}"
            )
        masks[spec[0]] |= 1 << spec[1]
    return masks


def _packed_blocks(frame: StdbinFrame, masks: list[int]) -> tuple[list[bytes], list[int]]:
    """The blocks the masks name, packed in wire order, and the bytes of each mask's blocks
    (:class:`DriverError` naming the block for a missing or unpackable field)."""
    parts: list[bytes] = []
    sizes = [0, 0, 0]
    for index, table in enumerate(BLOCK_TABLES):
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
    return parts, sizes


def encode_answer(payload: bytes, version: int = 5) -> bytes:
    if not 3 <= version <= 5:
        raise DriverError(f"STDBIN answer version {version!r}: expected 3, 4 or 5")
    size = ANSWER_HEADER_SIZE + len(payload) + CHECKSUM_SIZE
    body = b"AN" + bytes((version,)) + U16.pack(size) + payload
    return body + U32.pack(sum32(body))


def frame_from_nav(
    nav: NavRecord, version: int = 3, counter: int = 0, gps_minus_utc_s: int | None = None
) -> StdbinFrame:
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
    blocks["speed_geographic_frame"] = {
        "north_m_s": nav.v_north_m_s,
        "east_m_s": nav.v_east_m_s,
        "up_m_s": -nav.v_down_m_s,
    }
    blocks["speed_geographic_frame_deviation"] = {
        "north_sd_m_s": nav.sigma_v_north_m_s,
        "east_sd_m_s": nav.sigma_v_east_m_s,
        "up_sd_m_s": nav.sigma_v_down_m_s,
    }
    if nav.gps_ns is not None:
        utc, tod = gps_ns_to_utc_fields(nav.gps_ns, gps_minus_utc_s)
        blocks["system_date"] = {"day": utc.day, "month": utc.month, "year": utc.year}
    else:
        tod = nav.time_of_day_ns or 0
    if nav.algorithm_status is not None:
        words = (tuple(nav.algorithm_status) + (0, 0, 0, 0))[:4]
        blocks["ins_algorithm_status"] = dict(
            zip(("status1", "status2", "status3", "status4"), words, strict=True)
        )
    if nav.system_status is not None:
        words = (tuple(nav.system_status) + (0, 0, 0))[:3]
        blocks["ins_system_status"] = dict(zip(("status1", "status2", "status3"), words, strict=True))
    if nav.user_status is not None:
        blocks["ins_user_status"] = {"status": nav.user_status}
    validity = tod // NS_PER_100US
    if nav.gps_ns is not None:
        blocks["utc"] = {"validity_time_100us": validity, "source": 0}
    return StdbinFrame(protocol_version=version, counter=counter, validity_time_100us=validity, blocks=blocks)


def encode_nav(
    nav: NavRecord, version: int = 3, counter: int = 0, gps_minus_utc_s: int | None = None
) -> bytes:
    """Canonical NavRecord → one STDBIN navigation frame (UTC tags made with
    ``gps_minus_utc_s`` instead of the leap-second table's count when given)."""
    return encode_frame(frame_from_nav(nav, version, counter, gps_minus_utc_s))
