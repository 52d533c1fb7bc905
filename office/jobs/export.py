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
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from acquire.errors import AcquireError
from acquire.log.read import SessionReadError, channel_metadata, iter_messages, session_summary
from calib.core import frames

NS_PER_S = 1_000_000_000
PASS_SOURCES = ("auto", "events", "plan")
END_SLACK_M = 1.0  # plan passes: how far beyond a planned line's ends the vessel still counts


class ExportError(AcquireError, ValueError):
    """The session cannot be exported as asked (the message says why and what to do)."""


@dataclass(frozen=True)
class ExportOptions:
    passes: str = "auto"  # auto: events when the session has marks, else the plan
    site_file: Path | None = None  # overrides the site file stored in the session
    max_cross_track_m: float = 5.0  # plan: distance from the planned line
    max_heading_error_deg: float = 20.0  # plan: heading against the line's
    min_pass_s: float = 3.0  # plan: shorter stretches are not passes
    max_gap_s: float = 1.0  # trajectory gap that breaks interpolation (bundle reader's)
    laz_dir: Path | None = None
    sbet_path: Path | None = None
    require_complete: bool = False  # refuse a session with a segment that did not end normally

    def __post_init__(self) -> None:
        if self.passes not in PASS_SOURCES:
            raise ExportError(f"passes {self.passes!r}: expected one of {', '.join(PASS_SOURCES)}")


@dataclass(frozen=True)
class PassWindow:
    pass_id: int
    start_gps_ns: int
    end_gps_ns: int
    source: str  # "can:marks", "mqtt", "plan"


@dataclass
class ExportResult:
    bundle: Path
    epochs: int
    epochs_from_clock: int  # epochs whose time came from the clock model (INS not synced)
    points: int
    points_per_pass: dict[int, int]
    returns_outside_passes: int
    packets: int
    packets_unsynced: int  # datagrams timed by the clock model (no PPS-locked time tag)
    pass_source: str  # "events" or "plan"
    passes: list[PassWindow]
    warnings: list[str] = field(default_factory=list)
    laz: list = field(default_factory=list)  # calib georef PassOutput per pass
    sbet: Path | None = None


# -- reading ------------------------------------------------------------------------------------


@dataclass
class _Nav:
    t_ns: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    h: np.ndarray
    rpy_deg: np.ndarray
    sig: np.ndarray  # (n, 6) north, east, down m, roll, pitch, heading deg (NaN when absent)
    from_clock: int
    retimed: int  # of those, logged while the clock was unlocked: timed by the INS tags around


_SIGMAS = (
    "sigma_north_m",
    "sigma_east_m",
    "sigma_down_m",
    "sigma_roll_deg",
    "sigma_pitch_deg",
    "sigma_heading_deg",
)


def _read_nav_and_events(session: Path, progress) -> tuple[_Nav, list]:
    """The INS epochs, and the events as ``(gps_ns, how, data)``: the event's log time when
    the clock model was locked (or holding over), else its receipt mapped to GPS time through
    the INS time tags around it (``how``: ``clock`` / ``ins`` / ``system``). An INS epoch timed
    by the clock model while it was unlocked (the INS not synced for that epoch, e.g. one that
    lost its STATUS sentence) is re-timed the same way, so it does not land where the
    free-running clock put it."""
    rows, raw_events, sync_host, sync_t, unlocked = [], [], [], [], []
    for env in iter_messages(session, {"/ins/nav", "/events"}, progress):
        d = env.payload
        if env.topic == "/events":
            raw_events.append((env.log_time_ns, env.host_ns, env.clock, d))
            continue
        t = d.get("time_gps_ns")
        vals = [d.get(k) for k in ("lat_deg", "lon_deg", "height_m", "roll_deg", "pitch_deg", "heading_deg")]
        if t is None:
            continue
        from_clock = d.get("time_source") == "clock"
        if not from_clock:
            sync_host.append(env.host_ns)
            sync_t.append(int(t))
        if any(v is None for v in vals):
            continue
        if from_clock and env.clock == "UNLOCKED":
            unlocked.append((len(rows), env.host_ns))
        sig = [np.nan if d.get(k) is None else d[k] for k in _SIGMAS]
        rows.append([int(t), *vals, *sig, from_clock])
    if len(rows) < 2:
        raise ExportError(
            f"{session}: {len(rows)} INS epochs with position and attitude in "
            f"/ins/nav; a trajectory needs at least 2"
        )
    ins_time = _InsTime(np.array(sync_host, np.int64), np.array(sync_t, np.int64))
    retimed = 0
    for i, host_ns in unlocked:
        t_ins = ins_time.gps_ns(host_ns)
        if t_ins is not None:
            rows[i][0] = t_ins
            retimed += 1
    t = np.array([r[0] for r in rows], dtype=np.int64)
    a = np.array([r[1:13] for r in rows], dtype=np.float64)
    clock = np.array([r[13] for r in rows], dtype=bool)
    order = np.argsort(t, kind="stable")
    t, a, clock = t[order], a[order], clock[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    t, a, clock = t[keep], a[keep], clock[keep]
    nav = _Nav(t, a[:, 0], a[:, 1], a[:, 2], a[:, 3:6], a[:, 6:12], int(clock.sum()), retimed)
    events = []
    for log_ns, host_ns, state, d in raw_events:
        if state != "UNLOCKED":
            events.append((log_ns, "clock", d))
        elif (t_ins := ins_time.gps_ns(host_ns)) is not None:
            events.append((t_ins, "ins", d))
        else:
            events.append((log_ns, "system", d))
    return nav, events


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


def _fill_sigmas(t_ns: np.ndarray, sig: np.ndarray) -> tuple[np.ndarray | None, int]:
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


def _trajectory(nav: _Nav, sig: np.ndarray | None, frame, max_gap_s: float):
    """The trajectory of the INS epochs, with ``sig`` (:func:`_fill_sigmas`) when not None."""
    from calib.core.trajectory import Trajectory

    with_sig = sig is not None
    return Trajectory.from_geodetic(
        frames.gps_ns_to_seconds(nav.t_ns),
        nav.lat,
        nav.lon,
        nav.h,
        np.radians(nav.rpy_deg),
        frame,
        sigma_p_m=sig[:, :3] if with_sig else None,
        sigma_rpy_rad=np.radians(sig[:, 3:]) if with_sig else None,
        max_gap_s=max_gap_s,
        name="/ins/nav",
    )


# -- passes -------------------------------------------------------------------------------------


def passes_from_events(events: list, end_ns: int) -> tuple[list[PassWindow], list[str]]:
    """``pass_start``/``pass_end`` marks (``(gps_ns, how, data)``) → windows; a start without
    its end ends at the next start or at ``end_ns``."""
    warnings: list[str] = []
    marks = [
        (t, how, d)
        for t, how, d in events
        if d.get("event") in ("pass_start", "pass_end") and isinstance(d.get("pass_id"), int)
    ]
    for how, text in (("ins", "the INS time tags around them"), ("system", "the system clock")):
        n = sum(1 for _, h, _ in marks if h == how)
        if n:
            warnings.append(
                f"{n} pass marks were logged while the clock model was UNLOCKED: timed from {text}"
            )
    marks = sorted(((t, d) for t, _, d in marks), key=lambda m: m[0])
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


def passes_from_plan(traj, site, t_ns: np.ndarray, options: ExportOptions) -> list[PassWindow]:
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
        for a, b in zip(np.concatenate([[0], breaks + 1]), np.concatenate([breaks, [idx.size - 1]])):
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


def _site(session: Path, options: ExportOptions, summary: dict):
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
        v = _summary_mount(session / "session.json", m)
        site = replace(
            site,
            mount=Mount(
                lever_arm_m=v["lever_arm_m"],
                nominal_rad=np.radians(v["nominal_deg"]),
                boresight_rad=np.radians(v["boresight_apriori_deg"]),
            ),
        )
    return site, path


def _summary_mount(path: Path, m) -> dict[str, np.ndarray]:
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


def _navigation(session: Path, options: ExportOptions, summary: dict, progress):
    """The site (with the session's mount), the INS epochs and events, their sigmas (filled:
    :func:`_fill_sigmas`) and the trajectory, as every job that reads a session's navigation
    reads them: ``(site, site path, nav, events, sigmas, epochs filled, trajectory)``."""
    from calib.core.trajectory import TrajectoryError

    try:
        site, site_path = _site(session, options, summary)
        nav, events = _read_nav_and_events(session, progress)
    except SessionReadError as e:
        raise ExportError(str(e)) from None
    sig, filled = _fill_sigmas(nav.t_ns, nav.sig)
    try:
        traj = _trajectory(nav, sig, site.reference, options.max_gap_s)
    except TrajectoryError as e:
        raise ExportError(f"{session}: /ins/nav: {e}") from None
    return site, site_path, nav, events, sig, filled, traj


# -- the export ---------------------------------------------------------------------------------


def export_session(
    session_dir: str | Path,
    bundle_dir: str | Path,
    options: ExportOptions = ExportOptions(),
    progress: Callable[[str, float, float | None], None] | None = None,
) -> ExportResult:
    """Write the calibration bundle of a session (module docstring); returns what it wrote."""
    from acquire.log.read import session_losses
    from acquire.log.recover import segment_paths
    from calib.io.bundle import SCANNER_RANGE_M, ScanPoints, pass_warnings, write_bundle

    session = Path(session_dir)

    def step(stage: str):
        return None if progress is None else (lambda done, total: progress(stage, done, total))

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
    site, site_path, nav, events, sig, filled, traj = _navigation(
        session, options, summary, step("reading navigation and events")
    )
    warnings: list[str] = [loss.describe() for loss in losses]
    windows: list[PassWindow] = []
    source = options.passes
    if source in ("auto", "events"):
        windows, w = passes_from_events(events, int(nav.t_ns[-1]))
        warnings += w
        if source == "events" and not windows:
            raise ExportError(
                f"{session}: no pass_start/pass_end marks in /events (use "
                f"--passes plan to take the passes from the site's pass plan)"
            )
        source = "events" if windows else "plan"
    if source == "plan":
        windows = passes_from_plan(traj, site, nav.t_ns, options)
        if not windows:
            raise ExportError(
                f"{session}: no marks in /events and the trajectory never runs along a planned "
                f"line of {site_path} (within {options.max_cross_track_m:g} m and "
                f"{options.max_heading_error_deg:g}° for {options.min_pass_s:g} s)"
            )
    protocol = meta.get("/lidar/raw", {}).get("protocol", "zfp1")
    try:
        (pid, t_ns, rng, ang, inten), packets, unsynced, bad, outside = _read_points(
            session, windows, protocol, step("decoding the profiler packets")
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
    if bad:
        warnings.append(f"{bad} /lidar/raw datagrams did not decode ({protocol})")
    if unsynced:
        warnings.append(
            f"{unsynced} profiler packets had no PPS-locked time tag: their points "
            f"were timed by the clock model (receipt time)"
        )
    if filled:
        warnings.append(
            f"{filled} of {nav.t_ns.size} INS epochs had no sigmas: interpolated from the neighbouring epochs"
        )
    elif sig is None:
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
    points = ScanPoints(pid, frames.gps_ns_to_seconds(t_ns), rng, np.radians(ang), inten)
    if progress is not None:
        progress("writing the bundle", 0, None)
    bundle = write_bundle(bundle_dir, site, traj, points)
    warnings += pass_warnings(site, pid, site_path, bundle / "points.csv")
    counts = {int(k): int(v) for k, v in zip(*np.unique(pid, return_counts=True))}
    result = ExportResult(
        bundle,
        int(nav.t_ns.size),
        nav.from_clock,
        int(t_ns.size),
        counts,
        outside,
        packets,
        unsynced,
        source,
        windows,
        warnings,
    )
    if options.sbet_path is not None:
        result.sbet = write_sbet(traj, options.sbet_path)
    if options.laz_dir is not None:
        from calib.io.georef_bundle import georeference_bundle

        laz = georeference_bundle(bundle, Path(options.laz_dir), skip_uncovered=True, out_option="--laz")
        result.laz = laz[0]
        warnings += laz[1]["warnings"]  # points left out of the LAZ, pass ids beyond 16 bits
    return result


def write_sbet(traj, path: str | Path) -> Path:
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
