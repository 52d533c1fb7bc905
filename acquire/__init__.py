"""The acquisition side: the daemon, its session log and status bus, and the operator tools.

Lowest layer first (a subpackage imports only lower ones; docs/architecture.md §2):

- ``alarms`` (a module): named alarms with raise/clear hysteresis, shared by the monitors.
- ``timing``: PPS pulses, the GPS clock model and the latency of the devices.
- ``log``: the session log: crash-safe MCAP segments, their salvage, reading them back.
- ``status``: the daemon's status bus (local socket, MQTT) and its clients.
- ``daemon``: the acquisition daemon (``mls acquire``): config, devices, supervisor.
- ``guidance``: line guidance for the calibration passes, in the daemon and to the autopilot.
- ``ui``: the operator's screens (``mls checklist``).
- ``jobs``: whole jobs over the daemon's parts (``mls demo``, ``mls export``).
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("marine-mls")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+source"
