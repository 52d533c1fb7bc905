"""GPS − UTC from a leap-second table that says until when it is valid, and the GPS week
rollover of device dates (docs/architecture.md §3).

**The table** (:class:`LeapTable`) is IERS's ``leap-seconds.list`` — the file tzdata ships as
``/usr/share/zoneinfo/leap-seconds.list`` — on the GPS time scale: the UTC midnights at which
GPS − UTC (= TAI − UTC − 19 s) went up by one second, the date the file was last updated and
the date it **expires**. IERS announces a leap second about six months ahead (Bulletin C), so a
table is only known to be complete up to its expiry ("File expires on 28 December 2026").
:data:`BUILTIN` is that file as updated by IERS on 2026-01-06 (expires 2026-12-28; from
tzdata 2026b). :func:`parse_leap_seconds_list` reads a newer file (its ``#h`` SHA-1 line is
checked) and :func:`use_leap_table` installs it for the process when it extends the table in
use without rewriting its past; :mod:`calib.core.frames` converts with the installed table. A
cache of values derived from the table keys on :func:`table_generation` (nothing is called back);
:func:`leap_table_scope` bounds a table to a block (a test's).
Past the expiry the last count is still used — nothing better is known — and
:meth:`LeapTable.expired_at_unix_ns` says so (the daemon raises ``leap_table_stale``).

**GPS week rollover.** A GPS receiver counts weeks modulo 1024 (the legacy navigation message)
and derives its calendar date from that count; a receiver whose firmware puts the week in the
wrong 1024-week era reports dates 1024 weeks (7168 days, ~19.6 years) in the past — the
2019-04-07 rollover. No project decoder reads a raw week number (NMEA ZDA/RMC and the STDBIN
system date are calendar dates), so the rollover shows in those dates: :func:`unroll_week_rollover`
moves a device date by whole 1024-week eras into the era centred on a reference date (the
host's UTC date, or a recording's receive time). A real date is never moved: it would have to
be more than 9.8 years from the reference. Without a reference nothing is moved.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
from collections.abc import Iterator
from dataclasses import dataclass, field

NS_PER_S = 1_000_000_000
DAY_S = 86_400
GPS_EPOCH_DATE = _dt.date(1980, 1, 6)
UNIX_EPOCH_DATE = _dt.date(1970, 1, 1)
NTP_EPOCH_DATE = _dt.date(1900, 1, 1)
#: seconds from the Unix epoch to the GPS epoch
GPS_EPOCH_UNIX_S = (GPS_EPOCH_DATE - UNIX_EPOCH_DATE).days * DAY_S
TAI_MINUS_GPS_S = 19
ROLLOVER_DAYS = 1024 * 7  # one GPS week-number era


@dataclass(frozen=True)
class LeapTable:
    """GPS − UTC steps: ``steps[i] = (date, n)``: from 00:00 UTC of ``date`` GPS − UTC is ``n`` s."""

    steps: tuple[tuple[_dt.date, int], ...]
    expires: _dt.date  # complete before 00:00 UTC of this date
    updated: _dt.date
    source: str
    #: derived: the step instants in Unix ns (UTC) and in GPS ns
    _unix_ns: tuple[int, ...] = field(init=False, repr=False, compare=False)
    _gps_ns: tuple[int, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        previous = 0
        for day, n in self.steps:
            if n != previous + 1:
                raise ValueError(
                    f"leap-second table {self.source}: GPS − UTC {n} s from {day}: expected {previous + 1}"
                )
            previous = n
        unix = tuple((d - UNIX_EPOCH_DATE).days * DAY_S * NS_PER_S for d, _ in self.steps)
        object.__setattr__(self, "_unix_ns", unix)
        # the GPS instant at which the count becomes n: that midnight, plus n
        object.__setattr__(
            self,
            "_gps_ns",
            tuple(
                u - GPS_EPOCH_UNIX_S * NS_PER_S + n * NS_PER_S
                for u, (_, n) in zip(unix, self.steps, strict=True)
            ),
        )

    @property
    def expires_unix_ns(self) -> int:
        return (self.expires - UNIX_EPOCH_DATE).days * DAY_S * NS_PER_S

    def expired_at_unix_ns(self, unix_ns: int) -> bool:
        """Is ``unix_ns`` (UTC) at or past the expiry (a leap second may be missing)?"""
        return int(unix_ns) >= self.expires_unix_ns

    def gps_minus_utc_at_unix_ns(self, unix_ns: int) -> int:
        return _count_le(self._unix_ns, int(unix_ns))

    def gps_minus_utc_at_gps_ns(self, gps_ns: int) -> int:
        """GPS − UTC at a GPS instant; during an inserted second (23:59:60) the count before it."""
        return _count_le(self._gps_ns, int(gps_ns))

    def leap_second_at_gps_ns(self, gps_ns: int) -> bool:
        """Is the GPS instant inside an inserted second (UTC 23:59:60.x)?"""
        i = _count_le(self._gps_ns, int(gps_ns))
        return i < len(self._gps_ns) and self._gps_ns[i] - NS_PER_S <= int(gps_ns)

    def extends(self, other: LeapTable) -> bool:
        """Does this table agree with ``other`` on everything ``other`` knows (its steps
        before its expiry) and know at least as long?"""
        known = tuple(s for s in self.steps if s[0] < other.expires)
        return known == other.steps and self.expires >= other.expires

    def as_dict(self) -> dict:
        return {
            "gps_minus_utc_s": self.steps[-1][1] if self.steps else 0,
            "last_step": self.steps[-1][0].isoformat() if self.steps else None,
            "updated": self.updated.isoformat(),
            "expires": self.expires.isoformat(),
            "source": self.source,
        }


def _count_le(values: tuple[int, ...], x: int) -> int:
    """How many of the sorted ``values`` are ≤ x (a short list: a loop beats bisect's call)."""
    n = len(values)
    while n and values[n - 1] > x:
        n -= 1
    return n


#: the months (UTC, first day) from which GPS − UTC was 1, 2, … 18 s (IERS Bulletin C)
_STEPS = (
    "1981-07 1982-07 1983-07 1985-07 1988-01 1990-01 1991-01 1992-07 1993-07 "
    "1994-07 1996-01 1997-07 1999-01 2006-01 2009-01 2012-07 2015-07 2017-01"
).split()
BUILTIN = LeapTable(
    steps=tuple((_dt.date.fromisoformat(ym + "-01"), i + 1) for i, ym in enumerate(_STEPS)),
    expires=_dt.date(2026, 12, 28),
    updated=_dt.date(2026, 1, 6),
    source="built in: IERS leap-seconds.list updated 2026-01-06 (tzdata 2026b)",
)

_table = BUILTIN
_generation = 0


def leap_table() -> LeapTable:
    """The table the conversions use (the built-in one unless :func:`use_leap_table` changed it)."""
    return _table


def table_generation() -> int:
    """Changes each time another table is installed: a cache of values derived from the table
    takes it as part of its key (nothing is called back, nothing to reset)."""
    return _generation


def _installed(table: LeapTable) -> None:
    global _table, _generation
    _table, _generation = table, _generation + 1


def use_leap_table(table: LeapTable) -> bool:
    """Install ``table`` for this process when it extends the one in use and expires later;
    returns whether it was installed. Raises ValueError when it contradicts the table in use
    (a different past: not IERS's file, or a damaged one)."""
    current = _table
    if table.expires <= current.expires:
        if not current.extends(table):
            raise ValueError(
                f"leap-second table {table.source} contradicts the one in use ({current.source})"
            )
        return False
    if not table.extends(current):
        raise ValueError(f"leap-second table {table.source} contradicts the one in use ({current.source})")
    _installed(table)
    return True


@contextlib.contextmanager
def leap_table_scope(table: LeapTable = BUILTIN) -> Iterator[LeapTable]:
    """The conversions use ``table`` (default: :data:`BUILTIN`) inside the block, whatever was
    installed before it, and the table in use before it again after it, whatever the block
    installed (:func:`use_leap_table`): a test's table neither comes from nor outlives another
    test."""
    previous = _table
    if table is not previous:
        _installed(table)
    try:
        yield table
    finally:
        if _table is not previous:
            _installed(previous)


@dataclass(frozen=True)
class _LeapListLines:
    """What a ``leap-seconds.list`` says, before it is checked."""

    updated: int | None  # NTP s of the last update ('#$')
    expires: int | None  # NTP s of the expiry ('#@')
    digest: str | None  # the '#h' SHA-1, lower case, without blanks
    data: list[tuple[int, int]]  # (NTP s, TAI − UTC s)


def _read_leap_lines(text: str, source: str) -> _LeapListLines:
    """The update, expiry, hash and data lines; ValueError naming a line that does not read."""
    updated = expires = digest = None
    data: list[tuple[int, int]] = []
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        try:
            if line.startswith("#$"):
                updated = int(line[2:].split()[0])
            elif line.startswith("#@"):
                expires = int(line[2:].split()[0])
            elif line.startswith("#h"):
                digest = "".join(line[2:].split()).lower()
            elif line and not line.startswith("#"):
                ntp, dtai = line.split("#")[0].split()[:2]
                data.append((int(ntp), int(dtai)))
        except (ValueError, IndexError):
            raise ValueError(f"{source}:{lineno}: {raw!r}: expected '<NTP seconds> <TAI−UTC>'") from None
    return _LeapListLines(updated=updated, expires=expires, digest=digest, data=data)


def parse_leap_seconds_list(text: str, source: str = "leap-seconds.list") -> LeapTable:
    """IERS's ``leap-seconds.list`` → a :class:`LeapTable` (GPS − UTC = TAI − UTC − 19).

    Lines: ``#$ <NTP s>`` last update, ``#@ <NTP s>`` expiry, ``#h <SHA-1>`` the hash of the
    update and expiry numbers and the data's first two columns, data ``<NTP s> <TAI−UTC> # …``.
    Raises ValueError naming the line (or the missing part, or a wrong hash)."""
    lines = _read_leap_lines(text, source)
    updated, expires, data = lines.updated, lines.expires, lines.data
    for what, value in (("'#$' (last update)", updated), ("'#@' (expiry)", expires)):
        if value is None:
            raise ValueError(f"{source}: no {what} line")
    if not data:
        raise ValueError(f"{source}: no leap-second lines")
    if lines.digest is not None:
        payload = f"{updated}{expires}" + "".join(f"{a}{b}" for a, b in data)
        if hashlib.sha1(payload.encode("ascii")).hexdigest() != lines.digest:
            raise ValueError(f"{source}: the '#h' SHA-1 does not match the data (a damaged file)")

    def ntp_date(s: int) -> _dt.date:
        return NTP_EPOCH_DATE + _dt.timedelta(seconds=s)

    assert updated is not None, "checked above"
    assert expires is not None, "checked above"
    steps = tuple((ntp_date(s), d - TAI_MINUS_GPS_S) for s, d in data if d > TAI_MINUS_GPS_S)
    return LeapTable(steps, ntp_date(expires), ntp_date(updated), source)


def unroll_week_rollover(day: int, reference_day: int | None) -> tuple[int, int]:
    """A device's date (days since the Unix epoch) moved by whole 1024-week eras into the era
    centred on ``reference_day``: ``(day, eras moved)``; unchanged without a reference."""
    if reference_day is None:
        return day, 0
    eras = (reference_day - day + ROLLOVER_DAYS // 2) // ROLLOVER_DAYS
    return day + eras * ROLLOVER_DAYS, eras
