"""The acquisition daemon (``mls acquire``).

- ``config``: the vessel config (``vessel.yaml``): loading and validation, every error at once.
- ``configschema``: the vessel config's parsed form, one frozen dataclass per section and device.
- ``configdevices``: the ``devices`` section: each device by its kind, and the checks across them.
- ``confignodes``: the checks of the config's YAML nodes (keys, ranges, choices, names, paths).
- ``devices``: the daemon's devices, one class per config ``kind``, each run as one task.
- ``consumers``: taps on the daemon's record stream for consumers, and the checklist publisher.
- ``sdnotify``: the systemd notification protocol and the health watchdog.
- ``pidlock``: one daemon per status socket: a lock file naming its holder's PID, host and start.
- ``sessionfiles``: the start-up salvage report and the files written into a new session.
- ``reports``: the status documents, the pre-survey checks and the watchdog's device check.
- ``devicetasks``: each device kept open and running, its failures recorded and alarmed.
- ``monitoring``: the monitor loop's alarms (time steps, packet loss, consumer overflow, clock).
- ``supervisor``: :class:`Supervisor`, one vessel config run from start-up to shutdown.
"""
