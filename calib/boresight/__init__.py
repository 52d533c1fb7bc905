"""Boresight calibration: targets extracted from the passes, the Gauss–Helmert adjustment, the result.

Modules, each importing only modules above it:

- ``errormodel``: how POS errors are correlated in time, and the O(n) sums that propagate them;
- ``ghmodel``: the plane condition per point and its derivatives, vectorized over points;
- ``segmentation``: point-cloud building blocks of the extraction (RANSAC plane, intensity
  split, incidence correction, clusters, extents);
- ``extract``: target planes extracted from each pass's points;
- ``observations``: the adjustment's input (per-point observations, their checks, the options)
  and :class:`~calib.boresight.observations.AdjustmentError`;
- ``observability``: whether the passes and targets determine the boresight, and what would;
- ``gausshelmert``: one iterated Gauss–Helmert solution (parameter layout, normal equations);
- ``covariance``: the realistic covariance under time-correlated POS errors, and the covariance
  predicted for a geometry without adjusting;
- ``adjust``: the adjustment's entry point (observability, solution, outliers, jackknife, result);
- ``result``: ``result.json``, the calibration result as users and tools read it;
- ``report``: ``report.md`` and its plots;
- ``pipeline``: a bundle in, the boresight and its uncertainties out.
"""
