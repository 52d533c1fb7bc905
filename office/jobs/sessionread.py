"""A session's navigation as every job that reads one reads it (``mls export``, ``mls georef``,
the Foxglove export): the site with the session's mount, the INS epochs of ``/ins/nav`` (re-timed
where the clock model could not time them), the ``/events``, the per-epoch sigmas and the
trajectory (:func:`read_navigation`)."""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from acquire.log.read import SessionReadError, iter_messages
from calib.core import frames
from office.jobs.exportbase import ExportError, ExportOptions

if TYPE_CHECKING:
    from calib.core.frames import LocalFrame
    from calib.core.trajectory import Trajectory
    from calib.io.site import Site

NS_PER_S = 1_000_000_000


@dataclass
class InsEpochs:
    t_ns: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    h: np.ndarray
    rpy_deg: np.ndarray
    sig: np.ndarray  # (n, 6) north, east, down m, roll, pitch, heading deg (NaN when absent)
    from_clock: int
    retimed: int  # of those, logged while the clock was unlocked: timed by the INS tags around


_POSE = ("lat_deg", "lon_deg", "height_m", "roll_deg", "pitch_deg", "heading_deg")
_SIGMAS = (
    "sigma_north_m",
    "sigma_east_m",
    "sigma_down_m",
    "sigma_roll_deg",
    "sigma_pitch_deg",
    "sigma_heading_deg",
)


#: an event of ``/events`` as timed: (GPS ns, how it was timed, its document)
TimedEvent = tuple[int, str, dict[str, Any]]
#: the progress of a read: (bytes done, bytes in all)
ReadProgress = Callable[[float, float | None], None]


#: a message of /ins/nav or /events as :func:`read_nav_and_events` reads it: (topic, log time,
#: host receive time, clock state, the JSON document's data)
NavMessage = tuple[str, int, int, str, Any]
NAV_TOPICS = ("/ins/nav", "/events")


def nav_messages(session: Path, progress: ReadProgress | None) -> Iterator[NavMessage]:
    """The messages of :data:`NAV_TOPICS` in file order, as :func:`acquire.log.read.iter_messages`
    decodes them (the same values, the same errors): when every segment closed normally, the
    JSON envelopes of each MCAP chunk parsed together (:func:`_chunk_messages`, a third of the
    time of one parse per message); else through ``iter_messages``."""
    paths = _indexed_segments(session)
    if not paths:
        for env in iter_messages(session, set(NAV_TOPICS), progress):
            yield env.topic, env.log_time_ns, env.host_ns, env.clock, env.payload
        return
    total = sum(p.stat().st_size for p in paths)
    done = 0
    for path in paths:
        yield from _segment_messages(path)
        done += path.stat().st_size
        if progress is not None:
            progress(done, total)


def _indexed_segments(session: Path) -> list[Path]:
    """The session's segments when every one closed normally (has its index); else none."""
    from acquire.log.indexed import segment_summary
    from acquire.log.recover import segment_paths

    paths = segment_paths(session) if Path(session).is_dir() else []
    return paths if all(p.is_file() and _indexed(segment_summary(p)) for p in paths) else []


def _indexed(summary) -> bool:
    """The segment has a summary with chunk indexes (:func:`acquire.log.indexed.indexed_blocks`)."""
    return summary is not None and bool(summary.chunk_indexes)


def _segment_messages(path: str | Path, chunks_of: slice | None = None) -> Iterator[NavMessage]:
    """:func:`nav_messages` of one segment that closed normally (``chunks_of``: of those of its
    MCAP chunks that hold them, :func:`acquire.log.indexed.indexed_blocks`)."""
    from acquire.log.indexed import indexed_blocks

    found = indexed_blocks(path, NAV_TOPICS, chunks_of=chunks_of)
    if found is None:  # (checked before: the segment has its index)
        raise SessionReadError(f"{path}: the segment's index could not be read")
    channels, blocks = found
    for block in blocks:
        yield from _chunk_messages(channels, block)


def _chunk_messages(channels: dict[int, tuple[str, str]], block) -> list[NavMessage]:
    """The messages of one MCAP chunk: their JSON envelopes parsed as one JSON array; one by one
    through :func:`acquire.log.schema.decode` when that fails or when one is not an envelope
    (decode then gives the error it gives)."""
    from acquire.log.schema import JSON_ENCODING, decode

    records = block.records
    datas = [records[a:b] for a, b in zip(block.data_start.tolist(), block.data_end.tolist(), strict=True)]
    topics = [channels[c] for c in block.channel_id.tolist()]
    log_times = block.log_time.tolist()
    if all(encoding == JSON_ENCODING for _, encoding in topics):
        try:
            docs = json.loads(b"[" + b",".join(datas) + b"]")
            if len(docs) == len(datas):
                return [
                    _envelope(topic, t, doc)
                    for (topic, _), t, doc in zip(topics, log_times, docs, strict=True)
                ]
        except Exception:  # noqa: BLE001 - one of them is not an envelope: decode them one by one
            pass
    publish = block.publish_time.tolist()
    out: list[NavMessage] = []
    for (topic, encoding), t, p, data in zip(topics, log_times, publish, datas, strict=True):
        env = decode(topic, encoding, t, p, data)
        out.append((env.topic, env.log_time_ns, env.host_ns, env.clock, env.payload))
    return out


def _envelope(topic: str, log_time_ns: int, doc: Any) -> NavMessage:
    """What :func:`acquire.log.schema.decode` takes from a JSON envelope (its checks too)."""
    int(doc["seq"])
    host_ns = int(doc["host_ns"])
    doc["device_ns"]  # noqa: B018 - an envelope has it
    clock = str(doc["clock"])
    data = doc["data"]
    doc.get("time_base")
    return topic, log_time_ns, host_ns, clock, data


#: an ordered map, ``mapper(fn, items) == [fn(x) for x in items]``, that may run the calls in
#: parallel (``mls georef`` on a cluster: :func:`office.deliver.executors.ordered_map`)
Mapper = Callable[[Callable[[Any], Any], list], list]
#: a segment's navigation is read in this many pieces at most when a mapper shares them out
PIECES_PER_SEGMENT = 8


@dataclass
class NavPiece:
    """What a run of :data:`NAV_TOPICS` messages (in file order) gives: the INS epochs with a
    GPS time, position and attitude (``values``: the pose, then the six sigmas, NaN when absent;
    ``from_clock``: timed by the clock model), the rows the unlocked clock model timed (with
    their receipt), the synced epochs' receipt and time tags, and the raw events."""

    t_ns: np.ndarray
    values: np.ndarray  # (k, 12)
    from_clock: np.ndarray
    unlocked_rows: np.ndarray
    unlocked_host_ns: np.ndarray
    sync_host_ns: np.ndarray
    sync_t_ns: np.ndarray
    raw_events: list[tuple[int, int, str, dict[str, Any]]]


def _collect(messages: Iterable[NavMessage]) -> NavPiece:
    """The :class:`NavPiece` of ``messages``."""
    t_ns: list[int] = []
    values: list[list[Any]] = []
    from_clock: list[bool] = []
    raw_events: list[tuple[int, int, str, dict[str, Any]]] = []
    sync_host: list[int] = []
    sync_t: list[int] = []
    unlocked: list[tuple[int, int]] = []  # (row, receipt) of the epochs the unlocked clock timed
    for topic, log_time_ns, host_ns, clock, d in messages:
        assert isinstance(d, dict)  # /ins/nav and /events are JSON documents
        if topic == "/events":
            raw_events.append((log_time_ns, host_ns, clock, d))
            continue
        t = d.get("time_gps_ns")
        if t is None:
            continue
        by_clock = d.get("time_source") == "clock"
        if not by_clock:
            sync_host.append(host_ns)
            sync_t.append(int(t))
        vals = list(map(d.get, _POSE))
        if None in vals:  # (JSON values: only None equals None)
            continue
        if by_clock and clock == "UNLOCKED":
            unlocked.append((len(t_ns), host_ns))
        t_ns.append(int(t))
        values.append([*vals, *(np.nan if v is None else v for v in map(d.get, _SIGMAS))])
        from_clock.append(by_clock)
    return NavPiece(
        np.array(t_ns, np.int64),
        np.array(values, np.float64).reshape(-1, 12),
        np.array(from_clock, bool),
        np.array([row for row, _ in unlocked], np.int64),
        np.array([host for _, host in unlocked], np.int64),
        np.array(sync_host, np.int64),
        np.array(sync_t, np.int64),
        raw_events,
    )


def _join(pieces: list[NavPiece]) -> NavPiece:
    """The pieces of consecutive runs of messages as the piece of the whole run."""
    if len(pieces) == 1:
        return pieces[0]
    starts = np.cumsum([0] + [p.t_ns.size for p in pieces[:-1]])
    return NavPiece(
        np.concatenate([p.t_ns for p in pieces]),
        np.concatenate([p.values for p in pieces]),
        np.concatenate([p.from_clock for p in pieces]),
        np.concatenate([p.unlocked_rows + k for p, k in zip(pieces, starts.tolist(), strict=True)]),
        np.concatenate([p.unlocked_host_ns for p in pieces]),
        np.concatenate([p.sync_host_ns for p in pieces]),
        np.concatenate([p.sync_t_ns for p in pieces]),
        [e for p in pieces for e in p.raw_events],
    )


def nav_piece(task: tuple[str, int, int]) -> NavPiece:
    """The :class:`NavPiece` of the MCAP chunks [lo, hi) of those holding :data:`NAV_TOPICS`
    of the segment ``task`` = (path, lo, hi), which closed normally (a task a mapper runs)."""
    path, lo, hi = task
    return _collect(_segment_messages(path, slice(lo, hi)))


def _pieces(session: Path, progress: ReadProgress | None, mapper: Mapper | None) -> list[NavPiece]:
    """The session's navigation in pieces: one, read here; or, with a ``mapper`` and every
    segment closed normally, up to :data:`PIECES_PER_SEGMENT` per segment, run by it."""
    from acquire.log.indexed import topic_chunks

    paths = _indexed_segments(session) if mapper is not None else None
    if not paths:
        return [_collect(nav_messages(session, progress))]
    tasks = []
    for path in paths:
        n = topic_chunks(path, NAV_TOPICS) or 0
        step = max(1, -(-n // PIECES_PER_SEGMENT))
        tasks += [(str(path), lo, min(lo + step, n)) for lo in range(0, n, step)]
    assert mapper is not None
    return mapper(nav_piece, tasks)


def read_nav_and_events(
    session: Path, progress: ReadProgress | None, mapper: Mapper | None = None
) -> tuple[InsEpochs, list[TimedEvent]]:
    """The INS epochs, and the events as ``(gps_ns, how, data)``: the event's log time when
    the clock model was locked (or holding over), else its receipt mapped to GPS time through
    the INS time tags around it (``how``: ``clock`` / ``ins`` / ``system``). An INS epoch timed
    by the clock model while it was unlocked (the INS not synced for that epoch, e.g. one that
    lost its STATUS sentence) is re-timed the same way, so it does not land where the
    free-running clock put it. ``mapper``: the messages decoded in pieces by it (:func:`_pieces`;
    the same result)."""
    piece = _join(_pieces(session, progress, mapper))
    if piece.t_ns.size < 2:
        raise ExportError(
            f"{session}: {piece.t_ns.size} INS epochs with position and attitude in "
            f"/ins/nav; a trajectory needs at least 2"
        )
    ins_time = _InsTime(piece.sync_host_ns, piece.sync_t_ns)
    retimed = _retime(piece, ins_time)
    return _epochs(piece, retimed), _time_events(piece.raw_events, ins_time)


def _retime(piece: NavPiece, ins_time: _InsTime) -> int:
    """Re-time the epochs the unlocked clock model timed through the INS time tags around
    their receipt (in place); how many could be."""
    retimed = 0
    for i, host_ns in zip(piece.unlocked_rows.tolist(), piece.unlocked_host_ns.tolist(), strict=True):
        t_ins = ins_time.gps_ns(host_ns)
        if t_ins is not None:
            piece.t_ns[i] = t_ins
            retimed += 1
    return retimed


def _epochs(piece: NavPiece, retimed: int) -> InsEpochs:
    """The rows as epochs in time order, a repeated time kept once."""
    order = np.argsort(piece.t_ns, kind="stable")
    t, a, clock = piece.t_ns[order], piece.values[order], piece.from_clock[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    t, a, clock = t[keep], a[keep], clock[keep]
    return InsEpochs(t, a[:, 0], a[:, 1], a[:, 2], a[:, 3:6], a[:, 6:12], int(clock.sum()), retimed)


def _time_events(
    raw_events: list[tuple[int, int, str, dict[str, Any]]], ins_time: _InsTime
) -> list[TimedEvent]:
    """The events at their log time when the clock model was not unlocked, else through the INS
    time tags around their receipt, else (no synced epoch near) at the system clock's."""
    events: list[TimedEvent] = []
    for log_ns, host_ns, state, d in raw_events:
        if state != "UNLOCKED":
            events.append((log_ns, "clock", d))
        elif (t_ins := ins_time.gps_ns(host_ns)) is not None:
            events.append((t_ins, "ins", d))
        else:
            events.append((log_ns, "system", d))
    return events


class _InsTime:
    """Host receive time → GPS time through the synced INS epochs received around it (their
    time tags against their receive stamps), for what the clock model could not time."""

    def __init__(self, host_ns: np.ndarray, gps_ns: np.ndarray) -> None:
        order = np.argsort(host_ns, kind="stable")
        self.host, self.t = host_ns[order], gps_ns[order]

    def gps_ns(self, host_ns: int) -> int | None:
        """None when no synced epoch was received within 1 s of ``host_ns``."""
        host, t = self.host, self.t
        k = int(np.searchsorted(host, host_ns))
        near = [j for j in (k - 1, k) if 0 <= j < host.size and abs(int(host[j]) - host_ns) < NS_PER_S]
        if not near:
            return None
        if len(near) == 2 and host[near[1]] > host[near[0]]:
            a, b = near
            w = (host_ns - int(host[a])) / (int(host[b]) - int(host[a]))
            return int(t[a]) + round(w * (int(t[b]) - int(t[a])))
        j = near[0]
        return int(t[j]) + host_ns - int(host[j])


def fill_sigmas(t_ns: np.ndarray, sig: np.ndarray) -> tuple[np.ndarray | None, int]:
    """The per-epoch sigmas with the epochs that lack some (a lost STDPOS/STDHRP sentence, the
    first epoch after start-up) interpolated in time from the epochs that have all six; None
    when fewer than half the epochs have them. Returns (sigmas, epochs filled)."""
    good = np.all(np.isfinite(sig) & (sig > 0), axis=1)
    if good.all():
        return sig, 0
    if good.sum() < max(2, 0.5 * good.size):
        return None, 0
    t = (t_ns - t_ns[0]).astype(np.float64)
    filled = sig.copy()
    for j in range(sig.shape[1]):
        filled[~good, j] = np.interp(t[~good], t[good], sig[good, j])
    return filled, int((~good).sum())


def nav_trajectory(
    nav: InsEpochs, sig: np.ndarray | None, frame: LocalFrame | None, max_gap_s: float
) -> Trajectory:
    """The trajectory of the INS epochs, with ``sig`` (:func:`fill_sigmas`) when not None."""
    from calib.core.trajectory import Trajectory

    return Trajectory.from_geodetic(
        frames.gps_ns_to_seconds(nav.t_ns),
        nav.lat,
        nav.lon,
        nav.h,
        np.radians(nav.rpy_deg),
        frame,
        sigma_p_m=sig[:, :3] if sig is not None else None,
        sigma_rpy_rad=np.radians(sig[:, 3:]) if sig is not None else None,
        max_gap_s=max_gap_s,
        name="/ins/nav",
    )


def session_site(session: Path, options: ExportOptions, summary: dict) -> tuple[Site, Path]:
    from calib.core.georef import Mount
    from calib.io.configfile import ConfigError
    from calib.io.site import load_site

    path = options.site_file or (session / "site.yaml")
    if options.site_file is None and not path.exists():  # else load_site says what is wrong
        raise ExportError(
            f"{session}: no site file in the session (the vessel config had no "
            f"site_file): give one with --site site.yaml"
        )
    try:
        site = load_site(path)
    except ConfigError as e:
        raise ExportError(str(e)) from None
    m = summary.get("mount")
    if m is not None:  # the vessel config's mount is what was installed during the session
        v = summary_mount(session / "session.json", m)
        site = replace(
            site,
            mount=Mount(
                lever_arm_m=v["lever_arm_m"],
                nominal_rad=np.radians(v["nominal_deg"]),
                boresight_rad=np.radians(v["boresight_apriori_deg"]),
            ),
        )
    return site, path


def summary_mount(path: Path, m: object) -> dict[str, np.ndarray]:
    """session.json's ``mount``, checked: three finite numbers for each of its three keys."""
    keys = ("lever_arm_m", "nominal_deg", "boresight_apriori_deg")
    if not isinstance(m, dict):
        raise ExportError(f"{path}: mount: got {m!r}, expected an object with {', '.join(keys)}")
    out = {}
    for key in keys:
        v = m.get(key)
        ok = (
            isinstance(v, list)
            and len(v) == 3
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)
        )
        if not ok:
            raise ExportError(f"{path}: mount.{key}: got {v!r}, expected a list of 3 numbers")
        out[key] = np.asarray(v, float)
    return out


@dataclass(frozen=True)
class Navigation:
    """A session's navigation as every job that reads one reads it (:func:`read_navigation`)."""

    site: Site  # with the mount of the session's vessel config
    site_path: Path
    nav: InsEpochs
    events: list[TimedEvent]
    sigmas: np.ndarray | None  # per epoch (:func:`fill_sigmas`); None when too few epochs have them
    filled: int  # epochs whose sigmas were interpolated
    trajectory: Trajectory


def read_navigation(
    session: Path,
    options: ExportOptions,
    summary: dict,
    progress: ReadProgress | None,
    mapper: Mapper | None = None,
) -> Navigation:
    """The site (with the session's mount), the INS epochs and events, their sigmas (filled:
    :func:`fill_sigmas`) and the trajectory, as every job that reads a session's navigation
    reads them (``mapper``: :func:`read_nav_and_events`)."""
    from calib.core.trajectory import TrajectoryError

    try:
        site, site_path = session_site(session, options, summary)
        nav, events = read_nav_and_events(session, progress, mapper)
    except SessionReadError as e:
        raise ExportError(str(e)) from None
    sig, filled = fill_sigmas(nav.t_ns, nav.sig)
    try:
        traj = nav_trajectory(nav, sig, site.reference, options.max_gap_s)
    except TrajectoryError as e:
        raise ExportError(f"{session}: /ins/nav: {e}") from None
    return Navigation(
        site=site, site_path=site_path, nav=nav, events=events, sigmas=sig, filled=filled, trajectory=traj
    )
