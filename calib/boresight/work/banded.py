"""``L⁻¹ B`` for a lower banded factor ``L`` and many right-hand sides, in blocks of rows.

LAPACK's ``dtbtrs`` sweeps the band once per right-hand side (level-2 BLAS): with ~100 columns
(the GLS Schur complement's) it was the largest cost of a small adjustment. Here the rows go in
blocks of :data:`BLOCK_ROWS`: each block subtracts the coupling to the previous block's last
``bandwidth`` rows (one ``dgemm``) and solves its own dense lower triangle (one ``dtrsm``), for
all columns at once, in place in a row-major result. The block matrices are gathered from the
banded factor by an index built once per size (:class:`BlockLayout`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.linalg.blas import dgemm, dtrsm

#: rows per block (bandwidth 11, ~100 right-hand sides: 32 measured fastest of 16 … 96)
BLOCK_ROWS = 32


@dataclass(frozen=True)
class BlockLayout:
    """Where each block's dense lower triangle and its coupling block sit in the banded factor
    (flat indices into ``chol.ravel()``; ``-1``: a structural zero)."""

    size: int
    bandwidth: int
    block: int
    diag_index: np.ndarray  # (nb, block, block)
    coupling_index: np.ndarray  # (nb, block, bandwidth): columns s − bandwidth … s − 1
    diag_index_t: np.ndarray  # (nb, block, block): each block transposed

    @property
    def n_blocks(self) -> int:
        return int(self.diag_index.shape[0])


#: layouts of up to this many rows are kept for the next solution of the same size (a few MB)
CACHED_ROWS = 1 << 14


def block_layout(size: int, bandwidth: int, block: int = BLOCK_ROWS) -> BlockLayout:
    """The gather indices for an L of ``size`` rows in lower banded form ``(bandwidth + 1, size)``
    (read-only arrays; the small ones are made once per size: :data:`CACHED_ROWS`)."""
    if size <= CACHED_ROWS:
        return _cached_block_layout(size, bandwidth, block)
    return _block_layout(size, bandwidth, block)


@lru_cache(maxsize=4)
def _cached_block_layout(size: int, bandwidth: int, block: int) -> BlockLayout:
    return _block_layout(size, bandwidth, block)


def _block_layout(size: int, bandwidth: int, block: int) -> BlockLayout:
    block = max(block, bandwidth)
    nb = -(-size // block)
    s = (np.arange(nb) * block)[:, None, None]
    r = np.arange(block)[None, :, None]
    c = np.arange(block)[None, None, :]
    d = r - c
    ok = (d >= 0) & (d <= bandwidth) & (s + r < size)
    diag = np.where(ok, d * size + s + c, -1)
    t = np.arange(bandwidth)[None, None, :]
    d = r + bandwidth - t
    ok = (d <= bandwidth) & (s > 0) & (s + r < size)
    coupling = np.where(ok, d * size + s - bandwidth + t, -1)
    diag_t = np.ascontiguousarray(diag.transpose(0, 2, 1))
    for a in (diag, coupling, diag_t):
        a.flags.writeable = False
    return BlockLayout(size, bandwidth, block, diag, coupling, diag_t)


def solve_lower(chol: np.ndarray, rhs: np.ndarray, lay: BlockLayout, overwrite: bool = False) -> np.ndarray:
    """``L⁻¹ rhs`` (size × p, row-major) for ``L`` in lower banded form, as ``dtbtrs`` would;
    in place in ``rhs`` with ``overwrite`` (when it is row-major)."""
    flat = np.append(chol.ravel(), 0.0)  # index −1: the structural zero at the end
    D = flat[lay.diag_index]
    E = flat[lay.coupling_index]
    own = overwrite and rhs.dtype == np.float64 and rhs.flags.c_contiguous
    W = rhs if own else np.array(rhs, dtype=float, order="C", copy=True)
    b, bw = lay.block, lay.bandwidth
    for i in range(lay.n_blocks):
        s = i * b
        m = min(s + b, lay.size) - s
        Wt = W[s : s + m].T  # column-major view of the block: the BLAS work in place
        if i:
            out = dgemm(-1.0, W[s - bw : s].T, E[i, :m].T, beta=1.0, c=Wt, overwrite_c=1)
            if not np.shares_memory(out, Wt):
                Wt[...] = out
        out = dtrsm(1.0, D[i, :m, :m], Wt, side=1, lower=1, trans_a=1, overwrite_b=1)
        if not np.shares_memory(out, Wt):
            Wt[...] = out
    return W


class BlockSolver:
    """:func:`solve_lower` for one size and one number of right-hand sides, repeated (once per
    iteration): the right-hand sides, the gathered blocks of the factor and the views of every
    block are made once, so that a solve is the two BLAS calls per block and nothing else."""

    def __init__(self, lay: BlockLayout, columns: int):
        """For factors of ``lay.size`` rows and ``columns`` right-hand sides."""
        self.lay = lay
        self.W = np.empty((lay.size, columns))  # the right-hand sides, then the solution
        self._flat = np.zeros((lay.bandwidth + 1) * lay.size + 1)  # the factor; [-1]: zero
        # the diagonal blocks transposed: each block's view ``[i].T`` is column-major (no copy
        # by the BLAS wrapper)
        self._D = np.empty(lay.diag_index.shape)
        self._E = np.empty(lay.coupling_index.shape)
        b, bw = lay.block, lay.bandwidth
        self._steps = []
        for i in range(lay.n_blocks):
            s = i * b
            m = min(s + b, lay.size) - s
            # column-major views: the BLAS work in place
            previous = (self.W[s - bw : s].T, self._E[i, :m].T) if i else None
            self._steps.append((self.W[s : s + m].T, previous, self._D[i, :m, :m].T))
        self._in_place = False  # every BLAS call computes in its block's view (after a check)
        self._in_place_seen = True

    def solve(self, chol: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """``L⁻¹ rhs`` (as :func:`solve_lower`) into :attr:`W` (returned; overwritten by the
        next solve); ``rhs`` may be :attr:`W` itself."""
        lay = self.lay
        self._flat[:-1].reshape(chol.shape)[...] = chol
        np.take(self._flat, lay.diag_index_t, out=self._D, mode="wrap")  # −1: the zero
        np.take(self._flat, lay.coupling_index, out=self._E, mode="wrap")
        if rhs is not self.W:
            np.copyto(self.W, rhs)
        for Wt, previous, D in self._steps:
            if previous is not None:
                out = dgemm(-1.0, previous[0], previous[1], beta=1.0, c=Wt, overwrite_c=1)
                if not self._in_place:
                    self._land(out, Wt)
            out = dtrsm(1.0, D, Wt, side=1, lower=1, trans_a=1, overwrite_b=1)
            if not self._in_place:
                self._land(out, Wt)
        self._in_place = self._in_place_seen
        return self.W

    def _land(self, out: np.ndarray, target: np.ndarray) -> None:
        """Put a BLAS result into ``target`` when it was not computed there; the first solve
        checks every block, the later ones only when a block was not in place (it is, for the
        column-major views here)."""
        if not np.shares_memory(out, target):
            target[...] = out
            self._in_place_seen = False
