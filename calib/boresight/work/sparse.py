"""The GLS estimator's design and knot matrices as sparse matrices.

The iterations do without them (:mod:`.normals`); the group tests
(:mod:`calib.boresight.checks.grouptest`) and the dense oracle (:mod:`calib.boresight.oracle`)
take rows of them, built on demand.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from calib.boresight.gausshelmert import Layout
from calib.boresight.observations import Observations

CHANNELS = 6


def design_matrix(lin, layout: Layout, obs: Observations) -> sp.csr_matrix:
    """A (n × p) as a sparse matrix: the dense boresight/extras columns, three plane columns and
    (with pass offsets) three offset columns per row."""
    n = len(obs)
    cols = [
        np.broadcast_to(np.arange(3), (n, 3)),
        *(np.full((n, 1), layout.i_extra + i) for i in range(len(layout.extras))),
    ]
    vals = [lin.A_boresight, *(lin.A_extra[name][:, None] for name in layout.extras)]
    cols.append(layout.i_plane + 3 * obs.plane_index[:, None] + np.arange(3))
    vals.append(lin.A_plane)
    if layout.offsets:
        cols.append(layout.i_offset + 3 * obs.pass_index[:, None] + np.arange(3))
        vals.append(lin.A_offset)
    c = np.concatenate(cols, axis=1)
    v = np.concatenate(vals, axis=1)
    per_row = c.shape[1]
    return sp.csr_matrix(
        (v.reshape(-1), c.reshape(-1), np.arange(0, n * per_row + 1, per_row)), shape=(n, layout.n)
    )


def knot_matrix(lin, obs: Observations, fr) -> sp.csr_matrix:
    """J (n × 6K): ``B_ic σ_ic`` times the bridge weights of the point's two knots."""
    n = len(obs)
    g = lin.B[:, :CHANNELS] * obs.sigma_l[:, :CHANNELS]
    v = np.concatenate([g * fr.br.a, g * fr.br.b], axis=1)
    c = CHANNELS * fr.br.k[:, None] + np.arange(2 * CHANNELS)
    return sp.csr_matrix(
        (v.reshape(-1), c.reshape(-1), np.arange(0, n * 2 * CHANNELS + 1, 2 * CHANNELS)),
        shape=(n, CHANNELS * fr.grid.n),
    )
