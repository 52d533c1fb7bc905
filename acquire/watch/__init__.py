"""The mount watch in the daemon (docs/architecture.md §8.2a, issue 19): during a survey, the
boresight is re-estimated block by block from the live records and tested against the
calibrated mount (:mod:`calib.watch`).

- ``lines``: survey lines cut from the navigation (by heading) or the pass marks;
- ``buffers``: the navigation and the decimated returns kept for the current block;
- ``blockjob``: one block's trajectory, points and estimate;
- ``solver``: the worker process that estimates the blocks, off the daemon's event loop;
- ``report``: the ``mount`` checklist section, a block's summary (the verdict is calib.watch.report's);
- ``consumer``: :class:`MountWatchConsumer`, the consumer of the record stream;
- ``daemon``: the calibrated mount and the site's model from the vessel config, and the wiring.
"""
