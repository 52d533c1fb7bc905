"""A ``mls georef`` writer that holds its output directory until told to go on (not a test module).

``python -m tests.acquire.deliver.heldwriter BUNDLE OUT FLAGS`` runs :func:`run_georef` in this
process; once the job is planned (its lock taken, its plan written) it creates ``FLAGS/started``
and waits for ``FLAGS/go`` (60 s at most) before it runs its first task."""

from __future__ import annotations

import sys
import time
from pathlib import Path

from acquire.deliver.engine import run_georef
from acquire.deliver.executors import InProcess
from acquire.deliver.options import GeorefOptions


class HeldUntilGo(InProcess):
    def __init__(self, flags: Path):
        super().__init__()
        self.flags = flags
        self.waited = False

    def results(self):
        if not self.waited:
            self.waited = True
            (self.flags / "started").touch()
            deadline = time.monotonic() + 60.0
            while not (self.flags / "go").exists():
                if time.monotonic() > deadline:
                    raise SystemExit("heldwriter: no go within 60 s")
                time.sleep(0.01)
        yield from super().results()


def main(bundle: str, out: str, flags: str) -> None:
    run_georef(bundle, out, GeorefOptions(chunk_s=1.0), executor=HeldUntilGo(Path(flags)))


if __name__ == "__main__":
    main(*sys.argv[1:4])
