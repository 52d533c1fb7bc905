"""The mount watch (docs/architecture.md §7.8): during a production survey, the boresight
correction that reconciles the tie patches of consecutive lines of opposite headings
(:mod:`calib.watch.block`), tested block by block against the calibrated mount with a
sequential test of stated false-alarm rate (:mod:`calib.watch.sequential`)."""
