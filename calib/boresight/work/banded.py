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

    @property
    def n_blocks(self) -> int:
        return int(self.diag_index.shape[0])


def block_layout(size: int, bandwidth: int, block: int = BLOCK_ROWS) -> BlockLayout:
    """The gather indices for an L of ``size`` rows in lower banded form ``(bandwidth + 1, size)``."""
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
    return BlockLayout(size, bandwidth, block, diag, coupling)


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
