"""The GLS normal equations as segment Gram matrices, in buffers reused across iterations.

Point i's row of the weighted system is ``u_i = [a_i | j_i | F_i] / √m_i``: its nonzero design
entries ``a_i`` (boresight, extras, its plane's three, its pass's three offsets), its twelve knot
entries ``j_i`` (``B_ic σ_ic`` times the bridge weights of the two knots around it) and its
misclosure. Every block of the normal equations is a sum of ``u_i u_iᵀ`` over points that share
their columns: ``N_xx`` and ``g_x`` over the points of one *x-group* (a plane, or a plane in one
pass with pass offsets), the knot block ``N_aa`` and ``g_a`` over the points of one knot interval,
``N_xa`` over the points of one *segment* (an x-group within a knot interval).

So the points are sorted once per solution by segment and laid out in a zero-padded buffer of
chunks of ``c`` rows (a segment fills whole chunks); each iteration writes the rows into it, one
batched matrix product gives every chunk's ``uᵀu``, the chunks of a segment are summed and the
segment sums scattered into the dense ``N_xx``, the entries of ``N_ax`` (row-major, or as they
are for :mod:`.schur`) and the banded ``N_aa`` by indices built once (:class:`GramPlan`). No sparse matrix, no full-size temporary per
iteration: the rows are written in blocks of :data:`WRITE_BLOCK` points. Memory: the buffer
(``width`` doubles a point, plus the padding of each segment's last chunk) and the segment sums
(``width²`` doubles a segment), allocated once per solution.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

CHANNELS = 6
#: a point touches two knots × six channels
KNOT_COLS = 2 * CHANNELS
#: points per block of the per-point work (the temporaries of a block stay small)
POINT_BLOCK = 1 << 15
#: points per block when rows are written into the buffer (a block's rows stay in L2)
WRITE_BLOCK = 1 << 14
#: chunks per batched product (bounds its output buffer)
CHUNK_BLOCK = 4096
#: the longest chunk
MAX_CHUNK = 64


@dataclass(frozen=True)
class Columns:
    """Which columns of the unknowns a point's design row fills: ``dense`` columns shared by
    every point (boresight, extras) and one x-group's own (``group_cols``)."""

    dense: int  # boresight + extras
    group_cols: np.ndarray  # (G, q − dense) columns of each x-group
    p: int  # all unknowns


def layout_columns(layout, n_passes: int) -> tuple[Columns, int]:
    """The column table of ``layout`` (:class:`calib.boresight.gausshelmert.Layout`) and the
    number of x-groups (planes, or planes × passes with pass offsets)."""
    dense = 3 + len(layout.extras)
    planes = np.arange(layout.n_planes)
    if layout.offsets:
        j, k = np.divmod(np.arange(layout.n_planes * n_passes), n_passes)
        cols = np.concatenate(
            [layout.i_plane + 3 * j[:, None] + np.arange(3), layout.i_offset + 3 * k[:, None] + np.arange(3)],
            axis=1,
        )
    else:
        cols = layout.i_plane + 3 * planes[:, None] + np.arange(3)
    return Columns(dense, cols, layout.n), cols.shape[0]


@dataclass
class NormalBlocks:
    N_xx: np.ndarray  # (p, p)
    N_ax: np.ndarray | None  # (6K, p) row-major (None: not made, ``cross`` holds its entries)
    ab: np.ndarray  # (12, 6K) N_aa in lower banded form (without the prior)
    g_x: np.ndarray  # (p,)
    g_a: np.ndarray  # (6K,)
    cross: np.ndarray  # N_ax's entries at :attr:`GramPlan.cross_at`


class GramPlan:
    """The sorted, chunked layout of the points (built once per solution) and its buffers.

    ``group``: each point's x-group; ``knot``: its knot interval (of ``n_knots − 1``);
    ``knot_cols``: the knot entries of a row (0: the normal matrix of the unknowns alone)."""

    def __init__(
        self,
        group: np.ndarray,
        knot: np.ndarray,
        n_knots: int,
        columns: Columns,
        n_groups: int,
        knot_cols: int = KNOT_COLS,
    ):
        self.columns, self.n_groups, self.n_knots = columns, n_groups, n_knots
        self.q = columns.dense + columns.group_cols.shape[1]
        self.knot_cols = knot_cols
        self.width = self.q + knot_cols + 1
        intervals = max(n_knots - 1, 1)
        key = group.astype(np.int64) * intervals + knot
        order = np.argsort(key, kind="stable")
        ks = key[order]
        starts = np.r_[0, np.flatnonzero(np.diff(ks)) + 1]
        lengths = np.diff(np.r_[starts, ks.size])
        self.chunk = int(min(MAX_CHUNK, 2 ** int(np.log2(max(1.0, lengths.mean() / 2)))))
        per_seg = -(-lengths // self.chunk)
        first = np.r_[0, np.cumsum(per_seg)[:-1]]
        seg_of = np.repeat(np.arange(starts.size), lengths)
        offset = np.arange(ks.size) - starts[seg_of]
        self.slot = np.empty(ks.size, np.int64)
        self.slot[order] = (first[seg_of] + offset // self.chunk) * self.chunk + offset % self.chunk
        self.chunk_seg = np.repeat(np.arange(starts.size), per_seg)
        self.seg_group = ks[starts] // intervals
        self.seg_knot = ks[starts] % intervals
        self.buf = np.zeros((int(per_seg.sum()), self.chunk, self.width))
        self.gram = np.empty((min(CHUNK_BLOCK, self.buf.shape[0]), self.width, self.width))
        self.rows = np.empty((min(WRITE_BLOCK, ks.size), self.width))
        self.sums = np.empty((starts.size, self.width**2))  # Σ uuᵀ per segment
        self._dot: np.ndarray | None = None  # (chunks, c, 1) for :meth:`row_dot`
        self._pick_buffers: dict[str, np.ndarray] = {}  # for :meth:`_picked`
        self.chunk_blocks = [self._chunk_block(lo) for lo in range(0, self.buf.shape[0], CHUNK_BLOCK)]
        self._group_tables()
        if knot_cols:
            self._knot_tables()

    def _chunk_block(self, lo: int) -> tuple:
        """(lo, hi, first segment, end segment, continues the previous block's last segment,
        the indicator summing the block's chunks per segment)."""
        hi = min(lo + CHUNK_BLOCK, self.buf.shape[0])
        seg = self.chunk_seg[lo:hi]
        continues = bool(lo and self.chunk_seg[lo - 1] == seg[0])
        return (
            lo,
            hi,
            int(seg[0]),
            int(seg[-1]) + 1,
            continues,
            _indicator(seg - seg[0], seg[-1] - seg[0] + 1),
        )

    def _group_tables(self) -> None:
        """From the segments' sums to ``N_xx`` and ``g_x``."""
        q, w = self.q, self.width
        xi = np.r_[np.arange(q), w - 1]
        self.x_pick = (xi[:, None] * w + xi[None, :]).reshape(-1)
        self.group_sum = _indicator(self.seg_group, self.n_groups)
        dense = self.columns.dense
        cols = np.concatenate(
            [np.broadcast_to(np.arange(dense), (self.n_groups, dense)), self.columns.group_cols], axis=1
        )
        self.group_cols = cols  # (G, q)
        p = self.columns.p
        self.xx_index = (cols[:, :, None] * p + cols[:, None, :]).reshape(-1)

    def _knot_tables(self) -> None:
        """From the segments' sums to the banded ``N_aa``, ``g_a`` and the row-major ``N_ax``."""
        q, w, kc = self.q, self.width, self.knot_cols
        self.cross_pick = (np.arange(q)[:, None] * w + np.arange(q, q + kc)[None, :]).reshape(-1)
        p, size = self.columns.p, CHANNELS * self.n_knots
        rows = CHANNELS * self.seg_knot[:, None, None] + np.arange(kc)[None, None, :]
        cross_index = (rows * p + self.group_cols[self.seg_group][:, :, None]).reshape(-1)
        # the distinct places of N_ax the segments add to, and where each addition goes
        mark = np.zeros(size * p, bool)
        mark[cross_index] = True
        self.cross_at = np.flatnonzero(mark)
        rank = np.empty(size * p, np.int64)  # read only where written: at the places
        rank[self.cross_at] = np.arange(self.cross_at.size)
        self.cross_into = rank[cross_index]
        # each segment's knot entries straight into ab[r − c, 6k + c] (r ≥ c) and g_a[6k + r]
        r, c = np.tril_indices(kc)
        k = self.seg_knot[:, None]
        self.ab_pick = (q + r) * w + q + c
        self.ab_index = ((r - c)[None, :] * size + CHANNELS * k + c[None, :]).reshape(-1)
        self.ga_pick = (q + np.arange(kc)) * w + w - 1
        self.ga_index = (CHANNELS * k + np.arange(kc)[None, :]).reshape(-1)

    def write_rows(self, lo: int, hi: int, values: list[np.ndarray], sw: np.ndarray) -> None:
        """Rows ``lo:hi`` (``values``: the row's column blocks in order, each (hi − lo, ·), or
        a pair (x, y) for the block ``x * y``), scaled by ``sw = 1/√m``, into their slots."""
        rows = self.rows[: hi - lo]
        c = 0
        for v in values:
            if isinstance(v, tuple):
                w = v[0].shape[1]
                np.multiply(v[0], v[1], out=rows[:, c : c + w])
            else:
                w = v.shape[1] if v.ndim == 2 else 1
                rows[:, c : c + w] = v.reshape(hi - lo, w)
            c += w
        rows *= sw[:, None]
        # one row as one element: a row copy instead of an element-wise gather
        row = np.dtype((np.void, self.width * rows.itemsize))
        self.buf.reshape(-1, self.width).view(row)[self.slot[lo:hi], 0] = rows.view(row)[:, 0]

    def segment_sums(self) -> np.ndarray:
        """(S, width²): ``Σ uuᵀ`` of every segment (one batched product per block of chunks,
        the chunks of a segment summed by an indicator matrix)."""
        w = self.width
        for lo, hi, s0, s1, continues, ind in self.chunk_blocks:
            P = self.buf[lo:hi]
            if self.chunk == 1:  # one row a chunk: einsum beats a batched product here
                G = np.einsum("nci,ncj->nij", P, P, out=self.gram[: hi - lo])
            else:
                G = np.matmul(P.transpose(0, 2, 1), P, out=self.gram[: hi - lo])
            part = ind @ G.reshape(hi - lo, w * w)
            if continues:  # the first segment began in the previous block
                self.sums[s0] += part[0]
                self.sums[s0 + 1 : s1] = part[1:]
            else:
                self.sums[s0:s1] = part
        return self.sums

    def row_dot(self, vec_seg: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """``u_i · vec_seg[segment of i]`` for every point i in its original order (the rows
        as last written), into ``out`` when given."""
        vec = vec_seg[self.chunk_seg][:, :, None]  # (chunks, width, 1)
        if self._dot is None:
            self._dot = np.empty((self.buf.shape[0], self.chunk, 1))
        np.matmul(self.buf, vec, out=self._dot)
        return np.take(self._dot.reshape(-1), self.slot, out=out)

    def group_normals(self, G: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``N_xx`` and ``g_x`` from the segments' sums ``G``."""
        p, q = self.columns.p, self.q
        gx = (self.group_sum @ self._picked(G, "x_pick")).reshape(-1, q + 1, q + 1)
        N_xx = np.bincount(self.xx_index, gx[:, :q, :q].reshape(-1), minlength=p * p).reshape(p, p)
        g_x = np.bincount(self.group_cols.reshape(-1), gx[:, :q, q].reshape(-1), minlength=p)
        return N_xx, g_x

    def _picked(self, G: np.ndarray, name: str) -> np.ndarray:
        """``G[:, self.<name>]`` (a pick of columns) into a buffer kept per pick (no fresh
        pages per iteration)."""
        pick = getattr(self, name)
        buf = self._pick_buffers.get(name)
        if buf is None:
            buf = self._pick_buffers[name] = np.empty((G.shape[0], pick.size))
        return np.take(G, pick, axis=1, out=buf, mode="clip")  # the indices are in range

    def normals(self, N_ax_out: np.ndarray | None = None, dense_cross: bool = True) -> NormalBlocks:
        """The normal equations from the rows written (:meth:`write_rows`); ``N_ax`` into
        ``N_ax_out`` (6K, p) when given, not made without ``dense_cross`` (its entries at
        :attr:`cross_at` are in ``cross`` either way)."""
        G = self.segment_sums()
        N_xx, g_x = self.group_normals(G)
        p, size, kc = self.columns.p, CHANNELS * self.n_knots, self.knot_cols
        ab = np.bincount(self.ab_index, self._picked(G, "ab_pick").reshape(-1), minlength=kc * size)
        g_a = np.bincount(self.ga_index, self._picked(G, "ga_pick").reshape(-1), minlength=size)
        cross = np.bincount(
            self.cross_into, self._picked(G, "cross_pick").reshape(-1), minlength=self.cross_at.size
        )
        N_ax = None
        if dense_cross:
            N_ax = np.empty((size, p)) if N_ax_out is None else N_ax_out
            N_ax.fill(0.0)
            N_ax.reshape(-1)[self.cross_at] = cross
        return NormalBlocks(N_xx, N_ax, ab.reshape(kc, size), g_x, g_a, cross)


def _indicator(rows: np.ndarray, n_rows: int) -> sp.csr_matrix:
    """The (n_rows × len(rows)) matrix that sums the columns j into row ``rows[j]``."""
    cols = np.arange(rows.size)
    return sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n_rows, rows.size))


@dataclass(frozen=True)
class KnotWeights:
    """Each point's knot entries without its ``B``: ``σ_c`` times the bridge weights."""

    k: np.ndarray  # (n,) left knot
    sa: np.ndarray  # (n, 6) σ_c a_c
    sb: np.ndarray  # (n, 6) σ_c b_c


def knot_weights(sigma_l: np.ndarray, br) -> KnotWeights:
    """From the observations' σ and the bridge (:class:`calib.boresight.gls.Bridge`)."""
    sig = sigma_l[:, :CHANNELS]
    return KnotWeights(br.k, sig * br.a, sig * br.b)


def _design_blocks(lin, layout, sl: slice) -> list[np.ndarray]:
    """The design entries of the points in ``sl`` in the order of :func:`layout_columns`."""
    blocks = [lin.A_boresight[sl], *(lin.A_extra[name][sl] for name in layout.extras), lin.A_plane[sl]]
    if layout.offsets:
        blocks.append(lin.A_offset[sl])
    return blocks


def gls_row_values(lin, layout, kw: KnotWeights, sl: slice) -> list:
    """The column blocks of the rows ``[a | j | F]`` of the points in ``sl`` (unweighted; the
    knot entries as the pairs of factors :meth:`GramPlan.write_rows` multiplies in place)."""
    g = lin.B[sl, :CHANNELS]
    return [*_design_blocks(lin, layout, sl), (g, kw.sa[sl]), (g, kw.sb[sl]), lin.F[sl]]


def white_misclosure(
    plan: GramPlan, m: np.ndarray, dx: np.ndarray, z: np.ndarray, out: np.ndarray | None = None
) -> np.ndarray:
    """``F + A dx + J z`` per point (the white part of each misclosure after a step): the
    weighted rows in the plan's buffer (:func:`gls_row_values`) times ``[dx | z | 1]``, times
    ``√m`` (into ``out`` when given)."""
    d = plan.columns.dense
    vec = np.empty((plan.seg_group.size, plan.width))
    vec[:, :d] = dx[:d]
    vec[:, d : plan.q] = dx[plan.group_cols[plan.seg_group, d:]]
    vec[:, plan.q : plan.q + KNOT_COLS] = z[CHANNELS * plan.seg_knot[:, None] + np.arange(KNOT_COLS)]
    vec[:, -1] = 1.0
    e = plan.row_dot(vec, out=out)
    for lo in range(0, e.size, POINT_BLOCK):
        sl = slice(lo, min(lo + POINT_BLOCK, e.size))
        e[sl] *= np.sqrt(m[sl])
    return e


def normal_matrix(lin, layout, obs, M: np.ndarray) -> np.ndarray:
    """``Aᵀ M⁻¹ A``: the white-weighted normal matrix of the unknowns (as
    :func:`calib.boresight.gausshelmert.normal_equations` forms it from dense rows), from the
    x-groups' Gram matrices."""
    columns, n_groups = layout_columns(layout, len(obs.pass_ids))
    plan = GramPlan(x_groups(obs, layout), np.zeros(len(obs), np.int64), 2, columns, n_groups, knot_cols=0)
    n = len(obs)
    zero = np.zeros(min(WRITE_BLOCK, n))
    for lo in range(0, n, WRITE_BLOCK):
        sl = slice(lo, min(lo + WRITE_BLOCK, n))
        plan.write_rows(
            lo, sl.stop, [*_design_blocks(lin, layout, sl), zero[: sl.stop - lo]], 1.0 / np.sqrt(M[sl])
        )
    return plan.group_normals(plan.segment_sums())[0]


def x_groups(obs, layout) -> np.ndarray:
    """Each point's x-group: its plane, or its plane in its pass with pass offsets."""
    if layout.offsets:
        return obs.plane_index * len(obs.pass_ids) + obs.pass_index
    return obs.plane_index
