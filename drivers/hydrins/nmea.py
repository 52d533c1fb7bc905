"""Hydrins NMEA: the "PHINS standard" block and standard sentences, sans-I/O (DESIGN §5).

Three layers:

1. :class:`NmeaDecoder` — bytes → one typed record per sentence. A sentence starts at ``$`` or
   ``!``, ends at CR/LF, and must carry ``*hh`` (XOR of the bytes between the start character
   and ``*``); otherwise it is rejected and counted (``missing_checksum``, ``bad_checksum``,
   ``bad_field``, ``too_long``). Bytes outside sentences are skipped and counted. Every valid
   sentence becomes a record: a typed one for ``$--ZDA``, ``$--GGA``, ``$--RMC``, ``$--HDT``,
   ``$--VTG`` and the ``$PIXSE`` block (``ATITUD``, ``POSITI``, ``SPEED_``, ``HEAVE_``,
   ``TIME__``, ``STDHRP``, ``STDPOS``, ``STDSPD``, ``ALGSTS``, ``STATUS``, ``HT_STS``), a generic
   :class:`Sentence` for anything else — a valid sentence is never thrown away. Empty fields are
   missing values (NaN/None), never zeros. ``decoder.counts`` counts sentences by id
   (``'GPGGA'``, ``'PIXSE,ATITUD'``, ``'PSXN'``).

   The typed sentence records carry the **native** values of the wire (degrees, iXblue signs:
   pitch + bow down, sway + port, heave + up, speed east/north/up, longitude 0–360). They are
   the decode view; nothing else in the project should use them for geometry.

2. :class:`NmeaNavAssembler` — sentences → one canonical :class:`~drivers.hydrins.nav.NavRecord`
   per epoch (canonical signs, radians, NED). An epoch closes at ``$PIXSE,HT_STS`` (the last
   sentence of the PHINS block), when a sentence id repeats (the next epoch has begun), or at
   :meth:`flush`. ``TIME__`` (or GGA/ZDA time when there is no ``TIME__``) gives the time of
   day; the date comes from the last ZDA (``date_source='zda'``) or else from the host's UTC
   date (``'host'``), nearest day within ±12 h. Once the stream has carried ``TIME__``, an
   epoch that lost its own (a line dropping bytes) is rejected
   (``rejected['epoch_without_time']``) rather than dated by a ZDA or GGA of another instant.
   ``gps_ns`` stays None when the INS says it is not on UTC (system status 2 bit 9 clear),
   because ``TIME__`` is then the INS system time.

3. Encoders for the emulators: :func:`encode_sentence`, :func:`encode_epoch` (a canonical
   NavRecord → the PHINS standard block, in the order HEHDT, ATITUD, POSITI, SPEED_, HEAVE_,
   TIME__, STDHRP, STDPOS, STDSPD, ALGSTS, STATUS, HT_STS) and :func:`encode_zda`.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from functools import reduce
from operator import xor

from calib.core.frames import attitude_from_ixblue, attitude_to_ixblue, gps_ns_to_utc
from drivers.base import DecoderStats
from drivers.hydrins.nav import NavRecord, wrap_heading_rad, wrap_lon_deg
from drivers.hydrins.timeofday import (
    DAY_NS,
    format_hhmmss,
    parse_hhmmss_ns,
    resolve_gps_ns,
    utc_date_ns,
    utc_time_of_day_ns,
)

NAN = math.nan
KNOT_M_S = 1852.0 / 3600.0
MAX_LINE = 1024  # NMEA says 82 characters; some receivers (PSTI) send ~400

# ---------------------------------------------------------------------------------------------
# Typed sentence records (native wire values; see the module docstring).
# ---------------------------------------------------------------------------------------------


@dataclass(slots=True)
class Sentence:
    """Any valid sentence without a typed record: ``kind`` is e.g. 'GSA', 'PSXN', 'PIXSE,UTMWGS'."""

    talker: str
    kind: str
    fields: list[str]
    host_ns: int | None = None


@dataclass(slots=True)
class Zda:
    talker: str
    time_of_day_ns: int | None
    day: int | None
    month: int | None
    year: int | None
    host_ns: int | None = None


@dataclass(slots=True)
class Gga:
    talker: str
    time_of_day_ns: int | None
    lat_deg: float
    lon_deg: float
    quality: int | None
    n_satellites: int | None
    hdop: float
    altitude_msl_m: float
    geoid_separation_m: float
    dgps_age_s: float
    host_ns: int | None = None


@dataclass(slots=True)
class Rmc:
    talker: str
    time_of_day_ns: int | None
    valid: bool | None
    lat_deg: float
    lon_deg: float
    speed_m_s: float
    course_deg: float
    day: int | None
    month: int | None
    year: int | None
    host_ns: int | None = None


@dataclass(slots=True)
class Hdt:
    talker: str
    heading_deg: float
    host_ns: int | None = None


@dataclass(slots=True)
class Vtg:
    talker: str
    course_true_deg: float
    course_magnetic_deg: float
    speed_m_s: float
    mode: str | None
    host_ns: int | None = None


@dataclass(slots=True)
class PixseAtitud:
    """Roll (+ port up) and pitch (+ bow down, iXblue native) in degrees."""

    roll_deg: float
    pitch_deg: float
    host_ns: int | None = None


@dataclass(slots=True)
class PixsePositi:
    lat_deg: float
    lon_deg: float  # 0–360 as sent
    altitude_m: float
    host_ns: int | None = None


@dataclass(slots=True)
class PixseSpeed:
    east_m_s: float
    north_m_s: float
    up_m_s: float
    host_ns: int | None = None


@dataclass(slots=True)
class PixseHeave:
    """Surge (+ bow), sway (+ port), heave (+ up), iXblue native, metres."""

    surge_m: float
    sway_m: float
    heave_m: float
    host_ns: int | None = None


@dataclass(slots=True)
class PixseTime:
    time_of_day_ns: int | None
    host_ns: int | None = None


@dataclass(slots=True)
class PixseStdhrp:
    heading_deg: float
    roll_deg: float
    pitch_deg: float
    host_ns: int | None = None


@dataclass(slots=True)
class PixseStdpos:
    north_m: float
    east_m: float
    altitude_m: float
    host_ns: int | None = None


@dataclass(slots=True)
class PixseStdspd:
    north_m_s: float
    east_m_s: float
    up_m_s: float
    host_ns: int | None = None


@dataclass(slots=True)
class PixseAlgsts:
    """INS algorithm status words 1 (LSB) and 2 (MSB)."""

    status1: int | None
    status2: int | None
    host_ns: int | None = None


@dataclass(slots=True)
class PixseStatus:
    """INS system status words 1 (LSB) and 2 (MSB)."""

    status1: int | None
    status2: int | None
    host_ns: int | None = None


@dataclass(slots=True)
class PixseHtSts:
    """INS high-level (user) status word."""

    status: int | None
    host_ns: int | None = None


# ---------------------------------------------------------------------------------------------
# Field parsers: empty → missing, anything else must parse or the sentence is rejected.
# ---------------------------------------------------------------------------------------------


def _f(s: str) -> float:
    return float(s) if s else NAN


def _i(s: str) -> int | None:
    return int(s) if s else None


def _hex(s: str) -> int | None:
    if not s:
        return None
    value = int(s, 16)
    if not 0 <= value <= 0xFFFFFFFF:
        raise ValueError(f"status word {s!r} is not 32-bit hex")
    return value


def _tod(s: str) -> int | None:
    return parse_hhmmss_ns(s) if s else None


def _latlon(value: str, hemisphere: str) -> float:
    if not value:
        return NAN
    v = float(value)
    deg = int(v // 100.0)
    result = deg + (v - 100.0 * deg) / 60.0
    if hemisphere in ("S", "W"):
        return -result
    if hemisphere not in ("N", "E", ""):
        raise ValueError(f"hemisphere {hemisphere!r}")
    return result


def _pad(f: list[str], n: int) -> list[str]:
    return f if len(f) >= n else f + [""] * (n - len(f))


def _p_zda(t, f, h):
    f = _pad(f, 5)
    return Zda(t, _tod(f[1]), _i(f[2]), _i(f[3]), _i(f[4]), h)


def _p_gga(t, f, h):
    f = _pad(f, 14)
    return Gga(
        t, _tod(f[1]), _latlon(f[2], f[3]), _latlon(f[4], f[5]), _i(f[6]), _i(f[7]),
        _f(f[8]), _f(f[9]), _f(f[11]), _f(f[13]), h,
    )  # fmt: skip


def _p_rmc(t, f, h):
    f = _pad(f, 10)
    date = f[9]
    if date and (len(date) != 6 or not date.isdigit()):
        raise ValueError(f"RMC date {date!r}")
    day, month, year = (int(date[0:2]), int(date[2:4]), 2000 + int(date[4:6])) if date else (None,) * 3
    valid = {"A": True, "V": False}.get(f[2])
    kn = _f(f[7])
    return Rmc(
        t, _tod(f[1]), valid, _latlon(f[3], f[4]), _latlon(f[5], f[6]), kn * KNOT_M_S, _f(f[8]),
        day, month, year, h,
    )  # fmt: skip


def _p_hdt(t, f, h):
    f = _pad(f, 2)
    return Hdt(t, _f(f[1]), h)


def _p_vtg(t, f, h):
    f = _pad(f, 10)
    if f[2] in ("T", ""):  # NMEA 2.3+: value,unit pairs
        kn, mode = _f(f[5]), f[9] or None
        return Vtg(t, _f(f[1]), _f(f[3]), kn * KNOT_M_S, mode, h)
    return Vtg(t, _f(f[1]), _f(f[2]), _f(f[3]) * KNOT_M_S, None, h)  # NMEA 1.5


def _p3(cls):
    def parse(t, f, h):
        f = _pad(f, 5)
        return cls(_f(f[2]), _f(f[3]), _f(f[4]), h)

    return parse


def _p_atitud(t, f, h):
    f = _pad(f, 4)
    return PixseAtitud(_f(f[2]), _f(f[3]), h)


def _p_time(t, f, h):
    f = _pad(f, 3)
    return PixseTime(_tod(f[2]), h)


def _p_words(cls):
    def parse(t, f, h):
        f = _pad(f, 4)
        return cls(_hex(f[2]), _hex(f[3]), h)

    return parse


def _p_htsts(t, f, h):
    f = _pad(f, 3)
    return PixseHtSts(_hex(f[2]), h)


_STANDARD = {"ZDA": _p_zda, "GGA": _p_gga, "RMC": _p_rmc, "HDT": _p_hdt, "VTG": _p_vtg}
_PIXSE = {
    "ATITUD": _p_atitud,
    "POSITI": _p3(PixsePositi),
    "SPEED_": _p3(PixseSpeed),
    "HEAVE_": _p3(PixseHeave),
    "TIME__": _p_time,
    "STDHRP": _p3(PixseStdhrp),
    "STDPOS": _p3(PixseStdpos),
    "STDSPD": _p3(PixseStdspd),
    "ALGSTS": _p_words(PixseAlgsts),
    "STATUS": _p_words(PixseStatus),
    "HT_STS": _p_htsts,
}


def checksum(body: bytes) -> int:
    """NMEA checksum: XOR of the bytes between ``$``/``!`` and ``*``."""
    return reduce(xor, body, 0)


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
        brought its first byte."""
        self.stats.bytes_in += len(data)
        first_ns = self._buf_ns if self._buf else host_ns
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
        self._buf_ns = host_ns if lines else first_ns
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
            if head == "PIXSE" and len(fields) > 1:
                sid = "PIXSE," + fields[1]
                parser = _PIXSE.get(fields[1])
                rec = parser("", fields, host_ns) if parser else Sentence("", sid, fields, host_ns)
            elif head[:1] == "P" or len(head) != 5:
                sid = head
                rec = Sentence("", head, fields, host_ns)
            else:
                sid = head
                parser = _STANDARD.get(head[2:])
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
        self._epoch: dict[type, object] = {}
        self._zda_utc_ns: int | None = None
        self._zda_host_ns: int | None = None
        self._hint: int | None = None
        self._time_sentences = False  # the stream carries TIME__: every epoch must have its own

    @property
    def stats(self) -> DecoderStats:
        return self.decoder.stats

    def feed(self, data: bytes, host_ns: int | None = None, utc_hint_ns: int | None = None) -> list[NavRecord]:
        self._hint = utc_hint_ns
        out: list[NavRecord] = []
        for rec in self.decoder.feed(data, host_ns):
            out.extend(self.push(rec))
        return out

    def push(self, rec) -> list[NavRecord]:
        """Add one sentence record; returns the epoch it closed, if any."""
        out: list[NavRecord] = []
        if isinstance(rec, Zda) and None not in (rec.time_of_day_ns, rec.day, rec.month, rec.year):
            try:
                self._zda_utc_ns = utc_date_ns(rec.year, rec.month, rec.day) + rec.time_of_day_ns
                self._zda_host_ns = rec.host_ns
            except ValueError:  # impossible date in a checksum-valid sentence
                self.decoder.stats.rejected["bad_field"] += 1
        if isinstance(rec, Sentence):
            return out
        kind = type(rec)
        if kind is PixseTime:
            self._time_sentences = True
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
        tod = None
        for r in epoch.values():
            if isinstance(r, Hdt):
                nav.heading_rad = wrap_heading_rad(math.radians(r.heading_deg))
            elif isinstance(r, PixseAtitud):
                roll, pitch, _ = attitude_from_ixblue(math.radians(r.roll_deg), math.radians(r.pitch_deg), 0.0)
                nav.roll_rad, nav.pitch_rad = float(roll), float(pitch)
            elif isinstance(r, PixsePositi):
                nav.lat_deg, nav.lon_deg, nav.height_m = r.lat_deg, wrap_lon_deg(r.lon_deg), r.altitude_m
            elif isinstance(r, PixseSpeed):
                nav.v_north_m_s, nav.v_east_m_s, nav.v_down_m_s = r.north_m_s, r.east_m_s, -r.up_m_s
            elif isinstance(r, PixseHeave):
                nav.surge_m, nav.sway_m, nav.heave_m = r.surge_m, -r.sway_m, -r.heave_m
            elif isinstance(r, PixseTime):
                tod = r.time_of_day_ns
            elif isinstance(r, PixseStdhrp):
                nav.sigma_heading_rad = math.radians(r.heading_deg)
                nav.sigma_roll_rad = math.radians(r.roll_deg)
                nav.sigma_pitch_rad = math.radians(r.pitch_deg)
            elif isinstance(r, PixseStdpos):
                nav.sigma_north_m, nav.sigma_east_m, nav.sigma_down_m = r.north_m, r.east_m, r.altitude_m
            elif isinstance(r, PixseStdspd):
                nav.sigma_v_north_m_s, nav.sigma_v_east_m_s, nav.sigma_v_down_m_s = r.north_m_s, r.east_m_s, r.up_m_s
            elif isinstance(r, PixseAlgsts):
                if r.status1 is not None and r.status2 is not None:
                    nav.algorithm_status = (r.status1, r.status2)
            elif isinstance(r, PixseStatus):
                if r.status1 is not None and r.status2 is not None:
                    nav.system_status = (r.status1, r.status2)
            elif isinstance(r, PixseHtSts):
                nav.user_status = r.status
            elif isinstance(r, Gga):
                if math.isnan(nav.lat_deg):
                    nav.lat_deg, nav.lon_deg = r.lat_deg, r.lon_deg
                    if not math.isnan(r.geoid_separation_m):
                        nav.height_m, nav.height_ref = r.altitude_msl_m + r.geoid_separation_m, "ellipsoid"
                    elif not math.isnan(r.altitude_msl_m):
                        nav.height_m, nav.height_ref = r.altitude_msl_m, "geoid"
        if tod is None and self._time_sentences and any(
                isinstance(r, (Hdt, PixseAtitud, PixsePositi)) for r in epoch.values()):
            # the stream has TIME__ but this epoch lost its own (bytes lost on the line): a ZDA
            # or GGA next to it belongs to another instant, so its time is unknown
            self.decoder.stats.rejected["epoch_without_time"] += 1
            return []
        if tod is None:
            for cls in (Gga, Zda, Rmc):
                tod = next((r.time_of_day_ns for r in epoch.values() if isinstance(r, cls)), None)
                if tod is not None:
                    break
        nav.time_of_day_ns = tod
        if tod is not None and nav.utc_detected is not False:
            self._resolve(nav, tod)
        return [nav]

    def _resolve(self, nav: NavRecord, tod: int) -> None:
        zda_fresh = self._zda_utc_ns is not None and (
            nav.host_ns is None or self._zda_host_ns is None or abs(nav.host_ns - self._zda_host_ns) < DAY_NS // 2
        )
        if zda_fresh:
            nav.gps_ns, nav.date_source = resolve_gps_ns(tod, self._zda_utc_ns), "zda"
            return
        hint = self._hint if self._hint is not None else (self.utc_clock() if self.utc_clock else None)
        if hint is not None:
            nav.gps_ns, nav.date_source = resolve_gps_ns(tod, hint), "host"


# ---------------------------------------------------------------------------------------------
# Encoders (for the emulators).
# ---------------------------------------------------------------------------------------------


def encode_sentence(body: str, start: str = "$") -> bytes:
    """``'PIXSE,ATITUD,1.000,2.000'`` → ``b'$PIXSE,ATITUD,1.000,2.000*hh\\r\\n'``."""
    raw = body.encode("ascii")
    return b"%s%s*%02X\r\n" % (start.encode("ascii"), raw, checksum(raw))


def _fmt(value: float, spec: str) -> str:
    return "" if value is None or value != value else format(value, spec)


def _deg(value_rad: float, spec: str = ".3f") -> str:
    return _fmt(math.degrees(value_rad), spec) if value_rad == value_rad else ""


def _neg(value: float) -> float:
    return -value if value == value else value


def _word(value: int | None) -> str:
    return "" if value is None else f"{value & 0xFFFFFFFF:08X}"


def encode_epoch(nav: NavRecord, talker: str = "HE") -> bytes:
    """A canonical NavRecord → the PHINS standard block (iXblue signs and units on the wire).

    TIME__ carries the UTC time of day of ``nav.gps_ns`` when it is set, else
    ``nav.time_of_day_ns``; missing values become empty fields.
    """
    roll, pitch, _ = attitude_to_ixblue(nav.roll_rad, nav.pitch_rad, 0.0)
    lon = nav.lon_deg % 360.0 if nav.lon_deg == nav.lon_deg else NAN
    if nav.gps_ns is not None:
        tod = utc_time_of_day_ns(nav.gps_ns)
    else:
        tod = nav.time_of_day_ns
    words_a = nav.algorithm_status or (None, None)
    words_s = nav.system_status or (None, None)
    bodies = [
        f"{talker}HDT,{_deg(nav.heading_rad)},T",
        f"PIXSE,ATITUD,{_deg(float(roll))},{_deg(float(pitch))}",
        f"PIXSE,POSITI,{_fmt(nav.lat_deg, '.8f')},{_fmt(lon, '.8f')},{_fmt(nav.height_m, '.3f')}",
        f"PIXSE,SPEED_,{_fmt(nav.v_east_m_s, '.3f')},{_fmt(nav.v_north_m_s, '.3f')},{_fmt(_neg(nav.v_down_m_s), '.3f')}",
        f"PIXSE,HEAVE_,{_fmt(nav.surge_m, '.3f')},{_fmt(_neg(nav.sway_m), '.3f')},{_fmt(_neg(nav.heave_m), '.3f')}",
        f"PIXSE,TIME__,{format_hhmmss(tod, 6) if tod is not None else ''}",
        f"PIXSE,STDHRP,{_deg(nav.sigma_heading_rad)},{_deg(nav.sigma_roll_rad)},{_deg(nav.sigma_pitch_rad)}",
        f"PIXSE,STDPOS,{_fmt(nav.sigma_north_m, '.2f')},{_fmt(nav.sigma_east_m, '.2f')},{_fmt(nav.sigma_down_m, '.2f')}",
        f"PIXSE,STDSPD,{_fmt(nav.sigma_v_north_m_s, '.3f')},{_fmt(nav.sigma_v_east_m_s, '.3f')},{_fmt(nav.sigma_v_down_m_s, '.3f')}",
        f"PIXSE,ALGSTS,{_word(words_a[0])},{_word(words_a[1])}",
        f"PIXSE,STATUS,{_word(words_s[0])},{_word(words_s[1])}",
        f"PIXSE,HT_STS,{_word(nav.user_status)}",
    ]
    return b"".join(encode_sentence(b) for b in bodies)


def encode_zda(gps_ns: int, talker: str = "GP", decimals: int = 2) -> bytes:
    """``$--ZDA`` for a GPS instant (UTC on the wire; local zone 00,00)."""
    utc = gps_ns_to_utc(gps_ns)
    tod = utc_time_of_day_ns(gps_ns)
    return encode_sentence(f"{talker}ZDA,{format_hhmmss(tod, decimals)},{utc.day:02d},{utc.month:02d},{utc.year:04d},00,00")
