"""Shared pieces of the doctor tests (not a module of tests): a vessel config on free ports, a
daemon user that is not root, a fake kernel PPS device and a staged installation."""

from __future__ import annotations

import errno
import hashlib
import json
import os
import socket
import struct
import threading
import time
from pathlib import Path

from acquire.daemon.config import load_vessel_config
from acquire.doctor.access import DaemonUser
from drivers.ppsfetch import PPS_FETCH

NS_PER_S = 1_000_000_000
#: a user the mode bits judge (root may open anything): no file here belongs to it
NOBODY = DaemonUser(name="mls", uid=54321, gids=frozenset({54321}), installed=True)


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def vessel_yaml(tmp_path: Path, *, pps: str, ins: str | None = None, extra: str = "") -> Path:
    """A valid vessel config in ``tmp_path`` (sessions and status socket there too): an INS
    (over TCP unless ``ins`` gives its transport), a profiler on a free UDP port, the PPS source
    ``pps``."""
    ins = ins or "{type: tcp, host: 127.0.0.1, port: 9}"
    text = f"""vessel: doctor-test
devices:
  - {{name: ins, kind: ins, protocol: nmea, transport: {ins}, latency: {{rate_hz: 200.0}}}}
  - {{name: profiler, kind: profiler, protocol: zfp1, transport: {{type: udp, host: 127.0.0.1, port: {free_udp_port()}}}, latency: {{rate_hz: 200.0}}}}
  - {{name: pps, kind: pps, source: {pps}, time_device: ins}}
session: {{directory: {tmp_path / "sessions"}}}
status: {{socket: {tmp_path / "run" / "status.sock"}}}
{extra}"""
    path = tmp_path / "vessel.yaml"
    path.write_text(text)
    (tmp_path / "run").mkdir(exist_ok=True)
    return path


def config(tmp_path: Path, **kw):
    return load_vessel_config(vessel_yaml(tmp_path, **kw))


class FakePpsKernel:
    """``PPS_FETCH`` played for :class:`drivers.pps.KernelPpsSource` (its ``ioctl`` seam): each
    fetch returns the next of ``pulses`` assert stamps (CLOCK_REALTIME ns), then blocks until
    its timeout like the kernel when no pulse comes."""

    def __init__(self, intervals_s: list[float]):
        t = time.clock_gettime_ns(time.CLOCK_REALTIME) - 5 * NS_PER_S
        self.stamps = []
        for dt in [0.0, *intervals_s]:
            t += int(dt * NS_PER_S)
            self.stamps.append(t)
        self.fetches = 0
        self._quiet = threading.Event()  # never set: the wait is the kernel's timeout

    def __call__(self, fd, request, buf, mutate):
        assert request == PPS_FETCH and mutate
        self.fetches += 1
        if self.fetches > len(self.stamps):
            sec, nsec, _ = struct.unpack_from("=qiI", buf, 48)
            self._quiet.wait(min(sec + nsec / 1e9, 0.05))
            raise OSError(errno.ETIMEDOUT, "timeout")
        t = self.stamps[self.fetches - 1]
        struct.pack_into("=II", buf, 0, self.fetches, 0)
        struct.pack_into("=qiI", buf, 8, t // NS_PER_S, t % NS_PER_S, 0)
        return 0


def staged_install(root: Path, version: str = "0.1.0", prefix: str = "/opt/marine-mls") -> Path:
    """What install.py leaves (unit, venv with marine-mls ``version``, install record), by hand."""
    unit = root / "etc/systemd/system/mls-acquire.service"
    unit.parent.mkdir(parents=True)
    unit.write_text(f"[Service]\nExecStart={prefix}/bin/mls acquire --config /etc/mls/vessel.yaml\n")
    venv = root / prefix.lstrip("/")
    (venv / "bin").mkdir(parents=True)
    (venv / "bin/mls").write_text("#!/bin/sh\n")
    os.chmod(venv / "bin/mls", 0o755)
    (venv / f"lib/python3.11/site-packages/marine_mls-{version}.dist-info").mkdir(parents=True)
    record = {"version": version, "unit": {"sha256": hashlib.sha256(unit.read_bytes()).hexdigest()}}
    (venv / "install-record.json").write_text(json.dumps(record))
    return unit
