"""The daemon's status bus and its clients.

- ``bus``: the status bus, the daemon's status to the local Unix socket and to MQTT.
- ``mqtt``: the MQTT publisher of the status bus (last will, reconnects, commands).
- ``feed``: the client side, the socket or MQTT as one async stream of ``(topic, data)``.
"""
