"""The pre-flight of the vessel PC (``mls doctor``, docs/doctor.md): each check a small function
returning a :class:`~acquire.doctor.result.CheckResult` (status, one-line message, advice).

- ``result``: :class:`CheckResult`, :class:`Status`, :class:`DoctorReport`, the exit status.
- ``access``: the daemon's user and what the file modes let it open.
- ``configcheck``: the config and its ports, from what ``mls acquire --check`` found.
- ``serial``: each serial device present and openable by the daemon's user.
- ``pps``: the PPS device (kernel, serial line or UDP) present and pulsing.
- ``clock``: the host clock disciplined (chrony, else systemd-timesyncd).
- ``host``: the UDP receive buffer (``net.core.rmem_max``) and the leap-second table.
- ``disk``: free space on the session disk against the hours planned at the configured rates.
- ``broker``: the MQTT broker reachable (TLS and credentials as configured).
- ``unit``: the installed systemd unit matches the installed software (install record).
- ``live``: the running daemon's own view (its status socket and lock).
- ``run``: all of them in order, with the seams tests replace.
"""
