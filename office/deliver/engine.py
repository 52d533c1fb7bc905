"""``mls georef``: a whole survey (session or bundle) → LAZ tiles with per-point σ.

:func:`run_georef` plans the job in this process (the source's trajectory, lines and time
chunks, the calibration, the output CRS), writes the plan to ``<out>/.georef/plan.json``, runs
every chunk (:func:`office.deliver.chunkjob.process_chunk`) and then every tile file
(:func:`office.deliver.tiles.write_file`) on the executor, and ends with ``summary.json`` and
``summary.md`` in ``<out>``. The chunks' parts are removed once every file is written.

Resuming (``resume=True``): the plan must be the same (same source, calibration, options:
its fingerprint); chunks with a record and files with a record are not run again. A job killed
at any point therefore loses no finished tile, and a tile file is never half written
(:func:`calib.io.lastile.write_tile`). Without ``resume`` a non-empty ``out`` is refused unless
``force`` (then the old job state is cleared and files of the same names are replaced).
"""

from __future__ import annotations

import hashlib
import json
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from office.deliver.chunkjob import (
    ChunkContext,
    ChunkDone,
    ChunkTask,
    chunk_record_path,
    process_chunk,
    slice_trajectory,
    state_dir,
    with_site_sigmas,
    write_atomic,
)
from office.deliver.executors import InProcess
from office.deliver.options import GeorefError, GeorefOptions
from office.deliver.space import check_space, is_out_of_space, out_of_space, source_returns, space_needed
from office.deliver.tiles import (
    FileTask,
    file_done,
    file_record_path,
    plan_files,
    read_chunk_records,
    write_file,
)

NS_PER_S = 1_000_000_000
Progress = Callable[[str, int, int, int], None]  # stage, done, total, points so far


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
    options: GeorefOptions = GeorefOptions(),
    calibration: str | None = None,
    *,
    executor=None,
    resume: bool = False,
    force: bool = False,
    sbet: str | Path | None = None,
    smrmsg: str | Path | None = None,
    db=None,
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
    executor,
    resume: bool,
    sbet: str | Path | None,
    smrmsg: str | Path | None,
    db,
    max_gap_s: float,
    progress: Progress | None,
    space: _Space,
) -> GeorefResult:
    """:func:`run_georef` with ``out`` held."""
    from calib.core.version import software_version
    from calib.io.laz import LasOutputError, output_crs
    from office.deliver.calibration import load_calibration
    from office.deliver.sources import open_source

    t_start = time.monotonic()
    executor = executor or InProcess()
    source = open_source(source_path, options.chunk_s, max_gap_s)
    warnings = list(source.warnings)
    traj, traj_name = source.trajectory, "/ins/nav" if source.kind == "session" else "trajectory.csv"
    if sbet is not None:
        from calib.io.sbet import SbetError, read_sbet_trajectory

        try:
            traj = read_sbet_trajectory(
                sbet, traj.frame, max_gap_s, near_gps_s=source.chunks[0].t0_ns / NS_PER_S, smrmsg_path=smrmsg
            )
        except SbetError as e:
            raise GeorefError(str(e)) from None
        traj_name = str(sbet)
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
    _prepare_out(out, resume, fingerprint)
    share = sum(not chunk_record_path(out, c.index).exists() for c in source.chunks) / len(source.chunks)
    space.need = space_needed(source_returns(source), options.compress, share)
    check_space(out, space.need)
    if not resume:
        write_atomic(
            state_dir(out) / "plan.json", json.dumps(dict(plan, fingerprint=fingerprint), indent=1).encode()
        )

    t_plan = time.monotonic()
    lines = np.array(source.lines, np.int64).reshape(-1, 3)
    ctx = ChunkContext(
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
        lines,
    )
    suffix = ".laz" if options.compress else ".las"
    first_t = float(traj.t_gps_s[0])  # dates every header: the same in any run of this plan

    def file_task(name: str, tile: str, chunks: tuple[int, ...], n: int) -> FileTask:
        return FileTask(
            str(out), name, tile, chunks, n, options.crs, traj.frame, software, provenance, first_t, suffix
        )

    # a line's tile needs only the chunks around the line: written as soon as they are done,
    # while later chunks still run (a part that turns up in another chunk after all, from a
    # record received > 1 s late, is caught by the final plan: that file is written again)
    margin_ns = NS_PER_S
    line_chunks = (
        {
            f"line-{pid}": {
                c.index for c in source.chunks if c.t0_ns <= end + margin_ns and c.t1_ns > start - margin_ns
            }
            for pid, start, end in source.lines
        }
        if options.tiling == "line"
        else {}
    )
    todo = [c for c in source.chunks if not chunk_record_path(out, c.index).exists()]
    records = read_chunk_records(out)
    submitted: dict[str, tuple[int, ...]] = {}  # file → its chunks, as submitted (or found done)
    rss: dict[int, float] = {}
    stats = {"chunks": len(source.chunks) - len(todo), "points": 0, "files": 0, "written": 0, "files_run": 0}

    def submit_files(tiles) -> None:
        for name, tile, chunks, n in plan_files(records, options.max_tile_points, tiles):
            if submitted.get(name) == chunks:
                continue
            submitted[name] = chunks
            if file_done(out, name, suffix, chunks):
                stats["files"] += 1
                continue
            stats["files_run"] += 1
            executor.submit(write_file, file_task(name, tile, chunks, n))

    early: set[str] = set()  # line tiles already submitted before the last chunk

    def ready_lines() -> list[str]:
        done = set(records)
        ready = [t for t, need in line_chunks.items() if t not in early and need <= done]
        early.update(ready)
        return ready

    for c in todo:
        executor.submit(
            process_chunk,
            ChunkTask(ctx, c, slice_trajectory(traj, c.t0_ns / NS_PER_S, c.t1_ns / NS_PER_S)),
        )
    submit_files(ready_lines())
    if progress:
        progress("georeferencing", stats["chunks"], len(source.chunks), stats["points"])
    t_chunks = None
    while True:
        for res in executor.results():
            rss[res.pid] = max(rss.get(res.pid, 0.0), res.peak_rss_mb)
            if isinstance(res, ChunkDone):
                records[res.index] = {"index": res.index, "tiles": res.tiles, "counters": res.counters}
                stats["chunks"] += 1
                stats["points"] += res.counters.get("written", 0)
                if progress:
                    progress("georeferencing", stats["chunks"], len(source.chunks), stats["points"])
                submit_files(ready_lines())
            else:
                stats["files"] += 1
                stats["written"] += int(res.summary["n_points"])
                if progress:
                    progress("writing tiles", stats["files"], len(submitted), stats["written"])
        if t_chunks is None:
            t_chunks = time.monotonic()
        missing = sorted({c.index for c in source.chunks} - set(records))
        if missing:
            raise GeorefError(
                f"{out}: chunks {missing[:5]} have no record after the run (see the errors above)"
            )
        before = len(submitted), stats["files_run"]
        submit_files(None)  # every tile, on every record: square tiles, transits, late parts
        if (len(submitted), stats["files_run"]) == before:
            break
    planned = plan_files(records, options.max_tile_points, None)
    if not planned:
        raise GeorefError(f"{source_path}: no return passed the filters: nothing to write")
    for name, *_ in planned:
        submitted.pop(name, None)
    for stale in submitted:  # files of an early plan that the final plan replaced by others
        (out / f"{stale}{suffix}").unlink(missing_ok=True)
        file_record_path(out, stale).unlink(missing_ok=True)

    t_files = time.monotonic()
    files = [
        json.loads((state_dir(out) / "tiles" / f"{name}.json").read_text())["summary"] for name, *_ in planned
    ]
    counters: dict[str, int] = {}
    for r in records.values():
        for k, v in r["counters"].items():
            counters[k] = counters.get(k, 0) + int(v)
    result = GeorefResult(
        out_dir=out,
        files=files,
        counters=counters,
        chunks=len(source.chunks),
        chunks_run=len(todo),
        files_run=stats["files_run"],
        executor=executor.name,
        provenance=provenance,
        warnings=warnings,
        peak_rss_mb=rss,
        wall_s=time.monotonic() - t_start,
        stage_s={"plan": t_plan - t_start, "tasks": t_chunks - t_plan, "last tiles": t_files - t_chunks},
    )
    _write_summary(result, options)
    shutil.rmtree(state_dir(out) / "parts", ignore_errors=True)
    return result


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
