"""A ``mls georef`` writer that holds its output directory until told to go on (not a test module).

``python -m tests.office.deliver.heldwriter BUNDLE OUT STARTED_FD GO_FD`` runs :func:`run_georef`
in this process; once the job is planned (its lock taken, its plan written) it writes a byte to
the pipe ``STARTED_FD`` and blocks on the pipe ``GO_FD`` (60 s at most) before it runs its first
task: the test and the writer wait on each other, never on the clock."""

from __future__ import annotations

import os
import select
import sys

from office.deliver.engine import run_georef
from office.deliver.executors import InProcess
from office.deliver.options import GeorefOptions


class HeldUntilGo(InProcess):
    def __init__(self, started_fd: int, go_fd: int):
        super().__init__()
        self.started_fd, self.go_fd = started_fd, go_fd
        self.waited = False

    def results(self):
        if not self.waited:
            self.waited = True
            os.write(self.started_fd, b"s")
            if not select.select([self.go_fd], [], [], 60.0)[0]:
                raise SystemExit("heldwriter: no go within 60 s")
        yield from super().results()


def main(bundle: str, out: str, started_fd: str, go_fd: str) -> None:
    executor = HeldUntilGo(int(started_fd), int(go_fd))
    run_georef(bundle, out, GeorefOptions(chunk_s=1.0), executor=executor)


if __name__ == "__main__":
    main(*sys.argv[1:5])
