"""``mls acquire`` with two test-only fault hooks, for the fault campaign (not a test module; never
used on a vessel: nothing in ``acquire/`` knows about it).

    python -m tests.acquire.daemon_proc acquire --config vessel.yaml

It is the daemon as ``mls acquire`` runs it (:func:`cli.app.main`, same arguments), plus:

- **an event-loop stall on SIGUSR1**: the handler sleeps ``$MLS_TEST_STALL_S`` seconds (default
  2). Python runs signal handlers in the main thread, which is the thread of the daemon's event
  loop, so the loop is blocked exactly as by a callback that hangs — while the other threads (the
  serial port's reader, the log writer) and the kernel's receive stamps go on. Each stall appends
  ``<start ns> <end ns>`` (host monotonic) to ``$MLS_TEST_STALL_LOG`` when that is set.
- **a simulated full disk**, only when ``$MLS_TEST_DISK_BALLAST`` names a file: every free-space
  query of the session writer (:func:`acquire.log.diskspace.free_bytes`) reports the byte count
  written in that file less than the file system has, as if another program had filled it (the
  fallback of the campaign where it may not mount a small tmpfs to fill for real).
"""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path


def _stall(signum, frame) -> None:
    t0 = time.monotonic_ns()
    time.sleep(float(os.environ.get("MLS_TEST_STALL_S", "2.0")))
    t1 = time.monotonic_ns()
    log = os.environ.get("MLS_TEST_STALL_LOG")
    if log:
        with open(log, "a", encoding="utf-8") as f:
            f.write(f"{t0} {t1}\n")


def _ballast_free_bytes(ballast_file: str):
    from acquire.log import diskspace

    real = diskspace.free_bytes

    def free_bytes(path):
        n = real(path)
        try:
            ballast = int(Path(ballast_file).read_text(encoding="utf-8").strip() or 0)
        except (OSError, ValueError):
            ballast = 0
        return None if n is None else max(n - ballast, 0)

    diskspace.free_bytes = free_bytes


def main() -> None:
    signal.signal(signal.SIGUSR1, _stall)
    if os.environ.get("MLS_TEST_DISK_BALLAST"):
        _ballast_free_bytes(os.environ["MLS_TEST_DISK_BALLAST"])
    from cli.app import main as mls

    sys.argv = ["mls", *sys.argv[1:]]
    mls()


if __name__ == "__main__":
    main()
