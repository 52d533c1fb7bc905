"""An INS unplugged and plugged in again: the daemon records every epoch the INS sends after the
replug, the first one included.

The supervisor runs in-process with one INS on the emulators' own pty (:class:`sim_devices.
serialpty.PtyPort`, the device of ``mls sim devices``: the link ``<dir>/ins`` removed and the
pty closed on unplug, a new pty behind the same link on replug, a 50 ms transmit FIFO and the
kernel's pty buffer in front of a reader that is late). A thread writes PHINS epochs at 200 Hz
(the Hydrins' top rate) and unplugs the device for 1 s, longer than the serial back-off's cap
(0.5 s), as in ``benchmarks/soak.py`` where epochs were lost after each replug."""

from __future__ import annotations

import asyncio
import queue
import textwrap
import threading
import time
from pathlib import Path

import pytest

from acquire.daemon.config import load_vessel_config
from acquire.daemon.supervisor import Supervisor
from acquire.log.read import iter_messages
from acquire.timing.timekeeper import coarse_gps_offset_ns
from drivers.hydrins.nmea_encode import encode_epoch
from sim_devices.serialpty import PtyPort
from tests.acquire.fakedevices import nav_at
from tests.waiting import wait_until_async

pytestmark = [pytest.mark.integration, pytest.mark.realtime]
NS = 1_000_000_000
PERIOD_NS = 5_000_000  # 200 Hz
UNPLUGGED_S = 1.0  # the fault's length: past the old back-off's 0.5 s cap
AFTER_S = 1.0  # epochs written after the replug
# The daemon must have the new pty open before the pty's buffer (4–64 kB by kernel: 50 ms to
# 800 ms of this 82 kB/s stream) and the emulated FIFO (50 ms) fill; the old back-off took up
# to 500 ms. Watching the path, it opens within a few ms: 150 ms leaves a loaded machine slack.
REOPEN_WITHIN_S = 0.15


class InsWriter(threading.Thread):
    """Epoch k (GPS ``gps0_ns + k·5 ms``) at its host instant, unplugging and replugging on
    request: a request is done just before the next epoch, so the epoch written after a
    replug is the first the new device sends."""

    def __init__(self, link: Path, gps0_ns: int) -> None:
        super().__init__(daemon=True, name="ins-writer")
        self.port = PtyPort(link)
        self.port.plug()
        self.gps0_ns = gps0_ns
        self.requests: queue.Queue[str] = queue.Queue()
        self.halt = threading.Event()
        self.written: list[int] = []  # GPS ns of every epoch written, plugged or not
        self.done: dict[str, tuple[int, int]] = {}  # request → (host ns, index of the next epoch)

    def gps_of(self, k: int) -> int:
        return self.gps0_ns + k * PERIOD_NS

    def run(self) -> None:
        t0 = time.monotonic_ns()
        k = 0
        while not self.halt.is_set():
            time.sleep(max(t0 + k * PERIOD_NS - time.monotonic_ns(), 0) / NS)
            while not self.requests.empty():
                what = self.requests.get()
                self.port.unplug() if what == "unplug" else self.port.plug()
                self.done[what] = (time.monotonic_ns(), k)
            self.port.write(encode_epoch(nav_at(self.gps_of(k), k)))
            self.written.append(self.gps_of(k))
            k += 1


class NavSeen:
    """A consumer tap: the device time tags of the epochs the daemon decoded."""

    name = "nav-seen"
    kinds = ("nav",)

    def __init__(self) -> None:
        self.tags: set[int] = set()

    async def run(self, tap, checklist) -> None:
        async for _, nav, _ in tap:
            self.tags.add(nav.gps_ns)


async def until(condition, timeout_s: float, what: str) -> None:
    await wait_until_async(condition, timeout_s, what, interval_s=0.01)


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
    writer = InsWriter(tmp_path / "ins", gps0)
    out: dict = {}

    async def scenario() -> None:
        seen = NavSeen()
        sup = Supervisor(load_vessel_config(_config(tmp_path)), consumers=[seen])
        task = asyncio.create_task(sup.run())
        ins = sup.devices["ins"]
        await until(lambda: ins.transport is not None and ins.transport.connected, 20, "the daemon")
        writer.start()
        await until(lambda: ins.records >= 50, 10, "the first 50 epochs")
        writer.requests.put("unplug")
        await until(lambda: not ins.transport.connected, 5, "the daemon to see the unplug")
        await asyncio.sleep(UNPLUGGED_S)  # the fault's length (not a wait for an outcome)
        writer.requests.put("plug")
        await until(lambda: "plug" in writer.done, 5, "the replug")
        plugged_ns, first = writer.done["plug"]
        await asyncio.sleep(AFTER_S)  # the stream after the replug (its length)
        writer.halt.set()
        await asyncio.to_thread(writer.join, 10)
        await until(lambda: writer.written[-1] in seen.tags, 10, "the daemon to decode the last epoch")
        out["connected_ns"] = [e.host_ns for e in ins.transport.events if e.kind == "connected"]
        out["plugged_ns"], out["first"] = plugged_ns, first
        sup.request_stop("test")
        assert await task == 0
        out["session"] = sup.writer.session_dir

    try:
        asyncio.run(asyncio.wait_for(scenario(), 60))
    finally:
        writer.halt.set()
        writer.join(10)
        writer.port.close()
    logged = {m.payload["gps_ns"] for m in iter_messages(out["session"], {"/ins/nav"})}
    first = out["first"]
    after = writer.written[first:]
    assert writer.gps_of(first) in logged, "the first epoch written after the replug is not recorded"
    missing = [(g - gps0) // PERIOD_NS for g in after if g not in logged]
    assert missing == [], f"epochs written after the replug (from {first}) not recorded: {missing}"
    reopened_s = (out["connected_ns"][-1] - out["plugged_ns"]) / NS
    assert 0 <= reopened_s <= REOPEN_WITHIN_S, f"the port reopened {reopened_s:.3f} s after the replug"
    assert writer.port.stats["bytes_overrun"] == 0
