"""The demo's child processes (:mod:`office.jobs.demo`): each in its own process group, its output
in a log file, the whole group signalled when it is stopped (SIGKILL after a grace period), and
asked by the kernel to stop (``PR_SET_PDEATHSIG``) should the demo itself be killed."""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import time
from collections.abc import Callable
from pathlib import Path


def _child_setup(parent_pid: int) -> Callable[[], None]:
    """In the child before exec: be stopped (SIGTERM) when the demo dies (Linux's
    ``PR_SET_PDEATHSIG``; nothing is imported or allocated after the fork)."""
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        prctl = None
    sigterm = int(signal.SIGTERM)

    def setup() -> None:
        if prctl is not None:
            prctl(1, sigterm)  # PR_SET_PDEATHSIG
        if os.getppid() != parent_pid:  # the demo died before the prctl
            os.kill(os.getpid(), sigterm)

    return setup


class Child:
    """A child process in its own process group (``setpgid``), output to ``log``; the group is
    what gets signalled."""

    def __init__(self, step: str, args: list[str], log: Path):
        self.step, self.args, self.log = step, args, log
        log.parent.mkdir(parents=True, exist_ok=True)
        with open(log, "wb") as f:
            f.write(("$ " + " ".join(args) + "\n").encode())
            f.flush()
            self.p = subprocess.Popen(
                args,
                stdin=subprocess.DEVNULL,
                stdout=f,
                stderr=subprocess.STDOUT,
                process_group=0,
                preexec_fn=_child_setup(os.getpid()),
            )

    def poll(self) -> int | None:
        return self.p.poll()

    def send(self, sig: int) -> None:
        try:
            os.killpg(self.p.pid, sig)
        except (ProcessLookupError, PermissionError):
            pass

    def group_left(self) -> list[int]:
        """Processes still in the child's group (in the demo's session: not a stranger that
        reused the number)."""
        sid, out = os.getsid(0), []
        for d in Path("/proc").iterdir():
            if d.name.isdigit():
                try:
                    stat = (d / "stat").read_text()
                except OSError:
                    continue
                f = stat[stat.rfind(")") + 2 :].split()  # state ppid pgrp session ...
                if f[0] != "Z" and int(f[2]) == self.p.pid and int(f[3]) == sid:
                    out.append(int(d.name))
        return out

    def stop(self, sig: int = signal.SIGTERM, grace_s: float = 10.0) -> int | None:
        """Signal the group and wait; SIGKILL the group after ``grace_s``. Returns the exit
        code of the child itself (None if it had to be killed)."""
        if self.p.poll() is None:
            self.send(sig)
            try:
                return self.p.wait(grace_s)
            except subprocess.TimeoutExpired:
                pass
        code = self.p.poll()
        if code is None or self.group_left():  # the child, or what is left of its group
            self.send(signal.SIGKILL)
        if code is None:
            try:
                self.p.wait(5.0)
            except subprocess.TimeoutExpired:
                pass
        return code

    def wait(self, timeout_s: float, interrupted: Callable[[], None]) -> int | None:
        """The child's exit code, or None when it has not ended within ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            interrupted()
            code = self.p.poll()
            if code is not None:
                return code
            if time.monotonic() > deadline:
                return None
            time.sleep(0.1)

    def tail(self, n: int = 4) -> str:
        try:
            lines = [ln.strip() for ln in self.log.read_text(errors="replace").splitlines()]
        except OSError:
            return ""
        return " / ".join([ln for ln in lines if ln][-n:])
