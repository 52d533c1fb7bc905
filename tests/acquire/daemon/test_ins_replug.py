"""An INS unplugged and plugged in again: the daemon records every epoch the INS sends after the
replug, the first one included.

The supervisor runs in-process with one INS on the emulators' own pty (:class:`sim_devices.
serialpty.PtyPort`, the device of ``mls sim devices``: the link ``<dir>/ins`` removed and the
pty closed on unplug, a new pty behind the same link on replug, a 50 ms transmit FIFO and the
kernel's pty buffer in front of a reader that is late). The test writes PHINS epochs in bursts
of 50 ms at 200 Hz (the Hydrins' top rate), each once the daemon has decoded the last, and
keeps the device unplugged until the daemon has failed to reopen it (its first look after
0.5 s, the old serial back-off's cap), as in ``benchmarks/soak.py`` where epochs were lost after
each replug. The first burst after the replug is written before the daemon can open the port."""

from __future__ import annotations

import asyncio
import textwrap
import time
from pathlib import Path

import pytest

from acquire.daemon.config import load_vessel_config
from acquire.daemon.devices import Device, InsDevice
from acquire.daemon.supervisor import Supervisor
from acquire.log.read import iter_messages
from acquire.log.schema import Envelope
from acquire.timing.timekeeper import coarse_gps_offset_ns
from drivers.hydrins.nmea_encode import encode_epoch
from drivers.transport.base import Transport
from sim_devices.serialpty import PtyPort
from tests.acquire.fakedevices import nav_at
from tests.waiting import wait_until_async

# realtime: REOPEN_WITHIN_S (below), the reopen held against the host clock
pytestmark = [pytest.mark.integration, pytest.mark.realtime]
NS = 1_000_000_000
PERIOD_NS = 5_000_000  # 200 Hz
BURST = 10  # epochs a burst: 50 ms of the stream, 4 kB (the pty holds more)
BEFORE = 50  # epochs written before the unplug
AFTER = 200  # epochs written after the replug (1 s of the stream)
# The daemon must have the new pty open before the pty's buffer (4–64 kB by kernel: 50 ms to
# 800 ms of this 82 kB/s stream) and the emulated FIFO (50 ms) fill; the old back-off took up
# to 500 ms. Watching the path, it opens within a few ms: 150 ms leaves a loaded machine slack.
REOPEN_WITHIN_S = 0.15


class InsOnPty:
    """Epoch k (GPS ``gps0_ns + k·5 ms``), written by the test in bursts; ``written`` keeps the
    GPS ns of every epoch written, plugged or not."""

    def __init__(self, link: Path, gps0_ns: int) -> None:
        self.port = PtyPort(link)
        self.port.plug()
        self.gps0_ns = gps0_ns
        self.written: list[int] = []

    def gps_of(self, k: int) -> int:
        return self.gps0_ns + k * PERIOD_NS

    def burst(self) -> None:
        for _ in range(BURST):
            k = len(self.written)
            self.port.write(encode_epoch(nav_at(self.gps_of(k), k)))
            self.written.append(self.gps_of(k))


class NavSeen:
    """A consumer tap: the device time tags of the epochs the daemon decoded (``changed`` set
    at each)."""

    name = "nav-seen"
    kinds = ("nav",)

    def __init__(self) -> None:
        self.tags: set[int] = set()
        self.changed = asyncio.Event()

    async def run(self, tap, checklist) -> None:
        async for _, nav, _ in tap:
            self.tags.add(nav.gps_ns)
            self.changed.set()

    async def burst(self, device: InsOnPty, until_written: int) -> None:
        """Bursts from ``device``, each once the daemon has decoded the last epoch written, until
        ``until_written`` epochs are written and decoded."""
        while True:
            last = len(device.written) - 1
            await until(
                lambda: device.written[-1] in self.tags,
                10,
                f"the daemon to decode epoch {last}",
                self.changed,
            )
            if len(device.written) >= until_written:
                return
            device.burst()


async def until(condition, timeout_s: float, what: str, changed: asyncio.Event | None = None) -> None:
    await wait_until_async(condition, timeout_s, what, interval_s=0.01, changed=changed)


def transport_of(ins: Device) -> Transport:
    """The INS's transport (made when the supervisor opened the device)."""
    assert isinstance(ins, InsDevice)
    assert ins.transport is not None, "the INS is not open yet"
    return ins.transport


def gps_ns_of(message: Envelope) -> int:
    assert isinstance(message.payload, dict), message.topic  # (a decoded record)
    return message.payload["gps_ns"]


def _config(tmp: Path) -> Path:
    cfg = tmp / "vessel.yaml"
    cfg.write_text(
        textwrap.dedent(f"""\
        vessel: replug-1
        devices:
          - {{name: ins, kind: ins, protocol: nmea, transport: {{type: serial, port: {tmp}/ins, baud: 115200}},
             latency: {{band_ms: [0.0, 50.0], rate_hz: 200.0, gap_s: 2.0}}}}
        session: {{directory: {tmp}/sessions, flush_s: 0.2}}
        status: {{socket: {tmp}/status.sock}}
        """)
    )
    return cfg


def test_the_first_epoch_after_a_replug_is_recorded(tmp_path):
    gps0 = (time.monotonic_ns() + coarse_gps_offset_ns()) // NS * NS + 300_000_000
    device = InsOnPty(tmp_path / "ins", gps0)
    out: dict = {}

    async def scenario() -> None:
        seen = NavSeen()
        sup = Supervisor(load_vessel_config(_config(tmp_path)), consumers=[seen])
        task = asyncio.create_task(sup.run())
        ins = sup.devices["ins"]
        await until(lambda: ins.opened and transport_of(ins).connected, 20, "the daemon")
        device.burst()
        await seen.burst(device, BEFORE)
        device.port.unplug()
        await until(lambda: not transport_of(ins).connected, 5, "the daemon to see the unplug")
        device.burst()  # sent while unplugged: lost with the device
        await until(  # the fault's length: until the daemon's first look at the path failed
            lambda: any(e.kind == "reconnect_failed" for e in transport_of(ins).events),
            5,
            "the daemon to fail a reopen",
        )
        device.port.plug()
        out["plugged_ns"], out["first"] = time.monotonic_ns(), len(device.written)
        device.burst()  # the device sends at once, before the daemon can have opened the port
        await seen.burst(device, out["first"] + AFTER)
        out["connected_ns"] = [e.host_ns for e in transport_of(ins).events if e.kind == "connected"]
        sup.request_stop("test")
        assert await task == 0
        assert sup.writer is not None
        out["session"] = sup.writer.session_dir

    try:
        asyncio.run(asyncio.wait_for(scenario(), 60))
    finally:
        device.port.close()
    logged = {gps_ns_of(m) for m in iter_messages(out["session"], {"/ins/nav"})}
    first = out["first"]
    after = device.written[first:]
    assert device.gps_of(first) in logged, "the first epoch written after the replug is not recorded"
    missing = [(g - gps0) // PERIOD_NS for g in after if g not in logged]
    assert missing == [], f"epochs written after the replug (from {first}) not recorded: {missing}"
    reopened_s = (out["connected_ns"][-1] - out["plugged_ns"]) / NS
    assert 0 <= reopened_s <= REOPEN_WITHIN_S, f"the port reopened {reopened_s:.3f} s after the replug"
    assert device.port.stats["bytes_overrun"] == 0
    assert device.port.stats["bytes_unplugged"] > 0  # (the burst while unplugged)
