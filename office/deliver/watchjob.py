"""``mls watch SESSION|BUNDLE``: the mount watch over a finished survey, block by block as the
daemon runs it live (:mod:`calib.watch`), with its report (:mod:`calib.watch.report`).

The survey is read as ``mls georef`` reads it (:func:`office.deliver.sources.open_source`: a
session's /lidar/raw chunk by chunk through the MCAP index, or a bundle's points); the lines
are the passes marked in /events (a bundle: its pass ids) or, in a session without marks, the
straight runs of the vessel's heading, cut by the daemon's own
:class:`acquire.watch.lines.LineCutter` fed the trajectory. Returns are
thinned evenly to ``max_points_per_s`` as the daemon thins them, so the offline verdict is the
live one."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from acquire.watch.lines import MIN_LINE_S, LineCutter
from calib.io.bundle import ScanPoints
from calib.watch.block import WatchOptions, site_error_model, site_sigmas
from calib.watch.runner import WatchRun, run_watch
from calib.watch.sequential import WatchDesign
from office.deliver.calibration import load_calibration
from office.deliver.options import GeorefError
from office.deliver.sources import open_source, read_chunk

NS_PER_S = 1_000_000_000
MAX_POINTS_PER_S = 20_000.0


@dataclass(frozen=True)
class WatchJob:
    source: Path
    out: Path
    calibration: str | None = None
    options: WatchOptions = field(default_factory=WatchOptions)
    design: WatchDesign = field(default_factory=WatchDesign)
    max_points_per_s: float = MAX_POINTS_PER_S
    min_line_s: float = MIN_LINE_S
    force: bool = False
    plot: bool = True


@dataclass
class WatchOutcome:
    run: WatchRun
    written: list[Path]
    warnings: list[str]
    n_points: int
    lines: list[tuple[int, int, int]]


def lines_from_heading(trajectory, min_line_s: float) -> list[tuple[int, int, int]]:
    """(line id, start, end GPS ns) of the straight runs of a trajectory's heading, cut as the
    daemon cuts them (the speed over ground from the positions)."""
    t = trajectory.t_gps_s
    p = trajectory.p_lgf_m
    dt = np.diff(t)
    speed = np.concatenate(
        [[np.nan], np.hypot(*(np.diff(p[:, :2], axis=0).T)) / np.where(dt > 0, dt, np.nan)]
    )
    cutter = LineCutter(min_line_s)
    out = []
    for ti, h, v in zip(t.tolist(), trajectory.rpy_rad[:, 2].tolist(), speed.tolist(), strict=True):
        out += cutter.on_nav(ti, h, v)
    out += cutter.finish()
    return [(ln.id, round(ln.t_start_s * NS_PER_S), round(ln.t_end_s * NS_PER_S)) for ln in out]


def collect_points(src, lines, max_points_per_s: float, progress=None) -> ScanPoints:
    """The returns on the lines, thinned evenly to ``max_points_per_s`` per chunk."""
    starts = np.array([a for _, a, _ in lines], np.int64)
    ends = np.array([b for _, _, b in lines], np.int64)
    ids = np.array([i for i, _, _ in lines], np.int64)
    parts = []
    for k, spec in enumerate(src.chunks):
        r = read_chunk(spec)
        if r.size:
            if r.pass_id is not None:
                pid = r.pass_id
                keep = np.isin(pid, ids)
            else:
                j = np.searchsorted(starts, r.t_gps_ns, side="right") - 1
                keep = (j >= 0) & (r.t_gps_ns <= ends[np.clip(j, 0, None)])
                pid = ids[np.clip(j, 0, None)]
            keep &= r.range_m > 0
            idx = np.flatnonzero(keep)
            span_s = max((spec.t1_ns - spec.t0_ns) / NS_PER_S, 1e-3)
            budget = max(1, int(max_points_per_s * span_s))
            if idx.size > budget:
                idx = idx[:: int(math.ceil(idx.size / budget))]
            if idx.size:
                parts.append(
                    ScanPoints(
                        pid[idx].astype(np.int64),
                        r.t_gps_ns[idx] / NS_PER_S,
                        r.range_m[idx].astype(float),
                        r.scan_angle_rad[idx].astype(float),
                        (r.intensity[idx] / 65535.0).astype(np.float32),
                    )
                )
        if progress is not None:
            progress("reading returns", k + 1, len(src.chunks))
    if not parts:
        raise GeorefError(f"{src.path}: no return on any line: nothing to watch")
    return ScanPoints.concatenate(parts)


def run_watch_job(job: WatchJob, software: str, progress: Callable | None = None) -> WatchOutcome:
    """Read, watch and report (module docstring); :class:`GeorefError` on bad input."""
    from calib.io.dirlock import LOCK_NAME

    out = Path(job.out)  # (its writer lock, taken by mls watch, is no content)
    if out.exists() and any(p.name != LOCK_NAME for p in out.iterdir()) and not job.force:
        raise GeorefError(f"{out}: not empty; add --force to replace the report in it")
    src = open_source(job.source, chunk_s=10.0)
    warnings = list(src.warnings)
    cal = load_calibration(src.site, job.calibration, software)
    warnings += cal.warnings
    lines = list(src.lines)
    if not lines:
        lines = lines_from_heading(src.trajectory, job.min_line_s)
        warnings.append(
            f"no pass marks: {len(lines)} line(s) cut from the heading (straight runs ≥ {job.min_line_s:g} s)"
        )
    if not lines:
        raise GeorefError(
            f"{src.path}: no survey line (no pass mark, no straight run of {job.min_line_s:g} s)"
        )
    points = collect_points(src, lines, job.max_points_per_s, progress)
    site = src.site

    def on_block(k, n, blk):
        if progress is not None:
            progress("watching blocks", k, n)

    run = run_watch(
        points,
        src.trajectory,
        cal.mount,
        site_sigmas(site),
        site_error_model(site),
        site.wall_azimuth_rad,
        job.options,
        job.design,
        on_block,
    )
    from calib.watch.report import calibration_verdict, write_report

    meta = {
        "source": str(src.path),
        "source_kind": src.kind,
        "calibration": cal.provenance.get("calibration"),
        "calibration_verdict": calibration_verdict(cal.provenance),
        "calibration_warning": cal.untrusted,
        "calibrated_boresight_deg": cal.provenance.get("boresight_deg"),
        "software": software,
        "points_used_per_s": job.max_points_per_s,
        "warnings": warnings,
    }
    written = write_report(run, out, meta, plot=job.plot)
    return WatchOutcome(run, written, warnings, len(points), lines)
