"""What a survey is made of: a session (the daemon's MCAP segments) or a calibration bundle.

:func:`open_source` reads what every chunk needs once (the site, the trajectory, the lines) and
cuts the returns into :class:`ChunkSpec` time chunks; :func:`read_chunk` then reads the returns
of one chunk, in whichever process runs it.

A session's chunks are windows of ``chunk_s`` seconds of GPS log time (aligned to multiples of
``chunk_s``) within each segment: a datagram belongs to exactly one chunk, and a chunk reads one
segment through its index (a segment that did not close normally is scanned instead). The
returns are timed as ``mls export`` times them (packet ``t0 + i·dt`` when the packet says
PPS-locked and time-valid, else from its receipt on the clock model); duplicated datagrams are
kept once within a chunk. A bundle's chunks carry their returns (a bundle is calibration-sized).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, cast

import numpy as np

from office.deliver.options import GeorefError

if TYPE_CHECKING:
    from calib.core.trajectory import Trajectory
    from calib.io.site import Site
    from office.jobs.sessionread import Mapper

NS_PER_S = 1_000_000_000
LIDAR_TOPIC = "/lidar/raw"


@dataclass(frozen=True)
class ChunkSpec:
    index: int
    t0_ns: int  # [t0, t1) of log time (session) or of point time (bundle)
    t1_ns: int
    segment: str | None = None  # session: the segment file
    returns: Returns | None = None  # bundle: the returns themselves


@dataclass(frozen=True)
class Returns:
    """Raw returns of one chunk (time-sorted for a profiler stream)."""

    t_gps_ns: np.ndarray  # int64
    range_m: np.ndarray
    scan_angle_rad: np.ndarray
    intensity: np.ndarray  # uint16 counts
    pass_id: np.ndarray | None = None  # int64 when the source says (bundle); else from the lines
    counters: dict = field(default_factory=dict)

    @property
    def size(self) -> int:
        return int(self.t_gps_ns.size)


@dataclass
class Source:
    kind: str  # "session" or "bundle"
    path: Path
    site: Site
    trajectory: Trajectory
    lines: list[tuple[int, int, int]]  # (pass id, start GPS ns, end GPS ns), sorted by start
    chunks: list[ChunkSpec]
    warnings: list[str] = field(default_factory=list)


def _windows(t0_ns: int, t1_ns: int, chunk_ns: int) -> list[tuple[int, int]]:
    first = t0_ns // chunk_ns * chunk_ns
    return [(a, a + chunk_ns) for a in range(first, t1_ns + 1, chunk_ns)]


def _segment_span(path: Path) -> tuple[int, int] | None:
    """(first, last) log time of the /lidar/raw messages of a segment: from its summary, else by
    scanning it."""
    from acquire.log.indexed import segment_summary

    try:
        summary = segment_summary(path)
        if summary is not None and summary.statistics is not None:
            ids = [c.id for c in summary.channels.values() if c.topic == LIDAR_TOPIC]
            if not any(summary.statistics.channel_message_counts.get(i, 0) for i in ids):
                return None
            return int(summary.statistics.message_start_time), int(summary.statistics.message_end_time)
    except Exception:  # noqa: BLE001 - a torn segment has no summary: scan it
        pass
    lo: int | None = None
    hi: int | None = None
    for t, _ in _scan_lidar(path, None, None):
        lo = t if lo is None else min(lo, t)
        hi = t if hi is None else max(hi, t)
    return None if lo is None or hi is None else (lo, hi)


def _scan_lidar(path: Path, t0_ns: int | None, t1_ns: int | None) -> Iterator[tuple[int, bytes]]:
    """(log time, raw record) of the /lidar/raw messages of a segment, by a scan (torn ones too)."""
    from mcap.records import Channel, Message

    from acquire.log.recover import scan_segment

    topic_of: dict[int, str] = {}
    for rec in scan_segment(path):
        if isinstance(rec, Channel):
            topic_of[rec.id] = rec.topic
        elif isinstance(rec, Message) and topic_of.get(rec.channel_id) == LIDAR_TOPIC:
            if (t0_ns is None or rec.log_time >= t0_ns) and (t1_ns is None or rec.log_time < t1_ns):
                yield rec.log_time, rec.data


def _scanned_datagrams(path: Path, t0_ns: int, t1_ns: int) -> tuple[np.ndarray, list[memoryview]]:
    """:func:`_datagrams` of a segment without an index (scanned up to its torn tail)."""
    log_t: list[int] = []
    grams: list[memoryview] = []
    for t, raw in _scan_lidar(path, t0_ns, t1_ns):
        hs = int.from_bytes(raw[2:4], "little")
        log_t.append(t)
        grams.append(memoryview(raw)[hs:])
    return np.asarray(log_t, np.int64), grams


def _datagrams(spec: ChunkSpec) -> tuple[np.ndarray, list[memoryview]]:
    """(log times, datagrams) of the chunk's profiler messages; the datagrams are views of the
    decompressed MCAP chunks (their bytes are copied once, into the chunk's points), located a
    chunk at a time (:func:`acquire.log.indexed.indexed_blocks`), not parsed one by one."""
    from acquire.log.indexed import indexed_blocks

    assert spec.segment is not None
    path = Path(spec.segment)
    try:
        found = indexed_blocks(path, [LIDAR_TOPIC], spec.t0_ns, spec.t1_ns)
    except OSError as e:
        raise GeorefError(f"{path}: cannot read the segment ({e.strerror or e})") from None
    if found is None:  # not closed normally: scanned up to its torn tail
        return _scanned_datagrams(path, spec.t0_ns, spec.t1_ns)
    times: list[np.ndarray] = []
    grams: list[memoryview] = []
    for block in found[1]:
        buf = np.frombuffer(block.records, np.uint8)
        # each message: the daemon's envelope (its size, u16 at byte 2), then the datagram
        envelope = buf[block.data_start + 2].astype(np.int64) | (
            buf[block.data_start + 3].astype(np.int64) << 8
        )
        view = memoryview(block.records)
        grams += [
            view[a:b]
            for a, b in zip((block.data_start + envelope).tolist(), block.data_end.tolist(), strict=True)
        ]
        times.append(block.log_time)
    return (np.concatenate(times) if times else np.zeros(0, np.int64)), grams


def _packet_headers(
    log_t: np.ndarray, grams: list[memoryview], counters: dict[str, int]
) -> tuple[np.ndarray, np.ndarray, list[memoryview]] | None:
    """(headers, log times, datagrams) of the valid packets (the others counted as bad); None
    when there is none."""
    from drivers.base import DriverError
    from drivers.zf.zfp1 import decode_packet, scan_packets

    if not grams:
        return None
    # (the decoder reads any buffer: views, not copies)
    head = scan_packets(cast("list[bytes]", grams))
    if head is not None:
        return head, log_t, grams
    good = []  # one at least is not a valid packet: keep the good ones, count the rest
    for j, g in enumerate(grams):
        try:
            decode_packet(cast(bytes, g))
            good.append(j)
        except DriverError:
            counters["bad_datagrams"] += 1
    grams = [grams[i] for i in good]
    log_t = log_t[np.asarray(good, np.intp)]
    head = scan_packets(cast("list[bytes]", grams)) if grams else None
    return None if head is None else (head, log_t, grams)


def _first_copies(head: np.ndarray, counters: dict[str, int]) -> np.ndarray:
    """Which packets are the first of their kind (profile, index, time): duplicates counted."""
    key = np.stack(
        [head["profile_counter"].astype(np.int64), head["packet_index"].astype(np.int64), head["t0_ns"]]
    )
    _, first = np.unique(key, axis=1, return_index=True)
    keep = np.zeros(head.size, bool)
    keep[first] = True
    counters["duplicates"] = int((~keep).sum())
    return keep


def read_session_chunk(spec: ChunkSpec, packet_share: float = 1.0) -> Returns:
    """Decode the profiler datagrams of one session chunk into returns (module docstring): every
    quantity for the hits only (range > 0), taken from their packets once, sorted once.
    ``packet_share`` < 1: only that share of the datagrams, drawn at random (seeded by the
    chunk: the same every read; at random, not every k-th, which could keep the same sector of
    every profile)."""
    from drivers.zf.codec import FLAG_PPS_LOCKED, FLAG_TIME_VALID
    from drivers.zf.zfp1 import CRC_SIZE, HEADER_SIZE, POINT_DTYPE, RANGE_UNIT_M

    log_t, grams = _datagrams(spec)
    if packet_share < 1.0:
        drawn = np.flatnonzero(np.random.default_rng(spec.index).random(len(grams)) < packet_share)
        log_t, grams = log_t[drawn], [grams[j] for j in drawn.tolist()]
    counters = {"datagrams": len(grams), "bad_datagrams": 0, "duplicates": 0, "unsynced_packets": 0}
    valid = _packet_headers(log_t, grams, counters)
    if valid is None:
        return Returns(
            np.zeros(0, np.int64), np.zeros(0), np.zeros(0), np.zeros(0, np.uint16), None, counters
        )
    head, log_t, grams = valid
    keep = _first_copies(head, counters)
    n = head["n_points"].astype(np.int64)
    n[~keep] = 0
    kept = grams if keep.all() else [g for g, k in zip(grams, keep.tolist(), strict=True) if k]
    pts = np.frombuffer(b"".join([g[HEADER_SIZE:-CRC_SIZE] for g in kept]), POINT_DTYPE)
    hit = np.flatnonzero(pts["range_01mm"] > 0)
    pk = np.repeat(np.arange(len(grams)), n)[hit]
    i = hit - (np.cumsum(n) - n)[pk]
    dt = head["dt_ns"].astype(np.int64)[pk]
    synced = (head["flags"] & FLAG_PPS_LOCKED).astype(bool) & (head["flags"] & FLAG_TIME_VALID).astype(bool)
    counters["unsynced_packets"] = int((~synced & keep).sum())
    t = head["t0_ns"][pk] + i * dt
    if not synced.all():  # the others from their receipt
        late = ~synced[pk]
        t[late] = log_t[pk[late]] - (n[pk[late]] - 1 - i[late]) * dt[late]
    if t.size > 1 and not bool(np.all(t[1:] >= t[:-1])):  # time order (a stable sort) when not already
        order = np.argsort(t, kind="stable")
        hit, pk, i, t = hit[order], pk[order], i[order], t[order]
    ang_udeg = head["angle0_udeg"].astype(np.int64)[pk] + i * head["dangle_udeg"].astype(np.int64)[pk]
    ang_deg = ang_udeg * 1e-6
    if ang_udeg.size and not (ang_udeg.min() >= 0 and ang_udeg.max() < 360_000_000):
        np.mod(ang_deg, 360.0, out=ang_deg)  # (within [0°, 360°) already it would change nothing)
    return Returns(
        t,
        pts["range_01mm"][hit].astype(np.float64) * RANGE_UNIT_M,
        np.radians(ang_deg, out=ang_deg),
        pts["intensity"][hit],
        None,
        counters,
    )


def read_chunk(spec: ChunkSpec, packet_share: float = 1.0) -> Returns:
    """The chunk's returns; a session's from ``packet_share`` of its datagrams
    (:func:`read_session_chunk`; a bundle's chunk: all of them)."""
    return spec.returns if spec.returns is not None else read_session_chunk(spec, packet_share)


def _session_source(path: Path, chunk_s: float, max_gap_s: float, mapper: Mapper | None) -> Source:
    from acquire.log.recover import segment_paths
    from office.jobs.export import ExportError, ExportOptions
    from office.jobs.sessionnav import session_navigation

    try:
        nav = session_navigation(path, ExportOptions(max_gap_s=max_gap_s), mapper)
    except ExportError as e:
        raise GeorefError(str(e)) from None
    chunk_ns = round(chunk_s * NS_PER_S)
    chunks: list[ChunkSpec] = []
    for seg in segment_paths(path):
        span = _segment_span(seg)
        if span is None:
            continue
        for a, b in _windows(span[0], span[1], chunk_ns):
            chunks.append(ChunkSpec(len(chunks), a, b, segment=str(seg)))
    if not chunks:
        raise GeorefError(f"{path}: no {LIDAR_TOPIC} message in any segment: nothing to georeference")
    lines = sorted(((w.pass_id, w.start_gps_ns, w.end_gps_ns) for w in nav.passes), key=lambda x: x[1])
    return Source(
        "session",
        path,
        nav.site,
        nav.trajectory,
        lines,
        chunks,
        list(nav.warnings),
    )


def _bundle_source(path: Path, chunk_s: float, max_gap_s: float) -> Source:
    from calib.io.bundle import BundleError, intensity_scale, read_bundle

    try:
        bundle = read_bundle(path, max_gap_s=max_gap_s)
    except BundleError as e:
        raise GeorefError(str(e)) from None
    pts = bundle.points
    scale = intensity_scale(pts.intensity, bundle.points_path)
    t_ns = np.round(pts.t_gps_s * NS_PER_S).astype(np.int64)
    order = np.argsort(t_ns, kind="stable")
    t_ns = t_ns[order]
    inten = np.round(pts.intensity[order] * scale.factor).astype(np.uint16)
    chunk_ns = round(chunk_s * NS_PER_S)
    chunks: list[ChunkSpec] = []
    for a, b in _windows(int(t_ns[0]), int(t_ns[-1]), chunk_ns):
        lo, hi = np.searchsorted(t_ns, [a, b])
        if hi > lo:
            sel = order[lo:hi]
            r = Returns(
                t_ns[lo:hi], pts.range_m[sel], pts.scan_angle_rad[sel], inten[lo:hi], pts.pass_id[sel]
            )
            chunks.append(ChunkSpec(len(chunks), a, b, returns=r))
    pid_sorted = pts.pass_id[order]
    lines = []
    for pid in pts.pass_ids():
        t = t_ns[pid_sorted == pid]
        lines.append((int(pid), int(t[0]), int(t[-1])))
    return Source("bundle", path, bundle.site, bundle.trajectory, sorted(lines, key=lambda x: x[1]), chunks)


def open_source(
    path: str | Path, chunk_s: float, max_gap_s: float = 1.0, mapper: Mapper | None = None
) -> Source:
    """A session directory (``seg-*.mcap``) or a bundle directory (``points.csv``); ``mapper``: a
    session's navigation decoded in pieces by it (:func:`office.deliver.executors.ordered_map`)."""
    p = Path(path)
    if not p.is_dir():
        raise GeorefError(f"{p}: not a directory (expected a session or a calibration bundle)")
    if any(p.glob("seg-*.mcap")):
        return _session_source(p, chunk_s, max_gap_s, mapper)
    if (p / "points.csv").exists() or (p / "points.csv.gz").exists():
        return _bundle_source(p, chunk_s, max_gap_s)
    raise GeorefError(f"{p}: neither a session (seg-*.mcap) nor a calibration bundle (points.csv)")
