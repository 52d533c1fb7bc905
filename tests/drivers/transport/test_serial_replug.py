"""The serial transport after its device went away: it waits for the path to come back (an
inotify watch, no polling), opens it at once, and keeps what the device sent before the open.

On the emulators' pty (:class:`sim_devices.serialpty.PtyPort`: the slave held open by the
emulator, as a UART holds what arrives, a link moved into place on plug)."""

from __future__ import annotations

import asyncio
import os
import select
import time
from pathlib import Path

import pytest

from drivers.transport.pathwatch import nearest_directory, wait_for_path
from drivers.transport.serial_port import SerialTransport
from sim_devices.serialpty import PtyPort
from tests.waiting import wait_until_async

pytestmark = pytest.mark.integration
# A reopen is due within this of the path's return: the watch wakes the loop at once (a few ms);
# the old back-off needed up to its 0.5 s cap. 0.15 s leaves a loaded machine its slack.
PROMPT_S = 0.15
# reconnect_max_s of a transport whose fallback look (and back-off cap) is a minute away: within
# PROMPT_S of the path's return only the watch can have reopened it, however long it waited.
NO_FALLBACK_S = 60.0


async def until(condition, timeout_s: float, what: str, changed: asyncio.Event | None = None) -> None:
    await wait_until_async(condition, timeout_s, what, interval_s=0.005, changed=changed)


async def read_exactly(t: SerialTransport, n: int, timeout_s: float = 5.0) -> bytes:
    got = b""
    async with asyncio.timeout(timeout_s):
        while len(got) < n:
            got += (await t.read()).data
    return got


def connected_at(t: SerialTransport) -> int:
    return [e.host_ns for e in t.events if e.kind == "connected"][-1]


class WatchedWatch:
    """The transport's path watch (:func:`wait_for_path`), watched: the directory each wait for
    the missing path watches, recorded (and ``changed`` set) once the real watch is in place —
    ``call_soon`` runs after this task's step, which installs it before its first suspension."""

    def __init__(self) -> None:
        self.dirs: list[Path] = []
        self.changed = asyncio.Event()

    def _record(self, directory: Path) -> None:
        self.dirs.append(directory)
        self.changed.set()

    async def __call__(self, path: str, timeout_s: float) -> bool:
        asyncio.get_running_loop().call_soon(self._record, nearest_directory(path))
        return await wait_for_path(path, timeout_s)

    async def watching(self, directory: Path, what: str) -> None:
        """Until the transport's latest wait watches ``directory``."""
        await until(lambda: self.dirs and self.dirs[-1] == directory, 5, what, self.changed)


def test_nearest_directory_is_the_deepest_that_exists(tmp_path):
    assert nearest_directory(tmp_path / "ins") == tmp_path
    assert nearest_directory(tmp_path / "serial" / "by-id" / "usb-ins") == tmp_path
    (tmp_path / "serial").mkdir()
    assert nearest_directory(tmp_path / "serial" / "by-id" / "usb-ins") == tmp_path / "serial"


@pytest.mark.realtime  # the bound: the watch's timeout, 0.3 s, against a loaded machine's slack
def test_wait_for_path_returns_at_the_timeout_when_nothing_comes(tmp_path):
    async def run() -> tuple[bool, float]:
        t0 = time.monotonic()
        found = await wait_for_path(tmp_path / "ins", 0.3)
        return found, time.monotonic() - t0

    found, waited_s = asyncio.run(run())
    assert not found
    assert 0.29 <= waited_s <= 0.3 + PROMPT_S


@pytest.mark.realtime  # PROMPT_S (above): the watch against the old back-off
def test_a_replugged_port_is_reopened_at_once_and_keeps_what_the_device_sent(tmp_path):
    """The device comes back and sends at once, before anyone opened it: its first bytes are
    read (pyserial's open would flush them; the first open of a transport still does)."""
    link = tmp_path / "ins"
    port = PtyPort(link)
    port.plug()
    watch = WatchedWatch()

    async def run() -> tuple[bytes, float]:
        async with SerialTransport(str(link), reconnect_max_s=NO_FALLBACK_S, path_watch=watch) as t:
            port.write(b"before\r\n")
            assert await read_exactly(t, 8) == b"before\r\n"
            port.unplug()
            await until(lambda: not t.connected, 5, "the unplug to be seen")
            await watch.watching(tmp_path, "the transport to wait for its path")
            staged = PtyPort(tmp_path / "staged")  # the new device, not at the path yet
            staged.plug()
            staged.write(b"first after replug\r\n")  # sent before the port can be opened
            os.replace(staged.link, link)  # udev's (or the emulator's) link moved into place
            moved_ns = time.monotonic_ns()
            await until(lambda: t.connected, 5, "the reopen")
            got = await read_exactly(t, 20)
            staged.close()
            return got, (connected_at(t) - moved_ns) / 1e9

    try:
        got, reopen_s = asyncio.run(run())
    finally:
        port.close()
    assert got == b"first after replug\r\n"
    assert reopen_s <= PROMPT_S


@pytest.mark.realtime  # PROMPT_S (above)
def test_a_port_in_a_directory_that_comes_back_is_found_at_once(tmp_path):
    """``/dev/serial/by-id/`` disappears with the last adapter and comes back with the next:
    the transport watches the deepest directory that exists and follows it down."""
    by_id = tmp_path / "serial" / "by-id"
    link = by_id / "usb-ins"
    watch = WatchedWatch()

    async def run() -> float:
        async with SerialTransport(str(link), reconnect_max_s=NO_FALLBACK_S, path_watch=watch) as t:
            await watch.watching(tmp_path, "the transport to watch the deepest directory there")
            by_id.mkdir(parents=True)
            # udev makes the link a moment after the directory: the watch has followed it down
            await watch.watching(by_id, "the transport to watch the new directory")
            port = PtyPort(link)
            port.plug()
            plugged_ns = time.monotonic_ns()
            try:
                await until(lambda: t.connected, 5, "the open")
            finally:
                port.close()
            return (connected_at(t) - plugged_ns) / 1e9

    assert asyncio.run(run()) <= PROMPT_S


@pytest.mark.realtime  # times the attempts against the fallback look every 0.5 s (1.6 s: its window)
def test_an_absent_port_is_not_polled(tmp_path):
    """While the path is missing the transport waits on the watch, looking only every
    ``reconnect_max_s`` (0.5 s) in case the watch misses it: a handful of attempts, not a spin."""
    link = tmp_path / "ins"
    attempts: list[float] = []
    watch = WatchedWatch()

    async def run() -> float:
        t = SerialTransport(str(link), path_watch=watch)
        connect = t._connect

        async def counted() -> None:
            attempts.append(time.monotonic())
            watch.changed.set()
            await connect()

        t._connect = counted  # type: ignore[method-assign]
        async with t:
            await watch.watching(tmp_path, "the transport to watch the directory")
            (tmp_path / "other-file").write_text("x")  # activity in the directory: looked at, not opened
            await until(lambda: len(attempts) >= 4, 10, "four attempts to open", watch.changed)
            return t.reconnect_max_s

    fallback_s = asyncio.run(run())
    gaps_s = [b - a for a, b in zip(attempts, attempts[1:4], strict=False)]
    # at open, then every 0.5 s (a millisecond: the clocks' rounding), and the looks do come
    assert all(fallback_s - 0.001 <= gap_s <= 1.6 for gap_s in gaps_s), attempts
    assert len(watch.dirs) >= 4, watch.dirs  # three fallback waits, the first woken by the activity


# -- the emulated device's accounting, which benchmarks/soak.py relies on ------------------------


def _fill(port: PtyPort, now_ns: int) -> int:
    """Write until the pty refuses (nobody reads); returns the bytes written."""
    while not port._backlog:
        port.write(b"x" * 400, now_ns)
    return port.stats["bytes_written"]


def _read_all(fd: int, n: int, timeout_s: float = 5.0) -> None:
    """Read ``n`` bytes from a non-blocking ``fd`` (what the pty holds: it is then empty)."""
    deadline = time.monotonic() + timeout_s
    while n > 0:
        assert select.select([fd], [], [], max(deadline - time.monotonic(), 0))[0], "the pty went quiet"
        n -= len(os.read(fd, 65536))


def test_the_emulated_fifo_drops_only_what_the_pty_still_refuses_after_backlog_s(tmp_path):
    port = PtyPort(tmp_path / "ins", backlog_s=0.05)
    port.plug()
    try:
        _fill(port, 0)
        port.write(b"y" * 400, 10_000_000)  # within backlog_s: kept
        assert port.stats["bytes_overrun"] == 0
        port.write(b"", 60_000_000)  # past it, nobody read: the oldest are lost
        assert port.stats["bytes_overrun"] > 0
        assert len(port.overruns) == 1
        lost = port.stats["bytes_overrun"]  # (the 'y's, not yet past backlog_s, wait)
        assert port.slave_path is not None  # (plugged)
        reader = os.open(port.slave_path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY)
        try:
            _read_all(reader, port.stats["bytes_written"])  # the reader catches up ...
            port.write(b"", 200_000_000)  # ... so the 'y's, now past backlog_s, are sent, not lost
        finally:
            os.close(reader)
        assert port.stats["bytes_overrun"] == lost
        assert not port._backlog
    finally:
        port.close()


def test_an_unplug_counts_the_bytes_it_cuts_off(tmp_path):
    port = PtyPort(tmp_path / "ins", backlog_s=0.05)
    port.plug()
    written = _fill(port, 0)  # all unread, and some refused: the FIFO holds them
    waiting = sum(len(c) for _, c in port._backlog)
    assert port.unplug() == written + waiting == port.stats["bytes_in_flight"]
    assert port.accepted == written + waiting
