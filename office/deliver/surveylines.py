"""A finished survey's lines and their returns, thinned at random, as the mount watch reads them
(``mls watch``) and as a targetless calibration of a session reads them (``mls calib run
SESSION`` without targets: :func:`thinned_bundle`).

The lines are the passes marked in /events (a bundle: its pass ids) or, in a session without
marks, the straight runs of the vessel's heading, cut by the daemon's own
:class:`acquire.watch.lines.LineCutter` fed the trajectory. The returns are read chunk by chunk
(:func:`office.deliver.sources.read_chunk`) and thinned to the budget per chunk by a seeded
random draw (:func:`calib.core.sampling.random_subset`), so an hour of survey at the profiler's
full rate is never in memory at once.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from acquire.watch.lines import MIN_LINE_S, LineCutter
from calib.core.sampling import random_subset
from calib.io.bundle import ScanPoints
from office.deliver.options import GeorefError
from office.deliver.sources import Source, open_source, read_chunk

NS_PER_S = 1_000_000_000
#: :func:`collect_points` with ``skip_packets``: a chunk with more returns on its lines than this
#: many times its budget makes the next chunks decode fewer datagrams, whatever else it spans
PACKET_SURPLUS = 4
#: a session chunk's log times trail its returns' times by the logging latency: far less than this
LOG_MARGIN_NS = NS_PER_S


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


def survey_lines(src: Source, min_line_s: float, warnings: list[str]) -> list[tuple[int, int, int]]:
    """The source's marked passes, else the straight runs of its heading (a warning added to
    ``warnings``); :class:`GeorefError` when there is neither."""
    lines = list(src.lines)
    if not lines:
        lines = lines_from_heading(src.trajectory, min_line_s)
        warnings.append(
            f"no pass marks: {len(lines)} line(s) cut from the heading (straight runs ≥ {min_line_s:g} s)"
        )
    if not lines:
        raise GeorefError(f"{src.path}: no survey line (no pass mark, no straight run of {min_line_s:g} s)")
    return lines


def collect_points(
    src: Source, lines, max_points_per_s: float, progress=None, skip_packets: bool = False
) -> ScanPoints:
    """The returns on the lines, thinned to ``max_points_per_s`` per chunk (chunks off
    the lines are not read). ``skip_packets``: the next chunk decodes only the share of its
    datagrams that yields about twice its budget (:func:`_next_share`,
    :func:`~office.deliver.sources.read_session_chunk`): at the profiler's full rate most of
    the datagrams of an hour are then never decoded."""
    starts = np.array([a for _, a, _ in lines], np.int64)
    ends = np.array([b for _, _, b in lines], np.int64)
    ids = np.array([i for i, _, _ in lines], np.int64)
    parts = []
    share = 1.0
    for k, spec in enumerate(src.chunks):
        on_lines_s = _on_lines_s(spec, starts, ends)
        r = read_chunk(spec, share) if on_lines_s > 0 else None
        if r is not None and r.size:
            pid, idx = _on_lines(r, starts, ends, ids)
            span_s = max((spec.t1_ns - spec.t0_ns) / NS_PER_S, 1e-3)
            budget = max(1, int(max_points_per_s * span_s))
            if skip_packets:
                share = _next_share(share, idx.size, budget, on_lines_s / span_s)
            idx = random_subset(idx, budget, spec.index)
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
        raise GeorefError(f"{src.path}: no return on any line")
    return ScanPoints.concatenate(parts)


def _on_lines(r, starts: np.ndarray, ends: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The line id of each return of ``r`` and the indices of the hits on a line."""
    if r.pass_id is not None:
        pid = r.pass_id
        keep = np.isin(pid, ids)
    else:
        j = np.searchsorted(starts, r.t_gps_ns, side="right") - 1
        keep = (j >= 0) & (r.t_gps_ns <= ends[np.clip(j, 0, None)])
        pid = ids[np.clip(j, 0, None)]
    return pid, np.flatnonzero(keep & (r.range_m > 0))


def _on_lines_s(spec, starts: np.ndarray, ends: np.ndarray) -> float:
    """Seconds of the chunk's span on the lines (a session's chunk spans log time, a little
    after the returns' own: its span is taken :data:`LOG_MARGIN_NS` earlier too)."""
    t0 = spec.t0_ns - (LOG_MARGIN_NS if spec.returns is None else 0)
    overlap = np.minimum(ends, spec.t1_ns) - np.maximum(starts, t0)
    return float(np.clip(overlap, 0, None).sum()) / NS_PER_S


def _next_share(share: float, n_on_lines: int, budget: int, on_lines: float) -> float:
    """The share of datagrams the next chunk decodes: about twice its budget of returns, judged
    by a chunk wholly on the lines that decoded ``share`` (others say nothing: a turn); more
    returns than :data:`PACKET_SURPLUS` × its budget always lowers it."""
    if (on_lines >= 0.9 and n_on_lines > 0) or n_on_lines > PACKET_SURPLUS * budget:
        return min(1.0, share * 2 * budget / n_on_lines)
    return share


@dataclass(frozen=True)
class ThinnedSurvey:
    """What :func:`thinned_bundle` wrote."""

    bundle: Path
    n_lines: int
    n_points: int
    line_seconds: float
    warnings: list[str]


def thinned_bundle(
    source: str | Path,
    bundle_dir: str | Path,
    max_points: int,
    min_line_s: float = MIN_LINE_S,
    progress: Callable[[str, float, float | None], None] | None = None,
) -> ThinnedSurvey:
    """A session's (or a bundle's) lines as a calibration bundle of at most ``max_points``
    returns, thinned at random over the line time: what a targetless calibration of a whole survey
    reads (it uses no more), without exporting every return of it."""
    from calib.io.bundle import write_bundle

    src = open_source(source, chunk_s=10.0)
    warnings = list(src.warnings)
    lines = survey_lines(src, min_line_s, warnings)
    line_s = sum((b - a) / NS_PER_S for _, a, b in lines)
    # twice the share: chunks partly off the lines take their whole span's budget and may have
    # fewer returns on the lines than that; then down to max_points by one more draw
    points = collect_points(src, lines, 2 * max_points / max(line_s, 1e-3), progress, skip_packets=True)
    points = points.select(random_subset(np.arange(len(points)), max_points, seed=len(src.chunks)))
    if progress is not None:
        progress("writing the thinned bundle", 0, None)
    bundle = write_bundle(bundle_dir, src.site, src.trajectory, points)
    return ThinnedSurvey(
        bundle=bundle, n_lines=len(lines), n_points=len(points), line_seconds=line_s, warnings=warnings
    )
