"""The daemon's wiring of the guidance: :class:`GuidanceConsumer` runs a
:class:`~acquire.guidance.state.Guidance` as a consumer of the record stream (the
:mod:`acquire.daemon.consumers` protocol)::

    site = load_site(cfg.site_file)
    g = Guidance(site, plan_site(site))
    Supervisor(cfg, consumers=[GuidanceConsumer(g, clock_state=lambda: ..., checks=lambda: ...)])

It feeds ``g.on_nav(rec)`` / ``g.on_profile(p)`` from the tap, ``g.on_clock(state)`` and
``g.update()`` every ``period_s``, runs ``g.refresh_prediction()`` in a thread after each
accepted pass, and publishes ``g.message(checks)`` as the ``guidance`` section of the
``checklist`` topic.
"""

from __future__ import annotations

from acquire.guidance.state import Guidance


class GuidanceConsumer:
    """Runs a :class:`Guidance` as a consumer of the daemon's record stream
    (:mod:`acquire.daemon.consumers`): ``nav`` and ``profile`` records feed it, ``pass_start`` events
    select a line; every ``period_s`` it updates and publishes its message as the ``guidance``
    section of the ``checklist`` topic. The σ prediction runs in a worker thread.

    ``clock_state()`` returns the clock model's state now (``"LOCKED"``…); ``checks()`` the
    pre-survey checks to publish with the guidance (e.g. :func:`prechecks` over the daemon's
    latest status), or None.
    """

    name = "guidance"
    kinds = ("nav", "profile", "event")

    def __init__(self, guidance: Guidance, *, clock_state=None, checks=None, period_s: float = 0.5):
        self.guidance = guidance
        self.clock_state = clock_state
        self.checks = checks
        self.period_s = period_s
        self.records = 0

    def feed(self, kind: str, record, gps_ns: int | None = None) -> None:
        g = self.guidance
        self.records += 1
        if kind == "nav":
            g.on_nav(record)
        elif kind == "profile":
            g.on_profile(record)
        elif kind == "event" and isinstance(record, dict) and record.get("event") == "pass_start":
            try:
                g.select_pass(int(record["pass_id"]))
            except (KeyError, TypeError, ValueError):
                pass  # an event naming no pass of the plan changes nothing

    async def run(self, tap, checklist) -> None:
        import asyncio

        async def read() -> None:
            async for kind, record, gps_ns in tap:
                self.feed(kind, record, gps_ns)

        reader = asyncio.create_task(read())
        predict: asyncio.Future | None = None
        predicted_for = -1  # accepted passes the last prediction was started for
        try:
            while True:
                g = self.guidance
                if self.clock_state is not None:
                    g.on_clock(self.clock_state())
                g.update(predict=False)
                if predict is not None and predict.done():
                    predict.result()  # a failed prediction ends the consumer (restarted)
                    predict = None
                n_acc = len(g.accepted_ids)
                if predict is None and n_acc != predicted_for:
                    predict = asyncio.ensure_future(asyncio.to_thread(g.refresh_prediction))
                    predicted_for = n_acc
                checklist.publish("guidance", g.message(self.checks() if self.checks else None))
                if reader.done():
                    reader.result()  # re-raise what ended the reader
                    return
                await asyncio.sleep(self.period_s)
        finally:
            reader.cancel()
            if predict is not None:
                await asyncio.gather(predict, return_exceptions=True)
