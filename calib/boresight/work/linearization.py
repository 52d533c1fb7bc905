"""The linearization of every GLS iteration written into buffers allocated once per solution.

:func:`calib.boresight.ghmodel.linearize` allocates its result (about 200 bytes a point) at
every call; at a million points and twenty iterations that is gigabytes of fresh pages, which
the kernel zeroes (the sys time of the adjustment). Here the same blocks are evaluated by the
same function (:func:`calib.boresight.ghmodel.linearize_block`, in blocks of the same size)
into one :class:`~calib.boresight.ghmodel.Linearization` reused by every iteration.
"""

from __future__ import annotations

import numpy as np

from calib.boresight.ghmodel import EXTRA_NAMES, LINEARIZE_BLOCK, Linearization, State, linearize_block


class LinearizationBuffers:
    """The observation buffer ``l`` (n, 8) and the linearization ``lin`` of n points."""

    def __init__(self, n: int, latency: bool, adopt: Linearization | None = None):
        """Buffers for n points (with the latency column when ``latency``); ``adopt``: a
        linearization of the same points whose arrays become the buffers (overwritten)."""
        names = list(EXTRA_NAMES[:4]) + (["latency"] if latency else [])
        self.l = np.empty((n, 8))
        self._pose_source: np.ndarray | None = None  # whose poses ``l[:, :6]`` holds
        if adopt is not None and sorted(adopt.A_extra) == sorted(names) and adopt.F.size == n:
            self.lin = adopt
            return
        self.lin = Linearization(
            F=np.empty(n),
            x_lgf_m=np.empty((n, 3)),
            A_boresight=np.empty((n, 3)),
            A_extra={k: np.empty(n) for k in names},
            A_plane=np.empty((n, 3)),
            A_offset=np.empty((n, 3)),
            B=np.empty((n, 8)),
        )

    def observations(self, l: np.ndarray, v: np.ndarray) -> np.ndarray:
        """``l`` with the scanner residuals ``v`` (n, 2) added to range and scan angle, in the
        buffer (the poses are copied only when they come from another array than last time)."""
        if self._pose_source is not l:
            self.l[:, :6] = l[:, :6]
            self._pose_source = l
        np.add(l[:, 6:8], v, out=self.l[:, 6:8])
        return self.l

    def linearize(
        self,
        state: State,
        r_nom: np.ndarray,
        plane_index: np.ndarray,
        pass_index: np.ndarray,
        l: np.ndarray,
        rates: tuple[np.ndarray, np.ndarray] | None,
        bases: np.ndarray,
    ) -> Linearization:
        """:func:`calib.boresight.ghmodel.linearize` into the buffers (the same numbers)."""
        res = self.lin
        n = l.shape[0]
        for lo in range(0, n, LINEARIZE_BLOCK):
            sl = slice(lo, min(lo + LINEARIZE_BLOCK, n))
            r = None if rates is None else (rates[0][sl], rates[1][sl])
            view = Linearization(
                res.F[sl],
                res.x_lgf_m[sl],
                res.A_boresight[sl],
                {k: v[sl] for k, v in res.A_extra.items()},
                res.A_plane[sl],
                res.A_offset[sl],
                res.B[sl],
            )
            linearize_block(state, r_nom, plane_index[sl], pass_index[sl], l[sl], r, bases, view)
        return res
