"""The vessel config's parsed form: frozen dataclasses, one per section and per device
(:class:`VesselConfig` is what :func:`acquire.daemon.config.load_vessel_config` returns)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from acquire.log.session import SessionOptions
from acquire.status.mqtt import MqttSettings
from acquire.timing.clock import ClockParams
from acquire.timing.latency import LatencyLimits


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
    """The ``guidance`` section (defaults = :class:`acquire.guidance.acceptance.AcceptanceTolerances`'s and
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
class WatchConfig:
    """The ``watch`` section: the mount watch the daemon runs when it names the calibrated mount
    (:mod:`acquire.watch`; defaults = :class:`calib.watch.sequential.WatchDesign`'s)."""

    calibration: Path | None = None  # the calibration's result.json: the calibrated mount
    enabled: bool = True
    shift_deg: float = 0.1  # the boresight change the sequential test is tuned to
    false_alarms_per_hour: float = 0.01
    max_points_per_s: int = 20_000  # returns kept for the watch (decimation budget)
    min_line_s: float = 20.0  # a shorter line is ignored
    max_line_s: float = 900.0  # a longer line is closed anyway (memory)

    @property
    def active(self) -> bool:
        """Whether the daemon runs the watch (enabled, and the calibrated mount named)."""
        return self.enabled and self.calibration is not None


@dataclass(frozen=True)
class WebConfig:
    """The ``web`` section: the bridge console the daemon serves (:mod:`acquire.console`). Off
    loopback it needs TLS (``cert_file``/``key_file``); operator actions need the token of
    ``credentials_file`` (read-only without it)."""

    host: str = "127.0.0.1"
    port: int = 8480
    cert_file: Path | None = None
    key_file: Path | None = None
    credentials_file: Path | None = None
    token: str | None = field(default=None, repr=False)  # the operator token, from credentials_file
    foxglove_port: int | None = None


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
    watch: WatchConfig = WatchConfig()
    web: WebConfig | None = None  # the bridge console, when the section is there

    def device(self, name: str) -> DeviceConfig:
        for d in self.devices:
            if d.name == name:
                return d
        raise KeyError(name)

    def devices_of(self, kind: str) -> list[DeviceConfig]:
        return [d for d in self.devices if d.kind == kind]
