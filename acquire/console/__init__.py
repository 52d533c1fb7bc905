"""The bridge console: a live web page of the survey served by the daemon (docs/console.md).

- ``fanout``: the status bus's sink that pushes every message to each WebSocket client (bounded, counted).
- ``actions``: the operator token and the actions (pass start/end, mark, alarm acknowledgement) through
  the MQTT commands' validation and rate limits, recorded in the session.
- ``server``: the aiohttp application (page, static assets, WebSocket, actions); TLS off loopback.
- ``daemon``: the console as a consumer of the supervisor (``web`` section of the vessel config).
- ``static/``: the page (our own HTML, CSS and JavaScript drawing on ``<canvas>``; nothing fetched).
"""
