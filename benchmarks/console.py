"""The bridge console's cost to the daemon: its CPU with 5 browsers connected, against the 5 %
ceiling of one core (issue 28).

The demo's montreal survey at ×1 (``mls sim devices`` with the demo's scenario overrides: the
guidance accepts passes and publishes every 0.5 s) feeds ``mls acquire`` with a ``web``
section. Over two windows of ``--seconds`` each the daemon's user + system CPU
(``/proc/PID/stat``) is measured: first with no page open, then with ``--browsers`` Chromium
pages (Debian's, headless, under Playwright) following the console live. The console's cost is
the difference, in % of one core; the goal is ≤ 5 %. Beside it: the messages each page received.
(Not run yet when it was written: the machine was shared with a stress test.)

    .venv/bin/python benchmarks/console.py [--seconds 20] [--browsers 5]
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks._procs import free_port, stop, wait_for  # noqa: E402
from tests.acquire.console.chromium import CHROMIUM, CHROMIUM_ARGS  # noqa: E402

MLS = [sys.executable, "-m", "cli.app"]
TICK = os.sysconf("SC_CLK_TCK")
GOAL_PERCENT = 5.0


def cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK


def start_devices(tmp: Path, seconds: float) -> subprocess.Popen:
    """The demo's survey on the simulated devices, long enough for both windows."""
    from office.jobs.demo import DemoSettings, scenario_overrides

    settings = DemoSettings(out=tmp, pass_gap_s=max(3.0, seconds / 3))
    return subprocess.Popen(
        [
            *MLS,
            *("sim", "devices", "--scenario", "montreal", "--speed", "1"),
            *("--devices", "ins,profiler,pps", "--run-dir", str(tmp / "run")),
            *("--write-config", str(tmp / "vessel.yaml"), "--lead-s", "4"),
            *(a for o in scenario_overrides(settings) for a in ("--set", o)),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )


def config_complete(path: Path) -> bool:
    from acquire.daemon.config import VesselConfigError, load_vessel_config
    from calib.io.configfile import ConfigError

    try:
        return path.is_file() and load_vessel_config(path).site_file is not None
    except (VesselConfigError, ConfigError, OSError):
        return False


def serving(url: str) -> bool:
    import urllib.request

    try:
        with urllib.request.urlopen(url + "api/session", timeout=2) as r:
            return r.status == 200
    except OSError:
        return False


def measure(pid: int, seconds: float) -> float:
    """The daemon's CPU over ``seconds``, in % of one core."""
    c0, t0 = cpu_s(pid), time.monotonic()
    time.sleep(seconds)
    return 100.0 * (cpu_s(pid) - c0) / (time.monotonic() - t0)


def with_browsers(url: str, n: int, seconds: float, pid: int) -> tuple[float, list[int]]:
    """The daemon's CPU % with ``n`` pages open, and the messages each page received."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        pages = [browser.new_page(viewport={"width": 1920, "height": 1080}) for _ in range(n)]
        for page in pages:
            page.goto(url)
        time.sleep(2.0)  # the pages' snapshots and first renders, outside the window
        percent = measure(pid, seconds)
        received = [int(page.evaluate("window.mlsConsole.state.messages")) for page in pages]
        browser.close()
    return percent, received


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="length of each window (s)")
    ap.add_argument("--browsers", type=int, default=5, help="pages connected in the second window")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="mls-console-bench-") as d:
        tmp = Path(d)
        devices = start_devices(tmp, a.seconds)
        daemon = None
        try:
            wait_for(lambda: config_complete(tmp / "vessel.yaml"), 120, "the devices' vessel config")
            port = free_port(socket.SOCK_STREAM)
            with (tmp / "vessel.yaml").open("a") as f:
                f.write(f"web: {{port: {port}}}\n")
            daemon = subprocess.Popen(
                [*MLS, "acquire", "--config", str(tmp / "vessel.yaml")],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                start_new_session=True,
            )
            url = f"http://127.0.0.1:{port}/"
            wait_for(lambda: serving(url), 60, "the console")
            bare = measure(daemon.pid, a.seconds)
            loaded, received = with_browsers(url, a.browsers, a.seconds, daemon.pid)
        finally:
            for proc in (daemon, devices):
                if proc is not None:
                    stop(proc)
    cost = loaded - bare
    print(f"daemon CPU without a page:   {bare:6.2f} % of a core ({a.seconds:g} s)")
    print(f"daemon CPU with {a.browsers} pages:    {loaded:6.2f} % of a core")
    print(
        f"the console's cost:          {cost:6.2f} % of a core = {cost / GOAL_PERCENT:.2f} × the {GOAL_PERCENT:g} % ceiling"
    )
    print(f"messages received per page:  {received}")
    sys.exit(0 if cost <= GOAL_PERCENT else 1)


if __name__ == "__main__":
    main()
