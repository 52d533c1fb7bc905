"""The PPS of the config present and pulsing: the driver's own source (:mod:`drivers.pps`) is
opened for a few seconds and its pulses counted — two pulses about 1 s apart (their kernel or
emulator stamps) is a PPS. The ``ioctl`` seam of the kernel and serial-line sources lets tests
play the kernel."""

from __future__ import annotations

import asyncio
import fcntl
import os
import socket
from collections.abc import Callable
from typing import Any

from acquire.doctor.access import READ, DaemonUser, describe, may
from acquire.doctor.result import CheckResult, fail, ok, warn
from drivers.base import DriverError
from drivers.pps import KernelPpsSource, PpsEdge, PpsSource, SerialLinePpsSource, UdpPpsSource

NS_PER_S = 1_000_000_000
PULSES = 2
INTERVAL_S = (0.9, 1.1)  # two consecutive pulses of a 1 Hz PPS
NO_PULSE = (
    "is the GNSS receiver tracking and its PPS output enabled? For a PPS on a serial DCD line, is "
    "the line discipline attached (systemctl status mls-pps-ldattach@<port>)? `ppstest {dev}` shows pulses"
)


async def _edges(source: PpsSource, wait_s: float) -> tuple[list[PpsEdge], str | None]:
    """Up to :data:`PULSES` pulses within ``wait_s``, or the source's error."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + wait_s
    edges: list[PpsEdge] = []
    async with source:
        while len(edges) < PULSES and (left := deadline - loop.time()) > 0:
            try:
                edges.append(await asyncio.wait_for(source.get(), left))
            except TimeoutError:
                break
            except DriverError as e:
                return edges, str(e)
    return edges, None


def pulses(source: PpsSource, wait_s: float) -> tuple[list[PpsEdge], str | None]:
    try:
        return asyncio.run(_edges(source, wait_s))
    except OSError as e:  # taken between the probe and the open
        return [], f"[Errno {e.errno}] {e.strerror}"


def judge(device: str, where: str, edges: list[PpsEdge], error: str | None, wait_s: float) -> CheckResult:
    data: dict[str, Any] = {"source": where, "pulses": len(edges), "waited_s": wait_s}
    advice = NO_PULSE.format(dev=where)
    if error is not None:
        return fail("pps", f"{where}: {error}", advice, device=device, data=data)
    if not edges:
        return fail("pps", f"{where}: no pulse in {wait_s:g} s", advice, device=device, data=data)
    if len(edges) < PULSES:
        return warn("pps", f"{where}: one pulse in {wait_s:g} s", advice, device=device, data=data)
    interval_s = (edges[1].host_ns - edges[0].host_ns) / NS_PER_S
    data["interval_s"] = round(interval_s, 6)
    if not INTERVAL_S[0] <= interval_s <= INTERVAL_S[1]:
        return warn(
            "pps", f"{where}: pulses {interval_s:.3f} s apart, expected 1 s", advice, device=device, data=data
        )
    return ok("pps", f"{where}: pulsing ({interval_s:.3f} s apart)", device=device, data=data)


def _device_node(device: str, path: str, user: DaemonUser) -> CheckResult | None:
    """A failure when the kernel PPS device is missing or the daemon may not read it."""
    try:
        st = os.stat(path)
    except OSError as e:
        return fail(
            "pps",
            f"{path}: {e.strerror}",
            "attach the PPS (udev rule 99-mls-pps.rules and mls-pps-ldattach@.service for a "
            "serial DCD line) or set the config's source.device",
            device=device,
            data={"source": path},
        )
    if not may(st, user, READ):
        return fail(
            "pps",
            f"{path} ({describe(st)}): {user.described} may not read it",
            'the udev rule SUBSYSTEM=="pps", GROUP="dialout", MODE="0640" (99-mls-pps.rules)',
            device=device,
            data={"source": path},
        )
    return None  # not a PPS device: the driver's PPS_FETCH says so


def pps_check(
    dev, user: DaemonUser, daemon_running: bool, wait_s: float = 2.5, ioctl: Callable | None = None
) -> CheckResult:
    """The PPS device ``dev`` (a config device of kind pps): present, readable, pulsing."""
    src, ioctl = dev.source, ioctl or fcntl.ioctl
    if src.type == "kernel":
        if (bad := _device_node(dev.name, src.device, user)) is not None:
            return bad
        source: PpsSource = KernelPpsSource(src.device, timeout_s=0.5, ioctl=ioctl)
        return judge(dev.name, src.device, *pulses(source, wait_s), wait_s)
    if src.type == "serial-line":
        where = f"{src.port} ({src.line})"
        return judge(
            dev.name, where, *pulses(SerialLinePpsSource(src.port, src.line, ioctl=ioctl), wait_s), wait_s
        )
    where = f"udp {src.host}:{src.udp_port}"
    if daemon_running:
        return ok(
            "pps",
            f"{where}: the running daemon listens there (its clock state is in the live view)",
            device=dev.name,
            data={"source": where},
        )
    try:  # (UdpPpsSource.open leaves its socket open when the bind fails)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            probe.bind((src.host, src.udp_port))
    except OSError as e:
        return judge(dev.name, where, [], f"[Errno {e.errno}] {e.strerror}", wait_s)
    return judge(dev.name, where, *pulses(UdpPpsSource(src.host, src.udp_port), wait_s), wait_s)
