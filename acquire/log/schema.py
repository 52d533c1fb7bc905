"""The session log's message encodings (docs/architecture.md §4): what each MCAP message of a session holds.

Every message, whatever the channel:

- MCAP ``log_time`` = GPS ns of the host receive stamp, from the clock model;
- MCAP ``publish_time`` = the device's own time tag (GPS ns) when it has one, else ``log_time``;
- MCAP ``sequence`` = the per-channel counter modulo 2³² (the full 64-bit count is inside);
- inside the record: the counter, the host receive stamp (``time.monotonic_ns()``), the device
  time tag (or none) and the clock state at ``log_time`` (LOCKED / HOLDOVER / UNLOCKED: the flag
  saying whether ``log_time`` is trustworthy).

Two encodings:

**Raw** (``message_encoding = "mls.raw.v1"``, no schema; ``/ins/raw``, ``/lidar/raw``,
``/can/<name>``): a 28-byte little-endian header then the exact bytes received, unchanged::

    u8  version = 1
    u8  flags     bit0 clock LOCKED, bit1 clock HOLDOVER (neither: UNLOCKED),
                  bit2 device time tag present,
                  bit3 host time: stamped before any PPS fit, log_time is the host's system
                       clock, not GPS (UNLOCKED; written since issue 26, 0 in older files)
    u16 header_size = 28 (readers skip this many bytes: later versions may append fields)
    u64 sequence  per-channel counter, from 1
    i64 host_ns   host monotonic receive stamp
    i64 device_ns device time tag, GPS ns (0 when bit2 is clear)
    ... the received bytes (one read / one datagram / one frame)

The channel's metadata names the protocol (``protocol: nmea``) so the bytes can be decoded again
by the drivers' codecs at any time.

**JSON** (``message_encoding = "json"``, schema ``mls.Envelope`` in JSON Schema; every other
channel): ``{"seq": n, "host_ns": …, "device_ns": … | null, "clock": "LOCKED", "data": {…}}``
with NaN written as ``null``; a record stamped before any PPS fit also has ``"time_base":
"host"`` after ``"clock": "UNLOCKED"`` (absent: the clock model's GPS time; older files never
have it).

Backward compatible both ways: a reader of the older format ignores flag bit3 and the extra key
and sees an UNLOCKED record, as before; this reader reads an older file's records as GPS time.
The writer's pipeline carries the host-time case as the clock state
:data:`~acquire.timing.clock.HOST_TIME_STATE`, which only the encoders here turn into the marks.
"""

from __future__ import annotations

import enum
import json
import math
import struct
from dataclasses import dataclass
from typing import Any

from acquire.errors import AcquireError
from acquire.timing.clock import HOST_TIME_STATE

RAW_ENCODING = "mls.raw.v1"
JSON_ENCODING = "json"
RAW = "raw"
JSON = "json"

RAW_HEADER = struct.Struct("<BBHQqq")
RAW_VERSION = 1
FLAG_LOCKED = 0x01
FLAG_HOLDOVER = 0x02
FLAG_DEVICE_TIME = 0x04
FLAG_HOST_TIME = 0x08
HOST_TIME_BASE = "host"  # the JSON envelope's "time_base" of a host-time record

CLOCK_STATES = ("LOCKED", "HOLDOVER", "UNLOCKED")

# docs/architecture.md §4 channels; /can/<name> channels are raw as well
CHANNELS: dict[str, str] = {
    "/ins/raw": RAW,
    "/ins/nav": JSON,
    "/lidar/raw": RAW,
    "/pps": JSON,
    "/clock": JSON,
    "/latency": JSON,
    "/status": JSON,
    "/events": JSON,
}

ENVELOPE_SCHEMA_NAME = "mls.Envelope"
ENVELOPE_SCHEMA = json.dumps(
    {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": ENVELOPE_SCHEMA_NAME,
        "type": "object",
        "properties": {
            "seq": {"type": "integer", "description": "per-channel counter, from 1"},
            "host_ns": {"type": "integer", "description": "host monotonic receive stamp"},
            "device_ns": {"type": ["integer", "null"], "description": "device time tag, GPS ns"},
            "clock": {"enum": list(CLOCK_STATES), "description": "clock state at log_time"},
            "time_base": {
                "enum": [HOST_TIME_BASE],
                "description": "present when log_time is the host's clock (stamped before any PPS fit)",
            },
            "data": {"type": "object"},
        },
        "required": ["seq", "host_ns", "device_ns", "clock", "data"],
    }
).encode()


def channel_kind(topic: str) -> str:
    """``"raw"`` or ``"json"`` for a session channel; ValueError for a topic not in docs/architecture.md §4."""
    kind = CHANNELS.get(topic)
    if kind is not None:
        return kind
    name = topic[len("/can/") :] if topic.startswith("/can/") else ""
    if name and "/" not in name:
        return RAW
    raise ValueError(f"session channel {topic!r}: expected one of {', '.join(CHANNELS)} or /can/<name>")


def clock_flags(clock_state: str) -> int:
    if clock_state == HOST_TIME_STATE:
        return FLAG_HOST_TIME
    return FLAG_LOCKED if clock_state == "LOCKED" else FLAG_HOLDOVER if clock_state == "HOLDOVER" else 0


def raw_head(seq: int, host_ns: int, device_ns: int | None, clock_state: str) -> bytes:
    """The envelope header of a raw record (the received bytes follow it)."""
    flags = clock_flags(clock_state) | (FLAG_DEVICE_TIME if device_ns is not None else 0)
    return RAW_HEADER.pack(RAW_VERSION, flags, RAW_HEADER.size, seq, host_ns, device_ns or 0)


def _plain(obj: Any) -> Any:
    """JSON-safe copy: NaN/inf → None, tuples → lists, numpy scalars → Python, bytes → hex,
    enums → their value."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, (bytes, bytearray)):
        return bytes(obj).hex()
    if hasattr(obj, "item") and callable(obj.item):  # numpy scalar
        return _plain(obj.item())
    if isinstance(obj, enum.Enum):
        return _plain(obj.value)
    return obj


def dumps(obj: Any) -> bytes:
    """Compact JSON bytes; non-finite floats become null (never the non-standard NaN token)."""
    try:
        return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()
    except (ValueError, TypeError):
        return json.dumps(_plain(obj), separators=(",", ":"), allow_nan=False).encode()


def encode_json(seq: int, host_ns: int, device_ns: int | None, clock_state: str, data: dict) -> bytes:
    if clock_state == HOST_TIME_STATE:
        return dumps(
            {
                "seq": seq,
                "host_ns": host_ns,
                "device_ns": device_ns,
                "clock": "UNLOCKED",
                "time_base": HOST_TIME_BASE,
                "data": data,
            }
        )
    return dumps({"seq": seq, "host_ns": host_ns, "device_ns": device_ns, "clock": clock_state, "data": data})


@dataclass(frozen=True)
class Envelope:
    """A decoded session message."""

    topic: str
    seq: int
    host_ns: int
    device_ns: int | None
    clock: str  # LOCKED | HOLDOVER | UNLOCKED
    log_time_ns: int
    publish_time_ns: int
    payload: bytes | dict  # the exact received bytes (raw channels) or the JSON data
    host_time: bool = False  # log_time is the host's clock (stamped before any PPS fit)


class FormatError(AcquireError, ValueError):
    """A session message that does not follow this module's encodings."""


def decode(
    topic: str, message_encoding: str, log_time_ns: int, publish_time_ns: int, data: bytes
) -> Envelope:
    if message_encoding == RAW_ENCODING:
        if len(data) < RAW_HEADER.size:
            raise FormatError(f"{topic}: raw message of {len(data)} bytes, shorter than its header")
        version, flags, size, seq, host_ns, device_ns = RAW_HEADER.unpack_from(data)
        if version != RAW_VERSION or size < RAW_HEADER.size or size > len(data):
            raise FormatError(f"{topic}: raw header version {version}, size {size}: not mls.raw.v1")
        clock = "LOCKED" if flags & FLAG_LOCKED else "HOLDOVER" if flags & FLAG_HOLDOVER else "UNLOCKED"
        return Envelope(
            topic,
            seq,
            host_ns,
            device_ns if flags & FLAG_DEVICE_TIME else None,
            clock,
            log_time_ns,
            publish_time_ns,
            bytes(data[size:]),
            bool(flags & FLAG_HOST_TIME),
        )
    if message_encoding == JSON_ENCODING:
        try:
            obj = json.loads(data)
            return Envelope(
                topic,
                int(obj["seq"]),
                int(obj["host_ns"]),
                obj["device_ns"],
                str(obj["clock"]),
                log_time_ns,
                publish_time_ns,
                obj["data"],
                obj.get("time_base") == HOST_TIME_BASE,
            )
        except (ValueError, KeyError, TypeError) as e:
            raise FormatError(f"{topic}: JSON envelope unreadable ({e})") from None
    raise FormatError(f"{topic}: message encoding {message_encoding!r} is not a session encoding")
