"""``mls georef``: a whole survey (session or bundle) → LAZ tiles with per-point σ.

:func:`run_georef` plans the job in this process (the source's trajectory, lines and time
chunks, the calibration, the output CRS), writes the plan to ``<out>/.georef/plan.json``, runs
every chunk (:func:`office.deliver.chunkjob.process_chunk`) and then every tile file
(:func:`office.deliver.tiles.write_file`) on the executor, and ends with ``summary.json`` and
``summary.md`` in ``<out>``. The chunks' parts are removed once every file is written.

Resuming (``resume=True``): the plan must be the same (same source, calibration, options:
its fingerprint); chunks with a record and files with a record are not run again. A job killed
at any point therefore loses no finished tile, and a tile file is never half written
(:func:`calib.io.tileparts.write_tile`). Without ``resume`` a non-empty ``out`` is refused unless
``force`` (then the old job state is cleared and files of the same names are replaced).
"""

from __future__ import annotations

import functools
import hashlib
import json
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from office.deliver.chunkjob import (
    ChunkContext,
    ChunkDone,
    ChunkTask,
    chunk_complete,
    chunk_record_path,
    process_chunk,
    slice_trajectory,
    state_dir,
    with_site_sigmas,
    write_atomic,
)
from office.deliver.executors import Executor, InProcess, ordered_map
from office.deliver.options import GeorefError, GeorefOptions
from office.deliver.space import check_space, is_out_of_space, out_of_space, source_returns, space_needed
from office.deliver.tiles import (
    FileDone,
    FileTask,
    file_done,
    file_record_path,
    plan_files,
    read_chunk_records,
    write_file,
)

if TYPE_CHECKING:
    from calib.core.trajectory import Trajectory
    from office.deliver.calibration import Calibration
    from office.deliver.sources import Source
    from office.jobs.sessionread import Mapper

NS_PER_S = 1_000_000_000
Progress = Callable[[str, int, int, int], None]  # stage, done, total, points so far
#: the options of a job that gives none
DEFAULT_OPTIONS = GeorefOptions()


@dataclass(kw_only=True)
class GeorefResult:
    out_dir: Path
    files: list[dict]
    counters: dict[str, int]
    chunks: int
    chunks_run: int
    files_run: int
    executor: str
    provenance: dict
    warnings: list[str] = field(default_factory=list)
    peak_rss_mb: dict[int, float] = field(default_factory=dict)  # worker pid → peak RSS
    wall_s: float = 0.0
    #: wall seconds of the plan (this process), of the tasks (chunks, and the line tiles ready
    #: meanwhile) and of the tiles left for the end (squares, transits, late parts)
    stage_s: dict[str, float] = field(default_factory=dict)

    @property
    def n_points(self) -> int:
        return sum(int(f["n_points"]) for f in self.files)


def _prepare_out(out: Path, resume: bool, fingerprint: str) -> None:
    """A resumed job's plan must be this one; a new job starts in an empty (checked) or forced
    ``out`` (created and locked: :func:`_claim_out`) without the old job's state."""
    plan = state_dir(out) / "plan.json"
    if resume:
        old = json.loads(plan.read_text()).get("fingerprint")
        if old != fingerprint:
            raise GeorefError(
                f"{out}: --resume: the job there was planned with other inputs or options "
                f"(plan {str(old)[:12]}…, now {fingerprint[:12]}…); use a new --out, or --force to start over"
            )
        return
    if state_dir(out).exists():
        shutil.rmtree(state_dir(out))


def run_georef(
    source_path: str | Path,
    out_dir: str | Path,
    options: GeorefOptions = DEFAULT_OPTIONS,
    calibration: str | None = None,
    *,
    executor: Executor | None = None,
    resume: bool = False,
    force: bool = False,
    sbet: str | Path | None = None,
    smrmsg: str | Path | None = None,
    db: str | Path | None = None,
    max_gap_s: float = 1.0,
    progress: Progress | None = None,
) -> GeorefResult:
    """Georeference a survey into tiles (module docstring), holding ``out``'s writer lock."""
    out = Path(out_dir)
    lock = _claim_out(out, resume, force)
    space = _Space()
    try:
        return _georef(
            source_path,
            out,
            options,
            calibration,
            executor=executor,
            resume=resume,
            sbet=sbet,
            smrmsg=smrmsg,
            db=db,
            max_gap_s=max_gap_s,
            progress=progress,
            space=space,
        )
    except OSError as e:
        if is_out_of_space(e):
            raise out_of_space(out, space.need) from None
        raise
    finally:
        lock.release()


class _Space:
    """What the job needs on disk (bytes), once its source is planned."""

    need: int | None = None


def _claim_out(out: Path, resume: bool, force: bool):
    """Check ``out`` (a new job: empty, or ``force``; a resumed job: its plan is there), create
    it and take its writer lock (:func:`calib.io.outputs.lock_output_dir`) before reading anything."""
    from calib.io.dirlock import OutputLocked
    from calib.io.outputs import OutputError, lock_output_dir

    if resume and not (state_dir(out) / "plan.json").exists():
        raise GeorefError(f"{out}: --resume: no job to resume here (no .georef/plan.json)")
    try:
        return lock_output_dir(out, "--out", force or resume)
    except (OutputError, OutputLocked) as e:
        raise GeorefError(str(e)) from None


def _georef(
    source_path: str | Path,
    out: Path,
    options: GeorefOptions,
    calibration: str | None,
    *,
    executor: Executor | None,
    resume: bool,
    sbet: str | Path | None,
    smrmsg: str | Path | None,
    db: str | Path | None,
    max_gap_s: float,
    progress: Progress | None,
    space: _Space,
) -> GeorefResult:
    """:func:`run_georef` with ``out`` held."""
    t_start = time.monotonic()
    executor = executor or InProcess()
    job = _plan_job(
        source_path,
        options,
        calibration,
        sbet=sbet,
        smrmsg=smrmsg,
        db=db,
        max_gap_s=max_gap_s,
        mapper=_mapper(executor),
    )
    _start_job(out, job, options, resume, space)
    t_plan = time.monotonic()
    run = _JobRun(out, job, options, executor, progress)
    run.submit_chunks()
    t_chunks = run.run_tasks()
    planned = plan_files(run.records, options.max_tile_points, None)
    if not planned:
        raise GeorefError(f"{source_path}: no return passed the filters: nothing to write")
    run.remove_stale(planned)
    t_files = time.monotonic()
    files = [
        json.loads((state_dir(out) / "tiles" / f"{name}.json").read_text())["summary"] for name, *_ in planned
    ]
    result = GeorefResult(
        out_dir=out,
        files=files,
        counters=_sum_counters(run.records),
        chunks=len(job.source.chunks),
        chunks_run=len(run.todo),
        files_run=run.stats["files_run"],
        executor=executor.name,
        provenance=job.provenance,
        warnings=job.warnings,
        peak_rss_mb=run.rss,
        wall_s=time.monotonic() - t_start,
        stage_s={"plan": t_plan - t_start, "tasks": t_chunks - t_plan, "last tiles": t_files - t_chunks},
    )
    _write_summary(result, options)
    shutil.rmtree(state_dir(out) / "parts", ignore_errors=True)
    _remove_orphans(out)
    return result


def _remove_orphans(out: Path) -> None:
    """Remove the temporaries of the job's state that a worker killed while writing them left
    (``.<name>.<pid>.tmp``: every task is done, none of them is written any more)."""
    for tmp in state_dir(out).rglob(".*.tmp"):
        tmp.unlink(missing_ok=True)


@dataclass(frozen=True, kw_only=True)
class _JobPlan:
    """What the job is made of, planned in this process before any chunk runs."""

    source: Source
    trajectory: Trajectory  # with σ for every epoch (the site's when it has none of its own)
    warnings: list[str]
    calibration: Calibration
    software: str
    provenance: dict
    #: provenance, options and chunks: what a resumed job must find the same (its fingerprint)
    plan: dict
    fingerprint: str


def _mapper(executor: Executor) -> Mapper | None:
    """How the plan shares out the reading of a session's navigation: over the executor's workers
    when it has several (the plan is the job's serial part), else not at all."""
    if executor.workers < 2:
        return None
    return functools.partial(ordered_map, executor)


def _plan_job(
    source_path: str | Path,
    options: GeorefOptions,
    calibration: str | None,
    *,
    sbet: str | Path | None,
    smrmsg: str | Path | None,
    db: str | Path | None,
    max_gap_s: float,
    mapper: Mapper | None,
) -> _JobPlan:
    """Open the source (``mapper``: :func:`office.deliver.sources.open_source`), take its
    trajectory (or the SBET's), load the calibration, name the output CRS, and fingerprint the plan."""
    from calib.core.version import software_version
    from calib.io.laz import LasOutputError, output_crs
    from office.deliver.calibration import load_calibration
    from office.deliver.sources import open_source

    source = open_source(source_path, options.chunk_s, max_gap_s, mapper)
    warnings = list(source.warnings)
    traj, traj_name = _trajectory(source, sbet, smrmsg, max_gap_s)
    if not traj.has_sigmas:
        warnings.append(f"{traj_name} carries no sigmas: σ uses the site's pos_sigmas for every epoch")
    traj = with_site_sigmas(traj, source.site)
    software = software_version()
    cal = load_calibration(source.site, calibration, software, db)
    warnings += cal.warnings
    try:
        crs_name = output_crs(options.crs, traj.frame).name
    except LasOutputError as e:
        raise GeorefError(str(e)) from None
    provenance = dict(
        cal.provenance, source=str(Path(source_path).resolve()), trajectory=traj_name, crs=crs_name
    )
    plan = {
        "provenance": provenance,
        "options": options.as_dict(),
        "chunks": [
            [c.index, c.t0_ns, c.t1_ns, Path(c.segment).name if c.segment else None] for c in source.chunks
        ],
    }
    fingerprint = hashlib.sha256(json.dumps(plan, sort_keys=True, default=str).encode()).hexdigest()
    return _JobPlan(
        source=source,
        trajectory=traj,
        warnings=warnings,
        calibration=cal,
        software=software,
        provenance=provenance,
        plan=plan,
        fingerprint=fingerprint,
    )


def _trajectory(
    source: Source, sbet: str | Path | None, smrmsg: str | Path | None, max_gap_s: float
) -> tuple[Trajectory, str]:
    """The trajectory the points are georeferenced on, and its name: the source's own, or the
    post-processed SBET's (with its SMRMSG sigmas)."""
    traj, traj_name = source.trajectory, "/ins/nav" if source.kind == "session" else "trajectory.csv"
    if sbet is None:
        return traj, traj_name
    from calib.io.sbet import SbetError, read_sbet_trajectory

    try:
        traj = read_sbet_trajectory(
            sbet, traj.frame, max_gap_s, near_gps_s=source.chunks[0].t0_ns / NS_PER_S, smrmsg_path=smrmsg
        )
    except SbetError as e:
        raise GeorefError(str(e)) from None
    return traj, str(sbet)


def _start_job(out: Path, job: _JobPlan, options: GeorefOptions, resume: bool, space: _Space) -> None:
    """Make ``out`` ready for the job (:func:`_prepare_out`), check the disk holds what the
    chunks still to run will write, and record a new job's plan."""
    chunks = job.source.chunks
    _prepare_out(out, resume, job.fingerprint)
    share = sum(not chunk_record_path(out, c.index).exists() for c in chunks) / len(chunks)
    space.need = space_needed(source_returns(job.source), options.compress, share)
    check_space(out, space.need)
    if not resume:
        write_atomic(
            state_dir(out) / "plan.json",
            json.dumps(dict(job.plan, fingerprint=job.fingerprint), indent=1).encode(),
        )


def _line_chunks(source: Source, options: GeorefOptions) -> dict[str, set[int]]:
    """The chunks each line's tile needs (those around the line, with a second's margin); none
    with square tiles."""
    if options.tiling != "line":
        return {}
    margin_ns = NS_PER_S
    return {
        f"line-{pid}": {
            c.index for c in source.chunks if c.t0_ns <= end + margin_ns and c.t1_ns > start - margin_ns
        }
        for pid, start, end in source.lines
    }


class _JobRun:
    """The tasks of one job on the executor: every chunk still to run, and every tile file as
    soon as the chunks it needs are done.

    A line's tile needs only the chunks around the line: written as soon as they are done,
    while later chunks still run (a part that turns up in another chunk after all, from a
    record received > 1 s late, is caught by the final plan: that file is written again)."""

    def __init__(
        self, out: Path, job: _JobPlan, options: GeorefOptions, executor: Executor, progress: Progress | None
    ) -> None:
        self.out, self.job, self.options, self.executor, self.progress = out, job, options, executor, progress
        traj, cal, source = job.trajectory, job.calibration, job.source
        self.suffix = ".laz" if options.compress else ".las"
        self.first_t = float(traj.t_gps_s[0])  # dates every header: the same in any run of this plan
        self.ctx = ChunkContext(
            str(out),
            options.crs,
            traj.frame,
            cal.mount,
            cal.covariance,
            cal.scanner,
            options.filters,
            options.tiling,
            options.tile_m,
            options.keep_transits,
            options.compress,
            np.array(source.lines, np.int64).reshape(-1, 3),
        )
        self.line_chunks = _line_chunks(source, options)
        self.todo = [c for c in source.chunks if not chunk_complete(out, c.index)]
        for c in self.todo:  # a record whose parts were lost: the chunk runs again
            chunk_record_path(out, c.index).unlink(missing_ok=True)
        self.records = read_chunk_records(out)
        self.submitted: dict[str, tuple[int, ...]] = {}  # file → its chunks, as submitted (or found done)
        self.rss: dict[int, float] = {}
        self.stats = {
            "chunks": len(source.chunks) - len(self.todo),
            "points": 0,
            "files": 0,
            "written": 0,
            "files_run": 0,
        }
        self.early: set[str] = set()  # line tiles already submitted before the last chunk

    def _file_task(self, name: str, tile: str, chunks: tuple[int, ...], n: int) -> FileTask:
        job = self.job
        return FileTask(
            str(self.out),
            name,
            tile,
            chunks,
            n,
            self.options.crs,
            job.trajectory.frame,
            job.software,
            job.provenance,
            self.first_t,
            self.suffix,
        )

    def submit_files(self, tiles: list[str] | None) -> None:
        """Submit the files of ``tiles`` (all when None) not submitted with these chunks yet;
        a file already written from them only counts."""
        for name, tile, chunks, n in plan_files(self.records, self.options.max_tile_points, tiles):
            if self.submitted.get(name) == chunks:
                continue
            self.submitted[name] = chunks
            if file_done(self.out, name, self.suffix, chunks):
                self.stats["files"] += 1
                continue
            self.stats["files_run"] += 1
            self.executor.submit(write_file, self._file_task(name, tile, chunks, n))

    def ready_lines(self) -> list[str]:
        """The line tiles whose chunks are all done, not submitted early yet."""
        done = set(self.records)
        ready = [t for t, need in self.line_chunks.items() if t not in self.early and need <= done]
        self.early.update(ready)
        return ready

    def submit_chunks(self) -> None:
        """Submit every chunk still to run (on its slice of the trajectory), and the line tiles
        that the done chunks already complete."""
        traj = self.job.trajectory
        for c in self.todo:
            self.executor.submit(
                process_chunk,
                ChunkTask(self.ctx, c, slice_trajectory(traj, c.t0_ns / NS_PER_S, c.t1_ns / NS_PER_S)),
            )
        self.submit_files(self.ready_lines())
        self._report_chunks()

    def _report_chunks(self) -> None:
        if self.progress:
            self.progress(
                "georeferencing", self.stats["chunks"], len(self.job.source.chunks), self.stats["points"]
            )

    def _take(self, res: ChunkDone | FileDone) -> None:
        """One task's result: a chunk's record (then the line tiles it completes), or a file."""
        stats = self.stats
        self.rss[res.pid] = max(self.rss.get(res.pid, 0.0), res.peak_rss_mb)
        if isinstance(res, ChunkDone):
            self.records[res.index] = {"index": res.index, "tiles": res.tiles, "counters": res.counters}
            stats["chunks"] += 1
            stats["points"] += res.counters.get("written", 0)
            self._report_chunks()
            self.submit_files(self.ready_lines())
        else:
            stats["files"] += 1
            stats["written"] += int(res.summary["n_points"])
            if self.progress:
                self.progress("writing tiles", stats["files"], len(self.submitted), stats["written"])

    def run_tasks(self) -> float:
        """Take every result until no file is left to write; the monotonic time the chunks
        (and the tiles ready meanwhile) were done."""
        t_chunks = None
        while True:
            for res in self.executor.results():
                self._take(res)
            if t_chunks is None:
                t_chunks = time.monotonic()
            missing = sorted({c.index for c in self.job.source.chunks} - set(self.records))
            if missing:
                raise GeorefError(
                    f"{self.out}: chunks {missing[:5]} have no record after the run (see the errors above)"
                )
            before = len(self.submitted), self.stats["files_run"]
            self.submit_files(None)  # every tile, on every record: square tiles, transits, late parts
            if (len(self.submitted), self.stats["files_run"]) == before:
                return t_chunks

    def remove_stale(self, planned: list[tuple[str, str, tuple[int, ...], int]]) -> None:
        """Remove the files of an early plan that the final plan replaced by others."""
        submitted = dict(self.submitted)
        for name, *_ in planned:
            submitted.pop(name, None)
        for stale in submitted:
            (self.out / f"{stale}{self.suffix}").unlink(missing_ok=True)
            file_record_path(self.out, stale).unlink(missing_ok=True)


def _sum_counters(records: dict[int, dict]) -> dict[str, int]:
    """The chunks' counters, summed."""
    counters: dict[str, int] = {}
    for r in records.values():
        for k, v in r["counters"].items():
            counters[k] = counters.get(k, 0) + int(v)
    return counters


def _write_summary(r: GeorefResult, options: GeorefOptions) -> None:
    doc = {
        "files": r.files,
        "n_points": r.n_points,
        "counters": r.counters,
        "provenance": r.provenance,
        "options": options.as_dict(),
        "warnings": r.warnings,
    }
    write_atomic(r.out_dir / "summary.json", (json.dumps(doc, indent=1, default=str) + "\n").encode())
    rows = [
        "| file | points | σ_h median / p95 (m) | σ_v median / p95 (m) | passes |",
        "|---|---:|---:|---:|---|",
    ]
    for f in r.files:
        h, v = f["sigma_h_m"], f["sigma_v_m"]
        passes = ", ".join(str(p) for p in f["passes"][:6]) + (" …" if len(f["passes"]) > 6 else "")
        rows.append(
            f"| {f['path']} | {f['n_points']:,} | {h['median']:.3f} / {h['p95']:.3f} "
            f"| {v['median']:.3f} / {v['p95']:.3f} | {passes} |"
        )
    dropped = [
        f"- {k.replace('_', ' ')}: {v:,}"
        for k, v in sorted(r.counters.items())
        if v and k not in ("returns", "written", "datagrams")
    ]
    text = "\n".join(
        [
            "# Survey deliverable",
            "",
            f"{r.n_points:,} points in {len(r.files)} files ({options.tiling} tiles, CRS {r.provenance['crs']}), "
            f"from {r.provenance['source']}.",
            f"Calibration: {r.provenance.get('calibration') or 'none (a-priori boresight)'}; mount "
            f"{r.provenance.get('mount_id')}; boresight roll, pitch, yaw "
            + ", ".join(f"{v:.4f}" for v in r.provenance["boresight_deg"])
            + " deg"
            + (
                " ± " + ", ".join(f"{v:.4f}" for v in r.provenance["boresight_sigma_deg"]) + " (1σ)."
                if r.provenance.get("boresight_sigma_deg")
                else "."
            ),
            "",
            *rows,
            "",
            "Returns read: " + f"{r.counters.get('returns', 0):,}; left out:",
            *(dropped or ["- none"]),
            *([""] + [f"Warning: {w}" for w in r.warnings] if r.warnings else []),
            "",
        ]
    )
    write_atomic(r.out_dir / "summary.md", text.encode("utf-8"))
