"""Acquisition daemon under load: the simulated devices at the full Z+F rate plus the INS at 200 Hz.

The emulators (``mls sim devices``: scenario montreal with ``--point-rate-scale 1`` and the
full 360° recorded, i.e. 200 profiles/s × 5080 points = 1.016 Mpts/s in 23 ZFP1 datagrams per
profile; the INS at 200 Hz NMEA on a pty; the PPS over UDP) feed ``mls acquire`` running as its
own process. For each rate multiple (``--speed``) the benchmark reports:

- **packets lost**: datagrams the profiler emulator sent minus the ``/lidar/raw`` records the
  daemon received (``metrics.devices.profiler.chunks``), plus the log writer's drops — goal 0;
  beside it the INS epochs lost (emitted minus the nav records the daemon decoded, and the bytes
  the emulated serial line had to drop because the daemon did not read them in time);
- **daemon CPU**: user + system time of the daemon process (``/proc/PID/stat``) over the run
  window, in % of one core — goal < 50 % at 1×;
- the highest multiple it sustains: zero loss, and the socket's backlog read within 1 s of the
  end of the run (a daemon slower than the stream would only hide its deficit in the 64 MiB
  socket buffer for a few seconds) — goal ≥ 5×.

Peer, measured in the same run: a bare UDP receive loop (``socket.recv_into`` in a Python
process, nothing else) on the same datagrams from the same emulator at 1×; the daemon's CPU is
printed as a ratio to it. The achieved datagram rate is printed too: above a few multiples the
emulator itself (one Python process) may not keep the pace, and a multiple it cannot emit is
reported as such, not as the daemon's.

With ``--pages N`` the vessel config gets a ``web`` section and N followers of the bridge
console stay connected for the whole run, from one separate process; each one's message count is
printed. By default they are bare WebSocket clients of ``/ws`` (what a page receives: the
snapshot, then every publication): on the ship the browsers run on the bridge's screens and
tablets, not on the acquisition PC, so this charges the daemon with what the pages cost it (the
fan-out and the sends) and not with Chromium rendering on the PC's own cores. ``--browsers``
makes them real Chromium pages (Debian's, headless, under Playwright) on this machine — the
harder case, their rendering competing with the daemon and the emulators for the same cores
(issue 28: 0 loss at 5× with the pages connected; ``benchmarks/console.py`` measures the
console's CPU with Chromium pages).

Run: ``.venv/bin/python benchmarks/acquire.py [--seconds 10] [--speeds 1,2,3,4,5,6,8] [--pages 5 [--browsers]]``
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from acquire.status.bus import read_snapshot  # noqa: E402
from benchmarks._procs import free_port, stop, wait_for  # noqa: E402

MLS = [sys.executable, "-m", "cli.app"]
TICK = os.sysconf("SC_CLK_TCK")
# --lead-s 2: the first emission 2 s after the emulators are up, so that the daemon (already running,
# retrying the INS port every 0.5 s at most) has opened the pty before the first epoch: the INS
# epochs lost then measure throughput, not the start-up race
SIM_ARGS = [
    "--scenario",
    "montreal",
    "--point-rate-scale",
    "1",
    "--set",
    "scanner.angular_windows_deg=[]",
    "--ins-rate",
    "200",
    "--start",
    "pass:1",
    "--lead-s",
    "2",
]


def cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK


def vessel_yaml(run: Path, prof_port: int, pps_port: int, speed: float, web_port: int | None = None) -> str:
    web = "" if web_port is None else f"web: {{port: {web_port}}}\n"
    return web + textwrap.dedent(f"""\
        vessel: bench
        devices:
          - name: ins
            kind: ins
            protocol: nmea
            transport: {{type: serial, port: {run}/ins, baud: 921600}}
            latency: {{band_ms: [0.0, 1000.0], rate_hz: {200 * speed}, gap_s: 2.0}}
          - name: profiler
            kind: profiler
            protocol: zfp1
            transport: {{type: udp, host: 127.0.0.1, port: {prof_port}}}
            latency: {{band_ms: [0.0, 1000.0], rate_hz: {200 * speed}, gap_s: 2.0}}
          - name: pps
            kind: pps
            source: {{type: udp, host: 127.0.0.1, port: {pps_port}}}
            time_device: ins
            time_messages: [ZDA]
        session: {{directory: {run}/sessions, queue_size: 200000}}
        status: {{socket: {run}/status.sock}}
        """)


def run_sim(
    run: Path, speed: float, seconds: float, prof_port: int, pps_port: int, devices: str, receiver_pid: int
) -> tuple[dict, float, float, float]:
    """Run the emulators; returns (their stats, the receiver's CPU s over the window, the window
    length s, the seconds after the window until the receiver's socket buffer was empty)."""
    (run / "truth_clock.json").unlink(missing_ok=True)
    sim = subprocess.Popen(
        [
            *MLS,
            "sim",
            "devices",
            *SIM_ARGS,
            "--speed",
            str(speed),
            "--duration",
            str(seconds * speed),
            "--devices",
            devices,
            "--run-dir",
            str(run),
            "--profiler-port",
            str(prof_port),
            "--pps-port",
            str(pps_port),
        ],
        cwd=run,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )
    try:
        wait_for(lambda: (run / "truth_clock.json").exists() or sim.poll() is not None, 120, "the emulators")
        if sim.poll() is not None:
            raise RuntimeError(f"mls sim devices failed: {sim.stderr.read().decode()[-2000:]}")
        w = json.loads((run / "truth_clock.json").read_text())["window"]
        start_s, end_s = w["start_host_ns"] / 1e9, w["end_host_ns"] / 1e9
        time.sleep(max(start_s - time.monotonic(), 0))
        c0 = cpu_s(receiver_pid)
        time.sleep(max(end_s - time.monotonic(), 0))
        c1 = cpu_s(receiver_pid)
        while (udp_socket(prof_port) or (0, 0))[0] > 0 and time.monotonic() < end_s + 60:
            time.sleep(0.02)  # the backlog the receiver still had to read at the end
        drain_s = time.monotonic() - end_s
        sim.wait(60)
    finally:
        stop(sim)
    stats = {name: json.loads((run / "stats" / f"{name}.json").read_text()) for name in devices.split(",")}
    return stats, c1 - c0, end_s - start_s, drain_s


PAGES = r"""
import asyncio, json, signal, sys
import aiohttp

async def follow(url, counts, i):
    async with aiohttp.ClientSession() as s, s.ws_connect(url) as ws:
        async for msg in ws:
            counts[i] += 1

async def main(url, n, out):
    counts = [0] * n
    tasks = [asyncio.ensure_future(follow(url + "ws", counts, i)) for i in range(n)]
    stop = asyncio.Event()
    asyncio.get_running_loop().add_signal_handler(signal.SIGTERM, stop.set)
    print("ready", flush=True)
    await stop.wait()
    for t in tasks:
        t.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    with open(out, "w") as f:
        json.dump(counts, f)

asyncio.run(main(sys.argv[1], int(sys.argv[2]), sys.argv[3]))
"""

BROWSERS = r"""
import json, signal, sys, threading
from playwright.sync_api import sync_playwright
from tests.acquire.console.chromium import CHROMIUM, CHROMIUM_ARGS

url, n, out = sys.argv[1], int(sys.argv[2]), sys.argv[3]
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *_: stop.set())
with sync_playwright() as p:
    browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
    pages = [browser.new_page(viewport={"width": 1920, "height": 1080}) for _ in range(n)]
    for page in pages:
        page.goto(url)
    print("ready", flush=True)
    while not stop.is_set():
        pages[0].wait_for_timeout(200)  # Playwright's own loop runs meanwhile
    counts = [int(page.evaluate("window.mlsConsole.state.messages")) for page in pages]
    browser.close()
with open(out, "w") as f:
    json.dump(counts, f)
"""


def start_pages(run: Path, web_port: int, n: int, browsers: bool) -> subprocess.Popen:
    """``n`` followers of the console in one process — Chromium pages (``browsers``) or bare
    WebSocket clients — their message counts to ``pages.json`` at SIGTERM."""
    url = f"http://127.0.0.1:{web_port}/"
    wait_for(lambda: console_serving(web_port), 30, "the console")
    pages = subprocess.Popen(
        [sys.executable, "-c", BROWSERS if browsers else PAGES, url, str(n), str(run / "pages.json")],
        stdout=subprocess.PIPE,
        cwd=ROOT,
        start_new_session=True,
    )
    pages.stdout.readline()
    return pages


def console_serving(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def daemon_run(tmp: Path, speed: float, seconds: float, n_pages: int = 0, browsers: bool = False) -> dict:
    run = tmp / f"x{speed:g}"
    run.mkdir()
    prof_port, pps_port = free_port(), free_port()
    web_port = free_port(socket.SOCK_STREAM) if n_pages else None
    cfg = run / "vessel.yaml"
    cfg.write_text(vessel_yaml(run, prof_port, pps_port, speed, web_port))
    daemon = subprocess.Popen(
        [*MLS, "acquire", "--config", str(cfg), "--log-level", "error"],
        cwd=run,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )
    pages = None
    try:
        wait_for(lambda: (run / "status.sock").exists() or daemon.poll() is not None, 30, "the daemon")
        if daemon.poll() is not None:
            raise RuntimeError(f"mls acquire failed: {daemon.stderr.read().decode()[-2000:]}")
        if web_port is not None:
            pages = start_pages(run, web_port, n_pages, browsers)
        stats, cpu, window, drain_s = run_sim(
            run, speed, seconds, prof_port, pps_port, "ins,profiler,pps", daemon.pid
        )
        snap, last, stable_since = None, -1, time.monotonic()
        while time.monotonic() - stable_since < 1.5 and time.monotonic() - stable_since < 30:
            time.sleep(0.5)  # until the daemon has worked through its socket buffer
            snap = read_snapshot(run / "status.sock")
            n = snap["metrics"]["devices"]["profiler"]["chunks"]
            if n != last:
                last, stable_since = n, time.monotonic()
        kernel_drops = udp_drops(prof_port)
    finally:
        if pages is not None:  # SIGTERM to the follower alone: it closes its Chromium itself
            pages.terminate()
            try:
                pages.wait(60)
            finally:
                stop(pages)
        stop(daemon)
    page_frames = json.loads((run / "pages.json").read_text()) if pages is not None else []
    prof = stats["profiler"]
    sent = prof["stats"]["datagrams_sent"]
    received = snap["metrics"]["devices"]["profiler"]["chunks"]
    log = snap["metrics"]["log"]
    lost = sent - received + sum(log["dropped"].values())
    ins = stats["ins"]["stats"]
    ins_lost = max(ins["epochs"] - snap["metrics"]["devices"]["ins"]["records"], 0)
    return {
        "speed": speed,
        "sent": sent,
        "received": received,
        "kernel_drops": kernel_drops,
        "lost": lost,
        "ins_lost": ins_lost,
        "ins_sent": ins["epochs"],
        "ins_overrun_bytes": ins["bytes_overrun"],
        "drain_s": drain_s,
        "sustained": lost == 0 and ins_lost == 0 and drain_s < 1.0,
        "cpu_pct": 100 * cpu / window,
        "rate": sent / window,
        "emulators_cpu_pct": 100
        * sum(st.get("timing", {}).get("cpu_fraction", 0.0) for st in stats.values()),
        "emitter_p99_ms": prof.get("timing", {}).get("error_p99_us", float("nan")) / 1e3,
        "page_frames": page_frames,
    }


def udp_socket(port: int) -> tuple[int, int] | None:
    """(bytes queued, drops) of the UDP socket bound to ``port`` (``/proc/net/udp``)."""
    with open("/proc/net/udp") as f:
        for line in f.readlines()[1:]:
            fields = line.split()
            if int(fields[1].split(":")[1], 16) == port:
                return int(fields[4].split(":")[1], 16), int(fields[-1])
    return None


def udp_drops(port: int) -> int | None:
    s = udp_socket(port)
    return None if s is None else s[1]


PEER = r"""
import socket, sys
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
s.bind(("127.0.0.1", int(sys.argv[1])))
s.settimeout(1.0)
buf = bytearray(65536)
n = 0
with open(sys.argv[2], "w") as out:
    print("ready", flush=True)
    while True:
        try:
            s.recv_into(buf)
            n += 1
        except socket.timeout:
            out.seek(0); out.write(str(n)); out.flush()
"""


def peer_run(tmp: Path, seconds: float) -> dict:
    run = tmp / "peer"
    run.mkdir()
    prof_port, pps_port = free_port(), free_port()
    count = run / "count"
    peer = subprocess.Popen(
        [sys.executable, "-c", PEER, str(prof_port), str(count)],
        stdout=subprocess.PIPE,
        start_new_session=True,
    )
    try:
        peer.stdout.readline()
        stats, cpu, window, _ = run_sim(run, 1.0, seconds, prof_port, pps_port, "profiler", peer.pid)
        time.sleep(1.5)
        received = int(count.read_text() or 0)
    finally:
        stop(peer)
    sent = stats["profiler"]["stats"]["datagrams_sent"]
    return {"sent": sent, "received": received, "lost": sent - received, "cpu_pct": 100 * cpu / window}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="host seconds of data per run")
    ap.add_argument("--speeds", default="1,2,3,4,5,6,8", help="rate multiples to try, ascending")
    ap.add_argument("--pages", type=int, default=0, help="console followers during each run")
    ap.add_argument(
        "--browsers",
        action="store_true",
        help="the followers are Chromium pages (default: WebSocket clients)",
    )
    args = ap.parse_args()
    speeds = [float(s) for s in args.speeds.split(",")]
    kind = "Chromium pages" if args.browsers else "WebSocket clients"
    with tempfile.TemporaryDirectory(prefix="mls-bench-acquire-") as d:
        tmp = Path(d)
        peer = peer_run(tmp, args.seconds)
        print(
            f"peer: bare UDP receive loop at 1×: {peer['received']:,} of {peer['sent']:,} datagrams, "
            f"lost {peer['lost']}, CPU {peer['cpu_pct']:.1f} % of one core"
        )
        results = []
        for s in speeds:
            r = daemon_run(tmp, s, args.seconds, args.pages, args.browsers)
            results.append(r)
            print(
                f"daemon ×{s:<4g} {r['rate']:>8,.0f} datagrams/s (emulators' CPU "
                f"{r['emulators_cpu_pct']:.0f} %, p99 late {r['emitter_p99_ms']:.1f} ms): lost "
                f"{r['lost']:,} of {r['sent']:,} (socket overflows {r['kernel_drops']}), INS epochs lost "
                f"{r['ins_lost']:,} of {r['ins_sent']:,} ({r['ins_overrun_bytes']:,} bytes overrun), backlog read "
                f"{r['drain_s']:.2f} s after the end, daemon CPU {r['cpu_pct']:.1f} % of one core"
                + (
                    f"; {args.pages} console {kind} received {r['page_frames']} messages"
                    if args.pages
                    else ""
                ),
                flush=True,
            )
            if not r["sustained"] and s > 1:
                break
    one = results[0]
    ok = [r["speed"] for r in results if r["sustained"]]
    best = max(ok) if ok else 0.0
    print()
    print(
        f"packets lost at 1× (1.016 Mpts/s + INS 200 Hz): {one['lost']} profiler, {one['ins_lost']} INS   "
        f"goal 0 ({'met' if one['lost'] == 0 and one['ins_lost'] == 0 else 'NOT met'})"
    )
    print(
        f"daemon CPU at 1×: {one['cpu_pct']:.1f} % of one core   peer {peer['cpu_pct']:.1f} %   ratio "
        f"{one['cpu_pct'] / max(peer['cpu_pct'], 1e-9):.1f}x   goal < 50 % "
        f"({'met' if one['cpu_pct'] < 50 else 'NOT met'})"
    )
    print(
        f"highest rate multiple with zero loss: {best:g}×   goal ≥ 5× ({'met' if best >= 5 else 'NOT met'})"
        + ("" if len(ok) < len(speeds) or best < max(speeds) else " (every multiple tried)")
        + (f", {args.pages} console {kind} connected throughout" if args.pages else "")
    )


if __name__ == "__main__":
    main()
