"""The knots' share of the GLS normal equations, ``[N_ax | g_a]ᵀ N_aa⁻¹ [N_ax | g_a]``, by
blocks of knot rows from the few columns each block touches.

``W = L⁻¹ N_ax`` (``N_aa = L Lᵀ`` banded, bandwidth ``bw``) is dense below each column's first
entry, so ``Wᵀ W`` costs ``6K·p²``: with 32 planes (p = 99) it and the solve for W took over 40 % of
a small adjustment. By blocks of ``b`` rows the forward substitution is
``W_i = X_i − M_i T_{i−1}`` with ``X_i = D_i⁻¹ N_i`` and ``M_i = D_i⁻¹ E_i`` (``D_i`` the block's
triangle of L, ``E_i`` its coupling to the previous block's last ``bw`` rows, ``T_{i−1}`` those
rows of W). ``N_i`` has only the columns of the points around the block's knots (boresight,
extras and the few planes seen then: ``P`` of the ``p``), so ``X_i`` is ``b × P``; only the
``bw × p`` tails ``T`` carry the fill, and

    Σ W_iᵀ W_i = Σ X_iᵀX_i − (X_iᵀM_i) T_{i−1} − T_{i−1}ᵀ (M_iᵀX_i) + T_{i−1}ᵀ (M_iᵀM_i) T_{i−1}

costs ``b·P² + bw·p²`` a block instead of ``b·p²``: each block's work is batched over the blocks,
only the tails' recurrence ``T_i = X_i,tail − M_i,tail T_{i−1}`` (one small ``dgemm``) and the
blocks' triangular solves (one ``dtrsm``) go block by block. The right-hand side ``g_a`` is one
more column of every block (the Gram's column of it is ``Wᵀv``, ``v = L⁻¹ g_a``). Columns are
indexed ``0 … p−1`` (the unknowns), ``p`` (``g_a``) and ``p + 1`` (a zero column: the padding of
blocks with fewer than ``P`` columns).

When the blocks touch most of the unknowns (every plane seen in every second of the survey) the
blocks gain nothing and their smaller products run slower: :func:`knot_schur` then takes
:class:`DenseSchur`, the dense ``L⁻¹ [N_ax | g_a]`` and its Gram.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.linalg.blas import dgemm, dtrsm
from scipy.linalg.lapack import dpbtrs, dtbtrs

from calib.boresight.work.banded import BlockSolver, block_layout, solve_lower

#: knot rows per block (bandwidth 11, 32 planes: 64 measured fastest of 32 … 96, whole solves)
BLOCK_ROWS = 64
#: the blocked reduction's flops run about this much slower than the dense one's (6K = 3972,
#: p = 99: blocks of P = 24 columns 2.4 ms against 3.1 ms dense, P = 43 3.6 against 3.1 ms,
#: P = 100 9.7 against 3.4 ms)
BLOCKED_SLOWDOWN = 2.0
#: rows per block of the dense solve (:class:`calib.boresight.work.banded.BlockSolver`)
DENSE_BLOCK_ROWS = 32


def knot_schur(cross_at: np.ndarray, size: int, p: int, bandwidth: int) -> KnotSchur | DenseSchur:
    """The reduction for ``N_ax``'s places ``cross_at`` (:class:`KnotSchur`): by blocks when
    their flops, :data:`BLOCKED_SLOWDOWN` times, are fewer than the dense ones', else dense."""
    b = max(BLOCK_ROWS, bandwidth + 1)
    nb = -(-size // b)
    P = int(_block_columns(cross_at, p, nb, b)[1][:, -1].max()) + 1
    blocked = size * (b / 2 * (P + bandwidth) + (P + bandwidth) ** 2) + nb * bandwidth * (p + 2) * (p + 2 + P)
    dense = size * ((DENSE_BLOCK_ROWS / 2 + bandwidth) * (p + 1) + (p + 1) ** 2)
    if BLOCKED_SLOWDOWN * blocked < dense:
        return KnotSchur(cross_at, size, p, bandwidth)
    return DenseSchur(cross_at, size, p, bandwidth)


def _block_columns(cross_at: np.ndarray, p: int, nb: int, b: int) -> tuple[np.ndarray, np.ndarray]:
    """(nb, p + 2): which columns each block of ``b`` rows touches (``g_a``'s in every one) and
    each used column's place among its block's."""
    rows, cols = np.divmod(cross_at, p)
    used = np.zeros((nb, p + 2), bool)
    used[rows // b, cols] = True
    used[:, p] = True
    return used, np.cumsum(used, axis=1) - 1


def _knots(chol: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``−N_aa⁻¹ u`` for the factor ``chol`` (LAPACK ``dpbtrs``: both sweeps in one call)."""
    z, info = dpbtrs(chol, u[:, None], lower=1)
    if info != 0:
        raise ValueError(f"dpbtrs: illegal argument {-info}")
    return -z[:, 0]


class KnotSchur:
    """The layout of one solution's ``N_ax`` by blocks (built once) and its buffers.

    ``cross_at``: the flat indices ``row·p + column`` of the entries of ``N_ax`` (6K × p) that
    can be nonzero (:attr:`calib.boresight.work.normals.GramPlan.cross_at`)."""

    def __init__(self, cross_at: np.ndarray, size: int, p: int, bandwidth: int, block: int = BLOCK_ROWS):
        self.size, self.p, self.bw = size, p, bandwidth
        self.b = b = max(block, bandwidth + 1)
        self.nb = nb = -(-size // b)
        self.ext = ext = p + 2  # the unknowns, g_a, the zero column
        self.cross_at = cross_at
        rows, cols = np.divmod(cross_at, p)
        used, rank = _block_columns(cross_at, p, nb, b)
        self.P = P = int(rank[:, -1].max()) + 1
        self.cols = np.full((nb, P), p + 1)  # each block's columns, padded with the zero column
        blk, c = np.nonzero(used)
        self.cols[blk, rank[blk, c]] = c

        def slot(r: np.ndarray, c: np.ndarray) -> np.ndarray:  # in the (nb, P, b) block of N
            blk = r // b
            return (blk * P + rank[blk, c]) * b + r - blk * b

        self.cross_slot = slot(rows, cols)
        self.rhs_slot = slot(np.arange(size), np.full(size, p))
        self.N = np.zeros((nb, P, b))  # each block's [N_i | g_a,i] by its columns and rows
        self.XM = np.empty((nb, P + bandwidth, b))  # [X_i | M_i] transposed, block by block
        self.D = np.empty((nb, b, b))  # D_iᵀ: ``D[i].T`` is D_i, column-major
        self._tables(size, bandwidth)
        self.T = np.zeros((nb + 1, bandwidth, ext))  # T[i + 1]: the last bw rows of W_i; T[0] = 0
        self.M_tail = np.empty((nb, bandwidth, bandwidth))  # M_i's last bw rows, row-major
        self.gram = np.empty((nb, P + bandwidth, P + bandwidth))
        self.H = np.empty((nb, P, ext))
        self.U = np.empty((nb, bandwidth, ext))
        self._solves = [(self.D[i].T, self.XM[i].T) for i in range(nb)]
        self._tails = [(self.T[i].T, self.M_tail[i].T, self.T[i + 1].T) for i in range(1, nb - 1)]
        # the blocks' columns summed into the (ext, ext) result, Σ_i Sel_iᵀ H_i: one entry a column
        self.select = sp.csc_matrix(
            (np.ones(nb * P), self.cols.reshape(-1), np.arange(nb * P + 1)), shape=(ext, nb * P)
        )

    def _tables(self, size: int, bandwidth: int) -> None:
        """The factor's band padded to whole blocks and the views that copy its diagonals into
        the blocks ``D_i`` (every other entry stays zero), where ``E_i``'s entries go, and the
        scatters of the tails and of ``X_iᵀ X_i``."""
        b, nb, P, ext, bw = self.b, self.nb, self.P, self.ext, bandwidth
        # L[j + d, j] at band[d, j]; past the end zero, but a unit diagonal (the padding rows
        # solve to zero)
        self.band = np.zeros((bw + 1, nb * b))
        self.band[0, size:] = 1.0
        self._band_rows = [(self.band[d, : size - d], d) for d in range(min(bw + 1, size))]
        # D[i, c, c + d] = L[s + c + d, s + c] = band[d, s + c] for c + d < b (s = i·b)
        D = self.D.reshape(nb, b * b)
        D[...] = 0.0
        self._diagonals = [
            (D[:, d :: b + 1][:, : b - d], self.band[d].reshape(nb, b)[:, : b - d]) for d in range(bw + 1)
        ]
        # the M part of XM[i, P + t, r] = E_i[r, t] = L[s + r, s − bw + t] for r ≤ t (i ≥ 1)
        i, t, r = np.meshgrid(np.arange(1, nb), np.arange(bw), np.arange(bw), indexing="ij", sparse=True)
        ok = np.broadcast_to((r <= t) & (i * b + r < size), (nb - 1, bw, bw))
        self.e_to = np.broadcast_to((i * (P + bw) + P + t) * b + r, ok.shape)[ok]
        self.e_from = np.broadcast_to((r + bw - t) * nb * b + i * b - bw + t, ok.shape)[ok]
        # T[i + 1, t, cols[i, a]] = X_i[b − bw + t, a]; (X_iᵀX_i)[a, a'] adds to (cols[i, a], cols[i, a'])
        tail, block = np.arange(bw), np.arange(nb)[:, None, None]
        self.tail_index = ((block[:-1] + 1) * bw + tail) * ext + self.cols[: nb - 1, :, None]
        self.gram_index = self.cols[:, :, None] * ext + self.cols[:, None, :]

    def reduce(self, chol: np.ndarray, cross: np.ndarray, g_a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(N_xa N_aa⁻¹ N_ax, N_xa N_aa⁻¹ g_a)`` for the factor ``chol`` (lower banded),
        the values ``cross`` of ``N_ax`` at :attr:`cross_at` and ``g_a``."""
        P, N, ext = self.P, self.N.reshape(-1), self.ext
        for row, d in self._band_rows:  # the entries past the end stay zero
            row[...] = chol[d, : row.size]
        for diagonal, row in self._diagonals:
            diagonal[...] = row
        N[self.cross_slot] = cross
        N[self.rhs_slot] = g_a
        np.copyto(self.XM[:, :P], self.N)
        self.XM[:, P:] = 0.0
        self.XM.reshape(-1)[self.e_to] = self.band.reshape(-1)[self.e_from]
        for D, XM in self._solves:
            out = dtrsm(1.0, D, XM, lower=1, overwrite_b=1)
            if not np.shares_memory(out, XM):  # not column-major after all: never here
                XM[...] = out
        self._tails_of_W()
        T = self.T[: self.nb]  # T_{i−1} of block i
        G = np.matmul(self.XM, self.XM.transpose(0, 2, 1), out=self.gram)
        H = np.matmul(G[:, :P, P:], T, out=self.H)
        U = np.matmul(G[:, P:, P:], T, out=self.U)
        K = self.select @ H.reshape(-1, ext)  # Σ (X_iᵀM_i) T_{i−1} into the block's columns
        gram = np.bincount(self.gram_index.reshape(-1), G[:, :P, :P].reshape(-1), minlength=ext * ext)
        gram = gram.reshape(ext, ext) - K - K.T + T.reshape(-1, ext).T @ U.reshape(-1, ext)
        return gram[: self.p, : self.p], gram[: self.p, self.p]

    def _tails_of_W(self) -> None:
        """``T_i = X_i,tail − M_i,tail T_{i−1}`` for every block but the last (its tail is not
        used), from the solved blocks in :attr:`XM`."""
        P, b, bw = self.P, self.b, self.bw
        self.T.fill(0.0)
        self.T.reshape(-1)[self.tail_index] = self.XM[: self.nb - 1, :P, b - bw :]
        np.copyto(self.M_tail, self.XM[:, P:, b - bw :].transpose(0, 2, 1))
        for T_prev, M_t, T_i in self._tails:
            out = dgemm(-1.0, T_prev, M_t, beta=1.0, c=T_i, overwrite_c=1)
            if not np.shares_memory(out, T_i):  # not column-major after all: never here
                T_i[...] = out

    def cross_times(self, dx: np.ndarray) -> np.ndarray:
        """``g_a + N_ax dx`` (6K,), from the blocks of N as last reduced."""
        x = np.zeros(self.ext)
        x[: self.p], x[self.p] = dx, 1.0
        u = np.matmul(x[self.cols][:, None, :], self.N)  # (nb, 1, b)
        return u.reshape(-1)[: self.size]

    def knots(self, chol: np.ndarray, dx: np.ndarray) -> np.ndarray:
        """``−N_aa⁻¹ (g_a + N_ax dx)`` for the factor ``chol`` of the last reduction."""
        return _knots(chol, self.cross_times(dx))

    def dense_cross(self) -> np.ndarray:
        """``N_ax`` (6K × p) as last reduced."""
        out = np.zeros(self.size * self.p)
        out[self.cross_at] = self.N.reshape(-1)[self.cross_slot]
        return out.reshape(self.size, self.p)

    def W(self, chol: np.ndarray) -> np.ndarray:
        """``L⁻¹ N_ax`` (6K × p) for the factor ``chol`` of the last reduction, densely."""
        return solve_lower(chol, self.dense_cross(), block_layout(self.size, self.bw))


class DenseSchur:
    """:class:`KnotSchur`'s reduction through the dense ``W = L⁻¹ [N_ax | g_a]`` (the blocked
    triangular solve of :class:`calib.boresight.work.banded.BlockSolver`, in place) and its
    Gram, for blocks that would touch most of the unknowns."""

    def __init__(self, cross_at: np.ndarray, size: int, p: int, bandwidth: int):
        self.size, self.p = size, p
        self.solver = BlockSolver(block_layout(size, bandwidth, DENSE_BLOCK_ROWS), p + 1)
        rows, cols = np.divmod(cross_at, p)
        self._at = rows * (p + 1) + cols  # N_ax's places in the solver's (6K, p + 1) buffer

    def reduce(self, chol: np.ndarray, cross: np.ndarray, g_a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """As :meth:`KnotSchur.reduce`."""
        W = self.solver.W
        W.fill(0.0)
        W.reshape(-1)[self._at] = cross
        W[:, self.p] = g_a
        W = self.solver.solve(chol, W)
        gram = W.T @ W
        return gram[: self.p, : self.p], gram[: self.p, self.p]

    def knots(self, chol: np.ndarray, dx: np.ndarray) -> np.ndarray:
        """As :meth:`KnotSchur.knots`: ``−L⁻ᵀ (W [dx, 1])``."""
        W = self.solver.W
        z, info = dtbtrs(chol, W[:, : self.p] @ dx + W[:, self.p], uplo="L", trans="T")
        if info != 0:
            raise ValueError(f"dtbtrs: singular factor ({info})")
        return -z

    def W(self, chol: np.ndarray) -> np.ndarray:
        """``L⁻¹ N_ax`` (6K × p) of the last reduction (a view of the solver's buffer)."""
        return self.solver.W[:, : self.p]
