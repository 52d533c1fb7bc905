"""Simulated devices: real-time emulators of the INS, the profiler, the PPS and the CAN event
markers, fed by :func:`calib.sim.simulate.simulate`, with fault injection and session replay
(docs/architecture.md §2, §5 "Simulated devices"). ``acquire`` never imports this package at module level;
``mls sim devices`` / ``mls sim replay`` load it inside the commands.

- :mod:`sim_devices.feed` — a simulation window cut into device streams: INS epochs, the
  profiler's profile grid with the scenario's returns, pass markers (pure numpy).
- :mod:`sim_devices.clock` — the truth clock (host monotonic → GPS, offset, drift, speed),
  written to ``truth_clock.json``.
- :mod:`sim_devices.faults` — the fault timeline (YAML, validated with file:line:key errors).
- :mod:`sim_devices.ins`, :mod:`sim_devices.profiler`, :mod:`sim_devices.pps`,
  :mod:`sim_devices.canbus` — the emulators (NMEA/STDBIN on a pty, ZFP1 over UDP, PPS1 over
  UDP, event markers on python-can); :mod:`sim_devices.serialpty` (a pty behind a stable link),
  :mod:`sim_devices.udp` (a UDP sender with loss/reorder/duplication),
  :mod:`sim_devices.pacing` (emission at scheduled instants, timing error, CPU).
- :mod:`sim_devices.runner` — :class:`~sim_devices.runner.DeviceRun`: one process per
  emulator, the run directory, clean stop; :mod:`sim_devices.replay` — re-emission of a
  recorded session; :mod:`sim_devices.vesselconfig` — the vessel config for ``mls acquire``.
"""
