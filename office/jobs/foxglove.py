"""Session → one MCAP file that Foxglove opens as it is (``mls export SESSION --foxglove OUT.mcap``).

:func:`export_foxglove` reads a session written by the daemon and writes its well-known-schema
copy: the channels of :mod:`acquire.foxglove.channels` (the same as the daemon's live server,
``web.foxglove_port``) — a fix and a pose on /vessel/fix and /tf at every INS epoch of /ins/nav,
the mount on /tf once, a cloud per 1/cloud_rate_hz s window of at most ``max_points_per_cloud``
points on /lidar/points, every /events, /clock and /latency record on /log, /clock, /latency.

Frames: :mod:`acquire.foxglove.frames` (z-up ENU and FLU for Foxglove's 3-D panel).

Times: every ``log_time`` and every message's ``timestamp`` (the same number) is **UTC as Unix
ns** — what Foxglove reads, so its timeline shows the real date and time — converted from the
session's GPS time (:func:`~acquire.foxglove.frames.gps_to_unix_ns`: GPS − UTC from the
project's leap-second table at each instant, 18 s since 2017-01-01). The GPS times are the INS
epoch's (:func:`office.jobs.sessionread.read_nav_and_events`) for the fix and the pose, the last
return of its window for a cloud, the record's log time for the others — those logged while the
clock model was UNLOCKED re-timed through the LOCKED ones around them
(:class:`~acquire.foxglove.frames.HostToGps`). The ``mls.session`` metadata states the time
base and the GPS − UTC used; :class:`FoxgloveResult` gives the span in both. Messages are
written in time order; a channel without messages (a session without /clock records) is not in
the file.

Profiles: each ``/lidar/raw`` datagram decoded again as ``mls export`` does (point i at
``t0 + i·dt`` when the packet is PPS-locked and time-valid, else its last point at its receipt,
re-timed like the records when the clock was UNLOCKED; no-returns, returns outside 0.3…119 m
and duplicated datagrams left out), georeferenced with :func:`calib.core.georef.georeference`
in the session's LGF (the stored site file's reference, else the trajectory's mean) with the
vessel config's mount (session.json; else the site's; else none, with a warning). A window's returns sorted by time, those the trajectory does not cover
left out, then every k-th kept (k = ceil(n / max_points_per_cloud)).

The output file is refused when it exists unless ``force``; it is written under a temporary
name in the same directory and renamed when complete: an error or Ctrl-C leaves no half file.
"""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from acquire.foxglove import frames as ff
from acquire.foxglove.channels import NS_PER_S, Channels
from acquire.foxglove.clouds import LATE_NS, Clouds
from acquire.log.read import SessionReadError, iter_messages, session_summary
from office.jobs.export import ExportError, ExportOptions
from office.jobs.foxglove_cloud import decode_profiles
from office.jobs.sessionread import (
    InsEpochs,
    ReadProgress,
    nav_trajectory,
    read_nav_and_events,
    session_site,
    summary_mount,
)

if TYPE_CHECKING:
    from calib.core.georef import Mount
    from calib.core.trajectory import Trajectory

CLOUD_RATE_HZ = 2.0
MAX_POINTS_PER_CLOUD = 50_000

#: every log_time and timestamp of the file (its ``mls.session`` metadata adds the GPS − UTC used)
TIME_BASE = "UTC, Unix ns"


@dataclass
class FoxgloveResult:
    path: Path
    messages: dict[str, int]  # topic → messages written (every topic of TOPICS)
    start_gps_ns: int  # the first and last message, GPS ns (their log times: start/end_unix_ns)
    end_gps_ns: int
    epochs: int  # INS epochs (fix and pose messages)
    packets: int  # /lidar/raw datagrams decoded (duplicates left out)
    returns: int  # returns georeferenced (the trajectory covers them), before decimation
    points: int  # points written in the clouds
    cloud_rate_hz: float
    warnings: list[str] = field(default_factory=list)

    @property
    def span_s(self) -> float:
        return (self.end_gps_ns - self.start_gps_ns) / NS_PER_S

    @property
    def start_unix_ns(self) -> int:
        """The first message's log time in the file (UTC, Unix ns)."""
        return ff.gps_to_unix_ns(self.start_gps_ns)[0]

    @property
    def end_unix_ns(self) -> int:
        return ff.gps_to_unix_ns(self.end_gps_ns)[0]


# -- the session's pieces -----------------------------------------------------------------------


def _mount_and_frame(session: Path, summary: dict, nav, warnings: list[str]):
    """The mount (vessel config's, else the stored site's) and the LGF (the stored site's
    reference, else the trajectory's mean)."""
    from calib.core.frames import LocalFrame
    from calib.core.georef import Mount

    if (session / "site.yaml").exists():
        site, _ = session_site(session, ExportOptions(), summary)  # with the vessel config's mount
        mount, frame = site.mount, site.reference
    else:
        frame, m = None, summary.get("mount")
        if m is not None:
            v = summary_mount(session / "session.json", m)
            mount = Mount(
                v["lever_arm_m"], np.radians(v["nominal_deg"]), np.radians(v["boresight_apriori_deg"])
            )
        else:
            mount = Mount()
            warnings.append(
                "no mount in session.json and no site.yaml in the session: the profiles are "
                "georeferenced with an identity mount (no lever arm, no rotation)"
            )
    return mount, frame or LocalFrame.at_mean(nav.lat, nav.lon, nav.h)


def _records(
    session: Path, progress: ReadProgress | None
) -> tuple[ff.HostToGps, list[tuple[int, str, dict]]]:
    """The host → GPS map, and the /clock, /latency and /events records as ``(gps_ns, topic,
    data)`` sorted by time (those logged UNLOCKED re-timed by the map)."""
    raw, pairs_host, pairs_gps = [], [], []
    for env in iter_messages(session, {"/clock", "/latency", "/events"}, progress):
        if not isinstance(env.payload, dict):
            continue
        raw.append((env.host_ns, env.log_time_ns, env.clock, env.topic, env.payload))
        if env.clock != "UNLOCKED":
            pairs_host.append(env.host_ns)
            pairs_gps.append(env.log_time_ns)
    to_gps = ff.HostToGps(pairs_host, pairs_gps)
    out = [
        (to_gps.gps_ns(host, log) if clock == "UNLOCKED" else log, topic, data)
        for host, log, clock, topic, data in raw
    ]
    out.sort(key=lambda r: r[0])
    return to_gps, out


# -- clouds -------------------------------------------------------------------------------------


class _Writer(Channels):
    """The channels of one export, in their own context, written to an MCAP file in time order."""

    def __init__(self, path: Path, devices: list[str]) -> None:
        import foxglove

        self.ctx = foxglove.Context()
        self.mcap = foxglove.open_mcap(path, allow_overwrite=True, context=self.ctx)
        super().__init__(self.ctx, devices)

    def close(self) -> None:
        self.mcap.close()


def _remove(path: Path) -> None:
    """Remove a temporary file, if it is there (never an error of its own)."""
    with contextlib.suppress(OSError):
        path.unlink()


# -- the export ---------------------------------------------------------------------------------


def _write_all(w: _Writer, session: Path, nav, traj, mount, to_gps, records, options: dict, step):
    """Every message, in time order: fixes, poses and records up to each cloud, then the cloud."""
    t_nav = nav.t_ns
    xyz, q = ff.vessel_pose_enu(traj.p_lgf_m, traj.r_b_n)
    s_xyz, s_q = ff.scanner_pose_flu(mount.lever_arm_m, mount.r_s_b)
    locked_offset = options["locked_offset_ns"]
    i = j = 0

    def upto(limit_ns: int) -> None:
        nonlocal i, j
        while i < t_nav.size or j < len(records):
            ti = int(t_nav[i]) if i < t_nav.size else None
            tj = records[j][0] if j < len(records) else None
            if ti is not None and (tj is None or ti <= tj):
                if ti > limit_ns:
                    return
                if i == 0:  # the mount, once: Foxglove keeps the latest transform of a frame
                    w.transform(ti, ff.VESSEL_FRAME, ff.SCANNER_FRAME, s_xyz, s_q)
                w.transform(ti, ff.WORLD_FRAME, ff.VESSEL_FRAME, xyz[i], q[i])
                w.fix_msg(ti, nav.lat[i], nav.lon[i], nav.h[i], nav.sig[i, :3])
                i += 1
            else:
                assert tj is not None  # the epochs are done or the record comes first
                if tj > limit_ns:
                    return
                t_rec, topic, data = records[j]
                w.record(t_rec, topic, data, locked_offset)
                j += 1

    period_ns = round(NS_PER_S / options["cloud_rate_hz"])
    clouds = Clouds(period_ns, options["max_points_per_cloud"], traj, mount)
    counts: dict[str, int] = {}
    decoded = decode_profiles(
        session, to_gps, options["protocol"], clouds, counts, step("georeferencing the profiles")
    )
    for _ in decoded:
        for t_ns, origin, packed, _n in clouds.ready():
            upto(t_ns)
            w.cloud(t_ns, origin, packed)
    for t_ns, origin, packed, _n in clouds.ready(final=True):
        upto(t_ns)
        w.cloud(t_ns, origin, packed)
    upto(2**63 - 1)
    return clouds, counts


def _metadata(
    session: Path, summary: dict, traj, mount, cloud_rate_hz: float, leaps: set[int]
) -> dict[str, str]:
    """The MCAP's ``mls.session`` metadata record: what the file is, its time base (with the
    GPS − UTC seconds ``leaps`` used) and frames."""
    from calib.core.gpstime import leap_table
    from calib.core.version import software_version

    ref = traj.frame
    deg = np.degrees
    table, counts = leap_table(), [str(n) for n in sorted(leaps)]
    leap = f"GPS − UTC = {', then '.join(counts) or '?'} s during this session"
    return {
        "session": session.name,
        "vessel": str(summary.get("vessel", "")),
        "time_base": f"{TIME_BASE} (leap seconds from the project's table: {leap})",
        "gps_minus_utc_s": " ".join(counts),  # the seconds subtracted (two: a leap second inside)
        "leap_table": f"{table.source}; expires {table.expires.isoformat()}",
        "world_frame": f"{ff.WORLD_FRAME}: east, north, up (m) at the LGF reference",
        "lgf_reference_lat_deg": repr(float(ref.lat_deg)),
        "lgf_reference_lon_deg": repr(float(ref.lon_deg)),
        "lgf_reference_height_m": repr(float(ref.height_m)),
        "vessel_frame": f"{ff.VESSEL_FRAME}: x bow, y port, z up (the INS body frame FRD turned z-up)",
        "scanner_frame": f"{ff.SCANNER_FRAME}: the scanner frame S (scan plane y-z)",
        "mount_lever_arm_m": " ".join(f"{v:.4f}" for v in mount.lever_arm_m),
        "mount_nominal_deg": " ".join(f"{v:.6f}" for v in deg(mount.nominal_rad)),
        "mount_boresight_deg": " ".join(f"{v:.6f}" for v in deg(mount.boresight_rad)),
        "cloud_rate_hz": f"{cloud_rate_hz:g}",
        "software": software_version(),
    }


def export_foxglove(
    session: str | Path,
    out: str | Path,
    *,
    cloud_rate_hz: float = CLOUD_RATE_HZ,
    max_points_per_cloud: int = MAX_POINTS_PER_CLOUD,
    force: bool = False,
    require_complete: bool = False,
    progress: Callable[[str, float, float | None], None] | None = None,
) -> FoxgloveResult:
    """Write the Foxglove MCAP of a session (module docstring); returns what it wrote.

    ``require_complete`` refuses a session with a segment that did not end normally (else it is
    exported with a warning naming the segment and the span lost); ``progress(stage, done,
    total)`` as :func:`office.jobs.export.export_session`'s."""
    from calib.io.outputs import check_output_file

    session, out = Path(session), Path(out)
    if not (math.isfinite(cloud_rate_hz) and 0.01 <= cloud_rate_hz <= 1000.0):
        raise ExportError(f"cloud rate {cloud_rate_hz!r} Hz: expected 0.01 … 1000 clouds per second")
    if max_points_per_cloud < 1:
        raise ExportError(f"max points per cloud {max_points_per_cloud}: expected at least 1")
    check_output_file(out, "--foxglove", force)

    def step(stage: str) -> Callable[[float, float | None], None] | None:
        return None if progress is None else (lambda done, total: progress(stage, done, total))

    s = _read_session(session, require_complete, step)
    options = {
        "cloud_rate_hz": cloud_rate_hz,
        "max_points_per_cloud": int(max_points_per_cloud),
        "protocol": s.protocol,
        # the first LOCKED clock record's offset: the zero of offset_drift_us
        "locked_offset_ns": _first_locked_offset_ns(s.records),
    }
    devices = sorted({str(k) for _, topic, d in s.records if topic == "/latency" for k in d})
    w, clouds, counts = _write_file(session, out, devices, s, options, step, progress)
    warnings = s.warnings + _left_out_warnings(counts, clouds, s.protocol)
    return FoxgloveResult(
        out,
        dict(w.counts),
        w.first_ns or 0,
        w.last_ns or 0,
        int(s.nav.t_ns.size),
        counts.get("packets", 0),
        clouds.returns,
        clouds.points,
        cloud_rate_hz,
        warnings,
    )


@dataclass(frozen=True, kw_only=True)
class _Session:
    """What the export reads of a session before it writes anything."""

    summary: dict
    protocol: str  # of /lidar/raw
    nav: InsEpochs
    mount: Mount
    trajectory: Trajectory
    to_gps: ff.HostToGps
    records: list[tuple[int, str, dict]]  # /clock, /latency, /events: (GPS ns, topic, data)
    warnings: list[str]  # the segments lost, the mount assumed


def _read_session(
    session: Path,
    require_complete: bool,
    step: Callable[[str], Callable[[float, float | None], None] | None],
) -> _Session:
    """The session's summary, navigation, mount and records (``require_complete``: refuse a
    session with a segment that did not end normally)."""
    from acquire.log.read import channel_metadata, session_losses
    from calib.core.trajectory import TrajectoryError

    warnings: list[str] = []
    try:
        summary = session_summary(session)
        losses = session_losses(session)
        if losses and require_complete:
            lost = "; ".join(loss.describe() for loss in losses)
            raise ExportError(f"{session}: incomplete session, not exported (--require-complete): {lost}")
        warnings += [loss.describe() for loss in losses]
        protocol = channel_metadata(session).get("/lidar/raw", {}).get("protocol", "zfp1")
        nav, _ = read_nav_and_events(session, step("reading navigation"))
        mount, frame = _mount_and_frame(session, summary, nav, warnings)
        to_gps, records = _records(session, step("reading clock, latency and events"))
    except SessionReadError as e:
        raise ExportError(str(e)) from None
    try:
        traj = nav_trajectory(nav, None, frame, ExportOptions().max_gap_s)
    except TrajectoryError as e:
        raise ExportError(f"{session}: /ins/nav: {e}") from None
    return _Session(
        summary=summary,
        protocol=protocol,
        nav=nav,
        mount=mount,
        trajectory=traj,
        to_gps=to_gps,
        records=records,
        warnings=warnings,
    )


def _first_locked_offset_ns(records: list[tuple[int, str, dict]]) -> int | None:
    """The offset of the first LOCKED ``/clock`` record (None when the clock never locked)."""
    return next(
        (
            d["offset_ns"]
            for _, topic, d in records
            if topic == "/clock" and d.get("state") == "LOCKED" and isinstance(d.get("offset_ns"), int)
        ),
        None,
    )


def _write_file(
    session: Path,
    out: Path,
    devices: list[str],
    s: _Session,
    options: dict,
    step: Callable[[str], Callable[[float, float | None], None] | None],
    progress: Callable[[str, float, float | None], None] | None,
) -> tuple[_Writer, Clouds, dict[str, int]]:
    """Write every message and the session's metadata under a temporary name, then rename it to
    ``out`` (the temporary file removed on any failure)."""
    tmp = out.with_name(f".{out.name}.{os.getpid()}.part")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        w = _Writer(tmp, devices)
    except OSError as e:  # the SDK's message does not name the file
        _remove(tmp)
        why = f"{e.filename}: {e.strerror}" if e.filename and e.strerror else e.strerror or str(e)
        raise ExportError(f"{out}: --foxglove: cannot write the file there ({why})") from None
    try:
        try:
            clouds, counts = _write_all(
                w, session, s.nav, s.trajectory, s.mount, s.to_gps, s.records, options, step
            )
            if progress is not None:
                progress("writing the MCAP file", 0, None)
            w.mcap.write_metadata(
                "mls.session",
                _metadata(session, s.summary, s.trajectory, s.mount, options["cloud_rate_hz"], w.leaps),
            )
        finally:
            w.close()
        os.replace(tmp, out)
    except BaseException:
        _remove(tmp)
        raise
    return w, clouds, counts


def _left_out_warnings(counts: dict[str, int], clouds: Clouds, protocol: str) -> list[str]:
    """What the clouds left out, and why (none when nothing was)."""
    warnings = []
    for n, what in (
        (counts.get("bad", 0), f"/lidar/raw datagrams did not decode ({protocol})"),
        (counts.get("out_of_range", 0), "returns outside the scanner's range window 0.3…119 m left out"),
        (
            clouds.uncovered,
            "returns outside the trajectory (before its first epoch, after its last, in a gap) left out",
        ),
        (
            clouds.late,
            f"returns came more than {LATE_NS / NS_PER_S:g} s after their cloud was written: left out",
        ),
    ):
        if n:
            warnings.append(f"{n:,} {what}")
    return warnings
