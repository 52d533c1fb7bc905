"""What the calibration checks so that it is never confidently wrong (docs/architecture.md §7.5a,
§7.7a): the input before anything is computed (``inputs``: points, coverage, reach), gross errors
per target group after the adjustment (``grouptest``), and the verdict on the whole result
(``verdict``)."""
