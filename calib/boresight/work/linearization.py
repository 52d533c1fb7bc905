"""The linearization of every GLS iteration written into buffers allocated once per solution.

:func:`calib.boresight.ghmodel.linearize` allocates its result (about 200 bytes a point) at
every call; at a million points and twenty iterations that is gigabytes of fresh pages, which
the kernel zeroes (the sys time of the adjustment). Here the same blocks are evaluated by the
same function (:func:`calib.boresight.ghmodel.linearize_block`, in blocks of the same size)
into one :class:`~calib.boresight.ghmodel.Linearization` reused by every iteration.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from calib.boresight.ghmodel import (
    EXTRA_NAMES,
    LINEARIZE_BLOCK,
    Linearization,
    State,
    attitude_trig,
    linearize_block,
)


class LinearizationBuffers:
    """The observation buffer ``l`` (n, 8) and the linearization ``lin`` of n points: only the
    columns the solution uses (the extras it estimates, the pass offsets' when estimated; no
    georeferenced points), with the poses' cos and sin kept while the poses stay the same."""

    def __init__(self, n: int, extras: Sequence[str], offsets: bool, adopt: Linearization | None = None):
        """Buffers for n points, the extra unknowns ``extras`` and (``offsets``) the pass
        offsets' column; ``adopt``: a linearization of the same points (with at least these
        extras) whose arrays become the buffers (overwritten)."""
        names = [k for k in EXTRA_NAMES if k in extras]
        self.l = np.empty((n, 8))
        self._pose_source: np.ndarray | None = None  # whose poses ``l[:, :6]`` holds
        self._trig = np.empty((6, n))  # attitude_trig of the poses in ``l``
        if adopt is not None and set(names) <= set(adopt.A_extra) and adopt.F.size == n:
            self.lin = replace(
                adopt,
                x_lgf_m=np.empty((0, 3)),
                A_extra={k: adopt.A_extra[k] for k in names},
                A_offset=adopt.A_offset if offsets else np.empty((0, 3)),
            )
            return
        self.lin = Linearization(
            F=np.empty(n),
            x_lgf_m=np.empty((0, 3)),
            A_boresight=np.empty((n, 3)),
            A_extra={k: np.empty(n) for k in names},
            A_plane=np.empty((n, 3)),
            A_offset=np.empty((n if offsets else 0, 3)),
            B=np.empty((n, 8)),
        )

    def observations(self, l: np.ndarray, v: np.ndarray) -> np.ndarray:
        """``l`` with the scanner residuals ``v`` (n, 2) added to range and scan angle, in the
        buffer (the poses and their cos and sin are copied and evaluated only when they come
        from another array than last time)."""
        if self._pose_source is not l:
            self.l[:, :6] = l[:, :6]
            for lo in range(0, l.shape[0], LINEARIZE_BLOCK):
                sl = slice(lo, min(lo + LINEARIZE_BLOCK, l.shape[0]))
                self._trig[:, sl] = attitude_trig(self.l[sl])
            self._pose_source = l
        np.add(l[:, 6:8], v, out=self.l[:, 6:8])
        return self.l

    def linearize(
        self,
        state: State,
        r_nom: np.ndarray,
        plane_index: np.ndarray,
        pass_index: np.ndarray,
        rates: tuple[np.ndarray, np.ndarray] | None,
        bases: np.ndarray,
    ) -> Linearization:
        """:func:`calib.boresight.ghmodel.linearize` of the observations in the buffer
        (:meth:`observations`) into the buffers (the same numbers in the columns kept)."""
        res, l = self.lin, self.l
        n = l.shape[0]
        for lo in range(0, n, LINEARIZE_BLOCK):
            sl = slice(lo, min(lo + LINEARIZE_BLOCK, n))
            r = None if rates is None else (rates[0][sl], rates[1][sl])
            view = Linearization(
                res.F[sl],
                res.x_lgf_m,
                res.A_boresight[sl],
                {k: v[sl] for k, v in res.A_extra.items()},
                res.A_plane[sl],
                res.A_offset[sl],
                res.B[sl],
            )
            linearize_block(
                state, r_nom, plane_index[sl], pass_index[sl], l[sl], r, bases, view, self._trig[:, sl]
            )
        return res
