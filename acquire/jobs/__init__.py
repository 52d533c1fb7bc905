"""Whole jobs over the daemon's parts.

- ``demo``: ``mls demo``, the whole job on simulated devices, end to end.
- ``export``: a session → a calibration bundle (``mls export``).
"""
