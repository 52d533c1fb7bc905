"""iXblue STDBIN decoding, sans-I/O (docs/architecture.md §5): bytes → frames and answers → NavRecords.

:class:`StdbinDecoder` turns bytes into :class:`~drivers.hydrins.stdbin_records.StdbinFrame` /
:class:`~drivers.hydrins.stdbin_records.StdbinAnswer` records (the wire format:
:mod:`drivers.hydrins.stdbin_format`): frames split across reads are reassembled, garbage before
or between frames is skipped, and a frame with a bad checksum, an unknown version or a size that
does not match its masks is rejected and counted (``stats.rejected``) — the decoder never raises.
A frame still incomplete while a later header's whole frame is already buffered and valid (a
frame cut short, or a damaged size field) is dropped at once as ``truncated`` and decoding
resumes at that later frame, so a good frame is never held back behind a bogus one; ``flush()``
does the same search before dropping what is left. A mask bit the tables do not know
(``stats.events['unknown_block']``) stops decoding of that mask at that bit; the frame is still
delivered with the blocks before it (V4+: the external data too, found through the navigation
size).

:class:`StdbinNavDecoder` feeds bytes straight to canonical NavRecords, so the daemon treats
STDBIN and NMEA alike.
"""

from __future__ import annotations

import struct
import time
from bisect import bisect_right
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from drivers.base import DecoderStats
from drivers.hydrins.nav import NavRecord
from drivers.hydrins.stdbin_format import (
    ANSWER_HEADER_SIZE,
    BLOCK_SIZES,
    CHECKSUM_SIZE,
    EXTENDED_NAVIGATION_BLOCKS,
    EXTERNAL_DATA_BLOCKS,
    HEADER_SIZES,
    HEADER_V2,
    HEADER_V3,
    HEADER_V4,
    MAX_ANSWER,
    MAX_TELEGRAM,
    NAVIGATION_BLOCKS,
    U16,
    U32,
    sum32,
)
from drivers.hydrins.stdbin_records import StdbinAnswer, StdbinFrame

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
    _cache: dict[str, dict[str, Any]]

    def __init__(self, index: dict, values: list) -> None:
        self._index, self._values, self._cache = index, values, {}

    def __getitem__(self, name: str) -> dict[str, Any]:
        blk = self._cache.get(name)
        if blk is None:
            seg, k, names = self._index[name]
            blk = self._cache[name] = dict(zip(names, self._values[seg][k : k + len(names)], strict=False))
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
    specs: list[tuple[str, str, tuple[str, ...]]]
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


def _layout(
    version: int, nav_mask: int, ext_nav_mask: int | None, ext_mask: int, nav_size: int | None
) -> _Layout:
    key = (version, nav_mask, ext_nav_mask, ext_mask, nav_size)
    lay = _LAYOUTS.get(key)
    if lay is not None:
        return lay
    header = HEADER_SIZES[version]
    nav, nav_bytes, nav_cut = _blocks_of(nav_mask, NAVIGATION_BLOCKS)
    ext_nav: list[tuple[str, str, tuple[str, ...]]]
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
        nav_mask, ext_mask, size, validity, counter = HEADER_V2.unpack_from(buf, pos + 3)
    elif version == 3:
        nav_mask, ext_nav, ext_mask, size, validity, counter = HEADER_V3.unpack_from(buf, pos + 3)
    else:
        nav_mask, ext_nav, ext_mask, nav_size, size, validity, counter = HEADER_V4.unpack_from(buf, pos + 3)
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
        self._scan_state: tuple[int, list[int]]  # set by _later_frame before it returns -1

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
                need = header if have < header else U16.unpack_from(buf, pos + header - 10)[0]
            else:
                need = ANSWER_HEADER_SIZE if have < ANSWER_HEADER_SIZE else U16.unpack_from(buf, pos + 3)[0]
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
        pending: list[int]
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
            size = U16.unpack_from(buf, q + 3)[0]
            if not ANSWER_HEADER_SIZE + CHECKSUM_SIZE <= size <= MAX_ANSWER:
                return -1
        if have < size:
            return 0
        end = q + size - CHECKSUM_SIZE
        return size if U32.unpack_from(buf, end)[0] == sum32(buf[q:end]) else -1

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
        if U32.unpack_from(buf, end)[0] != sum32(buf[pos:end]):
            self.stats.rejected["bad_checksum"] += 1
            return -1
        blocks = _Blocks(lay.index, [st.unpack_from(buf, pos + offset) for offset, st, _ in lay.segments])
        if lay.unknown:
            self.stats.events["unknown_block"] += lay.unknown
        out.append(
            StdbinFrame(version, counter, validity, blocks, nav_mask, ext_nav, ext_mask, size, host_ns)
        )
        return size

    def _answer(self, buf: bytes, pos: int, version: int, host_ns, out: list) -> int:
        if not 3 <= version <= 5:
            self.stats.rejected["unknown_version"] += 1
            return -1
        if len(buf) - pos < ANSWER_HEADER_SIZE:
            return 0
        size = U16.unpack_from(buf, pos + 3)[0]
        if not ANSWER_HEADER_SIZE + CHECKSUM_SIZE <= size <= MAX_ANSWER:
            self.stats.rejected["size_mismatch"] += 1
            return -1
        if len(buf) - pos < size:
            return 0
        end = pos + size - CHECKSUM_SIZE
        if U32.unpack_from(buf, end)[0] != sum32(buf[pos:end]):
            self.stats.rejected["bad_checksum"] += 1
            return -1
        out.append(StdbinAnswer(version, buf[pos + ANSWER_HEADER_SIZE : end], host_ns))
        return size


class StdbinNavDecoder:
    """Bytes → canonical :class:`NavRecord` per navigation frame (answers are counted, not returned).

    ``utc_clock`` (host UTC ns since the Unix epoch) dates frames without a system-date block
    and is the reference that undoes a GPS week rollover of the system date; None never dates
    them from the host (nor moves a date).
    """

    def __init__(self, utc_clock: Callable[[], int] | None = time.time_ns) -> None:
        self.decoder = StdbinDecoder()
        self.utc_clock = utc_clock

    @property
    def stats(self) -> DecoderStats:
        return self.decoder.stats

    def feed(
        self, data: bytes, host_ns: int | None = None, utc_hint_ns: int | None = None
    ) -> list[NavRecord]:
        return self._navs(self.decoder.feed(data, host_ns), utc_hint_ns)

    def _navs(self, records: list, utc_hint_ns: int | None) -> list[NavRecord]:
        out = []
        for rec in records:
            if isinstance(rec, StdbinFrame):
                hint = utc_hint_ns
                if hint is None and self.utc_clock is not None:
                    hint = self.utc_clock()
                out.append(rec.to_nav(hint))
            else:
                self.stats.events["answers"] += 1
        return out

    def flush(self, utc_hint_ns: int | None = None) -> list[NavRecord]:
        return self._navs(self.decoder.flush(), utc_hint_ns)
