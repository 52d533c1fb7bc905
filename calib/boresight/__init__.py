"""Boresight calibration: the plane-based adjustments (GLS and the thesis's Gauss–Helmert), the result.

Modules, each importing only modules above it:

- ``errormodel``: how POS errors are correlated in time, and the O(n) sums that propagate them;
- ``ghmodel``: the plane condition per point and its derivatives, vectorized over points;
- ``observations``: the adjustment's input (per-point observations, their checks, the options)
  and :class:`~calib.boresight.observations.AdjustmentError`;
- ``observability``: whether the passes and targets determine the boresight, and what would;
- ``gausshelmert``: one iterated Gauss–Helmert solution (parameter layout, normal equations);
- ``gls``: the default estimator: the POS errors as Gauss–Markov processes on a knot grid,
  estimated with the boresight in O(n), and the planes' roughness;
- ``covariance``: the realistic covariance under time-correlated POS errors, and the covariance
  predicted for a geometry without adjusting;
- ``oracle``: the dense GLS with the exact covariance (tests and benchmarks: the Cramér–Rao bound);
- ``tau``: the POS correlation time from the data, and the boresight at τ/3, τ, 3τ;
- ``scene_ties``: tie patches of the scene added to the targets, chosen by information;
- ``adjust``: the adjustment's entry point (observability, solution, outliers, jackknife, result);
- ``result``: ``result.json``, the calibration result as users and tools read it;
- ``report``, ``report_gls``: ``report.md`` and its plots (``report_gls``: the estimator section);
- ``pipeline``: a bundle in, the boresight and its uncertainties out.
"""
