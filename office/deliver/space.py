"""The disk space ``mls georef`` needs, checked before it starts; running out of it, an error.

A job holds on disk, at its peak, every chunk's parts (``.georef/parts``, :mod:`calib.io.tileparts`:
the tiles' own LAS records, 46 bytes a point, compressed into LAZ chunks for LAZ tiles) and every
tile (LAZ about 7–10 bytes a point, LAS 46), the parts being removed only once every tile is
written (measured on the simulated bundle of the tests: peak 20 bytes a return with LAZ, 94 with
LAS; a session gave 0.17 returns a byte of MCAP segment). :func:`space_needed` adds a quarter to
that; :func:`check_space` refuses a job whose need the file system of ``--out`` does not have
free. Running out all the same (a disk shared with a recording daemon) is :func:`out_of_space`:
one line naming the directory and the space needed; the job keeps its finished chunks and tiles
for ``--resume``.
"""

from __future__ import annotations

import errno
import shutil
from pathlib import Path

from office.deliver.options import GeorefError

#: bytes a return costs at the job's peak: its part, its share of a tile (LAZ, LAS)
PART_BYTES = {True: 12, False: 47}
TILE_BYTES = {True: 12, False: 47}
#: returns a byte of session segment holds (measured: 223,121 returns in 1,316,764 bytes)
RETURNS_PER_SESSION_BYTE = 0.17
MARGIN = 1.25
FIXED_BYTES = 1 << 20  # plan, records, summaries
NO_SPACE = (errno.ENOSPC, errno.EDQUOT)


def source_returns(source) -> int:
    """The returns of a source: counted (bundle), or estimated from its segments (session)."""
    if source.kind == "bundle":
        return sum(c.returns.size for c in source.chunks if c.returns is not None)
    segments = {c.segment for c in source.chunks if c.segment}
    size = 0
    for s in segments:
        try:
            size += Path(s).stat().st_size
        except OSError:
            pass
    return int(size * RETURNS_PER_SESSION_BYTE)


def space_needed(n_returns: int, compress: bool, share_to_run: float = 1.0) -> int:
    """Bytes a job of ``n_returns`` needs on disk; ``share_to_run``: the share of its chunks
    still to run (a resumed job has the others' parts already)."""
    per_return = PART_BYTES[compress] * share_to_run + TILE_BYTES[compress]
    return int(n_returns * per_return * MARGIN) + FIXED_BYTES


def mb(n: int) -> str:
    return f"{n / 1e6:,.0f} MB" if n >= 10e6 else f"{n / 1e6:.1f} MB"


def check_space(out: Path, need: int) -> None:
    """:class:`GeorefError` when the file system of ``out`` has less than ``need`` bytes free."""
    free = shutil.disk_usage(out).free
    if free < need:
        raise GeorefError(
            f"{out}: not enough free space: the job needs about {mb(need)} (tiles and their "
            f"temporary parts), {mb(free)} free; free some space or choose another --out"
        )


def is_out_of_space(e: BaseException) -> bool:
    return isinstance(e, OSError) and e.errno in NO_SPACE


def out_of_space(out: Path, need: int | None) -> GeorefError:
    """The one-line error of a job that ran out of space while writing into ``out``."""
    needs = f"; the job needs about {mb(need)}" if need is not None else ""
    return GeorefError(
        f"{out}: no space left on the device while writing{needs} (tiles and their temporary "
        f"parts); free some space, then continue with --resume"
    )
