"""Process and port helpers shared by the benchmarks that run the real daemon (acquire.py,
soak.py): a free loopback port, waiting on a condition with a deadline, stopping a process group,
sampling a process (RSS, descriptors, threads) and the host's load, a UDP socket's drops."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import threading
import time
from dataclasses import dataclass
from pathlib import Path

SAMPLE_S = 2.0


def free_port(kind=socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(cond, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return
        time.sleep(0.05)
    raise RuntimeError(f"timed out waiting for {what}")


def stop(proc: subprocess.Popen, grace_s: float = 30.0) -> None:
    """SIGTERM to the process group, SIGKILL after ``grace_s``."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(grace_s)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)


@dataclass(frozen=True)
class Sample:
    t_ns: int
    rss_kb: int
    fds: int
    threads: int
    load1: float  # the host's 1-minute load average


def proc_sample(pid: int) -> Sample | None:
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        fds = len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return None
    fields = dict(line.split(":", 1) for line in status.splitlines() if ":" in line)
    if "VmRSS" not in fields:  # a zombie: the daemon has exited
        return None
    return Sample(
        time.monotonic_ns(),
        int(fields["VmRSS"].split()[0]),
        fds,
        int(fields["Threads"].split()[0]),
        os.getloadavg()[0],
    )


class Sampler(threading.Thread):
    """VmRSS, open file descriptors and threads of the daemon, and the host's load, every
    :data:`SAMPLE_S`."""

    def __init__(self, pid: int):
        super().__init__(daemon=True, name="sampler")
        self.pid, self.samples = pid, []
        self.halt = threading.Event()

    def run(self) -> None:
        while not self.halt.wait(SAMPLE_S):
            if (s := proc_sample(self.pid)) is not None:
                self.samples.append(s)


def udp_drops(port: int) -> int | None:
    """Datagrams the kernel dropped at the socket bound to ``port`` (``/proc/net/udp``)."""
    with open("/proc/net/udp") as f:
        for line in f.readlines()[1:]:
            fields = line.split()
            if int(fields[1].split(":")[1], 16) == port:
                return int(fields[-1])
    return None
