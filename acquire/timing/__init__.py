"""Time on the vessel PC: PPS pulses, the GPS clock model and the latency of the devices.

- ``clock``: the clock model, host monotonic ns → GPS ns fitted over labelled PPS edges.
- ``timekeeper``: PPS edges and time messages → labelled pulses → the clock model.
- ``latency``: the latency monitor and sync check, device time tags against the clock model.
"""
