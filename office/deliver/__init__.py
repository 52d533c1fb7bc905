"""Survey deliverables (``mls georef``, docs/architecture.md §8): a whole survey georeferenced into
LAZ tiles with per-point uncertainty, in time chunks, in-process or on a Dask cluster.

- :mod:`~acquire.deliver.options` — what the surveyor asks for (tiling, CRS, filters);
- :mod:`~acquire.deliver.calibration` — the calibrated mount, its covariance and provenance;
- :mod:`~acquire.deliver.sources` — a session or a bundle: trajectory, lines, time chunks, and the
  returns of one chunk;
- :mod:`~acquire.deliver.chunkjob` — one chunk: filter, georeference, σ, sort into tile parts;
- :mod:`~acquire.deliver.tiles` — which parts make which tile file, and writing one;
- :mod:`~acquire.deliver.engine` — the job: plan, chunks, tiles, resume, summary;
- :mod:`~acquire.deliver.executors` — where the tasks run (this process, or Dask).
"""
