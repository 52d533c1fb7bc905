"""One time chunk of a survey: filter, georeference, per-point σ, sort into tile parts.

:func:`process_chunk` is the task a worker runs (this process, or a Dask worker process). It
reads the chunk's returns (:func:`office.deliver.sources.read_chunk`), drops what the filters
say (counted per reason), georeferences the rest on the chunk's slice of the trajectory,
computes σ_h and σ_v (:func:`calib.core.tpu.point_sigmas`), converts to the output CRS, and
writes one part per tile it touches, ``<out>/.georef/parts/<tile>/c<chunk>.part``: the tile
file's own LAS records (:func:`calib.io.lastile.record_dtype`, encoded by
:mod:`office.deliver.lasrecords`), time order, compressed into LAZ chunks for a ``.laz`` tile
(:mod:`calib.io.tileparts`: the compression runs here, in parallel, not in the tile's task). A
projected output CRS is reached through a local model fitted per chunk (:mod:`office.deliver.projection`), checked
against pyproj to ≤ 0.01 mm: the tolerance of the tiles' coordinates is 0.1 mm — each stored
coordinate is pyproj's on the 0.1-mm LAS grid or, for the rare point within 0.01 mm of the middle
between two grid values, the neighbouring one (measured: 1 coordinate in 10⁵); every other field
is unchanged. The LGF and geographic CRSs are not modelled: their tiles are those pyproj gives.
Every file is written under a temporary name and renamed; the parts are not synced (an
intermediate file), the chunk's record ``<out>/.georef/chunks/c<chunk>.json`` comes last,
synced, with the size of each part. A chunk is therefore idempotent: run twice (a worker killed,
a job resumed) it writes the same bytes, and a chunk without its record, or whose parts are not
all whole (:func:`chunk_complete`), is simply run again.

The work arrays of a chunk are large (tens of MB): :func:`calib.core.allocator.tune_allocator` keeps glibc from
mapping and unmapping them afresh for every chunk (page faults and kernel time), in this process
and in a Dask worker alike.
"""

from __future__ import annotations

import json
import math
import os
import resource
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from office.deliver.options import Filters
from office.deliver.sources import ChunkSpec, Returns, read_chunk

if TYPE_CHECKING:
    from calib.core.frames import LocalFrame
    from calib.core.georef import Mount
    from calib.core.tpu import MountCovariance, ScannerSigmas
    from calib.core.trajectory import Trajectory

NS_PER_S = 1_000_000_000
STATE_DIR = ".georef"
TRANSIT = "transit"
#: trajectory kept on each side of a chunk (covers the mount's time offset and interpolation)
TRAJECTORY_OVERLAP_S = 2.0
#: returns per step of σ within a chunk (their temporaries stay in the CPU's caches)
BLOCK = 1 << 16


@dataclass(frozen=True)
class ChunkContext:
    """What every chunk of one job shares (small: the trajectory travels sliced per chunk)."""

    out_dir: str
    crs: str
    frame: LocalFrame
    mount: Mount
    covariance: MountCovariance
    scanner: ScannerSigmas
    filters: Filters
    tiling: str
    tile_m: float | None
    keep_transits: bool
    compress: bool  # LAZ tiles (their parts LAZ chunks), else LAS
    lines: np.ndarray  # (n, 3) int64: pass id, start GPS ns, end GPS ns; sorted by start


@dataclass(frozen=True)
class ChunkTask:
    context: ChunkContext
    spec: ChunkSpec
    trajectory: Trajectory  # the chunk's slice of the survey's trajectory


@dataclass(frozen=True)
class ChunkDone:
    index: int
    tiles: dict[str, dict]  # tile name → {"n": points, "t_first_gps_s": …}
    counters: dict[str, int]
    peak_rss_mb: float
    pid: int


def slice_trajectory(traj, t0_s: float, t1_s: float):
    """The epochs of ``traj`` within [t0 − overlap, t1 + overlap] (one more on each side)."""
    from calib.core.trajectory import Trajectory

    tt = traj.t_gps_s
    a = max(int(np.searchsorted(tt, t0_s - TRAJECTORY_OVERLAP_S)) - 1, 0)
    b = min(int(np.searchsorted(tt, t1_s + TRAJECTORY_OVERLAP_S)) + 1, tt.size)
    a = min(a, tt.size - 2)  # two epochs at least (a trajectory has two or more)
    b = max(b, a + 2)
    sl = slice(a, b)
    return Trajectory(
        tt[sl],
        traj.p_lgf_m[sl],
        traj.rpy_rad[sl],
        traj.frame,
        None if traj.sigma_p_m is None else traj.sigma_p_m[sl],
        None if traj.sigma_rpy_rad is None else traj.sigma_rpy_rad[sl],
        traj.max_gap_s,
        traj.name,
    )


CRS_CACHE: dict[tuple, object] = {}


def crs_for(spec: str, frame):
    from calib.io.laz import output_crs

    key = (spec, frame.lat_deg, frame.lon_deg, frame.height_m)
    if key not in CRS_CACHE:  # a pyproj transformer per process, not per chunk
        CRS_CACHE[key] = output_crs(spec, frame)
    return CRS_CACHE[key]


def state_dir(out_dir: str | Path) -> Path:
    return Path(out_dir) / STATE_DIR


def chunk_record_path(out_dir: str | Path, index: int) -> Path:
    return state_dir(out_dir) / "chunks" / f"c{index:06d}.json"


def part_path(out_dir: str | Path, tile: str, index: int) -> Path:
    return state_dir(out_dir) / "parts" / tile / f"c{index:06d}.part"


def _part_whole(path: Path, size: int | None) -> bool:
    """The part is there, of its recorded size, and begins as a part does."""
    from calib.io.tileparts import MAGIC

    try:
        with open(path, "rb") as f:
            return os.fstat(f.fileno()).st_size == size and f.read(len(MAGIC)) == MAGIC
    except FileNotFoundError:
        return False


def chunk_complete(out_dir: str | Path, index: int) -> bool:
    """The chunk has its record and, while the job's parts are kept, every part it names whole
    (the parts are not synced: a part lost with the machine's power runs its chunk again)."""
    path = chunk_record_path(out_dir, index)
    if not path.exists():
        return False
    if not (state_dir(out_dir) / "parts").exists():
        return True  # the job wrote its tiles and removed the parts
    rec = json.loads(path.read_text())
    return all(
        _part_whole(part_path(out_dir, tile, index), info.get("bytes")) for tile, info in rec["tiles"].items()
    )


def write_atomic(path: Path, data: bytes) -> None:
    """``path`` appears whole or not at all (temporary name, fsync, rename); a write that fails
    (the disk full) leaves no temporary file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _filter(r: Returns, f: Filters, counters: dict[str, int]) -> np.ndarray:
    keep = np.ones(r.size, bool)

    def drop(name: str, bad: np.ndarray) -> None:
        counters[name] = int((bad & keep).sum())
        keep[bad] = False

    drop("outside_range_window", (r.range_m < f.range_m[0]) | (r.range_m > f.range_m[1]))
    if f.scan_angle_deg is not None:
        a = np.degrees(r.scan_angle_rad)
        drop("outside_scan_angle_window", (a < f.scan_angle_deg[0]) | (a > f.scan_angle_deg[1]))
    if f.intensity_min:
        drop("below_intensity_floor", r.intensity < f.intensity_min)
    if f.time_gps_s is not None:
        lo, hi = (round(v * NS_PER_S) for v in f.time_gps_s)
        drop("outside_time_window", (r.t_gps_ns < lo) | (r.t_gps_ns > hi))
    return keep


def _vessel(range_m, scan_angle_rad, mount, box) -> np.ndarray:
    """Returns inside the body-frame box (the vessel's own structure)."""
    from calib.core.frames import scanner_vector

    v_b = scanner_vector(range_m, scan_angle_rad) @ mount.r_s_b.T + mount.lever_arm_m
    inside = np.ones(v_b.shape[0], bool)
    for j in range(3):
        inside &= (v_b[:, j] >= box[2 * j]) & (v_b[:, j] <= box[2 * j + 1])
    return inside


def _pass_ids(r: Returns, lines: np.ndarray) -> np.ndarray:
    """Every return's pass id: that of the last line started at or before it, when the return
    is not after that line's end; -1 otherwise."""
    if r.pass_id is not None:
        return np.asarray(r.pass_id, np.int64)
    t = r.t_gps_ns
    if lines.size == 0:
        return np.full(r.size, -1, np.int64)
    if t.size > 1 and not bool(np.all(t[1:] >= t[:-1])):
        k = np.searchsorted(lines[:, 1], t, side="right") - 1
        inside = (k >= 0) & (t <= lines[np.maximum(k, 0), 2])
        return np.where(inside, lines[np.maximum(k, 0), 0], -1)
    # time order (a profiler's stream): line j is the last started for the returns within
    # [start j, start j+1); of those, the ones up to its end are on it
    pid = np.full(t.size, -1, np.int64)
    first = np.searchsorted(t, lines[:, 1], side="left")
    upto = np.minimum(np.append(first[1:], t.size), np.searchsorted(t, lines[:, 2], side="right"))
    for j in np.flatnonzero(upto > first):
        pid[first[j] : upto[j]] = lines[j, 0]
    return pid


def _index_of(key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(sorted distinct keys, index of each key among them): ``np.unique(…, return_inverse=True)``
    without its sort of every point (the keys are few: a search among them)."""
    if key.size and key.min() == key.max():  # one key (a chunk within one line or one square)
        return key[:1], np.zeros(key.size, np.intp)
    keys = np.unique(key)
    return keys, np.searchsorted(keys, key)


def tile_names(
    ctx: ChunkContext, x: np.ndarray, y: np.ndarray, pass_id: np.ndarray
) -> tuple[np.ndarray, list[str]]:
    """(tile index per point, tile names sorted by their key): lines, or squares named by their
    south-west corner."""
    if ctx.tiling == "line":
        keys, inv = _index_of(pass_id)
        return inv, [TRANSIT if k < 0 else f"line-{int(k)}" for k in keys]
    assert ctx.tile_m is not None  # square tiling has its size (GeorefOptions checks it)
    s = float(ctx.tile_m)
    ix, iy = np.floor(x / s).astype(np.int64), np.floor(y / s).astype(np.int64)
    if not ix.size:
        return np.zeros(0, np.intp), []
    # one int64 key in the order of (ix, iy)
    x0, y0 = int(ix.min()), int(iy.min())
    span_y = int(iy.max()) - y0 + 1
    ix -= x0
    ix *= span_y
    ix += iy
    ix -= y0
    keys, inv = _index_of(ix)
    digits = 0 if s == math.floor(s) else 3
    names = [
        f"tile-{(x0 + k // span_y) * s:.{digits}f}-{(y0 + k % span_y) * s:.{digits}f}" for k in keys.tolist()
    ]
    return inv, names


def tile_order(inv: np.ndarray, n_tiles: int) -> np.ndarray | None:
    """The points' order by tile, time order within each (a stable sort); None when they are in
    that order already."""
    if inv.size < 2 or bool(np.all(inv[1:] >= inv[:-1])):
        return None
    if n_tiles <= np.iinfo(np.uint16).max:  # a radix sort: linear in the points
        return np.argsort(inv.astype(np.uint16), kind="stable")
    return np.argsort(inv, kind="stable")


@dataclass(frozen=True)
class _Selection:
    """The returns of a chunk that go into the deliverable: their indices in the chunk (time
    order), their GPS times (s) and every return's pass id (-1: none)."""

    idx: np.ndarray
    t_s: np.ndarray
    pass_id: np.ndarray

    def take(self, a: np.ndarray) -> np.ndarray:
        """``a[idx]``: a view of ``a`` when the indices are one run (a chunk within a line, the
        common case: no copy), else a gather."""
        idx = self.idx
        if idx.size and int(idx[-1]) - int(idx[0]) + 1 == idx.size:  # sorted and distinct: a run
            return a[int(idx[0]) : int(idx[-1]) + 1]
        return a[idx]


def _select(r: Returns, ctx: ChunkContext, traj: Trajectory, counters: dict[str, int]) -> _Selection:
    """Apply the filters, the lines (without transits), the vessel box and the trajectory's
    coverage, counting what each drops into ``counters``."""
    from calib.core import frames

    keep = _filter(r, ctx.filters, counters)
    pid = _pass_ids(r, ctx.lines)
    if ctx.tiling == "line" and not ctx.keep_transits:
        counters["outside_lines"] = int((keep & (pid < 0)).sum())
        keep &= pid >= 0
    mount = ctx.mount
    if ctx.filters.vessel_box_m is not None:
        inside = np.zeros(r.size, bool)
        inside[keep] = _vessel(r.range_m[keep], r.scan_angle_rad[keep], mount, ctx.filters.vessel_box_m)
        counters["vessel_itself"] = int(inside.sum())
        keep &= ~inside
    t_s = frames.gps_ns_to_seconds(r.t_gps_ns[keep])
    uncovered = traj.uncovered(t_s + mount.time_offset_s)
    counters["outside_trajectory"] = int(uncovered.sum())
    return _Selection(idx=np.flatnonzero(keep)[~uncovered], t_s=t_s[~uncovered], pass_id=pid)


def _lgf_and_sigmas(
    ctx: ChunkContext, traj: Trajectory, r: Returns, sel: _Selection, rec: np.ndarray
) -> np.ndarray:
    """The selected returns' LGF coordinates (n, 3; column-major), georeferenced in one call
    (which works in blocks that stay in the CPU's caches); their σ_h and σ_v go into ``rec``."""
    from calib.core.georef import georeference
    from calib.core.tpu import point_sigmas

    t_s, mount = sel.t_s, ctx.mount
    rng, ang = sel.take(r.range_m), sel.take(r.scan_angle_rad)
    p = georeference(t_s, rng, ang, traj, mount)
    # straight into the records' float32 fields (the same rounding as a cast of the float64 σ)
    point_sigmas(
        t_s,
        rng,
        ang,
        traj,
        mount,
        ctx.scanner,
        ctx.covariance,
        block=BLOCK,
        out=(rec["sigma_h_m"], rec["sigma_v_m"]),
    )
    return p


def _encode_points(ctx: ChunkContext, traj: Trajectory, r: Returns, sel: _Selection) -> np.ndarray:
    """The selected returns as the tile files' LAS records (:mod:`office.deliver.lasrecords`):
    georeferenced, projected on the output CRS's LAS grid (:mod:`office.deliver.projection`),
    with their σ_h and σ_v, in time order."""
    from calib.core import frames
    from calib.io import lastile
    from office.deliver import lasrecords
    from office.deliver.projection import project_on_grid

    idx = sel.idx
    crs = crs_for(ctx.crs, ctx.frame)
    # zeroed: the classification, its flags and the user data stay 0
    rec = np.zeros(idx.size, lastile.record_dtype())
    grid = project_on_grid(crs, _lgf_and_sigmas(ctx, traj, r, sel, rec))
    lasrecords.check_grid(grid, crs, ctx.out_dir)
    rec["X"], rec["Y"], rec["Z"] = grid
    rec["gps_time"] = frames.gps_seconds_to_las(sel.t_s)
    rec["intensity"] = sel.take(r.intensity)
    rec["bit_fields"] = lasrecords.FIRST_OF_ONE
    rec["scan_angle"] = lasrecords.scan_angle_units(sel.take(r.scan_angle_rad).astype(np.float32))
    pid = sel.take(sel.pass_id)
    rec["pass_id"] = pid
    rec["point_source_id"] = lasrecords.source_ids(pid)
    return rec


def _tile_xy(ctx: ChunkContext, rec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The records' x and y in the output CRS (what square tiles are cut by)."""
    if ctx.tiling == "line":
        return np.zeros(0), np.zeros(0)
    crs = crs_for(ctx.crs, ctx.frame)
    return (
        rec["X"] * crs.scales[0] + crs.offsets[0],
        rec["Y"] * crs.scales[1] + crs.offsets[1],
    )


def _write_parts(ctx: ChunkContext, index: int, rec: np.ndarray, t_s: np.ndarray) -> dict[str, dict]:
    """Write one part per tile the records touch (time order within each: ``t_s``, the records'
    GPS times); what each holds."""
    from calib.io.tileparts import make_part, save_part

    tiles: dict[str, dict] = {}
    inv, names = tile_names(ctx, *_tile_xy(ctx, rec), rec["pass_id"])
    order = tile_order(inv, len(names))  # None: in tile order already, no gather
    bounds = np.searchsorted(inv if order is None else inv[order], np.arange(len(names) + 1))
    for j, name in enumerate(names):
        a, b = int(bounds[j]), int(bounds[j + 1])
        part = make_part(rec[a:b] if order is None else rec[order[a:b]], ctx.compress)
        size = save_part(part_path(ctx.out_dir, name, index), part)
        first = a if order is None else int(order[a])
        tiles[name] = {"n": part.n_points, "t_first_gps_s": float(t_s[first]), "bytes": size}
    return tiles


def process_chunk(task: ChunkTask) -> ChunkDone:
    """Run one chunk (module docstring) and return what it wrote."""
    from calib.core.allocator import tune_allocator

    tune_allocator()
    ctx, spec, traj = task.context, task.spec, task.trajectory
    r = read_chunk(spec)
    counters: dict[str, int] = dict(r.counters)
    counters["returns"] = r.size
    sel = _select(r, ctx, traj, counters)
    tiles: dict[str, dict] = {}
    if sel.idx.size:
        tiles = _write_parts(ctx, spec.index, _encode_points(ctx, traj, r, sel), sel.t_s)
    counters["written"] = int(sel.idx.size)
    record = {
        "index": spec.index,
        "t0_ns": spec.t0_ns,
        "t1_ns": spec.t1_ns,
        "tiles": tiles,
        "counters": counters,
    }
    write_atomic(chunk_record_path(ctx.out_dir, spec.index), json.dumps(record, sort_keys=True).encode())
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return ChunkDone(spec.index, tiles, counters, rss_mb, os.getpid())


def with_site_sigmas(traj, site):
    """The trajectory with the site's constant POS sigmas where it has none of its own."""
    if traj.has_sigmas:
        return traj
    n = traj.t_gps_s.size
    return replace(
        traj,
        sigma_p_m=np.tile(np.asarray(site.sigma_position_m, float), (n, 1)),
        sigma_rpy_rad=np.tile(np.asarray(site.sigma_attitude_rad, float), (n, 1)),
    )
