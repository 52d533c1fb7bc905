"""The reduced normal equations' Cholesky factor, made once per iteration and used for all
that needs the matrix: the step, the formal σ of the convergence test and the covariance (the
inverse from the factor, made when first asked), and the log-determinant of the likelihood."""

from __future__ import annotations

import numpy as np
from scipy.linalg.lapack import dpotrf, dpotri, dpotrs


class CholeskyFactor:
    """``S = L Lᵀ`` of a symmetric positive definite matrix (LAPACK ``dpotrf``, lower)."""

    def __init__(self, S: np.ndarray):
        """Factor ``S``; ``numpy.linalg.LinAlgError`` (as ``numpy.linalg.cholesky`` raises)
        when it is not positive definite."""
        L, info = dpotrf(S, lower=1, clean=1)
        if info != 0:
            raise np.linalg.LinAlgError(f"dpotrf info {info}")
        self.L = L
        self._inverse: np.ndarray | None = None

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """``S⁻¹ rhs``."""
        x, info = dpotrs(self.L, rhs, lower=1)
        if info != 0:  # an argument error: not reached with a factor of ours
            raise np.linalg.LinAlgError(f"dpotrs info {info}")
        return x

    def inverse(self) -> np.ndarray:
        """``S⁻¹`` (symmetric, from the factor: ``dpotri``; made at the first call)."""
        if self._inverse is None:
            lower, info = dpotri(self.L, lower=1)
            if info != 0:
                raise np.linalg.LinAlgError(f"dpotri info {info}")
            self._inverse = np.tril(lower) + np.tril(lower, -1).T
        return self._inverse

    @property
    def log_det(self) -> float:
        """``log det S``."""
        return 2.0 * float(np.sum(np.log(np.diag(self.L))))
