"""Session → calibration bundle (``mls export``, docs/architecture.md §4).

:func:`export_session` reads a session written by the daemon and writes a bundle directory:

- ``trajectory.csv`` from ``/ins/nav``: one row per INS epoch at its GPS time (the INS time tag
  when it was synced, else the clock model's — ``time_source`` of the record), canonical
  attitude, and the per-epoch sigmas (STDHRP/STDPOS, or the STDBIN deviation blocks) when at
  least half the epochs carry them (the others interpolated in time, with a warning). Epochs
  without position or attitude are dropped, repeated times kept once.
- ``points.csv`` from ``/lidar/raw``, every datagram decoded again with the codec named by the
  channel's ``protocol``: point i of a packet at ``t0 + i·dt`` (the packet's own time tag when
  it says PPS-locked and time-valid; otherwise the packet's last point is put at the clock
  model's GPS time of its receipt), its range (m), scan angle (deg, [0, 360)) and intensity
  (the scanner's 16-bit count); no-returns (range 0) dropped, duplicated datagrams kept once.
  Only points inside a pass are written, with the pass id.
- the passes: from the ``/events`` marks (``pass_start`` / ``pass_end`` from the CAN event
  markers or the operator's MQTT commands, at their GPS log time); when the session has none,
  from the site's pass plan (:func:`calib.survey.passplan.plan_site`): the stretches where the
  trajectory runs along a planned line (within ``max_cross_track_m`` of it, heading within
  ``max_heading_error_deg``, between its ends give or take 1 m) for at least ``min_pass_s``.
- ``site.yaml``: the site file (``--site``, else the copy the daemon stored in the session)
  with the mount of the session's vessel config (lever arm, nominal mount, a-priori boresight).

Warnings: a planned pass without points or points of an unplanned pass (naming the site file
and points.csv); returns outside the scanner's range window (0.3…119 m, what the bundle reader
accepts), dropped and counted. Pass ids are int64 throughout.

Optionally ``laz_dir`` (one LAZ per pass, :func:`calib.io.georef_bundle.
georeference_bundle`; points outside the trajectory are left out of the LAZ and counted in a
warning) and ``sbet_path`` (the trajectory as an Applanix SBET, with its SMRMSG
when it has sigmas, :mod:`calib.io.sbet`).

A segment that did not end normally (unfinished with a torn tail, salvaged after a crash:
:func:`acquire.log.read.session_losses`) is exported with a warning naming it and the time span
lost; ``require_complete`` refuses such a session instead.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from acquire.log.read import SessionReadError, channel_metadata, session_summary
from calib.core import frames
from office.jobs.exportbase import PASS_SOURCES, ExportError, ExportOptions, ExportResult, PassWindow
from office.jobs.sessionread import Navigation, TimedEvent, read_navigation

if TYPE_CHECKING:
    from acquire.log.read import SegmentLoss
    from calib.core.trajectory import Trajectory
    from calib.io.site import Site

__all__ = [
    "PASS_SOURCES",
    "ExportError",
    "ExportOptions",
    "ExportResult",
    "PassWindow",
    "export_session",
    "passes_from_events",
    "passes_from_plan",
    "write_sbet",
]

NS_PER_S = 1_000_000_000
END_SLACK_M = 1.0  # plan passes: how far beyond a planned line's ends the vessel still counts


# -- passes -------------------------------------------------------------------------------------


def passes_from_events(events: list[TimedEvent], end_ns: int) -> tuple[list[PassWindow], list[str]]:
    """``pass_start``/``pass_end`` marks (``(gps_ns, how, data)``) → windows; a start without
    its end ends at the next start or at ``end_ns``."""
    warnings: list[str] = []
    timed = [
        (t, how, d)
        for t, how, d in events
        if d.get("event") in ("pass_start", "pass_end") and isinstance(d.get("pass_id"), int)
    ]
    for how, text in (("ins", "the INS time tags around them"), ("system", "the system clock")):
        n = sum(1 for _, h, _ in timed if h == how)
        if n:
            warnings.append(
                f"{n} pass marks were logged while the clock model was UNLOCKED: timed from {text}"
            )
    marks = sorted(((t, d) for t, _, d in timed), key=lambda m: m[0])
    out: list[PassWindow] = []
    open_: tuple[int, int, str] | None = None  # (pass id, start, source)
    for t, d in marks:
        pid, source = int(d["pass_id"]), str(d.get("source", "?"))
        if d["event"] == "pass_start":
            if open_ is not None:
                warnings.append(f"pass {open_[0]} has no pass_end: it ends where pass {pid} starts")
                out.append(PassWindow(open_[0], open_[1], t, open_[2]))
            open_ = (pid, t, source)
        elif open_ is not None and open_[0] == pid:
            out.append(PassWindow(pid, open_[1], t, open_[2]))
            open_ = None
        else:
            warnings.append(f"pass_end of pass {pid} without its pass_start: ignored")
    if open_ is not None:
        warnings.append(f"pass {open_[0]} has no pass_end: it runs to the end of the session")
        out.append(PassWindow(open_[0], open_[1], end_ns, open_[2]))
    return [w for w in out if w.end_gps_ns > w.start_gps_ns], warnings


def passes_from_plan(
    traj: Trajectory, site: Site, t_ns: np.ndarray, options: ExportOptions
) -> list[PassWindow]:
    """Stretches of the trajectory along the site's planned lines (module docstring)."""
    from calib.survey.passplan import plan_site

    plan = plan_site(site, traj.frame)
    p = traj.p_lgf_m
    heading = traj.rpy_rad[:, 2]
    out: list[PassWindow] = []
    max_dh = math.radians(options.max_heading_error_deg)
    for pp in plan.passes:
        d = pp.direction
        rel = p - pp.start_lgf_m
        along = rel @ d
        cross = np.hypot(*(rel - along[:, None] * d)[:, :2].T)
        on = (
            (along >= -END_SLACK_M)
            & (along <= pp.length_m + END_SLACK_M)
            & (cross <= options.max_cross_track_m)
            & (np.abs(frames.wrap_pi(heading - pp.heading_rad)) <= max_dh)
        )
        if not on.any():
            continue
        # runs of consecutive epochs on the line (a short dropout does not split a pass)
        idx = np.flatnonzero(on)
        breaks = np.flatnonzero(np.diff(t_ns[idx]) > options.max_gap_s * NS_PER_S)
        starts, ends = np.concatenate([[0], breaks + 1]), np.concatenate([breaks, [idx.size - 1]])
        for a, b in zip(starts, ends, strict=True):
            t0, t1 = int(t_ns[idx[a]]), int(t_ns[idx[b]])
            if t1 - t0 >= options.min_pass_s * NS_PER_S:
                out.append(PassWindow(pp.id, t0, t1, "plan"))
    return sorted(out, key=lambda w: w.start_gps_ns)


# -- points -------------------------------------------------------------------------------------


def _read_points(session: Path, windows: list[PassWindow], protocol: str, progress):
    """Decoded returns inside the pass windows: (pass_id, gps_ns, range_m, angle_deg,
    intensity), plus counters."""
    from acquire.log.profiles import iter_packets
    from drivers.zf.zfp1 import RANGE_UNIT_M

    starts = np.array([w.start_gps_ns for w in windows], dtype=np.int64)
    ends = np.array([w.end_gps_ns for w in windows], dtype=np.int64)
    ids = np.array([w.pass_id for w in windows], dtype=np.int64)  # survey line ids exceed 32 bits
    order = np.argsort(starts)
    starts, ends, ids = starts[order], ends[order], ids[order]
    parts: list[tuple] = []
    counts: dict[str, int] = {}
    outside = 0
    for _, pk, i, t in iter_packets(session, protocol, counts, progress=progress):
        r = pk.range_01mm
        hit = r > 0
        if not hit.any():
            continue
        t = t[hit]
        k = np.searchsorted(starts, t, side="right") - 1
        inside = (k >= 0) & (t <= ends[np.maximum(k, 0)])
        outside += int((~inside).sum())
        if not inside.any():
            continue
        ang_udeg = (pk.angle0_udeg + i[hit] * pk.dangle_udeg)[inside]
        parts.append(
            (
                ids[k[inside]],
                t[inside],
                r[hit][inside].astype(np.float64) * RANGE_UNIT_M,
                np.mod(ang_udeg * 1e-6, 360.0),
                pk.intensity[hit][inside].astype(np.float32),
            )
        )
    if parts:
        cols = [np.concatenate([p[j] for p in parts]) for j in range(5)]
    else:
        cols = [
            np.zeros(0, np.int64),
            np.zeros(0, np.int64),
            np.zeros(0),
            np.zeros(0),
            np.zeros(0, np.float32),
        ]
    return cols, counts["packets"], counts["unsynced"], counts["bad"], outside


# -- site ---------------------------------------------------------------------------------------


# -- the export ---------------------------------------------------------------------------------


#: the export options of a caller that gives none
DEFAULT_OPTIONS = ExportOptions()


def export_session(
    session_dir: str | Path,
    bundle_dir: str | Path,
    options: ExportOptions = DEFAULT_OPTIONS,
    progress: Callable[[str, float, float | None], None] | None = None,
) -> ExportResult:
    """Write the calibration bundle of a session (module docstring); returns what it wrote."""
    from calib.io.bundle import ScanPoints, pass_warnings, write_bundle

    session = Path(session_dir)

    def step(stage: str) -> Callable[[float, float | None], None] | None:
        return None if progress is None else (lambda done, total: progress(stage, done, total))

    summary, losses, meta = _open_session(session, options)
    nv = read_navigation(session, options, summary, step("reading navigation and events"))
    warnings: list[str] = [loss.describe() for loss in losses]
    windows, source = _pass_windows(session, options, nv, warnings)
    protocol = meta.get("/lidar/raw", {}).get("protocol", "zfp1")
    pts = _bundle_points(session, windows, protocol, step("decoding the profiler packets"), warnings)
    warnings += _reading_warnings(pts, protocol, nv)
    points = ScanPoints(
        pts.pass_id, frames.gps_ns_to_seconds(pts.t_ns), pts.range_m, np.radians(pts.angle_deg), pts.intensity
    )
    if progress is not None:
        progress("writing the bundle", 0, None)
    bundle = write_bundle(bundle_dir, nv.site, nv.trajectory, points)
    warnings += pass_warnings(nv.site, pts.pass_id, nv.site_path, bundle / "points.csv")
    counts = {int(k): int(v) for k, v in zip(*np.unique(pts.pass_id, return_counts=True), strict=True)}
    result = ExportResult(
        bundle,
        int(nv.nav.t_ns.size),
        nv.nav.from_clock,
        int(pts.t_ns.size),
        counts,
        pts.outside,
        pts.packets,
        pts.unsynced,
        source,
        windows,
        warnings,
    )
    if options.sbet_path is not None:
        result.sbet = write_sbet(nv.trajectory, options.sbet_path)
    if options.laz_dir is not None:
        from calib.io.georef_bundle import georeference_bundle

        laz = georeference_bundle(bundle, Path(options.laz_dir), skip_uncovered=True, out_option="--laz")
        result.laz = laz[0]
        warnings += laz[1]["warnings"]  # points left out of the LAZ, pass ids beyond 16 bits
    return result


def _open_session(session: Path, options: ExportOptions) -> tuple[dict, list[SegmentLoss], dict]:
    """The session's summary, its segments that did not end normally (refused with
    ``require_complete``, or when not one message is left to read) and its channels' metadata."""
    from acquire.log.read import session_losses
    from acquire.log.recover import segment_paths

    try:
        summary = session_summary(session)
        losses = session_losses(session)  # segments that did not end normally: data lost
        if losses and options.require_complete:
            lost = "; ".join(loss.describe() for loss in losses)
            raise ExportError(f"{session}: incomplete session, not exported (--require-complete): {lost}")
        empty = {loss.segment for loss in losses if loss.last_ns is None}
        if empty and empty >= {p.name for p in segment_paths(session)}:  # not one message to read
            lost = "; ".join(loss.describe() for loss in losses)
            raise ExportError(f"{session}: nothing to export, no segment holds a complete message: {lost}")
        meta = channel_metadata(session)
    except SessionReadError as e:
        raise ExportError(str(e)) from None
    return summary, losses, meta


def _pass_windows(
    session: Path, options: ExportOptions, nv: Navigation, warnings: list[str]
) -> tuple[list[PassWindow], str]:
    """The passes and where they came from (``events`` or ``plan``, as ``options.passes``
    asks); the warnings of the marks are added to ``warnings``."""
    windows: list[PassWindow] = []
    source = options.passes
    if source in ("auto", "events"):
        windows, w = passes_from_events(nv.events, int(nv.nav.t_ns[-1]))
        warnings += w
        if source == "events" and not windows:
            raise ExportError(
                f"{session}: no pass_start/pass_end marks in /events (use "
                f"--passes plan to take the passes from the site's pass plan)"
            )
        source = "events" if windows else "plan"
    if source == "plan":
        windows = passes_from_plan(nv.trajectory, nv.site, nv.nav.t_ns, options)
        if not windows:
            raise ExportError(
                f"{session}: no marks in /events and the trajectory never runs along a planned "
                f"line of {nv.site_path} (within {options.max_cross_track_m:g} m and "
                f"{options.max_heading_error_deg:g}° for {options.min_pass_s:g} s)"
            )
    return windows, source


@dataclass(frozen=True, kw_only=True)
class _BundlePoints:
    """The returns of the bundle (by pass, then time; within the scanner's range window), and
    what the decoding counted."""

    pass_id: np.ndarray
    t_ns: np.ndarray
    range_m: np.ndarray
    angle_deg: np.ndarray
    intensity: np.ndarray
    packets: int
    unsynced: int  # packets timed by the clock model
    bad: int  # datagrams that did not decode
    outside: int  # returns outside the passes


def _bundle_points(
    session: Path,
    windows: list[PassWindow],
    protocol: str,
    progress: Callable[[float, float | None], None] | None,
    warnings: list[str],
) -> _BundlePoints:
    """Decode the returns inside the passes, sorted by pass then time, those outside the
    scanner's range window dropped (a warning added to ``warnings``)."""
    from calib.io.bundle import SCANNER_RANGE_M

    try:
        (pid, t_ns, rng, ang, inten), packets, unsynced, bad, outside = _read_points(
            session, windows, protocol, progress
        )
    except SessionReadError as e:  # a protocol without a decoder here
        raise ExportError(str(e)) from None
    if t_ns.size == 0:
        raise ExportError(f"{session}: no profiler return inside the {len(windows)} passes")
    order = np.lexsort((t_ns, pid))
    pid, t_ns, rng, ang, inten = pid[order], t_ns[order], rng[order], ang[order], inten[order]
    lo, hi = SCANNER_RANGE_M  # what the bundle reader accepts
    keep = (rng >= lo) & (rng <= hi)
    if not keep.all():
        warnings.append(
            f"{int((~keep).sum()):,} returns outside the scanner's range window {lo:g}…{hi:g} m dropped"
        )
        pid, t_ns, rng, ang, inten = pid[keep], t_ns[keep], rng[keep], ang[keep], inten[keep]
    return _BundlePoints(
        pass_id=pid,
        t_ns=t_ns,
        range_m=rng,
        angle_deg=ang,
        intensity=inten,
        packets=packets,
        unsynced=unsynced,
        bad=bad,
        outside=outside,
    )


def _reading_warnings(pts: _BundlePoints, protocol: str, nv: Navigation) -> list[str]:
    """What the reading of the packets and the INS epochs had to make do with."""
    nav, warnings = nv.nav, []
    if pts.bad:
        warnings.append(f"{pts.bad} /lidar/raw datagrams did not decode ({protocol})")
    if pts.unsynced:
        warnings.append(
            f"{pts.unsynced} profiler packets had no PPS-locked time tag: their points "
            f"were timed by the clock model (receipt time)"
        )
    if nv.filled:
        warnings.append(
            f"{nv.filled} of {nav.t_ns.size} INS epochs had no sigmas: interpolated from the neighbouring epochs"
        )
    elif nv.sigmas is None:
        warnings.append(
            "the INS epochs carry no sigmas (or fewer than half do): the trajectory "
            "is written without them and the calibration uses the site's pos_sigmas"
        )
    if nav.from_clock:
        warnings.append(
            f"{nav.from_clock} INS epochs were timed by the clock model (INS not on "
            f"UTC + PPS)"
            + (
                f", {nav.retimed} of them, received while the clock was "
                f"unlocked, through the INS time tags around them"
                if nav.retimed
                else ""
            )
        )
    return warnings


def write_sbet(traj: Trajectory, path: str | Path) -> Path:
    """The trajectory as an SBET (and ``<path>.smrmsg`` beside it when it has sigmas)."""
    from calib.io.sbet import sbet_records, smrmsg_records, write_smrmsg
    from calib.io.sbet import write_sbet as _write

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rec, _week = sbet_records(traj)
    _write(path, rec)
    if traj.has_sigmas:
        write_smrmsg(path.with_suffix(".smrmsg"), smrmsg_records(traj))
    return path
