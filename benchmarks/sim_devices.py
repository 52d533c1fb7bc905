"""Emulator timing and CPU: the profiler at the full Z+F rate with the INS at 100 Hz (and the PPS).

Measured: each emulator's timing error, emitted − scheduled (median, p99, max over every
emission, taken right after the write/send returns), and the CPU its process used (process
time / wall time), while a receiver in this process drains the UDP sockets and the pty.
Scenario: montreal, one 60 m pass, the full Z+F rate (200 profiles/s × 5080 points over 360°
= 1.016 Mpts/s, 23 ZFP1 datagrams per profile, 4600 datagrams/s, 6.1 MB/s) and the PHINS NMEA
block at 100 Hz, for ``--seconds`` (8) of real time across the pass's target capture.

Peer, measured in the same run on the same machine: a bare loop in a process of its own (the
same runner, pacer and timer slack) sending the **same datagrams and NMEA blocks**, precomputed,
at the same instants — no content generation, no fault checks. The ratios say what generating
the streams costs on top of merely pacing them out.

Both are measured twice: with the default scheduling, and with ``--realtime`` (SCHED_FIFO for
the emitting processes where the system permits it; the stats say which policy was in effect).

Goals: p99 ≤ 2 ms; the full-rate profiler on less than one core.

Run: ``.venv/bin/python benchmarks/sim_devices.py [--seconds 8]``
"""

from __future__ import annotations

import argparse
import os
import select
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from calib.sim.simulate import simulate  # noqa: E402
from sim_devices.clock import TruthClock  # noqa: E402
from sim_devices.feed import make_feed  # noqa: E402
from sim_devices.ins import InsEmulator, InsSettings  # noqa: E402
from sim_devices.pps import PpsSettings  # noqa: E402
from sim_devices.profiler import ProfilerEmulator, ProfilerSettings  # noqa: E402
from sim_devices.runner import DeviceRun, DevicesSpec, EmulatorRun, free_udp_port  # noqa: E402
from sim_devices.serialpty import PtyPort  # noqa: E402

FULL_RATE = [
    "scanner.point_rate_scale=1",
    "scanner.angular_windows_deg=[]",
    "site.passes=[{id: 1, relative_heading_deg: 0}]",
]


class Sink:
    """Drains UDP ports and a pty link in a thread (the receiving side every emitter needs)."""

    def __init__(self, ports: list[int], link: Path) -> None:
        self.socks = []
        for p in ports:
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
            s.bind(("127.0.0.1", p))
            s.setblocking(False)
            self.socks.append(s)
        self.link = link
        self.fd: int | None = None
        self.datagrams = self.serial_bytes = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            if self.fd is None and self.link.is_symlink():
                try:
                    self.fd = os.open(self.link, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
                except OSError:
                    pass
            fds = self.socks + ([self.fd] if self.fd is not None else [])
            ready, _, _ = select.select(fds, [], [], 0.05)
            for r in ready:
                if r is self.fd:
                    try:
                        data = os.read(self.fd, 65536)
                    except OSError:
                        data = b""
                    if not data:
                        os.close(self.fd)
                        self.fd = None
                    self.serial_bytes += len(data)
                    continue
                while True:
                    try:
                        r.recv(65536)
                    except BlockingIOError:
                        break
                    self.datagrams += 1

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        for s in self.socks:
            s.close()
        if self.fd is not None:
            os.close(self.fd)


class _Bare:
    """A peer emitter: precomputed (host offset ns, bytes) sent at anchor + offset, nothing else
    (with the pacing of the emulator it stands for)."""

    def __init__(self, name: str, items: list[tuple[int, bytes]], target, spin_ns: int) -> None:
        self.name, self.items, self.target, self.spin_ns = name, items, target, spin_ns
        self.sent = 0

    def prepare(self) -> dict:
        if isinstance(self.target, Path):
            self.port = PtyPort(self.target)
            return {"link": str(self.target), "pty": self.port.plug()}
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
        return {"address": list(self.target)}

    def run(self, clock, pacer, timing) -> bool:
        anchor, mono, wait = clock.host_anchor_ns, time.monotonic_ns, pacer.wait_until
        if isinstance(self.target, Path):
            send = self.port.write
        else:
            sendto, target = self.sock.sendto, self.target
            send = lambda data: sendto(data, target)  # noqa: E731
        for offset, data in self.items:
            host = anchor + offset
            if not wait(host):
                return False
            send(data)
            timing.record(host, mono())
            self.sent += 1
        return True

    def close(self) -> None:
        if isinstance(self.target, Path):
            self.port.close()
        else:
            self.sock.close()

    def stats(self) -> dict:
        return {"sent": self.sent}


class PeerRun(EmulatorRun):
    def __init__(self, run_dir: Path, bares: list[_Bare], gps_anchor_ns: int, realtime: bool) -> None:
        super().__init__(run_dir, realtime=realtime)
        self.bares, self.gps_anchor_ns = bares, gps_anchor_ns

    def emulators(self) -> list:
        return self.bares

    def make_clock(self) -> TruthClock:
        return TruthClock.starting_in(self.lead_s, self.gps_anchor_ns)

    def write_run_files(self) -> None:
        self._devices_json()


def run_and_sink(run, ports: list[int], seconds: float) -> dict:
    sink = Sink(ports, run.run_dir / "ins")
    sink.start()
    try:
        with run:
            run.start()
            run.wait(seconds + 10.0)
            stats = run.stop()
    finally:
        sink.stop()
    stats["_sink"] = {"datagrams": sink.datagrams, "serial_bytes": sink.serial_bytes}
    return stats


def fmt_row(name: str, ours: dict, peer: dict | None) -> None:
    t = ours["timing"]
    line = (
        f"{name:<26} {t['emissions']:>7} emissions  timing error median {t['error_median_us'] / 1e3:6.3f} ms"
        f"  p99 {t['error_p99_us'] / 1e3:6.3f} ms  max {t['error_max_us'] / 1e3:6.2f} ms"
        f"  CPU {100 * t['cpu_fraction']:5.1f} % of a core"
    )
    if peer is not None:
        p = peer["timing"]
        line += (
            f"   | peer p99 {p['error_p99_us'] / 1e3:6.3f} ms, CPU {100 * p['cpu_fraction']:5.1f} %"
            f"   ratio p99 {t['error_p99_us'] / p['error_p99_us']:5.2f}x, CPU "
            f"{t['cpu_fraction'] / max(p['cpu_fraction'], 1e-9):5.2f}x"
        )
    print(line)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=8.0, help="real seconds of emission per measurement")
    args = ap.parse_args()

    t0 = time.perf_counter()
    sim = simulate("montreal", 0, overrides=FULL_RATE)
    t_sim = time.perf_counter() - t0
    feed = make_feed(sim, 11.0, args.seconds, 100.0, time_shift="now")
    g = feed.grid
    per_profile = ProfilerEmulator(g, ProfilerSettings(), [], feed.start_gps_ns).layout
    pts = sum(n for _, n in per_profile)
    print(
        f"scenario montreal, full Z+F rate: {g.profile_rate_hz:g} profiles/s × {pts} points = "
        f"{g.profile_rate_hz * pts / 1e6:.3f} Mpts/s, {len(per_profile)} datagrams/profile "
        f"({g.profile_rate_hz * len(per_profile):,.0f}/s); INS NMEA 100 Hz; PPS; {args.seconds:g} s each "
        f"(simulated in {t_sim:.1f} s)"
    )

    zero = TruthClock(0, feed.start_gps_ns)
    datagrams = [
        (h, d) for h, _, d in ProfilerEmulator(g, ProfilerSettings(), [], feed.start_gps_ns).packets(zero)
    ]
    ins = InsEmulator(feed.ins, InsSettings(), [], feed.start_gps_ns, feed.end_gps_ns, "/nonexistent")
    hosts, kinds, args_ = ins.schedule(zero)
    blocks = [(int(h), ins.nav_bytes(int(a))) for h, k, a in zip(hosts, kinds, args_) if k == 2]

    def measure(tmp: Path, realtime: bool) -> tuple[dict, dict]:
        prof_port, pps_port = free_udp_port(), free_udp_port()
        spec = DevicesSpec(
            run_dir=tmp / "emulators",
            devices=("ins", "profiler", "pps"),
            ins=InsSettings(),
            profiler=ProfilerSettings(port=prof_port),
            pps=PpsSettings(port=pps_port),
            realtime=realtime,
        )
        ours = run_and_sink(DeviceRun(feed, spec), [prof_port, pps_port], args.seconds)
        for name in ("profiler", "ins", "pps"):
            if ours[name].get("status") != "finished":
                sys.exit(f"the {name} emulator did not finish: {ours[name]}")
        # the peer: the same bytes at the same instants, precomputed
        peer_port = free_udp_port()
        bares = [
            _Bare("profiler", datagrams, ("127.0.0.1", peer_port), ProfilerEmulator.spin_ns),
            _Bare("ins", blocks, tmp / "peer" / "ins", InsEmulator.spin_ns),
        ]
        peer = run_and_sink(
            PeerRun(tmp / "peer", bares, feed.start_gps_ns, realtime), [peer_port], args.seconds
        )
        print(
            f"received: {ours['_sink']['datagrams']:,} datagrams, {ours['_sink']['serial_bytes']:,} pty bytes "
            f"(peer {peer['_sink']['datagrams']:,}, {peer['_sink']['serial_bytes']:,})"
        )
        return ours, peer

    results = {}
    for realtime in (False, True):
        with tempfile.TemporaryDirectory(prefix="mls-bench-sim-") as tmp:
            ours, peer = measure(Path(tmp), realtime)
        policy = ours["profiler"]["scheduling"]
        print(f"-- scheduling: {policy}" + ("  (mls sim devices --realtime)" if realtime else "  (default)"))
        fmt_row("profiler (full Z+F rate)", ours["profiler"], peer["profiler"])
        fmt_row("INS NMEA 100 Hz", ours["ins"], peer["ins"])
        fmt_row("PPS", ours["pps"], None)
        results[policy] = ours
    for policy, ours in results.items():
        worst_p99_ms = max(ours[n]["timing"]["error_p99_us"] for n in ("profiler", "ins", "pps")) / 1e3
        cpu = ours["profiler"]["timing"]["cpu_fraction"]
        print(
            f"{policy}: goal p99 ≤ 2 ms: worst {worst_p99_ms:.3f} ms ({'met' if worst_p99_ms <= 2.0 else 'NOT met'}); "
            f"goal full-rate profiler < 1 core: {cpu:.2f} core ({'met' if cpu < 1.0 else 'NOT met'})"
        )


if __name__ == "__main__":
    main()
