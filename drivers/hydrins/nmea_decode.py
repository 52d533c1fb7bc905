"""Hydrins NMEA decoding, sans-I/O (docs/architecture.md §5): bytes → sentence records → one NavRecord per epoch.

1. :class:`NmeaDecoder` — bytes → one typed record per sentence
   (:mod:`drivers.hydrins.nmea_sentences`). A sentence starts at ``$`` or ``!``, ends at CR/LF,
   and must carry ``*hh`` (XOR of the bytes between the start character and ``*``); otherwise it
   is rejected and counted (``missing_checksum``, ``bad_checksum``, ``bad_field``,
   ``too_long``). Bytes outside sentences are skipped and counted. Every valid sentence becomes
   a record: a typed one where the sentence has one, a generic :class:`Sentence` for anything
   else — a valid sentence is never thrown away. ``decoder.counts`` counts sentences by id
   (``'GPGGA'``, ``'PIXSE,ATITUD'``, ``'PSXN'``).

2. :class:`NmeaNavAssembler` — sentences → one canonical :class:`~drivers.hydrins.nav.NavRecord`
   per epoch (canonical signs, radians, NED). An epoch closes at ``$PIXSE,HT_STS`` (the last
   sentence of the PHINS block), when a sentence id repeats (the next epoch has begun), or at
   :meth:`flush`. ``TIME__`` (or GGA/ZDA time when there is no ``TIME__``) gives the time of
   day; the date comes from the last ZDA (``date_source='zda'``) or else from the host's UTC
   date (``'host'``), nearest day within ±12 h. Once the stream has carried ``TIME__``, an
   epoch that lost its own (a line dropping bytes) is rejected
   (``rejected['epoch_without_time']``) rather than dated by a ZDA or GGA of another instant.
   ``gps_ns`` stays None when the INS says it is not on UTC (system status 2 bit 9 clear),
   because ``TIME__`` is then the INS system time. UTC → GPS uses the leap-second table, or the
   GPS − UTC the INS announces (``$PMLS,GPSUTC``, kept in ``gps_minus_utc_s``): its tags are then
   undone with its own count. A ZDA date more than 9.8 years from the reference (the feed's
   ``utc_hint_ns`` or the host's clock) is a GPS week rollover, moved by whole 1024-week eras
   (``events['gps_week_rollover']``).
"""

from __future__ import annotations

import math
import time
from collections import Counter
from collections.abc import Callable
from functools import reduce
from operator import xor
from typing import Any

from calib.core.frames import attitude_from_ixblue
from drivers.base import DecoderStats
from drivers.hydrins.nav import NavRecord, wrap_heading_rad, wrap_lon_deg
from drivers.hydrins.nmea_sentences import (
    PIXSE_PARSERS,
    PMLS_PARSERS,
    STANDARD_PARSERS,
    Gga,
    GpsUtcOffset,
    Hdt,
    PixseAlgsts,
    PixseAtitud,
    PixseHeave,
    PixseHtSts,
    PixsePositi,
    PixseSpeed,
    PixseStatus,
    PixseStdhrp,
    PixseStdpos,
    PixseStdspd,
    PixseTime,
    Rmc,
    Sentence,
    Zda,
)
from drivers.hydrins.timeofday import DAY_NS, device_date_ns, resolve_gps_ns

MAX_LINE = 1024  # NMEA says 82 characters; some receivers (PSTI) send ~400
_PROPRIETARY = {"PIXSE": PIXSE_PARSERS, "PMLS": PMLS_PARSERS}

# ---------------------------------------------------------------------------------------------
# Sentence decoder.
# ---------------------------------------------------------------------------------------------


class NmeaDecoder:
    """Bytes → sentence records (see the module docstring). Never raises on bad bytes."""

    def __init__(self, max_line: int = MAX_LINE) -> None:
        self.max_line = max_line
        self.stats = DecoderStats()
        self.counts: Counter[str] = Counter()
        self._buf = b""
        self._buf_ns: int | None = None

    def feed(self, data: bytes, host_ns: int | None = None) -> list:
        """Decode what ``data`` completes; a sentence's ``host_ns`` is the stamp of the chunk that
        brought its start (``$`` or ``!``: bytes of line noise before it do not date it)."""
        self.stats.bytes_in += len(data)
        first_ns = self._buf_ns if self._buf and self._buf_ns is not None else host_ns
        buf = self._buf + bytes(data) if self._buf else bytes(data)
        if b"\r" in buf:
            buf = buf.replace(b"\r", b"\n")
        lines = buf.split(b"\n")
        rest = lines.pop()
        if len(rest) > self.max_line:
            start = max(rest.rfind(b"$"), rest.rfind(b"!"))
            keep = rest[start:] if start >= 0 and len(rest) - start <= self.max_line else b""
            dropped = len(rest) - len(keep)
            self.stats.skipped_bytes += dropped
            if start >= 0 and not keep:
                self.stats.rejected["too_long"] += 1
            rest = keep
        self._buf = rest
        # the stamp of the buffered start; None while the buffer holds no start (noise only)
        self._buf_ns = (host_ns if lines else first_ns) if b"$" in rest or b"!" in rest else None
        out = []
        for i, line in enumerate(lines):
            if line:
                rec = self._line(line, host_ns if i else first_ns)
                if rec is not None:
                    out.append(rec)
        self.stats.records += len(out)
        return out

    def flush(self) -> list:
        """Decode a last sentence that had no line terminator."""
        rest, self._buf = self._buf, b""
        if not rest:
            return []
        rec = self._line(rest, self._buf_ns)
        if rec is None:
            return []
        self.stats.records += 1
        return [rec]

    def _line(self, line: bytes, host_ns: int | None):
        start = max(line.rfind(b"$"), line.rfind(b"!"))
        if start < 0:
            if line.strip():
                self.stats.skipped_bytes += len(line)
            return None
        if start:
            self.stats.skipped_bytes += len(line[:start].strip())
        if len(line) - start > self.max_line:
            self.stats.rejected["too_long"] += 1
            return None
        star = line.rfind(b"*", start)
        if star < 0:
            self.stats.rejected["missing_checksum"] += 1
            return None
        body = line[start + 1 : star]
        given = line[star + 1 : star + 3]
        try:
            ok = len(given) == 2 and int(given, 16) == reduce(xor, body, 0)
        except ValueError:
            ok = False
        if not ok:
            self.stats.rejected["bad_checksum"] += 1
            return None
        text = body.decode("latin-1")
        fields = text.split(",")
        head = fields[0]
        try:
            if head in _PROPRIETARY and len(fields) > 1:
                sid = head + "," + fields[1]
                parser = _PROPRIETARY[head].get(fields[1])
                rec = parser("", fields, host_ns) if parser else Sentence("", sid, fields, host_ns)
            elif head[:1] == "P" or len(head) != 5:
                sid = head
                rec = Sentence("", head, fields, host_ns)
            else:
                sid = head
                parser = STANDARD_PARSERS.get(head[2:])
                if parser:
                    rec = parser(head[:2], fields, host_ns)
                else:
                    rec = Sentence(head[:2], head[2:], fields, host_ns)
        except (ValueError, IndexError):
            self.stats.rejected["bad_field"] += 1
            return None
        self.counts[sid] += 1
        return rec


# ---------------------------------------------------------------------------------------------
# Epoch assembler → canonical NavRecord.
# ---------------------------------------------------------------------------------------------


class NmeaNavAssembler:
    """Sentences of one epoch → one canonical :class:`NavRecord` (see the module docstring).

    ``utc_clock`` gives the host's UTC time in ns since the Unix epoch (the date of last resort);
    pass None to never take the date from the host. A ``utc_hint_ns`` given to :meth:`feed`
    (e.g. the receive time written in a log file) takes precedence over the clock.
    """

    def __init__(self, utc_clock: Callable[[], int] | None = time.time_ns) -> None:
        self.decoder = NmeaDecoder()
        self.utc_clock = utc_clock
        self._epoch: dict[type, Any] = {}  # sentence record type → the epoch's record of it
        self._zda_utc_ns: int | None = None
        self._zda_host_ns: int | None = None
        self._hint: int | None = None
        self._time_sentences = False  # the stream carries TIME__: every epoch must have its own
        self.gps_minus_utc_s: int | None = None  # announced by the INS ($PMLS,GPSUTC), else None

    @property
    def stats(self) -> DecoderStats:
        return self.decoder.stats

    def feed(
        self, data: bytes, host_ns: int | None = None, utc_hint_ns: int | None = None
    ) -> list[NavRecord]:
        self._hint = utc_hint_ns
        out: list[NavRecord] = []
        for rec in self.decoder.feed(data, host_ns):
            out.extend(self.push(rec))
        return out

    def push(self, rec) -> list[NavRecord]:
        """Add one sentence record; returns the epoch it closed, if any."""
        out: list[NavRecord] = []
        if (
            isinstance(rec, Zda)
            and rec.time_of_day_ns is not None
            and rec.day is not None
            and rec.month is not None
            and rec.year is not None
        ):
            try:
                midnight, eras = device_date_ns(rec.year, rec.month, rec.day, self._reference())
                self._zda_utc_ns = midnight + rec.time_of_day_ns
                self._zda_host_ns = rec.host_ns
                if eras:
                    self.decoder.stats.events["gps_week_rollover"] += 1
            except ValueError:  # impossible date in a checksum-valid sentence
                self.decoder.stats.rejected["bad_field"] += 1
        if isinstance(rec, Sentence):
            return out
        kind = type(rec)
        if kind is PixseTime:
            self._time_sentences = True
        elif kind is GpsUtcOffset:  # not part of an epoch
            if rec.gps_minus_utc_s is not None:
                self.gps_minus_utc_s = rec.gps_minus_utc_s
            return out
        if kind in self._epoch:
            out.extend(self._close())
        self._epoch[kind] = rec
        if kind is PixseHtSts:  # the last sentence of the PHINS standard block
            out.extend(self._close())
        return out

    def flush(self) -> list[NavRecord]:
        out = []
        for rec in self.decoder.flush():
            out.extend(self.push(rec))
        out.extend(self._close())
        return out

    def _close(self) -> list[NavRecord]:
        epoch, self._epoch = self._epoch, {}
        if not epoch:
            return []
        nav = NavRecord("nmea")
        # received with the epoch's own sentences: a ZDA (sent once a second after the PPS edge,
        # between two blocks) that happens to precede the block does not date its arrival
        own = [r for k, r in epoch.items() if k is not Zda] or list(epoch.values())
        hosts = [r.host_ns for r in own if r.host_ns is not None]
        nav.host_ns = min(hosts) if hosts else None
        for kind, r in epoch.items():  # in arrival order (a GGA position only without POSITI)
            put = _EPOCH_FIELDS.get(kind)
            if put is not None:
                put(nav, r)
        time_rec = epoch.get(PixseTime)
        tod = None if time_rec is None else time_rec.time_of_day_ns
        if (
            tod is None
            and self._time_sentences
            and (Hdt in epoch or PixseAtitud in epoch or PixsePositi in epoch)
        ):
            # the stream has TIME__ but this epoch lost its own (bytes lost on the line): a ZDA
            # or GGA next to it belongs to another instant, so its time is unknown
            self.decoder.stats.rejected["epoch_without_time"] += 1
            return []
        if tod is None:
            tod = _fix_time_of_day(epoch)
        nav.time_of_day_ns = tod
        if tod is not None and nav.utc_detected is not False:
            self._resolve(nav, tod)
        return [nav]

    def _resolve(self, nav: NavRecord, tod: int) -> None:
        zda_utc_ns = self._zda_utc_ns
        if zda_utc_ns is not None and (  # a fresh ZDA
            nav.host_ns is None
            or self._zda_host_ns is None
            or abs(nav.host_ns - self._zda_host_ns) < DAY_NS // 2
        ):
            nav.gps_ns, nav.date_source = resolve_gps_ns(tod, zda_utc_ns, self.gps_minus_utc_s), "zda"
            return
        hint = self._reference()
        if hint is not None:
            nav.gps_ns, nav.date_source = resolve_gps_ns(tod, hint, self.gps_minus_utc_s), "host"

    def _reference(self) -> int | None:
        """The host's UTC ns: the feed's hint, else the clock, else None."""
        return self._hint if self._hint is not None else (self.utc_clock() if self.utc_clock else None)


# -- the fields of a NavRecord each sentence of an epoch gives (records keyed by their exact type:
#    the epoch holds one record per sentence type)


def _put_hdt(nav: NavRecord, r: Hdt) -> None:
    nav.heading_rad = wrap_heading_rad(math.radians(r.heading_deg))


def _put_atitud(nav: NavRecord, r: PixseAtitud) -> None:
    roll, pitch, _ = attitude_from_ixblue(math.radians(r.roll_deg), math.radians(r.pitch_deg), 0.0)
    nav.roll_rad, nav.pitch_rad = float(roll), float(pitch)


def _put_positi(nav: NavRecord, r: PixsePositi) -> None:
    nav.lat_deg, nav.lon_deg, nav.height_m = r.lat_deg, wrap_lon_deg(r.lon_deg), r.altitude_m


def _put_speed(nav: NavRecord, r: PixseSpeed) -> None:
    nav.v_north_m_s, nav.v_east_m_s, nav.v_down_m_s = r.north_m_s, r.east_m_s, -r.up_m_s


def _put_heave(nav: NavRecord, r: PixseHeave) -> None:
    nav.surge_m, nav.sway_m, nav.heave_m = r.surge_m, -r.sway_m, -r.heave_m


def _put_stdhrp(nav: NavRecord, r: PixseStdhrp) -> None:
    nav.sigma_heading_rad = math.radians(r.heading_deg)
    nav.sigma_roll_rad = math.radians(r.roll_deg)
    nav.sigma_pitch_rad = math.radians(r.pitch_deg)


def _put_stdpos(nav: NavRecord, r: PixseStdpos) -> None:
    nav.sigma_north_m, nav.sigma_east_m, nav.sigma_down_m = r.north_m, r.east_m, r.altitude_m


def _put_stdspd(nav: NavRecord, r: PixseStdspd) -> None:
    nav.sigma_v_north_m_s, nav.sigma_v_east_m_s, nav.sigma_v_down_m_s = r.north_m_s, r.east_m_s, r.up_m_s


def _put_algsts(nav: NavRecord, r: PixseAlgsts) -> None:
    if r.status1 is not None and r.status2 is not None:
        nav.algorithm_status = (r.status1, r.status2)


def _put_status(nav: NavRecord, r: PixseStatus) -> None:
    if r.status1 is not None and r.status2 is not None:
        nav.system_status = (r.status1, r.status2)


def _put_htsts(nav: NavRecord, r: PixseHtSts) -> None:
    nav.user_status = r.status


def _put_gga(nav: NavRecord, r: Gga) -> None:
    """GGA's position, only when the epoch has none yet (POSITI, when before it, wins)."""
    if math.isnan(nav.lat_deg):
        nav.lat_deg, nav.lon_deg = r.lat_deg, r.lon_deg
        if not math.isnan(r.geoid_separation_m):
            nav.height_m, nav.height_ref = r.altitude_msl_m + r.geoid_separation_m, "ellipsoid"
        elif not math.isnan(r.altitude_msl_m):
            nav.height_m, nav.height_ref = r.altitude_msl_m, "geoid"


_EPOCH_FIELDS: dict[type, Callable[[NavRecord, Any], None]] = {
    Hdt: _put_hdt,
    PixseAtitud: _put_atitud,
    PixsePositi: _put_positi,
    PixseSpeed: _put_speed,
    PixseHeave: _put_heave,
    PixseStdhrp: _put_stdhrp,
    PixseStdpos: _put_stdpos,
    PixseStdspd: _put_stdspd,
    PixseAlgsts: _put_algsts,
    PixseStatus: _put_status,
    PixseHtSts: _put_htsts,
    Gga: _put_gga,
}


def _fix_time_of_day(epoch: dict[type, Any]) -> int | None:
    """An epoch's time of day without TIME__: its GGA's, else its ZDA's, else its RMC's."""
    for cls in (Gga, Zda, Rmc):
        r = epoch.get(cls)
        if r is not None and r.time_of_day_ns is not None:
            return r.time_of_day_ns
    return None
