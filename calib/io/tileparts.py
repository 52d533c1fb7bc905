"""A tile's points in parts, each made on its own (by the chunk that found them), ready to be
joined into the tile file without being decoded again.

A part (:class:`TilePart`) holds one chunk's records of one tile as they go into the file — LAZ
chunks of at most :data:`LAZ_CHUNK_POINTS` points each, compressed there and then, or the raw
records for a ``.las`` — and what the file's header and summary need from them: their extremes
(the least and the greatest value of each field the header bounds), their count per return
number, their pass ids and every 16th point's σ. LASzip compresses each chunk of a file on its
own (its coders start afresh at each chunk); with variable-size chunks (the LASzip VLR's chunk
size 2³² − 1) the chunk table names each chunk's points and bytes, so chunks compressed by
different workers join into one valid file (:func:`write_tile`), and the
compression — most of a tile's cost — runs in the chunk tasks, in parallel, not in one task per
tile at the end.

:func:`save_part` / :func:`load_part` keep a part in one file: a magic, a small JSON head, the
extremes, the σ sample and the payload (read back as a memory map).
"""

from __future__ import annotations

import io
import json
import os
import struct
from collections.abc import Iterable
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np

from calib.core import frames
from calib.core.errors import CalibError
from calib.io import lastile
from calib.io.laz import LasOutputError, OutputCrs, las_source_id

#: points per LAZ chunk at most (LASzip's default chunk size: a reader decodes a chunk at once)
LAZ_CHUNK_POINTS = 50_000
#: the σ summary of a tile is taken from every this many points of each part
SIGMA_STRIDE = 16
#: the first bytes of a part file
MAGIC = b"\x93MLSPRT1"
_EXTREME_FIELDS = ("X", "Y", "Z", "gps_time", "sigma_h_m", "sigma_v_m")  # and the pass id
_HEAD = struct.Struct("<I")  # the JSON head's length


class PartError(CalibError, ValueError):
    """A part file is not whole, or not one at all (the message names it)."""


@dataclass(frozen=True)
class TilePart:
    """One chunk's records of one tile, as they go into the file (module docstring)."""

    n_points: int
    payload: np.ndarray | bytes  # LAZ chunks one after another, or the raw records
    laz_chunks: tuple[tuple[int, int], ...] | None  # (points, bytes) of each chunk; None: raw
    extremes: np.ndarray  # two records: the least and the greatest of the header's fields
    by_return: tuple[int, ...]  # points with return number 1 … 15
    pass_ids: tuple[int, ...]
    sigma_sample: np.ndarray  # (2, m) float32: σ_h and σ_v of every SIGMA_STRIDE-th point

    @property
    def compressed(self) -> bool:
        return self.laz_chunks is not None

    @property
    def buffer(self) -> bytes | memoryview:
        """The payload's bytes, not copied."""
        return self.payload if isinstance(self.payload, bytes) else self.payload.data


@cache
def laz_vlr():
    """The LASzip VLR of a tile's records (point format 6 and its extra bytes), with
    variable-size chunks."""
    import lazrs

    return lazrs.LazVlr.new_for_compression(6, lastile.record_dtype().itemsize - 30, True)


def _extremes(records: np.ndarray, pass_ids: np.ndarray) -> np.ndarray:
    """The two records holding the least and the greatest of each field the header bounds
    (``pass_ids``: the records' distinct pass ids, sorted)."""
    ext = np.zeros(2, records.dtype)
    for name in _EXTREME_FIELDS:
        ext[name] = records[name].min(), records[name].max()  # (strided: 25 ms a million points)
    ext["pass_id"] = pass_ids[0], pass_ids[-1]
    return ext


def _compress(records: np.ndarray) -> tuple[bytes, tuple[tuple[int, int], ...]]:
    """The records as LAZ chunks of at most :data:`LAZ_CHUNK_POINTS` points (one thread), and
    each chunk's (points, bytes)."""
    import lazrs

    out = io.BytesIO()
    compressor = lazrs.LasZipCompressor(out, laz_vlr())
    compressor.reserve_offset_to_chunk_table()  # 8 bytes the file has once, not each part
    first = start = out.tell()
    table = []
    raw = records.view(np.uint8).reshape(-1)
    size = records.dtype.itemsize
    for a in range(0, records.size, LAZ_CHUNK_POINTS):
        b = min(a + LAZ_CHUNK_POINTS, records.size)
        compressor.compress_many(raw[a * size : b * size])
        compressor.finish_current_chunk()  # writes the chunk out
        table.append((b - a, out.tell() - start))
        start = out.tell()
    return out.getbuffer()[first:start].tobytes(), tuple(table)


def make_part(records: np.ndarray, compress: bool) -> TilePart:
    """The part of ``records`` (a tile's records, in the file's order; at least one)."""
    records = np.ascontiguousarray(records)
    pid = records["pass_id"]
    ids = pid[:1] if pid.min() == pid.max() else np.unique(pid)
    returns = np.bincount(records["bit_fields"] & 0x0F, minlength=16)[1:16]
    if compress:
        payload, table = _compress(records)
    else:
        payload, table = records.view(np.uint8).reshape(-1).tobytes(), None
    return TilePart(
        n_points=int(records.size),
        payload=payload,
        laz_chunks=table,
        extremes=_extremes(records, ids),
        by_return=tuple(int(c) for c in returns),
        pass_ids=tuple(int(i) for i in ids),
        sigma_sample=np.stack([records["sigma_h_m"][::SIGMA_STRIDE], records["sigma_v_m"][::SIGMA_STRIDE]]),
    )


def save_part(path: Path, part: TilePart) -> int:
    """Write ``part`` to ``path`` (temporary name, rename; not synced: an intermediate file) and
    return its size in bytes."""
    head = json.dumps(
        {
            "n_points": part.n_points,
            "laz_chunks": part.laz_chunks,
            "by_return": part.by_return,
            "pass_ids": part.pass_ids,
            "n_sigma": int(part.sigma_sample.shape[1]),
        }
    ).encode()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            for block in (MAGIC, _HEAD.pack(len(head)), head, part.extremes.tobytes()):
                f.write(block)
            f.write(np.ascontiguousarray(part.sigma_sample, np.float32).tobytes())
            f.write(part.buffer)
        size = tmp.stat().st_size
        os.replace(tmp, path)
        return size
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def load_part(path: Path, record_dtype: np.dtype) -> TilePart:
    """The part in ``path`` (its payload a memory map of the file); :class:`PartError` when the
    file is not a whole part."""
    with open(path, "rb") as f:
        if f.read(len(MAGIC)) != MAGIC:
            raise PartError(f"{path}: not a tile part (no {MAGIC!r} at its start)")
        try:
            (n_head,) = _HEAD.unpack(f.read(_HEAD.size))
            head = json.loads(f.read(n_head))
            extremes = np.frombuffer(f.read(2 * record_dtype.itemsize), record_dtype)
            n_sigma = int(head["n_sigma"])
            sigma = np.frombuffer(f.read(8 * n_sigma), np.float32).reshape(2, n_sigma)
            table = (
                None if head["laz_chunks"] is None else tuple((int(p), int(b)) for p, b in head["laz_chunks"])
            )
        except (struct.error, ValueError, KeyError, TypeError) as e:
            raise PartError(f"{path}: a torn or foreign part ({e})") from None
        offset = f.tell()
    size = sum(b for _, b in table) if table is not None else int(head["n_points"]) * record_dtype.itemsize
    if path.stat().st_size != offset + size:
        raise PartError(f"{path}: {path.stat().st_size} bytes, a whole part has {offset + size}")
    payload = np.memmap(path, np.uint8, "r", offset, (size,)) if size else np.zeros(0, np.uint8)
    return TilePart(
        n_points=int(head["n_points"]),
        payload=payload,
        laz_chunks=table,
        extremes=extremes,
        by_return=tuple(head["by_return"]),
        pass_ids=tuple(head["pass_ids"]),
        sigma_sample=sigma,
    )


def _header(
    parts: list[TilePart], source_id: int, crs: OutputCrs, software: str, provenance: dict, first_t: float
):
    """The tile's header for its ``parts``: grown by laspy from each part's extremes (two records
    holding the least and the greatest of every bounded field: the same bounds, to the bit, as
    a writer that saw every point), one record at a time — laspy 2.7 takes an extra-bytes
    dimension's least and greatest value from the first record it is given (so its own writer
    stored those of each batch's first point), and one record at a time gives it the true
    ones; its counts set from the parts' counts."""
    import laspy
    from laspy.vlrs.known import LasZipVlr

    header = lastile.tile_header(crs, source_id, software, provenance, lastile.survey_date(first_t))
    header.partial_reset()
    if parts[0].compressed:
        header.vlrs.append(LasZipVlr(laz_vlr().record_data()))
        header.are_points_compressed = True
    for p in parts:
        for k in range(2):
            header.grow(laspy.PackedPointRecord(p.extremes[k : k + 1].copy(), header.point_format))
    header.point_count = sum(p.n_points for p in parts)
    header.number_of_points_by_return = np.sum([p.by_return for p in parts], axis=0, dtype=np.uint64)
    return header


def _write_points(f, parts: list[TilePart]) -> None:
    """The parts' payloads after the header: raw records one after another, or LAZ chunks with
    the offset to the chunk table before them and the table after them."""
    if not parts[0].compressed:
        for p in parts:
            f.write(p.buffer)
        return
    import lazrs

    at = f.tell()
    f.write(b"\0" * 8)  # the offset to the chunk table, known at the end
    table: list[tuple[int, int]] = []
    for p in parts:
        f.write(p.buffer)
        table += p.laz_chunks or ()
    table_at = f.tell()
    lazrs.write_chunk_table(f, table, laz_vlr())
    f.seek(at)
    f.write(struct.pack("<q", table_at))


def _summary(path: Path, parts: list[TilePart], passes: list[int], header) -> lastile.TileSummary:
    lo, hi = np.asarray(header.mins, float), np.asarray(header.maxs, float)
    sigma = np.concatenate([p.sigma_sample for p in parts], axis=1)
    return lastile.TileSummary(
        name=path.stem,
        path=path.name,
        n_points=int(header.point_count),
        t_first_gps_s=float(frames.las_to_gps_seconds(header.min_gps_time)),
        t_last_gps_s=float(frames.las_to_gps_seconds(header.max_gps_time)),
        bbox=tuple(round(float(v), 4) for v in (*lo, *hi)),  # type: ignore[arg-type]
        sigma_h_m=lastile.quantiles(sigma[0]),
        sigma_v_m=lastile.quantiles(sigma[1]),
        passes=passes,
    )


def write_tile(
    path: str | Path,
    parts: Iterable[TilePart],
    crs: OutputCrs,
    software: str,
    provenance: dict,
    first_t_gps_s: float,
) -> lastile.TileSummary:
    """Write the tile ``path`` from ``parts`` (in the order their points are to appear; LAZ
    chunks for a ``.laz``, raw records for a ``.las``) and return its summary. The file appears
    only complete (``<name>.partial``, fsync, rename: :mod:`calib.io.lastile`); ``first_t_gps_s``
    (the survey's first point) dates the header."""
    path = Path(path)
    parts = [p for p in parts if p.n_points]
    if not parts:
        raise LasOutputError(f"{path}: a tile without points (nothing to write)")
    if any(p.compressed != (path.suffix == ".laz") for p in parts):
        raise LasOutputError(
            f"{path}: its parts must be {'LAZ chunks' if path.suffix == '.laz' else 'raw records'}"
        )
    passes = sorted({i for p in parts for i in p.pass_ids})
    # one source id per file: the line's (LAS's u16, else 0); square tiles mix lines
    source_id = las_source_id(passes[0]) if len(passes) == 1 else 0
    header = _header(parts, source_id, crs, software, provenance, first_t_gps_s)
    partial = path.with_name(path.name + ".partial")
    try:
        with open(partial, "wb") as f:
            header.write_to(f)
            _write_points(f, parts)
            f.flush()
            os.fsync(f.fileno())
        os.replace(partial, path)
    finally:
        partial.unlink(missing_ok=True)
    return _summary(path, parts, passes, header)
