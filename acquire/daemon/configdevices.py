"""The ``devices`` section of a vessel config (:mod:`acquire.daemon.config`): each device by its
``kind`` (protocol, transport, a pps device's source and time labels, latency thresholds), the
checks across devices (one pps source, its time device and messages) and the defaults they imply."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

from acquire.daemon.confignodes import (
    MS,
    NS_PER_S,
    Errors,
    abs_path,
    choice,
    host_name,
    int_between,
    mapping_keys,
    opt,
    valid_name,
    variant,
)
from acquire.daemon.configschema import CanTransport, DeviceConfig, NetTransport, PpsSource, SerialTransport
from acquire.timing.latency import LatencyLimits
from calib.io.configfile import Node

KINDS = ("ins", "profiler", "pps", "can")
PROTOCOLS = {"ins": ("nmea", "stdbin"), "profiler": ("zfp1",)}
TRANSPORTS = {"ins": ("serial", "udp", "tcp"), "profiler": ("udp", "tcp"), "can": ("can",)}
PPS_SOURCES = ("kernel", "serial-line", "udp")
TIME_MESSAGES = {"nmea": ("ZDA", "RMC", "GGA", "TIME__"), "stdbin": ("validity_time",)}
BAUDS = (4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)
CAN_INTERFACES = ("socketcan", "virtual", "udp_multicast")
SERIAL_LINES = ("dcd", "cts", "dsr", "ri")


_NET = (("host", "port"), ())
_TRANSPORT_KEYS = {
    "serial": (("port", "baud"), ()),
    "udp": _NET,
    "tcp": _NET,
    "can": (("interface", "channel"), ("bitrate",)),
}
_PPS_KEYS = {"kernel": (("device",), ()), "serial-line": (("port",), ("line",)), "udp": _NET}


def _transport(node: Node, kind: str, errs: Errors):
    v = variant(node, errs, "transport", TRANSPORTS[kind], _TRANSPORT_KEYS)
    if v is None:
        return None
    t, m = v
    if t == "serial":
        port = errs.get(lambda: abs_path(m["port"]))
        baud = errs.get(lambda: choice(m["baud"], BAUDS))
        return SerialTransport(port, baud) if port and baud else None
    if t in ("udp", "tcp"):
        host = errs.get(lambda: host_name(m["host"]))
        port = errs.get(lambda: int_between(m["port"], 1, 65535))
        return NetTransport(t, host, port) if host and port else None
    iface = errs.get(lambda: choice(m["interface"], CAN_INTERFACES))
    channel = errs.get(lambda: m["channel"].string())
    bitrate = opt(m, "bitrate", errs, lambda n: int_between(n, 1000, 8_000_000), None)
    return CanTransport(iface, channel, bitrate) if iface and channel else None


def _pps_source(node: Node, errs: Errors) -> PpsSource | None:
    v = variant(node, errs, "PPS source", PPS_SOURCES, _PPS_KEYS)
    if v is None:
        return None
    t, m = v
    if t == "kernel":
        dev = errs.get(lambda: abs_path(m["device"]))
        return PpsSource("kernel", device=dev) if dev else None
    if t == "serial-line":
        port = errs.get(lambda: abs_path(m["port"]))
        line = opt(m, "line", errs, lambda n: choice(n, SERIAL_LINES), "dcd")
        return PpsSource("serial-line", port=port, line=line) if port else None
    host = errs.get(lambda: host_name(m["host"]))
    port = errs.get(lambda: int_between(m["port"], 1, 65535))
    return PpsSource("udp", host=host, udp_port=port) if host and port else None


def _latency(node: Node, errs: Errors) -> LatencyLimits:
    m = mapping_keys(
        node,
        errs,
        optional={
            "band_ms",
            "jump_ms",
            "max_sigma_ms",
            "max_drift_ppm",
            "rate_hz",
            "gap_s",
            "expect_pps_flag",
        },
    )
    d = LatencyLimits()

    def band(n: Node) -> tuple[int, int]:
        lo, hi = n.vector(2)
        if not lo < hi:
            raise n.fail("[low, high] with low < high (ms)")
        return (round(lo * MS), round(hi * MS))

    def positive(scale: float) -> Callable[[Node], Any]:
        return lambda n: n.number(0.0, exclusive_minimum=True) * scale

    return LatencyLimits(
        band_ns=opt(m, "band_ms", errs, band, d.band_ns),
        jump_ns=round(opt(m, "jump_ms", errs, positive(MS), d.jump_ns)),
        max_sigma_ns=round(opt(m, "max_sigma_ms", errs, positive(MS), d.max_sigma_ns)),
        max_drift_ppm=opt(m, "max_drift_ppm", errs, positive(1.0), d.max_drift_ppm),
        rate_hz=opt(m, "rate_hz", errs, positive(1.0), d.rate_hz),
        gap_ns=round(opt(m, "gap_s", errs, positive(NS_PER_S), d.gap_ns)),
        expect_pps_flag=opt(m, "expect_pps_flag", errs, Node.boolean, d.expect_pps_flag),
    )


def _device(node: Node, errs: Errors) -> DeviceConfig | None:
    m = mapping_keys(
        node,
        errs,
        required={"name", "kind"},
        optional={"protocol", "transport", "source", "time_device", "time_messages", "latency"},
    )
    name = errs.get(lambda: valid_name(m["name"])) if "name" in m else None
    kind = errs.get(lambda: choice(m["kind"], KINDS)) if "kind" in m else None
    if kind is None:
        return None
    allowed = {
        "ins": {"protocol", "transport", "latency"},
        "profiler": {"protocol", "transport", "latency"},
        "can": {"transport", "latency"},
        "pps": {"source", "time_device", "time_messages"},
    }[kind]
    for key in sorted(set(m) - allowed - {"name", "kind"}):
        errs.add(
            f"{m[key].where()}: not a key of a device of kind {kind}; allowed: "
            f"{', '.join(sorted(allowed | {'name', 'kind'}))}"
        )
    for key in sorted(allowed - {"latency"} - set(m)):
        if kind == "pps" and key == "time_messages":
            continue  # defaults to the time device's protocol's messages
        errs.add(f"{node.where()}: missing required key {key!r} for a device of kind {kind}")
    protocol = transport = source = time_device = None
    time_messages: tuple[str, ...] = ()
    if kind in PROTOCOLS and "protocol" in m:
        protocol = errs.get(lambda: choice(m["protocol"], PROTOCOLS[kind]))
    if kind in TRANSPORTS and "transport" in m:
        transport = _transport(m["transport"], kind, errs)
    if kind == "pps":
        if "source" in m:
            source = _pps_source(m["source"], errs)
        if "time_device" in m:
            time_device = errs.get(lambda: valid_name(m["time_device"]))
        if "time_messages" in m:
            items = errs.get(lambda: m["time_messages"].sequence(min_len=1), [])
            time_messages = tuple(errs.get(n.string, "") for n in items)
    latency = _latency(m["latency"], errs) if "latency" in m and kind != "pps" else LatencyLimits()
    if name is None:
        return None
    return DeviceConfig(name, kind, protocol, transport, source, time_device, time_messages, latency)


def parse_devices(node: Node, errs: Errors) -> list[DeviceConfig]:
    """The ``devices`` list: every device (a name used twice is an error, the duplicate is still
    checked but not used), the checks across devices, and a pps device's default time messages."""
    devices: list[DeviceConfig] = []
    dev_nodes: dict[str, Node] = {}
    first_use: dict[str, Node] = {}
    for n in errs.get(lambda: node.sequence(min_len=1), []):
        name_node = n.value.get("name") if isinstance(n.value, dict) else None
        duplicate = False
        if name_node is not None and isinstance(name_node.value, str):
            duplicate = name_node.value in first_use
            if duplicate:
                errs.add(
                    f"{name_node.where()}: device name {name_node.value!r} is used "
                    f"twice (first at {first_use[name_node.value].path})"
                )
            first_use.setdefault(name_node.value, name_node)
        d = _device(n, errs)  # (a duplicate is still checked, but not used)
        if d is not None and not duplicate:
            devices.append(d)
            dev_nodes.setdefault(d.name, n)
    _cross_checks(devices, dev_nodes, errs)
    return [
        d
        if d.kind != "pps" or d.time_messages or d.time_device is None
        else _with_default_messages(d, devices)
        for d in devices
    ]


def _cross_checks(devices: list[DeviceConfig], dev_nodes: dict[str, Node], errs: Errors) -> None:
    _one_of_each(devices, dev_nodes, errs)
    _port_collisions(devices, dev_nodes, errs)
    _time_devices(devices, dev_nodes, errs)


def _one_of_each(devices: list[DeviceConfig], dev_nodes: dict[str, Node], errs: Errors) -> None:
    """One ins and one profiler: the session has one ``/ins/raw`` and one ``/lidar/raw``."""
    for kind, channel in (("ins", "/ins/raw"), ("profiler", "/lidar/raw")):
        same = [d for d in devices if d.kind == kind]
        first = dev_nodes[same[0].name] if same else None
        for extra in same[1:]:
            assert first is not None
            errs.add(
                f"{dev_nodes[extra.name].where()}: a second {kind} device ({extra.name!r}; the first, "
                f"{same[0].name!r}, at {first.source}:{first.line}): the session has one {channel} "
                f"channel: configure one {kind}"
            )


def listen_endpoints(devices) -> list[tuple[DeviceConfig, str, str, int]]:
    """``(device, protocol, bind address, port)`` of every socket the daemon listens on: the
    UDP transports and a UDP PPS source (a TCP transport connects out: it listens on nothing)."""
    out = []
    for d in devices:
        t, src = d.transport, d.source
        if isinstance(t, NetTransport) and t.type == "udp":
            out.append((d, "udp", t.host, t.port))
        if src is not None and src.type == "udp" and src.host is not None and src.udp_port is not None:
            out.append((d, "udp", src.host, src.udp_port))
    return out


WILDCARD_HOSTS = ("", "0.0.0.0", "::", "*")


def _port_collisions(devices: list[DeviceConfig], dev_nodes: dict[str, Node], errs: Errors) -> None:
    """Two devices bound to the same UDP port (the same address, or either on every address):
    the second bind would fail, or the two would share each other's datagrams."""
    seen: list[tuple[DeviceConfig, str, str, int]] = []
    for d, proto, host, port in listen_endpoints(devices):
        for other, proto2, host2, port2 in seen:
            if other.name == d.name or (proto, port) != (proto2, port2):
                continue
            if host == host2 or host in WILDCARD_HOSTS or host2 in WILDCARD_HOSTS:
                first = _port_node(dev_nodes[other.name])
                errs.add(
                    f"{_port_node(dev_nodes[d.name]).where()}: {proto} port {port} of device "
                    f"{d.name!r} ({host}) is also the port of device {other.name!r} ({host2}, at "
                    f"{first.source}:{first.line}): two devices cannot listen on one port"
                )
                break
        seen.append((d, proto, host, port))


def _port_node(dev_node: Node) -> Node:
    """The ``port`` node of a device's ``transport`` or ``source`` (for the error's line)."""
    value = dev_node.value if isinstance(dev_node.value, dict) else {}
    for key in ("source", "transport"):
        inner = value.get(key)
        if inner is not None and isinstance(inner.value, dict) and "port" in inner.value:
            return inner.value["port"]
    return dev_node


def _time_devices(devices: list[DeviceConfig], dev_nodes: dict[str, Node], errs: Errors) -> None:
    seen = {d.name: d for d in devices}
    pps = [d for d in devices if d.kind == "pps"]
    if len(pps) > 1:
        errs.add(
            f"{dev_nodes[pps[1].name].where()}: a second pps device ({pps[1].name!r}); "
            "the clock model takes one PPS source"
        )
    for p in pps:
        if p.time_device is None:
            continue
        target = seen.get(p.time_device)
        where = dev_nodes[p.name].where()
        if target is None or target.kind != "ins":
            names = ", ".join(d.name for d in devices if d.kind == "ins") or "none configured"
            errs.add(
                f"{where}.time_device: got {p.time_device!r}, expected the name of an ins device ({names})"
            )
            continue
        allowed = TIME_MESSAGES.get(target.protocol or "", ())
        for msg in p.time_messages:
            if msg and msg not in allowed:
                errs.add(
                    f"{where}.time_messages: got {msg!r}, expected messages of the "
                    f"{target.protocol} protocol: {', '.join(allowed)}"
                )


def _with_default_messages(pps: DeviceConfig, devices: list[DeviceConfig]) -> DeviceConfig:
    target = next((d for d in devices if d.name == pps.time_device), None)
    msgs = TIME_MESSAGES.get(target.protocol or "", ()) if target is not None else ()
    return replace(pps, time_messages=tuple(msgs))
