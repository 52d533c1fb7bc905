"""Whole jobs over the daemon's parts.

- ``demo``: ``mls demo``, the whole job on simulated devices, end to end.
- ``demo_children``: the demo's child processes, each in its own process group.
- ``demo_progress``: what the demo prints while the survey runs (live line, pass verdicts, σ).
- ``demo_compare``: the recovered boresight against the truth, and its table.
- ``export``: a session → a calibration bundle (``mls export``).
"""
