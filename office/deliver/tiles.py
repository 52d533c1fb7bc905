"""Tile files from chunk parts: which parts make which file, and writing one file.

After every chunk has run, :func:`plan_files` reads the chunks' records and gives each tile its
files: the tile's parts in chunk (= time) order, cut into consecutive runs of at most
``max_tile_points`` (a part is never split), named ``<tile>.laz`` or ``<tile>-p01.laz``,
``-p02``… when there are several. The plan depends only on the records, so a resumed or
distributed job plans the same files. :func:`write_file` writes one through
:func:`calib.io.tileparts.write_tile` (the parts are the file's own LAS records, LAZ chunks for a
``.laz``; whole or not at all) and then its record
``<out>/.georef/tiles/<file>.json`` (its summary and the chunks it was made of) — a file with
its record, made of the chunks the plan names, is done.
"""

from __future__ import annotations

import json
import os
import resource
from dataclasses import dataclass
from pathlib import Path

from office.deliver.chunkjob import part_path, state_dir, write_atomic


@dataclass(frozen=True)
class FileTask:
    out_dir: str
    name: str  # file stem, e.g. line-3, line-3-p02, tile-325100-5041200
    tile: str
    chunks: tuple[int, ...]  # the parts' chunk indexes, in order
    n_points: int
    crs: str
    frame: object
    software: str
    provenance: dict
    first_t_gps_s: float
    suffix: str = ".laz"


@dataclass(frozen=True)
class FileDone:
    name: str
    summary: dict
    peak_rss_mb: float
    pid: int


def read_chunk_records(out_dir: str | Path) -> dict[int, dict]:
    out = {}
    for p in sorted((state_dir(out_dir) / "chunks").glob("c*.json")):
        rec = json.loads(p.read_text())
        out[int(rec["index"])] = rec
    return out


def plan_files(
    records: dict[int, dict], max_tile_points: int, tiles=None
) -> list[tuple[str, str, tuple[int, ...], int]]:
    """(file stem, tile, chunk indexes, points) of every file of ``tiles`` (all when None), sorted
    by name (module docstring); a tile's files depend on that tile's parts only."""
    per_tile: dict[str, list[tuple[int, int]]] = {}
    wanted = None if tiles is None else set(tiles)
    for index in sorted(records):
        for tile, info in records[index]["tiles"].items():
            if wanted is None or tile in wanted:
                per_tile.setdefault(tile, []).append((index, int(info["n"])))
    files = []
    for tile, parts in sorted(per_tile.items()):
        runs: list[list[tuple[int, int]]] = [[]]
        for index, n in parts:
            if runs[-1] and sum(m for _, m in runs[-1]) + n > max_tile_points:
                runs.append([])
            runs[-1].append((index, n))
        for k, run in enumerate(runs):
            name = tile if len(runs) == 1 else f"{tile}-p{k + 1:02d}"
            files.append((name, tile, tuple(i for i, _ in run), sum(m for _, m in run)))
    return sorted(files)


def file_record_path(out_dir: str | Path, name: str) -> Path:
    return state_dir(out_dir) / "tiles" / f"{name}.json"


def file_done(out_dir: str | Path, name: str, suffix: str, chunks: tuple[int, ...]) -> bool:
    """The file exists and its record says it was written from exactly these chunks' parts."""
    rec = file_record_path(out_dir, name)
    if not (rec.exists() and (Path(out_dir) / f"{name}{suffix}").exists()):
        return False
    return tuple(json.loads(rec.read_text()).get("chunks", ())) == tuple(chunks)


def write_file(task: FileTask) -> FileDone:
    """Write one tile file from its parts, then its record (module docstring)."""
    from calib.io import lastile, tileparts
    from office.deliver.chunkjob import crs_for

    def parts():
        for index in task.chunks:
            yield tileparts.load_part(part_path(task.out_dir, task.tile, index), lastile.record_dtype())

    path = Path(task.out_dir) / f"{task.name}{task.suffix}"
    try:
        summary = tileparts.write_tile(
            path, parts(), crs_for(task.crs, task.frame), task.software, task.provenance, task.first_t_gps_s
        ).as_dict()
    except BaseException:
        # write_tile removes its partial file, unless closing it failed too (the disk full)
        path.with_name(path.name + ".partial").unlink(missing_ok=True)
        raise
    record = {"summary": summary, "chunks": list(task.chunks)}
    write_atomic(file_record_path(task.out_dir, task.name), json.dumps(record, sort_keys=True).encode())
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return FileDone(task.name, summary, rss_mb, os.getpid())
