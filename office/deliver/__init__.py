"""Survey deliverables (``mls georef``, docs/architecture.md §8): a whole survey georeferenced into
LAZ tiles with per-point uncertainty, in time chunks, in-process or on a Dask cluster.

- :mod:`~office.deliver.options` — what the surveyor asks for (tiling, CRS, filters);
- :mod:`~office.deliver.calibration` — the calibrated mount, its covariance and provenance;
- :mod:`~office.deliver.sources` — a session or a bundle: trajectory, lines, time chunks, and the
  returns of one chunk;
- :mod:`~office.deliver.chunkjob` — one chunk: filter, georeference, σ, sort into tile parts;
- :mod:`~office.deliver.tiles` — which parts make which tile file, and writing one;
- :mod:`~office.deliver.engine` — the job: plan, chunks, tiles, resume, summary;
- :mod:`~office.deliver.executors` — where the tasks run (this process, or Dask).
"""
