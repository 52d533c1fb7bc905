"""The vessel config (``mls acquire --config vessel.yaml``, docs/architecture.md §4): schema and validation.

Validation collects **every** error, one per bad field, each naming the file, line, column, key,
the value and what was expected (``vessel.yaml:14:13: devices[0].transport.baud: got 11520,
expected one of 4800, 9600, …``), and raises them together in :class:`VesselConfigError`.
See ``systemd/vessel.example.yaml`` for a complete, commented example.

Keys (units at the edge: ``_ms``, ``_us``, ``_s``, ``_mb``, ``_deg``; everything optional has the
default shown in the example):

- ``vessel`` (name used in session directories and MQTT topics);
- ``devices[]``: ``name``, ``kind`` (ins | profiler | pps | can), ``protocol`` (ins: nmea | stdbin;
  profiler: zfp1), ``transport`` (``type: serial`` with ``port``, ``baud``; ``type: udp`` /
  ``type: tcp`` with ``host``, ``port``; ``type: can`` with ``interface``, ``channel``,
  ``bitrate``), for ``kind: pps`` a ``source`` (``type: kernel`` + ``device``; ``type:
  serial-line`` + ``port``; ``type: udp`` + ``host``, ``port``) and the ``time_device`` and
  ``time_messages`` that label the pulses; ``latency`` thresholds;
- ``session`` (log directory, rotation, flush, fsync, queue), ``clock`` (fit window, gates,
  holdover), ``status`` (socket), ``mqtt`` (optional: host, port, credentials file, topic
  prefix, commands), ``mount`` (lever arm, nominal mount, a-priori boresight), ``site_file``;
- ``guidance`` (optional; needs ``site_file``): the line guidance the daemon runs when the config
  names a site file (:mod:`acquire.guidance.daemon`) — the pass acceptance tolerances
  (``max_xte_m``, ``max_heading_error_deg``, ``max_speed_error_mps``, ``min_points_per_target``,
  ``max_gap_s``), the profiler's settings the σ prediction of the passes still to sail assumes
  (``profile_rate_hz``, ``points_per_360``), the publication period ``period_s`` and
  ``enabled``. The tolerances live here rather than in the site file: they describe how this
  vessel is steered and how densely its profiler scans, not the site (whose keys docs/architecture.md §4
  fixes).
"""

from __future__ import annotations

import os
import re
import stat
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from acquire.log.session import COMPRESSIONS, SessionOptions
from acquire.status.mqtt import MqttSettings
from acquire.timing.clock import ClockParams
from acquire.timing.latency import LatencyLimits
from calib.io.configfile import ConfigError, Node, load_yaml

KINDS = ("ins", "profiler", "pps", "can")
PROTOCOLS = {"ins": ("nmea", "stdbin"), "profiler": ("zfp1",)}
TRANSPORTS = {"ins": ("serial", "udp", "tcp"), "profiler": ("udp", "tcp"), "can": ("can",)}
PPS_SOURCES = ("kernel", "serial-line", "udp")
TIME_MESSAGES = {"nmea": ("ZDA", "RMC", "GGA", "TIME__"), "stdbin": ("validity_time",)}
BAUDS = (4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)
CAN_INTERFACES = ("socketcan", "virtual", "udp_multicast")
SERIAL_LINES = ("dcd", "cts", "dsr", "ri")
NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")
MS, US, NS_PER_S = 1_000_000, 1_000, 1_000_000_000


class VesselConfigError(ConfigError):
    """All the errors of a vessel config, one per bad field (``errors``)."""

    def __init__(self, source: str, errors: list[str]):
        self.source = source
        self.errors = errors
        n = len(errors)
        super().__init__(f"{source}: {n} error{'s' if n != 1 else ''}:\n  " + "\n  ".join(errors))


@dataclass(frozen=True)
class SerialTransport:
    port: str
    baud: int
    type: str = "serial"


@dataclass(frozen=True)
class NetTransport:
    type: str  # udp (bind address) | tcp (remote address)
    host: str
    port: int


@dataclass(frozen=True)
class CanTransport:
    interface: str
    channel: str
    bitrate: int | None = None
    type: str = "can"


@dataclass(frozen=True)
class PpsSource:
    type: str  # kernel | serial-line | udp
    device: str | None = None  # kernel: /dev/ppsN
    port: str | None = None  # serial-line: the tty whose modem line carries the pulse
    line: str = "dcd"  # serial-line: dcd | cts | dsr | ri
    host: str | None = None  # udp: bind address
    udp_port: int | None = None


@dataclass(frozen=True)
class DeviceConfig:
    name: str
    kind: str
    protocol: str | None = None
    transport: SerialTransport | NetTransport | CanTransport | None = None
    source: PpsSource | None = None  # kind pps
    time_device: str | None = None  # kind pps: the device whose time messages label pulses
    time_messages: tuple[str, ...] = ()
    latency: LatencyLimits = field(default_factory=LatencyLimits)


@dataclass(frozen=True)
class StatusSettings:
    socket: Path = Path("/run/mls/status.sock")
    period_s: float = 1.0


@dataclass(frozen=True)
class MountConfig:
    lever_arm_m: tuple[float, float, float]
    nominal_deg: tuple[float, float, float]
    boresight_apriori_deg: tuple[float, float, float]


@dataclass(frozen=True)
class GuidanceConfig:
    """The ``guidance`` section (defaults = :class:`acquire.guidance.lines.AcceptanceTolerances`'s and
    the Z+F Profiler 9012 at its full rate)."""

    enabled: bool = True
    max_xte_m: float = 2.0  # |cross-track error| over the capture window
    max_heading_error_deg: float = 5.0
    max_speed_error_mps: float = 0.5  # |speed over ground − the line's planned speed|
    min_points_per_target: int = 100  # live hits on every target
    max_gap_s: float = 0.5  # longest gap in the INS records or between profiles
    profile_rate_hz: float = 200.0  # the profiler's settings, for the predicted σ of the
    points_per_360: int = 5080  # passes still to sail
    period_s: float = 0.5  # guidance update and publication period


@dataclass(frozen=True)
class VesselConfig:
    source: Path
    vessel: str
    devices: tuple[DeviceConfig, ...]
    session_dir: Path
    session: SessionOptions
    clock: ClockParams
    status: StatusSettings
    mqtt: MqttSettings | None
    mount: MountConfig | None
    site_file: Path | None
    guidance: GuidanceConfig = GuidanceConfig()

    def device(self, name: str) -> DeviceConfig:
        for d in self.devices:
            if d.name == name:
                return d
        raise KeyError(name)

    def devices_of(self, kind: str) -> list[DeviceConfig]:
        return [d for d in self.devices if d.kind == kind]


# -- validation helpers -------------------------------------------------------------------------


class _Errors:
    def __init__(self) -> None:
        self.items: list[str] = []

    def add(self, message: str) -> None:
        self.items.append(message)

    def get(self, fn: Callable[[], Any], default: Any = None) -> Any:
        """``fn()``, or ``default`` with its ConfigError recorded."""
        try:
            return fn()
        except ConfigError as e:
            self.add(str(e))
            return default


def _keys(node: Node, errs: _Errors, required=(), optional=()) -> dict[str, Node]:
    """The mapping's children; every unknown and every missing key is its own error."""
    if not isinstance(node.value, dict):
        errs.add(str(node.fail("a mapping")))
        return {}
    required, optional = set(required), set(optional)
    allowed = ", ".join(sorted(required | optional))
    for key in sorted(set(node.value) - required - optional):
        errs.add(f"{node.value[key].where()}: unknown key {key!r}; allowed keys here: {allowed}")
    for key in sorted(required - set(node.value)):
        errs.add(f"{node.where()}: missing required key {key!r}")
    return {k: v for k, v in node.value.items() if k in required | optional}


def _int(node: Node, lo: int, hi: int) -> int:
    v = node.integer(minimum=lo)
    if v > hi:
        raise node.fail(f"an integer between {lo} and {hi}")
    return v


def _choice(node: Node, choices) -> Any:
    if node.value not in choices or isinstance(node.value, bool):
        raise node.fail("one of " + ", ".join(str(c) for c in choices))
    return node.value


def _name(node: Node) -> str:
    v = node.string()
    if not NAME_RE.fullmatch(v):
        raise node.fail("a name of letters, digits, '_', '.', '-' (starting with a letter or digit)")
    return v


def _abs_path(node: Node) -> str:
    v = node.string()
    if not v.startswith("/"):
        raise node.fail("an absolute path (e.g. /dev/serial/by-id/...)")
    return v


def _path(node: Node, base: Path) -> Path:
    p = Path(node.string()).expanduser()
    return p if p.is_absolute() else (base / p)


def _host(node: Node) -> str:
    v = node.string()
    if any(c.isspace() for c in v) or "/" in v:
        raise node.fail("a host name or IP address")
    return v


def _opt(m: dict[str, Node], key: str, errs: _Errors, fn: Callable[[Node], Any], default: Any) -> Any:
    return errs.get(lambda: fn(m[key]), default) if key in m else default


# -- sections -----------------------------------------------------------------------------------


def _variant(
    node: Node,
    errs: _Errors,
    what: str,
    choices,
    variants: dict[str, tuple[tuple[str, ...], tuple[str, ...]]],
):
    """A mapping whose ``type`` says which keys it needs (and which it may have). Returns
    ``(type, children)``, or None after recording every unknown and every missing key."""
    optional = {k for need, extra in variants.values() for k in need + extra}
    m = _keys(node, errs, required={"type"}, optional=optional)
    t = errs.get(lambda: _choice(m["type"], choices)) if "type" in m else None
    if t is None:
        return None
    need, extra = variants[t]
    allowed = {"type", *need, *extra}
    for key in sorted(set(m) - allowed):
        errs.add(f"{m[key].where()}: not a key of a {t} {what}; allowed: {', '.join(sorted(allowed))}")
    missing = [k for k in need if k not in m]
    for key in missing:
        errs.add(f"{node.where()}: missing required key {key!r} for a {t} {what}")
    return None if missing else (t, m)


_NET = (("host", "port"), ())
_TRANSPORT_KEYS = {
    "serial": (("port", "baud"), ()),
    "udp": _NET,
    "tcp": _NET,
    "can": (("interface", "channel"), ("bitrate",)),
}
_PPS_KEYS = {"kernel": (("device",), ()), "serial-line": (("port",), ("line",)), "udp": _NET}


def _transport(node: Node, kind: str, errs: _Errors):
    v = _variant(node, errs, "transport", TRANSPORTS[kind], _TRANSPORT_KEYS)
    if v is None:
        return None
    t, m = v
    if t == "serial":
        port = errs.get(lambda: _abs_path(m["port"]))
        baud = errs.get(lambda: _choice(m["baud"], BAUDS))
        return SerialTransport(port, baud) if port and baud else None
    if t in ("udp", "tcp"):
        host = errs.get(lambda: _host(m["host"]))
        port = errs.get(lambda: _int(m["port"], 1, 65535))
        return NetTransport(t, host, port) if host and port else None
    iface = errs.get(lambda: _choice(m["interface"], CAN_INTERFACES))
    channel = errs.get(lambda: m["channel"].string())
    bitrate = _opt(m, "bitrate", errs, lambda n: _int(n, 1000, 8_000_000), None)
    return CanTransport(iface, channel, bitrate) if iface and channel else None


def _pps_source(node: Node, errs: _Errors) -> PpsSource | None:
    v = _variant(node, errs, "PPS source", PPS_SOURCES, _PPS_KEYS)
    if v is None:
        return None
    t, m = v
    if t == "kernel":
        dev = errs.get(lambda: _abs_path(m["device"]))
        return PpsSource("kernel", device=dev) if dev else None
    if t == "serial-line":
        port = errs.get(lambda: _abs_path(m["port"]))
        line = _opt(m, "line", errs, lambda n: _choice(n, SERIAL_LINES), "dcd")
        return PpsSource("serial-line", port=port, line=line) if port else None
    host = errs.get(lambda: _host(m["host"]))
    port = errs.get(lambda: _int(m["port"], 1, 65535))
    return PpsSource("udp", host=host, udp_port=port) if host and port else None


def _latency(node: Node, errs: _Errors) -> LatencyLimits:
    m = _keys(
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
        band_ns=_opt(m, "band_ms", errs, band, d.band_ns),
        jump_ns=round(_opt(m, "jump_ms", errs, positive(MS), d.jump_ns)),
        max_sigma_ns=round(_opt(m, "max_sigma_ms", errs, positive(MS), d.max_sigma_ns)),
        max_drift_ppm=_opt(m, "max_drift_ppm", errs, positive(1.0), d.max_drift_ppm),
        rate_hz=_opt(m, "rate_hz", errs, positive(1.0), d.rate_hz),
        gap_ns=round(_opt(m, "gap_s", errs, positive(NS_PER_S), d.gap_ns)),
        expect_pps_flag=_opt(m, "expect_pps_flag", errs, Node.boolean, d.expect_pps_flag),
    )


def _device(node: Node, errs: _Errors) -> DeviceConfig | None:
    m = _keys(
        node,
        errs,
        required={"name", "kind"},
        optional={"protocol", "transport", "source", "time_device", "time_messages", "latency"},
    )
    name = errs.get(lambda: _name(m["name"])) if "name" in m else None
    kind = errs.get(lambda: _choice(m["kind"], KINDS)) if "kind" in m else None
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
        protocol = errs.get(lambda: _choice(m["protocol"], PROTOCOLS[kind]))
    if kind in TRANSPORTS and "transport" in m:
        transport = _transport(m["transport"], kind, errs)
    if kind == "pps":
        if "source" in m:
            source = _pps_source(m["source"], errs)
        if "time_device" in m:
            time_device = errs.get(lambda: _name(m["time_device"]))
        if "time_messages" in m:
            items = errs.get(lambda: m["time_messages"].sequence(min_len=1), [])
            time_messages = tuple(errs.get(lambda n=n: n.string(), "") for n in items)
    latency = _latency(m["latency"], errs) if "latency" in m and kind != "pps" else LatencyLimits()
    if name is None:
        return None
    return DeviceConfig(name, kind, protocol, transport, source, time_device, time_messages, latency)


def _session(node: Node, errs: _Errors, base: Path) -> tuple[Path | None, SessionOptions]:
    m = _keys(
        node,
        errs,
        required={"directory"},
        optional={"rotate_s", "rotate_mb", "flush_s", "fsync_s", "queue_size", "compression", "min_free_mb"},
    )
    d = SessionOptions()
    directory = _opt(m, "directory", errs, lambda n: _path(n, base), None)

    def flush(n: Node) -> float:
        return n.number(0.0, 1.0, exclusive_minimum=True)

    kw = dict(
        rotate_s=_opt(m, "rotate_s", errs, lambda n: n.number(10.0), d.rotate_s),
        rotate_bytes=round(
            _opt(m, "rotate_mb", errs, lambda n: n.number(1.0), d.rotate_bytes / 2**20) * 2**20
        ),
        flush_s=_opt(m, "flush_s", errs, flush, d.flush_s),
        fsync_s=_opt(m, "fsync_s", errs, lambda n: n.number(0.1, 10.0), d.fsync_s),
        queue_size=_opt(m, "queue_size", errs, lambda n: _int(n, 100, 10_000_000), d.queue_size),
        compression=_opt(m, "compression", errs, lambda n: _choice(n, tuple(COMPRESSIONS)), d.compression),
        min_free_bytes=round(
            _opt(m, "min_free_mb", errs, lambda n: n.number(0.0), d.min_free_bytes / 2**20) * 2**20
        ),
    )
    return directory, SessionOptions(**kw)


def _clock(node: Node, errs: _Errors) -> ClockParams:
    m = _keys(
        node,
        errs,
        optional={
            "window_edges",
            "min_edges",
            "gate_us",
            "loss_timeout_s",
            "holdover_limit_us",
            "holdover_wander_ppm",
        },
    )
    d = ClockParams()
    window = _opt(m, "window_edges", errs, lambda n: _int(n, 2, 3600), d.window_edges)
    min_edges = _opt(m, "min_edges", errs, lambda n: _int(n, 2, 3600), d.min_edges)
    if min_edges > window:
        errs.add(
            f"{m['min_edges'].where() if 'min_edges' in m else node.where()}: min_edges "
            f"{min_edges} is larger than window_edges {window}"
        )
        min_edges = window
    return ClockParams(
        window_edges=window,
        min_edges=min_edges,
        gate_floor_ns=round(_opt(m, "gate_us", errs, lambda n: n.number(1.0), d.gate_floor_ns / US) * US),
        loss_timeout_ns=round(
            _opt(m, "loss_timeout_s", errs, lambda n: n.number(1.0, 60.0), d.loss_timeout_ns / NS_PER_S)
            * NS_PER_S
        ),
        holdover_limit_ns=round(
            _opt(m, "holdover_limit_us", errs, lambda n: n.number(1.0), d.holdover_limit_ns / US) * US
        ),
        holdover_wander_ppm=_opt(
            m,
            "holdover_wander_ppm",
            errs,
            lambda n: n.number(0.0, exclusive_minimum=True),
            d.holdover_wander_ppm,
        ),
    )


def _credentials(node: Node, base: Path) -> tuple[str, str]:
    path = _path(node, base)
    try:
        st = path.stat()
    except OSError as e:
        raise node.fail(f"a readable credentials file ({e.strerror})") from None
    if st.st_mode & stat.S_IROTH:
        raise node.fail(
            f"a credentials file not readable by others ({path} has mode "
            f"{stat.filemode(st.st_mode)}; chmod 600 it)"
        )
    inner = load_yaml(path)
    cm = inner.mapping(required={"username", "password"})
    return cm["username"].string(), cm["password"].string()


def _mqtt(node: Node, errs: _Errors, base: Path) -> MqttSettings | None:
    m = _keys(
        node,
        errs,
        required={"host"},
        optional={"port", "credentials_file", "topic_prefix", "commands_enabled", "keepalive_s"},
    )

    def prefix(n: Node) -> str:
        v = n.string()
        if any(c in v for c in "+#\0") or v.startswith("/") or v.endswith("/"):
            raise n.fail("an MQTT topic prefix without wildcards (+, #) or leading/trailing '/'")
        return v

    host = _opt(m, "host", errs, _host, None)
    user_pass = _opt(m, "credentials_file", errs, lambda n: _credentials(n, base), (None, None))
    kw = dict(
        port=_opt(m, "port", errs, lambda n: _int(n, 1, 65535), 1883),
        topic_prefix=_opt(m, "topic_prefix", errs, prefix, "mls"),
        commands_enabled=_opt(m, "commands_enabled", errs, Node.boolean, False),
        keepalive_s=_opt(m, "keepalive_s", errs, lambda n: _int(n, 2, 3600), 10),
    )
    if host is None:
        return None
    return MqttSettings(host, username=user_pass[0], password=user_pass[1], **kw)


def _mount(node: Node, errs: _Errors) -> MountConfig | None:
    m = _keys(node, errs, required={"lever_arm_m", "nominal_deg", "boresight_apriori_deg"})
    vecs = {k: errs.get(lambda k=k: tuple(float(x) for x in m[k].vector(3))) for k in m}
    if len(vecs) < 3 or any(v is None for v in vecs.values()):
        return None
    return MountConfig(**vecs)


def _status(node: Node, errs: _Errors, base: Path) -> StatusSettings:
    m = _keys(node, errs, optional={"socket", "period_s"})
    d = StatusSettings()
    return StatusSettings(
        socket=_opt(m, "socket", errs, lambda n: _path(n, base), d.socket),
        period_s=_opt(m, "period_s", errs, lambda n: n.number(0.1, 60.0), d.period_s),
    )


def _guidance(node: Node, errs: _Errors) -> GuidanceConfig:
    m = _keys(
        node,
        errs,
        optional={
            "enabled",
            "max_xte_m",
            "max_heading_error_deg",
            "max_speed_error_mps",
            "min_points_per_target",
            "max_gap_s",
            "profile_rate_hz",
            "points_per_360",
            "period_s",
        },
    )
    d = GuidanceConfig()

    def positive(n: Node) -> float:
        return n.number(0.0, exclusive_minimum=True)

    return GuidanceConfig(
        enabled=_opt(m, "enabled", errs, Node.boolean, d.enabled),
        max_xte_m=_opt(m, "max_xte_m", errs, positive, d.max_xte_m),
        max_heading_error_deg=_opt(
            m,
            "max_heading_error_deg",
            errs,
            lambda n: n.number(0.0, 90.0, exclusive_minimum=True),
            d.max_heading_error_deg,
        ),
        max_speed_error_mps=_opt(m, "max_speed_error_mps", errs, positive, d.max_speed_error_mps),
        min_points_per_target=_opt(
            m, "min_points_per_target", errs, lambda n: _int(n, 1, 10**7), d.min_points_per_target
        ),
        max_gap_s=_opt(m, "max_gap_s", errs, lambda n: n.number(0.01, 60.0), d.max_gap_s),
        profile_rate_hz=_opt(
            m, "profile_rate_hz", errs, lambda n: n.number(0.1, 10_000.0), d.profile_rate_hz
        ),
        points_per_360=_opt(m, "points_per_360", errs, lambda n: _int(n, 4, 1_000_000), d.points_per_360),
        period_s=_opt(m, "period_s", errs, lambda n: n.number(0.1, 10.0), d.period_s),
    )


def _cross_checks(devices: list[DeviceConfig], dev_nodes: dict[str, Node], errs: _Errors) -> None:
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


def vessel_config_from_node(root: Node, base_dir: Path) -> VesselConfig:
    """Validate a loaded YAML tree; raise :class:`VesselConfigError` with every error."""
    errs = _Errors()
    top = _keys(
        root,
        errs,
        required={"vessel", "devices", "session"},
        optional={"clock", "status", "mqtt", "mount", "site_file", "guidance"},
    )
    vessel = errs.get(lambda: _name(top["vessel"])) if "vessel" in top else None
    devices: list[DeviceConfig] = []
    dev_nodes: dict[str, Node] = {}
    if "devices" in top:
        first_use: dict[str, Node] = {}
        for n in errs.get(lambda: top["devices"].sequence(min_len=1), []):
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
    devices = [
        d
        if d.kind != "pps" or d.time_messages or d.time_device is None
        else _with_default_messages(d, devices)
        for d in devices
    ]
    session_dir, session = (
        _session(top["session"], errs, base_dir) if "session" in top else (None, SessionOptions())
    )
    clock = _clock(top["clock"], errs) if "clock" in top else ClockParams()
    status = _status(top["status"], errs, base_dir) if "status" in top else StatusSettings()
    mqtt = _mqtt(top["mqtt"], errs, base_dir) if "mqtt" in top else None
    mount = _mount(top["mount"], errs) if "mount" in top else None
    site_file = None
    if "site_file" in top:
        site_file = errs.get(lambda: _path(top["site_file"], base_dir))
        if site_file is not None:
            from calib.io.site import load_site

            if not site_file.is_file():
                errs.add(str(top["site_file"].fail(f"an existing site file ({site_file} not found)")))
            else:
                errs.get(lambda: load_site(site_file))
    guidance = _guidance(top["guidance"], errs) if "guidance" in top else GuidanceConfig()
    if "guidance" in top and "site_file" not in top and guidance.enabled:
        errs.add(
            f"{top['guidance'].where()}: the guidance needs the site's targets and pass "
            f"plan: add site_file (or set guidance.enabled: false)"
        )
    if errs.items:
        raise VesselConfigError(root.source, sorted(errs.items, key=_position))
    assert vessel is not None and session_dir is not None
    return VesselConfig(
        Path(root.source),
        vessel,
        tuple(devices),
        session_dir,
        session,
        clock,
        status,
        mqtt,
        mount,
        site_file,
        guidance,
    )


def _position(error: str) -> tuple[int, int]:
    """(line, column) of an error message ``file:line:col: ...`` (errors sort by position)."""
    m = re.match(r"^.*?:(\d+):(\d+): ", error)
    return (int(m.group(1)), int(m.group(2))) if m else (0, 0)


def _with_default_messages(pps: DeviceConfig, devices: list[DeviceConfig]) -> DeviceConfig:
    from dataclasses import replace

    target = next((d for d in devices if d.name == pps.time_device), None)
    msgs = TIME_MESSAGES.get(target.protocol or "", ()) if target is not None else ()
    return replace(pps, time_messages=tuple(msgs))


def load_vessel_config(path: str | Path) -> VesselConfig:
    path = Path(path)
    return vessel_config_from_node(load_yaml(path), path.resolve().parent)


def parse_vessel_config(
    text: str, source: str = "vessel.yaml", base_dir: str | Path | None = None
) -> VesselConfig:
    return vessel_config_from_node(load_yaml(text, source=source), Path(base_dir or os.getcwd()))
