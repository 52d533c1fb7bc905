"""Decoding recorded device files: raw streams, stamped NMEA logs, ZFP1 dumps, packet captures.

:class:`FileDecoder` is what ``mls decode`` (and a replay) iterates::

    fd = FileDecoder(path, "pcapng", payload="stdbin", port=8200)
    for rec in fd:          # StdbinFrame, NMEA sentence records, Profile, NavRecord (nav=True)...
        ...
    fd.stats                # the protocol decoder's DecoderStats (records, bytes, rejected by reason)

Formats:

- ``nmea``: a byte stream of sentences. Lines that start with an ISO 8601 UTC stamp followed by a
  space (``2014-08-01T00:00:00.814000Z $GPZDA,...``, as OpenRVDAS and many loggers write) have
  that stamp taken as the receive time: it becomes the record's ``host_ns`` (UTC ns since the
  Unix epoch on that scale) and the date hint of the nav assembler.
- ``stdbin``: a byte stream of STDBIN frames.
- ``zfp``: ZFP1 packets back to back (each packet's length follows from its header).
- ``pcapng`` (or classic pcap): the UDP payloads of the capture (optionally only ``port``),
  each decoded with the ``payload`` protocol (``stdbin``, ``nmea``, ``zfp``, ``pps``), with the
  capture timestamp as ``host_ns`` (UTC ns since the Unix epoch).

With ``nav=True`` INS formats give canonical :class:`~drivers.hydrins.nav.NavRecord` s instead
of native records. ``date`` (``'YYYY-MM-DD'``) dates NMEA/STDBIN time tags when the file has no
ZDA / system date and no stamped lines; without it such records keep ``gps_ns=None``.

Files are streamed, never read whole: raw streams in chunks fed to the sans-I/O decoders (ZFP1
dumps through :class:`ZfpPacketSplitter`), NMEA logs line by line (a line cut at
:data:`MAX_LINE` bytes), captures block by block; a file of any size decodes in bounded memory.
:meth:`FileDecoder.no_record_message` says what a file that gave no record held instead.

:func:`record_to_dict` (with :func:`json_default` for ``json.dumps``) turns a record into JSON,
:func:`record_type` gives its ``type`` alone (cheaply); :func:`time_sample` gives a time-tagged
record's (receive stamp, device time of day) pair.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import math
import re
import stat
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from drivers.base import DecoderStats, DriverError
from drivers.capture.pcapng import CaptureReader, udp_datagrams
from drivers.hydrins.nmea_decode import NmeaDecoder, NmeaNavAssembler
from drivers.hydrins.stdbin_decode import StdbinDecoder, StdbinNavDecoder
from drivers.pps import decode_pps_datagram
from drivers.zf.assembler import ProfileAssembler
from drivers.zf.codec import Profile
from drivers.zf.zfp1 import CRC_SIZE, HEADER_SIZE, MAGIC, POINT_SIZE

FORMATS = ("nmea", "stdbin", "zfp", "pcapng")
PAYLOADS = ("stdbin", "nmea", "zfp", "pps")
CHUNK = 65536  # raw STDBIN streams
ZFP_CHUNK = 1 << 20  # ZFP1 dumps (a packet is at most 393 254 bytes)
MAX_LINE = 65536  # NMEA logs: a longer "line" (binary garbage) is fed in pieces of this size

_STAMP = re.compile(rb"^(\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}(?:\.\d{1,9})?)Z? ")
_EPOCH = _dt.datetime(1970, 1, 1)


def split_stamped_line(line: bytes) -> tuple[int | None, bytes]:
    """``b'2014-08-01T00:00:00.814000Z $GPZDA...'`` → (UTC ns since the Unix epoch, payload)."""
    m = _STAMP.match(line)
    if m is None:
        return None, line
    text = m.group(1).decode("ascii")
    whole, _, frac = text.partition(".")
    try:
        t = _dt.datetime.strptime(whole, "%Y-%m-%dT%H:%M:%S")
    except ValueError:
        return None, line
    delta = t - _EPOCH
    ns = (delta.days * 86_400 + delta.seconds) * 1_000_000_000 + int((frac + "000000000")[:9] or 0)
    return ns, line[m.end() :]


class ZfpPacketSplitter:
    """Sans-I/O: bytes of back-to-back ZFP1 packets, in pieces of any size → whole packets.

    Bytes between packets are skipped and counted in ``stats.skipped_bytes``; :meth:`flush`
    counts a packet cut short by the end of the file in ``stats.rejected['truncated']``. At most
    one packet (and a chunk) is buffered."""

    def __init__(self, stats: DecoderStats) -> None:
        self.stats = stats
        self._buf = b""

    def feed(self, data: bytes) -> list[bytes]:
        buf = self._buf + data if self._buf else bytes(data)
        out: list[bytes] = []
        pos, n = 0, len(buf)
        while True:
            start = buf.find(MAGIC, pos)
            if start < 0:  # keep what may be the start of a magic
                keep = max(pos, n - len(MAGIC) + 1)
                self.stats.skipped_bytes += keep - pos
                pos = keep
                break
            self.stats.skipped_bytes += start - pos
            pos = start
            if n - start < HEADER_SIZE:
                break
            size = HEADER_SIZE + POINT_SIZE * struct.unpack_from("<H", buf, start + 36)[0] + CRC_SIZE
            if start + size > n:
                break
            out.append(buf[start : start + size])
            pos = start + size
        self._buf = buf[pos:]
        return out

    def flush(self) -> None:
        """End of the stream: what is left is skipped (a packet cut short counted as such)."""
        rest, self._buf = self._buf, b""
        self.stats.skipped_bytes += len(rest)
        if len(rest) >= HEADER_SIZE and rest.startswith(MAGIC):
            self.stats.rejected["truncated"] += 1


def _date_hint(date: str | None) -> int | None:
    if date is None:
        return None
    try:
        d = _dt.date.fromisoformat(date)
    except ValueError as exc:
        raise DriverError(f"date {date!r}: expected YYYY-MM-DD") from exc
    return (d - _dt.date(1970, 1, 1)).days * 86_400_000_000_000 + 43_200_000_000_000  # noon


def _check_regular_file(path: Path) -> None:
    """DriverError naming why ``path`` cannot be decoded: missing, a directory, or a FIFO,
    socket or device (not a regular file: no size, and a read may block forever)."""
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        raise DriverError(f"{path}: no such file") from None
    except OSError as exc:
        raise DriverError(f"{path}: {exc.strerror}") from None
    if stat.S_ISDIR(mode):
        raise DriverError(f"{path}: is a directory, expected a recorded file")
    if not stat.S_ISREG(mode):
        raise DriverError(f"{path}: not a regular file ({_file_kind(mode)}), expected a recorded file")


def _file_kind(mode: int) -> str:
    if stat.S_ISFIFO(mode):
        return "a FIFO"
    if stat.S_ISSOCK(mode):
        return "a socket"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    return "a special file"


class FileDecoder:
    """Iterate the records of a recorded file (see the module docstring)."""

    def __init__(
        self,
        path: str | Path,
        fmt: str,
        payload: str = "stdbin",
        port: int | None = None,
        nav: bool = False,
        date: str | None = None,
    ) -> None:
        if fmt not in FORMATS:
            raise DriverError(f"format {fmt!r}: expected one of {', '.join(FORMATS)}")
        if fmt == "pcapng" and payload not in PAYLOADS:
            raise DriverError(f"payload {payload!r}: expected one of {', '.join(PAYLOADS)}")
        self.path = Path(path)
        _check_regular_file(self.path)
        self.fmt, self.payload, self.port, self.nav = fmt, payload, port, nav
        self.date_hint_ns = _date_hint(date)
        self.size = self.path.stat().st_size
        self.bytes_done = 0  # progress, in file bytes
        self.capture_stats: DecoderStats | None = None  # packets read from a capture
        self.udp_stats: DecoderStats | None = None  # UDP datagrams kept, others by reason
        protocol = payload if fmt == "pcapng" else fmt
        self.protocol = protocol
        self.decoder: (
            NmeaNavAssembler
            | NmeaDecoder
            | StdbinNavDecoder
            | StdbinDecoder
            | ProfileAssembler
            | _PpsDatagrams
        )
        if protocol == "nmea":
            self.decoder = NmeaNavAssembler(utc_clock=None) if nav else NmeaDecoder()
        elif protocol == "stdbin":
            self.decoder = StdbinNavDecoder(utc_clock=None) if nav else StdbinDecoder()
        elif protocol == "zfp":
            self.decoder = ProfileAssembler()
        else:
            self.decoder = _PpsDatagrams()
        self.stats: DecoderStats = self.decoder.stats

    def _feed(self, data: bytes, host_ns: int | None, hint: int | None) -> list:
        if isinstance(self.decoder, (NmeaNavAssembler, StdbinNavDecoder)):
            return self.decoder.feed(data, host_ns, hint if hint is not None else self.date_hint_ns)
        return self.decoder.feed(data, host_ns)

    def __iter__(self) -> Iterator:
        if self.fmt == "pcapng":
            yield from self._pcap()
        elif self.fmt == "zfp":
            splitter = ZfpPacketSplitter(self.stats)
            with self.path.open("rb") as f:
                while chunk := f.read(ZFP_CHUNK):
                    for packet in splitter.feed(chunk):
                        yield from self.decoder.feed(packet)
                    self.bytes_done += len(chunk)
            splitter.flush()
        elif self.fmt == "nmea":
            yield from self._nmea()
        else:
            with self.path.open("rb") as f:
                while chunk := f.read(CHUNK):
                    yield from self._feed(chunk, None, None)
                    self.bytes_done += len(chunk)
        yield from self.decoder.flush()

    def _nmea(self) -> Iterator:
        with self.path.open("rb") as f:
            while line := f.readline(MAX_LINE):
                stamp, payload = split_stamped_line(line)
                self.bytes_done += len(line)
                yield from self._feed(payload, stamp, stamp)

    def _pcap(self) -> Iterator:
        reader = CaptureReader(self.path)
        self.capture_stats, self.udp_stats = reader.stats, DecoderStats()
        for dg in udp_datagrams(reader, self.port, self.udp_stats):
            yield from self._feed(
                dg.payload, dg.timestamp_ns, dg.timestamp_ns if self.date_hint_ns is None else None
            )
            self.bytes_done = reader.offset
        self.bytes_done = self.size

    def no_record_message(self) -> str:
        """For a file that gave no record: the file, its size and what was skipped instead (the
        capture's packets and why they were not decoded, the decoder's rejects and skipped
        bytes)."""
        what = []
        if self.capture_stats is not None and self.udp_stats is not None:
            port = "" if self.port is None else f" to or from port {self.port}"
            what.append(f"{self.capture_stats.records} packets, {self.udp_stats.records} UDP datagrams{port}")
            skipped = {**self.capture_stats.rejected, **self.udp_stats.events}
            if skipped:
                what.append("skipped " + ", ".join(f"{k}: {v}" for k, v in sorted(skipped.items())))
        st = self.stats
        if st.skipped_bytes:
            what.append(f"{st.skipped_bytes} bytes skipped")
        if st.rejected:
            what.append("rejected " + ", ".join(f"{k}: {v}" for k, v in sorted(st.rejected.items())))
        if st.events:
            what.append(", ".join(f"{k}: {v}" for k, v in sorted(st.events.items())))
        if not self.size:
            what = ["the file is empty"]
        kind = f"{self.protocol}{' navigation' if self.nav else ''}"
        return f"{self.path}: no valid {kind} record in {self.size} bytes ({'; '.join(what) or 'nothing decoded'})"


class _PpsDatagrams:
    """PPS emulator datagrams → PpsEdge records (for captures of the ``udp`` PPS source)."""

    def __init__(self) -> None:
        self.stats = DecoderStats()

    def feed(self, data: bytes, host_ns: int | None = None) -> list:
        self.stats.bytes_in += len(data)
        try:
            edge = decode_pps_datagram(data)
        except DriverError:
            self.stats.rejected["bad_datagram"] += 1
            return []
        self.stats.records += 1
        return [edge]

    def flush(self) -> list:
        return []


def record_to_dict(rec: Any) -> dict[str, Any]:
    """Any record of :mod:`drivers` → a JSON-ready dict with a ``type`` key (NaN → None)."""
    if hasattr(rec, "to_dict"):
        out = rec.to_dict()
        out.setdefault("type", "nav" if type(rec).__name__ == "NavRecord" else type(rec).__name__)
        out.setdefault("host_ns", getattr(rec, "host_ns", None))
        return out
    if isinstance(rec, Profile):
        finite = np.isfinite(rec.range_m)
        return {
            "type": "profile",
            "profile_counter": rec.profile_counter,
            "n_points": rec.n_points,
            "n_returns": int(finite.sum()),
            "complete": rec.complete,
            "packets_received": rec.packets_received,
            "packet_count": rec.packet_count,
            "t0_gps_ns": int(rec.gps_ns[0]) if rec.n_points else None,
            "t1_gps_ns": int(rec.gps_ns[-1]) if rec.n_points else None,
            "scan_angle0_deg": float(np.degrees(rec.scan_angle_rad[0])) if rec.n_points else None,
            "scan_angle1_deg": float(np.degrees(rec.scan_angle_rad[-1])) if rec.n_points else None,
            "range_min_m": float(rec.range_m[finite].min()) if finite.any() else None,
            "range_max_m": float(rec.range_m[finite].max()) if finite.any() else None,
            "pps_locked": rec.pps_locked,
            "time_valid": rec.time_valid,
            "host_ns": rec.host_ns,
        }
    out = {"type": getattr(rec, "kind", None) or type(rec).__name__}
    for f in dataclasses.fields(rec):
        v = getattr(rec, f.name)
        out[f.name] = None if isinstance(v, float) and math.isnan(v) else v
    return out


_TYPES = {"StdbinFrame": "navigation", "StdbinAnswer": "answer", "NavRecord": "nav"}


def record_type(rec: Any) -> str:
    """``record_to_dict(rec)["type"]`` without building the dict (``mls decode``'s counts)."""
    name = type(rec).__name__
    kind = _TYPES.get(name)
    if kind is not None:
        return kind
    if isinstance(rec, Profile):
        return "profile"
    if hasattr(rec, "to_dict"):
        return str(record_to_dict(rec)["type"])
    return getattr(rec, "kind", None) or name


def time_sample(rec: Any) -> tuple[int, int] | None:
    """(receive stamp ns, device time-of-day ns) of a time-tagged record, else None (the
    samples of ``mls decode --timing``, for :func:`drivers.timing.fit_clock`)."""
    host = getattr(rec, "host_ns", None)
    if host is None:
        return None
    name = type(rec).__name__
    if name == "StdbinFrame":
        return host, rec.validity_time_100us * 100_000
    if name == "NavRecord" and rec.time_of_day_ns is not None:
        return host, rec.time_of_day_ns
    if name in ("PixseTime", "Zda") and rec.time_of_day_ns is not None:
        return host, rec.time_of_day_ns
    return None


def json_default(o: Any) -> Any:
    """``json.dumps(record_to_dict(rec), default=json_default)``: numpy scalars as numbers,
    bytes as hex, tuples and sets as lists, anything else as its ``str``."""
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, bytes):
        return o.hex()
    if isinstance(o, (tuple, set)):
        return list(o)
    return str(o)
