"""The survey office: batch work on what the vessel recorded, never on the vessel's real-time path.

``jobs`` exports sessions (LAS/LAZ, MCAP for Foxglove) and orchestrates the demo; ``deliver``
georeferences whole surveys into tiles with per-point uncertainty (in process or on Dask) and
runs the mount watch over a recorded survey; ``simsession`` records a simulated session offline
through the real session writer. It imports ``calib``, ``drivers``, ``acquire`` and
``sim_devices``; ``acquire`` imports nothing of it (tests/test_architecture.py).
"""
