"""``mls watch SESSION|BUNDLE``: the mount watch over a finished survey, block by block as the
daemon runs it live (:mod:`calib.watch`), with its report (:mod:`calib.watch.report`).

The survey is read as ``mls georef`` reads it (:func:`office.deliver.sources.open_source`), its
lines and their returns as :mod:`office.deliver.surveylines` reads them: the marked passes or
the straight runs of the heading; returns thinned to ``max_points_per_s`` (a seeded random draw per
chunk; the daemon combs each profile at a shifting phase: both sample every sector of the profile
alike), so the offline verdict is the live one."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from acquire.watch.lines import MIN_LINE_S
from calib.watch.block import WatchOptions, site_error_model, site_sigmas
from calib.watch.runner import WatchRun, run_watch
from calib.watch.sequential import WatchDesign
from office.deliver.calibration import load_calibration
from office.deliver.options import GeorefError
from office.deliver.sources import open_source
from office.deliver.surveylines import collect_points, survey_lines

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
    lines = survey_lines(src, job.min_line_s, warnings)
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
