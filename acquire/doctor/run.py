"""Every check of ``mls doctor`` in order (docs/doctor.md), with the seams tests replace.

:func:`run_doctor` takes what ``mls acquire --check`` found (:class:`AcquireCheck`: the command
layer runs it), loads the config when it is valid, reads the running daemon's view, then checks
the devices, the clock, the UDP buffer, the disk, the broker, the leap-second table and the
installed unit. A check that needs a valid config is skipped without one.
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from acquire.daemon.config import load_vessel_config
from acquire.daemon.configschema import StatusSettings
from acquire.doctor.access import DaemonUser, daemon_user
from acquire.doctor.broker import broker_check
from acquire.doctor.clock import Runner, clock_check, run_command
from acquire.doctor.configcheck import AcquireCheck, config_result, ports_result
from acquire.doctor.disk import disk_check
from acquire.doctor.host import RMEM_MAX_PATH, leap_check, udp_buffer_check
from acquire.doctor.live import live_view
from acquire.doctor.pps import pps_check
from acquire.doctor.result import CheckResult, DoctorReport, Status, fail, skip
from acquire.doctor.serial import serial_check, serial_devices
from acquire.doctor.unit import unit_check
from acquire.log.diskspace import free_bytes
from acquire.timing.timekeeper import SYSTEM_LEAP_SECONDS_LIST
from calib.core.errors import MlsError


@dataclass(frozen=True, kw_only=True)
class DoctorOptions:
    config: Path
    hours: float = 8.0  # the survey the operator plans
    pps_wait_s: float = 2.5
    broker_timeout_s: float = 3.0
    software_version: str = "0.0.0+source"
    software_prefix: str = ""


@dataclass(frozen=True, kw_only=True)
class DoctorSeams:
    """What tests replace: the commands run, the files read, the kernel's PPS, the clock."""

    run: Runner = run_command
    rmem_max_path: Path = RMEM_MAX_PATH
    free_bytes: Callable[[Path], int | None] = free_bytes
    pps_ioctl: Callable | None = None  # None: the real fcntl.ioctl
    user: DaemonUser | None = None  # None: the mls user (or this one)
    leap_list: Path = Path(SYSTEM_LEAP_SECONDS_LIST)
    root: Path = Path("/")  # where the unit and the venv are looked for
    today: Callable[[], _dt.date] = field(default=lambda: _dt.datetime.now(_dt.UTC).date())
    systemd: bool | None = None  # None: when /run/systemd/system exists


def _device_checks(
    cfg, opts: DoctorOptions, seams: DoctorSeams, user: DaemonUser, running: bool
) -> list[CheckResult]:
    out = [serial_check(name, port, user, running) for name, port in serial_devices(cfg)]
    pps = cfg.devices_of("pps")
    if not pps:
        out.append(skip("pps", "no PPS device in the config"))
    for dev in pps:
        out.append(pps_check(dev, user, running, opts.pps_wait_s, seams.pps_ioctl))
    return out


def _needs_config(names: tuple[str, ...]) -> list[CheckResult]:
    return [skip(n, "not checked: the config is not valid") for n in names]


def run_doctor(
    opts: DoctorOptions, acquire_check: AcquireCheck, seams: DoctorSeams | None = None
) -> DoctorReport:
    seams = seams or DoctorSeams()
    user = seams.user or daemon_user()
    checks = [config_result(acquire_check, str(opts.config))]
    cfg = None
    if checks[0].status == Status.OK:
        try:
            cfg = load_vessel_config(opts.config)
        except (MlsError, OSError) as e:  # changed since mls acquire --check read it
            checks[0] = fail("config", f"{opts.config}: {e}", "run mls doctor again")
    live = live_view((cfg.status if cfg is not None else StatusSettings()).socket)
    running = live is not None and "error" not in live
    checks.append(ports_result(acquire_check, live.get("pid") if running and live else None))
    limit_s = cfg.clock.host_offset_alarm_ns / 1e9 if cfg is not None else 1.0
    if cfg is not None:
        checks += _device_checks(cfg, opts, seams, user, running)
    else:
        checks += _needs_config(("serial", "pps"))
    checks.append(clock_check(seams.run, limit_s))
    checks.append(udp_buffer_check(seams.rmem_max_path))
    if cfg is not None:
        checks.append(disk_check(cfg, opts.hours, user, seams.free_bytes))
        checks.append(broker_check(cfg.mqtt, opts.broker_timeout_s))
    else:
        checks += _needs_config(("disk", "broker"))
    checks.append(leap_check(seams.today(), seams.leap_list))
    systemd = seams.systemd if seams.systemd is not None else Path("/run/systemd/system").is_dir()
    checks.append(
        unit_check(seams.root, opts.software_version, opts.software_prefix, seams.run if systemd else None)
    )
    return DoctorReport(
        config=str(opts.config),
        hours=opts.hours,
        software_version=opts.software_version,
        software_prefix=opts.software_prefix,
        checks=checks,
        live=live,
    )
