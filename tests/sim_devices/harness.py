"""What a daemon would do with the emulators, reduced to capture: read every device on its real
transport (the pty link through the drivers' serial transport, UDP sockets, the CAN bus) and
decode with :mod:`drivers` while a :class:`~sim_devices.runner.DeviceRun` runs (not a test
module)."""

from __future__ import annotations

import asyncio
import fcntl
import gc
import struct
import termios
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

from drivers.can import EVENT_MARKER_ID, CanReader, decode_event_marker, open_can_bus
from drivers.hydrins.nmea_decode import NmeaNavAssembler
from drivers.hydrins.nmea_sentences import Zda
from drivers.hydrins.stdbin_decode import StdbinNavDecoder
from drivers.pps import decode_pps_datagram
from drivers.transport.registry import create_transport
from drivers.zf.assembler import ProfileAssembler
from sim_devices.canbus import CanSettings
from sim_devices.feed import make_feed
from sim_devices.replay import ReplayRun, ReplaySpec
from sim_devices.runner import DeviceRun, DevicesSpec
from tests.waiting import wait_until_async

#: receive-side slack for arrival instants: the test process decodes everything in Python on a
#: shared 2-core machine (other tests, other workers), so a read can come this late
RX_SLACK_NS = 200_000_000

#: the emulators end by themselves after their window; on a loaded machine, this late at most
FINISH_TIMEOUT_S = 30.0

#: shortened passes (10 s lines, 2 s apart), no scan-angle noise: ZFP1 then carries the exact angles
SHORT_PASSES = ["site.pass_length_m=20", "motion.pass_gap_s=2", "noise.scanner.sigma_scan_angle_deg=0"]


def slack(cap, device: str) -> int:
    """The emulator's own worst timing error plus the receive slack."""
    return round(cap.stats[device]["timing"]["error_max_us"] * 1e3) + RX_SLACK_NS


@dataclass
class Capture:
    run: DeviceRun
    chunks: list = field(default_factory=list)  # (host_ns, bytes) read from the pty
    nav: list = field(default_factory=list)  # NavRecord
    zda: list = field(default_factory=list)  # Zda sentence records (NMEA)
    serial_events: list = field(default_factory=list)  # TransportEvent
    nav_stats: object = None
    datagrams: list = field(default_factory=list)  # (host_ns, bytes) profiler
    profiles: list = field(default_factory=list)
    assembler_stats: object = None
    pps: list = field(default_factory=list)  # (arrival host_ns, PpsEdge)
    markers: list = field(default_factory=list)  # CanFrame with .decoded EventMarker
    stats: dict = field(default_factory=dict)  # the emulators' own stats (run.stop())

    @property
    def clock(self):
        return self.run.clock


def _chunk_hook(decoder, capture: Capture):
    """Wrap the NMEA decoder's sentence output to also keep the ZDA records."""
    feed = decoder.feed

    def fed(data, host_ns=None):
        out = feed(data, host_ns)
        capture.zda.extend(r for r in out if isinstance(r, Zda))
        return out

    decoder.feed = fed


def _drained(udp, ser, reader) -> bool:
    """Nothing left to read once the emulators have ended: no datagram waiting in a UDP socket
    (``FIONREAD``: the size of the next one) nor in a transport's queue, the INS pty read until
    the emulator closed it, the CAN frames handed over."""
    for t in udp:
        if t is None:
            continue
        sock = t._transport.get_extra_info("socket") if t._transport is not None else None
        waiting = (
            0
            if sock is None
            else struct.unpack("i", fcntl.ioctl(sock.fileno(), termios.FIONREAD, b"\0" * 4))[0]
        )
        if waiting or t._chunks:
            return False
    if ser is not None and (ser.connected or ser._chunks):
        return False
    return reader is None or reader._queue.empty()


async def _capture(
    cap: Capture, make_run, devices, ins_protocol: str, can_config: dict | None, end_host, grace_s: float
) -> None:
    """Open the receivers, ``make_run(profiler_port, pps_port)``, start it, capture until the
    emulators have ended (at the latest :data:`FINISH_TIMEOUT_S` after ``end_host(run)`` +
    ``grace_s``) and what they sent is read, stop it. The garbage collector is off meanwhile: in a test
    process a full collection holds the GIL for a few hundred ms, longer than the emulated
    UART buffers (the pty's 20 kB and the emulator's 50 ms)."""
    gc.collect()
    gc.disable()
    try:
        await _capture_with_gc_off(cap, make_run, devices, ins_protocol, can_config, end_host, grace_s)
    finally:
        gc.enable()


async def _capture_with_gc_off(
    cap: Capture, make_run, devices, ins_protocol: str, can_config: dict | None, end_host, grace_s: float
) -> None:
    loop_tasks = []
    prof_t = pps_t = None
    if "profiler" in devices:
        prof_t = create_transport({"kind": "udp", "host": "127.0.0.1", "port": 0, "max_chunks": 100_000})
        await prof_t.open()
    if "pps" in devices:
        pps_t = create_transport({"kind": "udp", "host": "127.0.0.1", "port": 0})
        await pps_t.open()
    cap.run = run = make_run(prof_t.port if prof_t else 0, pps_t.port if pps_t else 0)
    run.start()
    try:
        ser = None
        if "ins" in devices:
            ser = create_transport(
                {
                    "kind": "serial",
                    "port": str(run.run_dir / "ins"),
                    "reconnect_min_s": 0.02,
                    "reconnect_max_s": 0.05,
                },
                on_event=cap.serial_events.append,
            )
            await ser.open()
        reader = None
        if can_config is not None:
            reader = CanReader(
                open_can_bus(can_config), {EVENT_MARKER_ID: decode_event_marker}, close_bus=True
            )
            await reader.__aenter__()
        end = end_host(run) + round(grace_s * 1e9)

        async def pump(transport, sink):
            while True:
                try:
                    data, host_ns = await transport.read()
                except EOFError:
                    return
                sink(data, host_ns)

        if ser is not None:
            if ins_protocol == "nmea":
                asm = NmeaNavAssembler()
                _chunk_hook(asm.decoder, cap)
            else:
                asm = StdbinNavDecoder()
            cap.nav_stats = asm.stats

            def on_serial(data, host_ns):
                cap.chunks.append((host_ns, data))
                cap.nav.extend(asm.feed(data, host_ns))

            loop_tasks.append(asyncio.create_task(pump(ser, on_serial)))
        if prof_t is not None:
            assembler = ProfileAssembler()
            cap.assembler_stats = assembler.stats

            def on_datagram(data, host_ns):
                cap.datagrams.append((host_ns, data))
                cap.profiles.extend(assembler.feed(data, host_ns))

            loop_tasks.append(asyncio.create_task(pump(prof_t, on_datagram)))
        if pps_t is not None:
            loop_tasks.append(
                asyncio.create_task(pump(pps_t, lambda d, h: cap.pps.append((h, decode_pps_datagram(d)))))
            )
        if reader is not None:

            async def can_pump():
                while True:
                    cap.markers.append(await reader.get())

            loop_tasks.append(asyncio.create_task(can_pump()))
        # read until the emulators have ended (after their window; on a loaded machine they run
        # late; the INS keeps its pty open a while after its last write), then what is still in
        # transit: every queue empty and handed over, the INS pty read to its end
        await wait_until_async(
            lambda: not run.running(),
            max(end - time.monotonic_ns(), 0) / 1e9 + FINISH_TIMEOUT_S,
            "the emulators to end",
            interval_s=0.05,
            fail=False,
        )
        await wait_until_async(
            lambda: _drained((prof_t, pps_t), ser, reader), 10, "what is in transit", fail=False
        )
        for t in loop_tasks:
            t.cancel()
        await asyncio.gather(*loop_tasks, return_exceptions=True)
        if ser is not None:
            cap.nav.extend(asm.flush())
            await ser.close()
        if prof_t is not None:
            cap.profiles.extend(assembler.flush())
        if reader is not None:
            await reader.__aexit__(None, None, None)
    finally:
        cap.stats = run.stop()
        for t in (prof_t, pps_t):
            if t is not None:
                await t.close()


def capture(
    sim,
    run_dir: Path,
    *,
    start=None,
    duration_s=None,
    faults=None,
    grace_s: float = 0.4,
    time_shift="now",
    **spec_kwargs,
) -> Capture:
    """Run the emulators of a window of ``sim`` (moved to now) and capture every device."""
    ins = spec_kwargs.get("ins")
    feed = make_feed(sim, start, duration_s, ins.rate_hz if ins is not None else 100.0, time_shift)
    spec = DevicesSpec(run_dir=run_dir, **spec_kwargs)

    def make_run(profiler_port, pps_port):
        return DeviceRun(
            feed,
            replace(
                spec,
                profiler=replace(spec.profiler, port=profiler_port),
                pps=replace(spec.pps, port=pps_port),
            ),
            faults,
        )

    cap = Capture(None)
    # the coroutine returns nothing: asyncio.run (3.11) may repr its task, result included
    asyncio.run(
        _capture(
            cap,
            make_run,
            spec.devices,
            spec.ins.protocol,
            spec.can.bus_config() if "can" in spec.devices else None,
            lambda run: run.clock.host_ns(feed.end_gps_ns),
            grace_s,
        )
    )
    return cap


def capture_replay(
    session, run_dir: Path, *, speed: float = 1.0, can_port: int, grace_s: float = 0.5
) -> Capture:
    """Replay a recorded session (:class:`sim_devices.replay.RecordedSession`) and capture it."""
    can = CanSettings(port=can_port)
    channels = session.channels
    devices = {
        d
        for d, topic in (("ins", "/ins/raw"), ("profiler", "/lidar/raw"), ("pps", "/pps"))
        if topic in channels
    }
    has_can = any(t.startswith("/can/") for t in channels)

    def make_run(profiler_port, pps_port):
        return ReplayRun(
            session,
            ReplaySpec(
                run_dir=run_dir,
                speed=speed,
                profiler=("127.0.0.1", profiler_port),
                pps=("127.0.0.1", pps_port),
                can=can,
            ),
        )

    cap = Capture(None)
    protocol = channels.get("/ins/raw", {}).get("protocol", "nmea")
    asyncio.run(
        _capture(
            cap,
            make_run,
            devices,
            protocol,
            can.bus_config() if has_can else None,
            lambda run: (
                run.clock.host_anchor_ns + round((session.last_host_ns - session.first_host_ns) / speed)
            ),
            grace_s,
        )
    )
    return cap
