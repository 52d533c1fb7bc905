"""Whole jobs over the daemon's parts.

- ``demo``: ``mls demo``, the whole job on simulated devices, end to end.
- ``demo_children``: the demo's child processes, each in its own process group.
- ``demo_progress``: what the demo prints while the survey runs (live line, pass verdicts, σ).
- ``demo_compare``: the recovered boresight against the truth, and its table.
- ``export``: a session → a calibration bundle (``mls export``).
- ``exportbase``: what an export is asked and gives (options, error, pass windows, result).
- ``sessionread``: a session's navigation as every job reads it (site, INS epochs, events, trajectory).
- ``sessionnav``: a session's site, trajectory and passes without a bundle (``mls georef``).
- ``foxglove``: a session → an MCAP Foxglove opens as it is (``mls export --foxglove``).
- ``foxglove_cloud``: its profiles, decoded again for the clouds (the channels, frames and clouds
  themselves are :mod:`acquire.foxglove`'s, shared with the daemon's live server).
"""
