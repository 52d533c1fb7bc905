"""The daemon's status bus and its clients.

- ``bus``: the status bus, the daemon's status to the local Unix socket and to MQTT.
- ``mqtt``: the MQTT publisher of the status bus (TLS, last will, reconnects, commands).
- ``commands``: the commands taken from MQTT: payloads validated, rate-limited per kind.
- ``runfiles``: the files the daemon opens in its run directory (no links, no other owner).
- ``feed``: the client side, the socket or MQTT as one async stream of ``(topic, data)``.
"""
