"""The vessel config (``mls acquire --config vessel.yaml``, docs/architecture.md §4): loading and validation.

Validation collects **every** error, one per bad field, each naming the file, line, column, key,
the value and what was expected (``vessel.yaml:14:13: devices[0].transport.baud: got 11520,
expected one of 4800, 9600, …``), and raises them together in :class:`VesselConfigError`.
See ``systemd/vessel.example.yaml`` for a complete, commented example. The parsed form is
:mod:`acquire.daemon.configschema`; the ``devices`` section is checked in
:mod:`acquire.daemon.configdevices`, every section with the checks of :mod:`acquire.daemon.confignodes`.

Keys (units at the edge: ``_ms``, ``_us``, ``_s``, ``_mb``, ``_deg``; everything optional has the
default shown in the example):

- ``vessel`` (name used in session directories and MQTT topics);
- ``devices[]``: ``name``, ``kind`` (ins | profiler | pps | can), ``protocol`` (ins: nmea | stdbin;
  profiler: zfp1), ``transport`` (``type: serial`` with ``port``, ``baud``; ``type: udp`` /
  ``type: tcp`` with ``host``, ``port``; ``type: can`` with ``interface``, ``channel``,
  ``bitrate``), for ``kind: pps`` a ``source`` (``type: kernel`` + ``device``; ``type:
  serial-line`` + ``port``; ``type: udp`` + ``host``, ``port``) and the ``time_device`` and
  ``time_messages`` that label the pulses; ``latency`` thresholds;
- ``session`` (log directory, rotation, flush, fsync, queue, free-space thresholds
  ``min_free_mb``, ``disk_warning_mb``, ``disk_critical_mb``), ``clock`` (fit window, gates,
  holdover, ``host_offset_alarm_s``: the host clock's allowed offset from GPS time), ``status``
  (socket), ``mqtt`` (optional: host, port, credentials file, topic prefix, commands,
  ``commands_insecure_ok``, ``tls``: CA file, client certificate, ``outage_alarm_s``: no
  connection this long raises ``mqtt_unreachable``, default 30),
  ``mount`` (lever arm, nominal mount, a-priori boresight), ``site_file``;
- ``guidance`` (optional; needs ``site_file``): the line guidance the daemon runs when the config
  names a site file (:mod:`acquire.guidance.daemon`) — the pass acceptance tolerances
  (``max_xte_m``, ``max_heading_error_deg``, ``max_speed_error_mps``, ``min_points_per_target``,
  ``max_gap_s``), the profiler's settings the σ prediction of the passes still to sail assumes
  (``profile_rate_hz``, ``points_per_360``), the publication period ``period_s`` and
  ``enabled``. The tolerances live here rather than in the site file: they describe how this
  vessel is steered and how densely its profiler scans, not the site (whose keys docs/architecture.md §4
  fixes);
- ``watch`` (optional; needs ``site_file``): the mount watch (:mod:`acquire.watch`), which runs
  when ``calibration`` names the calibrated mount (a calibration ``result.json``, relative to
  this file; its boresight and extras on the config's mount) — the sequential test's
  ``shift_deg`` and ``false_alarms_per_hour``, the returns kept per second
  ``max_points_per_s``, the shortest and longest line ``min_line_s``, ``max_line_s``, and
  ``enabled``. The site file gives the LGF, the wall azimuth, the sigmas and τ;
- ``web`` (optional): the bridge console (:mod:`acquire.daemon.configweb`, docs/console.md).
"""

from __future__ import annotations

import os
import re
import ssl
import stat
from functools import partial
from pathlib import Path

from acquire.daemon.configdevices import parse_devices
from acquire.daemon.confignodes import (
    NS_PER_S,
    US,
    Errors,
    choice,
    host_name,
    int_between,
    mapping_keys,
    opt,
    resolved_path,
    vessel_name,
)
from acquire.daemon.configschema import GuidanceConfig, MountConfig, StatusSettings, VesselConfig, WatchConfig
from acquire.daemon.configweb import parse_web
from acquire.log.session import COMPRESSIONS, SessionOptions
from acquire.status.mqtt import MqttSettings, MqttTls, command_policy, tls_context
from acquire.timing.clock import ClockParams
from calib.io.configfile import ConfigError, Node, load_yaml


class VesselConfigError(ConfigError):
    """All the errors of a vessel config, one per bad field (``errors``)."""

    def __init__(self, source: str, errors: list[str]):
        self.source = source
        self.errors = errors
        n = len(errors)
        super().__init__(f"{source}: {n} error{'s' if n != 1 else ''}:\n  " + "\n  ".join(errors))


def _session(node: Node, errs: Errors, base: Path) -> tuple[Path | None, SessionOptions]:
    m = mapping_keys(
        node,
        errs,
        required={"directory"},
        optional={
            "rotate_s",
            "rotate_mb",
            "flush_s",
            "fsync_s",
            "queue_size",
            "compression",
            "min_free_mb",
            "disk_warning_mb",
            "disk_critical_mb",
        },
    )
    d = SessionOptions()
    directory = opt(m, "directory", errs, lambda n: resolved_path(n, base), None)
    if directory is not None and directory.exists() and not directory.is_dir():  # §4.1: one line
        errs.add(str(m["directory"].fail(f"a directory for the sessions ({directory} is a file)")))
        directory = None

    def flush(n: Node) -> float:
        return n.number(0.0, 1.0, exclusive_minimum=True)

    kw = dict(
        rotate_s=opt(m, "rotate_s", errs, lambda n: n.number(10.0), d.rotate_s),
        rotate_bytes=round(
            opt(m, "rotate_mb", errs, lambda n: n.number(1.0), d.rotate_bytes / 2**20) * 2**20
        ),
        flush_s=opt(m, "flush_s", errs, flush, d.flush_s),
        fsync_s=opt(m, "fsync_s", errs, lambda n: n.number(0.1, 10.0), d.fsync_s),
        queue_size=opt(m, "queue_size", errs, lambda n: int_between(n, 100, 10_000_000), d.queue_size),
        compression=opt(m, "compression", errs, lambda n: choice(n, tuple(COMPRESSIONS)), d.compression),
        min_free_bytes=round(
            opt(m, "min_free_mb", errs, lambda n: n.number(0.0), d.min_free_bytes / 2**20) * 2**20
        ),
    )
    warn = round(
        opt(m, "disk_warning_mb", errs, lambda n: n.number(0.0), d.disk_warning_bytes / 2**20) * 2**20
    )
    crit_default = min(d.disk_critical_bytes, warn / 5) / 2**20  # a low warning lowers it

    def critical(n: Node) -> float:
        v = n.number(0.0)
        if v * 2**20 > warn:
            raise n.fail(f"a number ≤ disk_warning_mb ({warn / 2**20:g})")
        return v

    crit = round(opt(m, "disk_critical_mb", errs, critical, crit_default) * 2**20)
    kw.update(disk_warning_bytes=warn, disk_critical_bytes=crit)
    return directory, SessionOptions(**kw)


def _clock(node: Node, errs: Errors) -> ClockParams:
    m = mapping_keys(
        node,
        errs,
        optional={
            "window_edges",
            "min_edges",
            "gate_us",
            "loss_timeout_s",
            "holdover_limit_us",
            "holdover_wander_ppm",
            "host_offset_alarm_s",
        },
    )
    d = ClockParams()
    window = opt(m, "window_edges", errs, lambda n: int_between(n, 2, 3600), d.window_edges)
    min_edges = opt(m, "min_edges", errs, lambda n: int_between(n, 2, 3600), d.min_edges)
    if min_edges > window:
        errs.add(
            f"{m['min_edges'].where() if 'min_edges' in m else node.where()}: min_edges "
            f"{min_edges} is larger than window_edges {window}"
        )
        min_edges = window
    return ClockParams(
        window_edges=window,
        min_edges=min_edges,
        gate_floor_ns=round(opt(m, "gate_us", errs, lambda n: n.number(1.0), d.gate_floor_ns / US) * US),
        loss_timeout_ns=round(
            opt(m, "loss_timeout_s", errs, lambda n: n.number(1.0, 60.0), d.loss_timeout_ns / NS_PER_S)
            * NS_PER_S
        ),
        holdover_limit_ns=round(
            opt(m, "holdover_limit_us", errs, lambda n: n.number(1.0), d.holdover_limit_ns / US) * US
        ),
        holdover_wander_ppm=opt(
            m,
            "holdover_wander_ppm",
            errs,
            lambda n: n.number(0.0, exclusive_minimum=True),
            d.holdover_wander_ppm,
        ),
        host_offset_alarm_ns=round(
            opt(
                m,
                "host_offset_alarm_s",
                errs,
                lambda n: n.number(0.001, 86_400.0),
                d.host_offset_alarm_ns / NS_PER_S,
            )
            * NS_PER_S
        ),
    )


def _credentials(node: Node, base: Path) -> tuple[str, str]:
    path = resolved_path(node, base)
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


def _mqtt(node: Node, errs: Errors, base: Path) -> MqttSettings | None:
    m = mapping_keys(
        node,
        errs,
        required={"host"},
        optional={
            "port",
            "credentials_file",
            "topic_prefix",
            "commands_enabled",
            "commands_insecure_ok",
            "keepalive_s",
            "outage_alarm_s",
            "tls",
        },
    )

    def prefix(n: Node) -> str:
        v = n.string()
        if any(c in v for c in "+#\0") or v.startswith("/") or v.endswith("/"):
            raise n.fail("an MQTT topic prefix without wildcards (+, #) or leading/trailing '/'")
        return v

    host = opt(m, "host", errs, host_name, None)
    user_pass = opt(m, "credentials_file", errs, lambda n: _credentials(n, base), (None, None))
    tls = _mqtt_tls(m["tls"], errs, base) if "tls" in m else None
    kw = dict(
        port=opt(m, "port", errs, lambda n: int_between(n, 1, 65535), 1883 if "tls" not in m else 8883),
        topic_prefix=opt(m, "topic_prefix", errs, prefix, "mls"),
        commands_enabled=opt(m, "commands_enabled", errs, Node.boolean, False),
        commands_insecure_ok=opt(m, "commands_insecure_ok", errs, Node.boolean, False),
        keepalive_s=opt(m, "keepalive_s", errs, lambda n: int_between(n, 2, 3600), 10),
        outage_alarm_s=opt(m, "outage_alarm_s", errs, lambda n: n.number(1.0, 86400.0), 30.0),
    )
    if host is None:
        return None
    settings = MqttSettings(host, username=user_pass[0], password=user_pass[1], tls=tls, **kw)
    why = command_policy(settings) if settings.commands_enabled and ("tls" not in m or tls) else None
    if why is not None:
        errs.add(f"{m['commands_enabled'].where()}: {why}")
    return settings


def _mqtt_tls(node: Node, errs: Errors, base: Path) -> MqttTls | None:
    """``mqtt.tls``: the CA file that verifies the broker, an optional client certificate."""
    m = mapping_keys(node, errs, required={"ca_file"}, optional={"cert_file", "key_file", "verify_hostname"})
    ca = opt(m, "ca_file", errs, lambda n: _tls_file(n, base, "CA certificates"), None)
    cert = opt(m, "cert_file", errs, lambda n: _tls_file(n, base, "client certificate"), None)
    key = opt(m, "key_file", errs, lambda n: _tls_file(n, base, "client key", private=True), None)
    if "key_file" in m and "cert_file" not in m:
        errs.add(f"{m['key_file'].where()}: a client key needs its certificate: add cert_file")
    verify = opt(m, "verify_hostname", errs, Node.boolean, True)
    if ca is None:
        return None
    tls = MqttTls(ca, cert, key, verify)
    try:
        tls_context(tls)
    except (OSError, ssl.SSLError) as e:
        where = m["cert_file"] if cert is not None else m["ca_file"]
        errs.add(f"{where.where()}: these TLS files cannot be used together ({e})")
        return None
    return tls


def _tls_file(node: Node, base: Path, what: str, private: bool = False) -> Path:
    path = resolved_path(node, base)
    try:
        st = path.stat()
        path.read_bytes()
    except OSError as e:
        raise node.fail(f"a readable PEM file of the {what} ({e.strerror})") from None
    if private and st.st_mode & stat.S_IROTH:
        raise node.fail(
            f"a {what} file not readable by others ({path} has mode {stat.filemode(st.st_mode)}; chmod 600 it)"
        )
    if b"-----BEGIN " not in path.read_bytes():
        raise node.fail(f"a PEM file of the {what} (no '-----BEGIN' block in {path})")
    return path


def _vector3(node: Node) -> tuple[float, ...]:
    return tuple(float(x) for x in node.vector(3))


def _mount(node: Node, errs: Errors) -> MountConfig | None:
    m = mapping_keys(node, errs, required={"lever_arm_m", "nominal_deg", "boresight_apriori_deg"})
    vecs = {k: errs.get(partial(_vector3, m[k])) for k in m}
    if len(vecs) < 3 or any(v is None for v in vecs.values()):
        return None
    return MountConfig(**vecs)


def _status(node: Node, errs: Errors, base: Path) -> StatusSettings:
    m = mapping_keys(node, errs, optional={"socket", "period_s"})
    d = StatusSettings()
    return StatusSettings(
        socket=opt(m, "socket", errs, lambda n: resolved_path(n, base), d.socket),
        period_s=opt(m, "period_s", errs, lambda n: n.number(0.1, 60.0), d.period_s),
    )


def _guidance(node: Node, errs: Errors) -> GuidanceConfig:
    m = mapping_keys(
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
        enabled=opt(m, "enabled", errs, Node.boolean, d.enabled),
        max_xte_m=opt(m, "max_xte_m", errs, positive, d.max_xte_m),
        max_heading_error_deg=opt(
            m,
            "max_heading_error_deg",
            errs,
            lambda n: n.number(0.0, 90.0, exclusive_minimum=True),
            d.max_heading_error_deg,
        ),
        max_speed_error_mps=opt(m, "max_speed_error_mps", errs, positive, d.max_speed_error_mps),
        min_points_per_target=opt(
            m, "min_points_per_target", errs, lambda n: int_between(n, 1, 10**7), d.min_points_per_target
        ),
        max_gap_s=opt(m, "max_gap_s", errs, lambda n: n.number(0.01, 60.0), d.max_gap_s),
        profile_rate_hz=opt(m, "profile_rate_hz", errs, lambda n: n.number(0.1, 10_000.0), d.profile_rate_hz),
        points_per_360=opt(
            m, "points_per_360", errs, lambda n: int_between(n, 4, 1_000_000), d.points_per_360
        ),
        period_s=opt(m, "period_s", errs, lambda n: n.number(0.1, 10.0), d.period_s),
    )


def _calibration(node: Node, base: Path) -> Path:
    """A calibration result.json (or the directory holding it), read and checked."""
    from calib.assess.history import ResultFormatError, load_result

    path = resolved_path(node, base)
    file = path / "result.json" if path.is_dir() else path
    if not file.is_file():
        raise node.fail(f"a calibration result.json ({file} not found)")
    try:
        load_result(file)
    except ResultFormatError as e:
        raise node.fail(f"a calibration result.json ({e})") from None
    return file


def _watch(node: Node, errs: Errors, base: Path) -> WatchConfig:
    m = mapping_keys(
        node,
        errs,
        optional={
            "calibration",
            "enabled",
            "shift_deg",
            "false_alarms_per_hour",
            "max_points_per_s",
            "min_line_s",
            "max_line_s",
        },
    )
    d = WatchConfig()
    min_line = opt(m, "min_line_s", errs, lambda n: n.number(1.0, 3600.0), d.min_line_s)

    def max_line(n: Node) -> float:
        v = n.number(60.0, 7200.0)
        if v <= min_line:
            raise n.fail(f"a number > min_line_s ({min_line:g})")
        return v

    return WatchConfig(
        calibration=opt(m, "calibration", errs, lambda n: _calibration(n, base), None),
        enabled=opt(m, "enabled", errs, Node.boolean, d.enabled),
        shift_deg=opt(
            m, "shift_deg", errs, lambda n: n.number(0.0, 5.0, exclusive_minimum=True), d.shift_deg
        ),
        false_alarms_per_hour=opt(
            m,
            "false_alarms_per_hour",
            errs,
            lambda n: n.number(0.0, 10.0, exclusive_minimum=True),
            d.false_alarms_per_hour,
        ),
        max_points_per_s=opt(
            m, "max_points_per_s", errs, lambda n: int_between(n, 100, 2_000_000), d.max_points_per_s
        ),
        min_line_s=min_line,
        max_line_s=opt(m, "max_line_s", errs, max_line, d.max_line_s),
    )


def _site_file(node: Node, errs: Errors, base_dir: Path) -> Path | None:
    """The ``site_file``: an existing file that loads as a site (else an error)."""
    site_file = errs.get(lambda: resolved_path(node, base_dir))
    if site_file is not None:
        from calib.io.site import load_site

        if not site_file.is_file():
            why = "is a directory" if site_file.is_dir() else "not found"
            errs.add(str(node.fail(f"an existing site file ({site_file} {why})")))
        else:
            errs.get(lambda: load_site(site_file))
    return site_file


def _check_watch_inputs(node: Node, has_site_file: bool, errs: Errors) -> None:
    """An enabled mount watch needs the calibrated mount and the site file."""
    m = node.value if isinstance(node.value, dict) else {}
    if "calibration" not in m:
        errs.add(
            f"{node.where()}: the mount watch needs the calibrated mount: add "
            f"watch.calibration (a calibration result.json; or set watch.enabled: false)"
        )
    if not has_site_file:
        errs.add(
            f"{node.where()}: the mount watch needs the site's frame, wall azimuth and "
            f"sigmas: add site_file (or set watch.enabled: false)"
        )


def vessel_config_from_node(root: Node, base_dir: Path) -> VesselConfig:
    """Validate a loaded YAML tree; raise :class:`VesselConfigError` with every error."""
    errs = Errors()
    top = mapping_keys(
        root,
        errs,
        required={"vessel", "devices", "session"},
        optional={"clock", "status", "mqtt", "mount", "site_file", "guidance", "watch", "web"},
    )
    vessel = errs.get(lambda: vessel_name(top["vessel"])) if "vessel" in top else None
    devices = parse_devices(top["devices"], errs) if "devices" in top else []
    session_dir, session = (
        _session(top["session"], errs, base_dir) if "session" in top else (None, SessionOptions())
    )
    clock = _clock(top["clock"], errs) if "clock" in top else ClockParams()
    status = _status(top["status"], errs, base_dir) if "status" in top else StatusSettings()
    mqtt = _mqtt(top["mqtt"], errs, base_dir) if "mqtt" in top else None
    mount = _mount(top["mount"], errs) if "mount" in top else None
    site_file = _site_file(top["site_file"], errs, base_dir) if "site_file" in top else None
    guidance = _guidance(top["guidance"], errs) if "guidance" in top else GuidanceConfig()
    if "guidance" in top and "site_file" not in top and guidance.enabled:
        errs.add(
            f"{top['guidance'].where()}: the guidance needs the site's targets and pass "
            f"plan: add site_file (or set guidance.enabled: false)"
        )
    watch = _watch(top["watch"], errs, base_dir) if "watch" in top else WatchConfig()
    if "watch" in top and watch.enabled:
        _check_watch_inputs(top["watch"], "site_file" in top, errs)
    web = parse_web(top["web"], errs, base_dir) if "web" in top else None
    if errs.items:
        raise VesselConfigError(root.source, sorted(errs.items, key=_position))
    assert vessel is not None, "a missing or invalid vessel name is an error"
    assert session_dir is not None, "a missing or invalid session section is an error"
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
        watch,
        web,
    )


def _position(error: str) -> tuple[int, int]:
    """(line, column) of an error message ``file:line:col: ...`` (errors sort by position)."""
    m = re.match(r"^.*?:(\d+):(\d+): ", error)
    return (int(m.group(1)), int(m.group(2))) if m else (0, 0)


def load_vessel_config(path: str | Path) -> VesselConfig:
    path = Path(path)
    return vessel_config_from_node(load_yaml(path), path.resolve().parent)


def parse_vessel_config(
    text: str, source: str = "vessel.yaml", base_dir: str | Path | None = None
) -> VesselConfig:
    return vessel_config_from_node(load_yaml(text, source=source), Path(base_dir or os.getcwd()))


def site_of(cfg: VesselConfig, error: type[Exception]):
    """The site of ``cfg.site_file`` (``error`` naming the file on a bad one), its LGF (the
    reference point, else the targets' mean centre, else None) and the mount installed (the
    vessel config's ``mount``, else None) — what the daemon's consumers build on."""
    import numpy as np

    from calib.core import frames
    from calib.io.site import load_site

    path = Path(str(cfg.site_file))
    try:
        site = load_site(path)
    except (ConfigError, OSError) as e:
        raise error(f"site_file {path}: {e}") from None
    frame = site.reference
    if frame is None and site.targets:  # no reference point: the LGF at the targets' mean centre
        c = np.mean([(t.lat_deg, t.lon_deg, t.height_m) for t in site.targets], axis=0)
        frame = frames.LocalFrame(float(c[0]), float(c[1]), float(c[2]))
    return site, frame, mount_of(cfg)


def mount_of(cfg: VesselConfig):
    """The mount installed (:class:`calib.core.georef.Mount` of the vessel config's ``mount``),
    None without one."""
    import numpy as np

    from calib.core.georef import Mount

    m = cfg.mount
    if m is None:
        return None
    return Mount(
        lever_arm_m=np.asarray(m.lever_arm_m, float),
        nominal_rad=np.radians(m.nominal_deg),
        boresight_rad=np.radians(m.boresight_apriori_deg),
    )
