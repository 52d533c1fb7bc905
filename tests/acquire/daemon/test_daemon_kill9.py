"""Durability of the real daemon: ``kill -9`` of ``mls acquire`` at 5
random (seeded) times while the fake devices stream, each time restarted in the same session
root (its start-up salvages the torn session; once ``mls logs info``/``mls logs recover`` do it
instead). Then, session by session, against what the fake devices record of every byte sent:

- every INS byte, profiler datagram and PPS edge emitted while that daemon was up and its
  device connected, earlier than (kill time − flush period), is in the session's raw channels,
  and nothing is there twice (in any session);
- per-channel sequence counters are contiguous within each session (from 1);
- every torn tail — what the kill left, plus the half-written chunk a power cut adds (appended
  on two trials) — is reported: by the restart's ``session_start`` event (``salvaged``) or by
  ``mls logs recover``, in the recovered segment's ``mls.recovery`` metadata, with the torn
  original kept, and its count of bytes and messages checked against a scan of that original.

"Emitted" per channel (the fake stamps each send call before it is made and after it returned,
so the data were in the kernel's pty or socket buffer by the second stamp; a piece is due only
when its call started inside the window and returned before its end, since a stamp taken after
the call can lag it by a GIL switch, past a reopening daemon's input flush): an INS byte when
the ``os.write`` holding it returned (the daemon reads the pty in arbitrary pieces, so the comparison is of byte streams:
a session's ``/ins/raw`` is one contiguous slice of everything sent, after the previous
session's slice); a profiler datagram when its ``sendto`` returned (compared as whole
datagrams, in order); a PPS edge when the ZDA sentence that labels it was written (the daemon
logs a pulse on ``/pps`` once its label arrives: docs/architecture.md §5, §6, :mod:`acquire.timing.timekeeper`),
identified by the datagram's sequence number. "Up and connected": from the later of the
daemon's READY=1 and the device's ``connected`` event in the session.
"""

from __future__ import annotations

import json
import os
import random
import signal
import socket
import struct
import subprocess
import textwrap
import threading
import time
from bisect import bisect_right
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import pytest

from acquire.log.read import iter_messages
from acquire.log.recover import SegmentScan, scan_segment, segment_paths, session_info, unfinished_segments
from acquire.log.schema import Envelope
from acquire.status.bus import read_snapshot
from drivers.pps import decode_pps_datagram
from tests.acquire.daemon_util import MLS, ROOT, NotifyCollector, Proc, free_port, wait_until
from tests.acquire.fakedevices import FakeDevices, devices_yaml

# realtime: what a kill must leave in the session is what was older than the flush period (0.5 s)
# when it landed (a deadline of the writer, held against the wall clock), at random instants
pytestmark = [
    pytest.mark.realtime,
    pytest.mark.integration,
    pytest.mark.slow,
    pytest.mark.xdist_group("daemon-kill9"),
]

NS = 1_000_000_000
FLUSH_S = 0.5
TRIALS = 5
SEED = 20240607
TORN_TRIALS = (1, 2)  # a power cut's half-written chunk appended after the kill
CLI_TRIAL = 2  # salvaged by `mls logs recover` before the restart (not by the daemon)


def _gps_now_ns() -> int:
    from acquire.timing.timekeeper import coarse_gps_offset_ns

    return (time.monotonic_ns() + coarse_gps_offset_ns()) // NS * NS + 300_000_000


class _Halt(Exception):
    """Ends the fake devices' thread (caught in :meth:`RecordingDevices.run`)."""


class _SendLog:
    """The fake's UDP socket, recording (host ns after ``sendto`` returned, address, datagram)."""

    def __init__(self, sock, dev: RecordingDevices):
        self.sock, self.dev = sock, dev

    def sendto(self, data, addr):
        if self.dev.halted.is_set():
            raise _Halt
        t0 = time.monotonic_ns()
        n = self.sock.sendto(data, addr)
        self.dev.sent.append(((t0, time.monotonic_ns()), addr, bytes(data)))
        return n

    def close(self):
        self.sock.close()


class RecordingDevices(FakeDevices):
    """The fake devices, plus when each piece was handed to the kernel, and a way to stop."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.halted = threading.Event()
        self.sent: list[tuple[tuple[int, int], tuple, bytes]] = []  # ((ns before, after), addr, datagram)
        self.ins_ends: list[tuple[int, int, int]] = []  # (ns before os.write, after it returned, end offset)
        self.zda_ns: list[int] = []  # when each ZDA sentence was written whole
        self.sock = cast(socket.socket, _SendLog(self.sock, self))  # (sendto and close, recorded)

    def run(self) -> None:
        try:
            super().run()
        except _Halt:
            pass

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            if self.halted.is_set():
                raise _Halt
            t0 = time.monotonic_ns()
            n = os.write(self.master, view)
            self.ins_bytes += view[:n]
            self.ins_ends.append((t0, time.monotonic_ns(), len(self.ins_bytes)))
            view = view[n:]
        if b"ZDA," in data:
            self.zda_ns.append(self.ins_ends[-1][1])

    def ins_due(self, lo_ns: int, hi_ns: int) -> tuple[int, int]:
        """Byte offsets [first, last) of the writes that started at or after ``lo_ns`` and had
        returned before ``hi_ns``."""
        i = bisect_right([t0 for t0, _, _ in self.ins_ends], lo_ns - 1)
        j = bisect_right([t1 for _, t1, _ in self.ins_ends], hi_ns - 1)
        first = self.ins_ends[i - 1][2] if i else 0
        return first, max(first, self.ins_ends[j - 1][2] if j else 0)

    def ins_offset_at(self, t_ns: int) -> int:
        """Bytes handed to the pty by host time ``t_ns``."""
        return self.ins_due(0, t_ns + 1)[1]


def _data_flowing(sock: Path) -> bool:
    """The daemon's status snapshot shows an INS epoch, a profile and a PPS pulse handled."""
    try:
        snap = read_snapshot(sock, 3.0)
    except (OSError, ValueError):
        return False
    return (
        snap.get("sensors/ins", {}).get("records", 0) > 0
        and snap.get("sensors/profiler", {}).get("records", 0) > 0
        and snap.get("clock", {}).get("pps", {}).get("pulses", 0) > 0
    )


@dataclass
class Run:
    trial: int
    pid: int
    ready_ns: int
    kill_ns: int | None  # None: the last daemon, stopped with SIGTERM
    session: Path | None = None
    torn_appended: bytes = b""
    cli: dict | None = None


def _config(tmp: Path, prof: int, pps: int) -> Path:
    cfg = tmp / "vessel.yaml"
    cfg.write_text(
        "vessel: kill9\ndevices:\n"
        + devices_yaml(tmp, prof, pps)
        + textwrap.dedent(f"""\
        session: {{directory: {tmp}/sessions, flush_s: {FLUSH_S}, fsync_s: 1.0, rotate_s: 10, rotate_mb: 1}}
        status: {{socket: {tmp}/status.sock, period_s: 0.5}}
        """)
    )
    return cfg


def _mls(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [*MLS, *args],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=60,
        env={**os.environ, "COLUMNS": "250"},
    )


def _power_cut_tail(rng: random.Random) -> bytes:
    """The start of a chunk record whose pages did not all reach the disk."""
    return struct.pack("<BQ", 0x06, 80_000) + bytes(rng.randrange(256) for _ in range(777))


def _record(m: Envelope) -> dict:
    """A decoded record's payload (``/events``, ``/pps``)."""
    assert isinstance(m.payload, dict), m.topic
    return m.payload


def _raw(m: Envelope) -> bytes:
    """A raw channel's payload (``/ins/raw``, ``/lidar/raw``)."""
    assert isinstance(m.payload, bytes), m.topic
    return m.payload


def _events(session: Path) -> list[dict]:
    return [_record(m) for m in iter_messages(session, {"/events"})]


@pytest.fixture(scope="module")
def kill_runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("kill9")
    prof, pps = free_port(), free_port()
    cfg = _config(tmp, prof, pps)
    notify = NotifyCollector(tmp / "notify.sock")
    notify.start()
    env = {"NOTIFY_SOCKET": str(tmp / "notify.sock")}
    fake = RecordingDevices(tmp / "ins", prof, pps, seconds=120.0, gps0_ns=_gps_now_ns())
    rng = random.Random(SEED)
    runs: list[Run] = []
    procs: list[Proc] = []
    t_start = time.monotonic()
    try:
        fake.start()
        for trial in range(TRIALS + 1):
            d = Proc([*MLS, "acquire", "--config", str(cfg)], tmp / f"daemon{trial}.log", env)
            procs.append(d)
            wait_until(
                lambda trial=trial: len(notify.with_line("READY=1")) > trial, 30, f"READY=1 ({trial})", d
            )
            run = Run(trial, d.pid, notify.with_line("READY=1")[trial], None)
            runs.append(run)
            if trial == TRIALS:  # the last one salvages the 5th session, then stops cleanly
                wait_until(  # data in its session: an INS epoch, a profile and a pulse
                    lambda: _data_flowing(tmp / "status.sock"), 30, "data in the last session", d
                )
                fake.halted.set()
                fake.join(5)
                d.signal(signal.SIGTERM)
                assert d.wait(30) == 0, d.output()[-3000:]
                break
            # data flowing; the kill lands anywhere: at a random point of the INS stream (and so
            # of the writer's flush cycle), once the fake has sent the epoch that many seconds
            # of device time past READY (it paces its epochs by the host clock: as many real
            # seconds at least); 0.8 s at least: 0.3 s of data past the flush period in every
            # session, a pulse (1 Hz) labelled in most
            kill_gps_ns = fake.gps(run.ready_ns) + round(rng.uniform(0.8, 3.2) * NS)
            wait_until(
                lambda g=kill_gps_ns: bool(fake.epochs) and fake.epochs[-1] >= g,
                30,
                f"the fake to send the INS epoch of the kill ({trial})",
                d,
                poll_s=0.005,
            )
            run.kill_ns = time.monotonic_ns()
            d.signal(signal.SIGKILL)
            assert d.wait(10) == -signal.SIGKILL
            session = next(
                q
                for q in (tmp / "sessions").iterdir()
                if (q / "session.lock").read_text().strip() == str(d.pid)
            )
            run.session = session
            torn = unfinished_segments(session)
            if trial in TORN_TRIALS and torn:
                run.torn_appended = _power_cut_tail(rng)
                with open(torn[-1], "ab") as f:
                    f.write(run.torn_appended)
            if trial == CLI_TRIAL:
                before = _mls("logs", "info", str(session), "--json")
                recover = _mls("logs", "recover", str(session))
                after = _mls("logs", "info", str(session), "--json")
                again = _mls("logs", "recover", str(session))
                run.cli = {
                    "before": (before.returncode, before.stdout),
                    "recover": (recover.returncode, recover.stdout),
                    "after": (after.returncode, after.stdout),
                    "again": (again.returncode, again.stdout),
                }
        wall_s = time.monotonic() - t_start
    finally:
        fake.halted.set()
        for p in procs:
            p.kill()
        fake.join(5)
        fake.close()
        notify.stop()
    sessions = sorted(q for q in (tmp / "sessions").iterdir() if q.is_dir())
    by_pid = {}
    for s in sessions:
        start = [e for e in _events(s) if e["event"] == "session_start"]
        by_pid[start[0]["pid"]] = s
    for r in runs:
        assert r.session is None or by_pid[r.pid] == r.session
        r.session = by_pid[r.pid]
    logs = [p.output() for p in procs]
    return {"runs": runs, "fake": fake, "sessions": sessions, "logs": logs, "wall_s": wall_s}


def _window(run: Run, device: str) -> tuple[int, int]:
    """[up and connected, kill − flush period) of one daemon run for one device."""
    assert run.session is not None  # (every run's, found after the runs)
    assert run.kill_ns is not None  # (a killed run)
    ev = [e for e in _events(run.session) if e.get("device") == device]
    kinds = [e["event"] for e in ev]
    assert "disconnected" not in kinds, (run.trial, device, ev)
    connected = [
        m.host_ns
        for m in iter_messages(run.session, {"/events"})
        if _record(m).get("device") == device and _record(m)["event"] == "connected"
    ]
    start = max([run.ready_ns, *connected[:1]])
    return start, run.kill_ns - int(FLUSH_S * NS)


def test_every_session_is_complete_after_salvage_with_contiguous_counters(kill_runs):
    runs = kill_runs["runs"]
    assert len(kill_runs["sessions"]) == TRIALS + 1 == len({r.session for r in runs})
    assert all("Traceback" not in log for log in kill_runs["logs"])
    for r in runs:
        info = session_info(r.session)
        assert all(s.state == "complete" for s in info.segments), (r.trial, info.segments)
        assert len(info.segments) >= 1
        for t in ("/ins/raw", "/lidar/raw", "/pps", "/ins/nav", "/events", "/status"):
            assert t in info.channels, (r.trial, t)
        for c in info.channels.values():
            assert (c.seq_first, c.missing, c.duplicates, c.backwards) == (1, 0, 0, 0), (r.trial, c)
            assert c.seq_last == c.messages  # (from 1, none missing)
    print(
        f"\n{TRIALS} kill -9 trials of `mls acquire` in {kill_runs['wall_s']:.1f} s; kill after "
        + ", ".join(f"{(r.kill_ns - r.ready_ns) / NS:.2f}" for r in runs if r.kill_ns)
        + " s of READY"
    )


def test_every_ins_byte_emitted_before_the_flush_period_is_logged_exactly_once(kill_runs):
    fake, runs = kill_runs["fake"], kill_runs["runs"]
    sent = bytes(fake.ins_bytes)
    prev_end = 0
    for r in runs:
        logged = b"".join(_raw(m) for m in iter_messages(r.session, {"/ins/raw"}))
        a = sent.find(logged, prev_end) if logged else -1
        assert a >= prev_end, (
            r.trial,
            "the session's /ins/raw is not one slice of the bytes sent after the previous session's",
        )
        b = a + len(logged)
        if r.kill_ns is not None:
            first_due, last_due = fake.ins_due(*_window(r, "ins"))
            assert a <= first_due, (r.trial, a, first_due, last_due, b)
            assert b >= last_due, (r.trial, a, first_due, last_due, b)
            print(
                f"trial {r.trial}: INS bytes {a}–{b} logged, {first_due}–{last_due} due; "
                f"{fake.ins_offset_at(r.kill_ns) - b} B sent before the kill not logged"
            )
        prev_end = b


def test_every_profiler_datagram_emitted_before_the_flush_period_is_logged_exactly_once(kill_runs):
    fake, runs = kill_runs["fake"], kill_runs["runs"]
    sent = [(t, d) for t, addr, d in fake.sent if addr == fake.addr_prof]
    index = {d: i for i, (_, d) in enumerate(sent)}
    assert len(index) == len(sent)  # every datagram is unique (counter, time tag, points)
    prev = -1
    for r in runs:
        known = [index.get(_raw(m)) for m in iter_messages(r.session, {"/lidar/raw"})]
        assert None not in known, (r.trial, "a logged datagram that was never sent")
        got = [i for i in known if i is not None]
        assert got == sorted(set(got)), (r.trial, "twice or out of order")
        assert not got or got[0] > prev, (r.trial, "twice or out of order")
        if r.kill_ns is not None:
            lo, hi = _window(r, "profiler")
            due = {i for i, ((t0, t1), _) in enumerate(sent) if lo <= t0 and t1 < hi}
            assert len(due) > 10, (r.trial, len(due))
            assert due <= set(got), (r.trial, sorted(due - set(got))[:5])
        prev = got[-1] if got else prev


def test_every_pps_edge_labelled_before_the_flush_period_is_logged_exactly_once(kill_runs):
    fake, runs = kill_runs["fake"], kill_runs["runs"]
    pulses = [
        (t0, decode_pps_datagram(d).sequence) for (t0, _), addr, d in fake.sent if addr == fake.addr_pps
    ]
    second = {k + 1: s for k, (s, _) in enumerate(fake.pulses)}
    seen: set[int] = set()
    due_total = 0
    for r in runs:
        logged = [_record(m) for m in iter_messages(r.session, {"/pps"})]
        seqs = [p["sequence"] for p in logged]
        assert len(seqs) == len(set(seqs)), (r.trial, "an edge logged twice")
        assert not set(seqs) & seen, (r.trial, "an edge logged twice")
        seen |= set(seqs)
        for p in logged:
            assert p["gps_s"] in (None, second[p["sequence"]]), p
        if r.kill_ns is not None:
            lo, hi = _window(r, "pps")
            due = []
            for t, seq in pulses:
                zda = next((z for z in fake.zda_ns if z > t), None)  # the sentence labelling it
                if t >= lo and zda is not None and zda < hi:
                    due.append(seq)
            assert set(due) <= set(seqs), (r.trial, due, seqs)  # (a short run may have none)
            due_total += len(due)
    assert due_total >= 3, due_total


def test_torn_tails_are_detected_and_reported_not_dropped(kill_runs):
    runs = kill_runs["runs"]
    total_torn, appended = 0, 0
    for r, nxt in zip(runs, runs[1:], strict=False):
        start = next(e for e in _events(nxt.session) if e["event"] == "session_start")
        salvaged = start["salvaged"]
        info = session_info(r.session)
        recovered = {s.name: s for s in info.segments if s.recovery}
        if r.trial == CLI_TRIAL:  # salvaged by `mls logs recover` before the restart
            assert r.session.name not in salvaged
            rc, out = r.cli["before"]
            before = json.loads(out)
            assert rc == 1
            assert [s["state"] for s in before["segments"]][-1] == "unfinished"
            rc, out = r.cli["recover"]
            assert rc == 0, out
            assert all(name in out for name in recovered), out
            reports = [
                {"segment": s["name"], "torn_bytes": s["torn_bytes"], "problem": s["problem"]}
                for s in before["segments"]
                if s["state"] == "unfinished"
            ]
            rc, out = r.cli["after"]
            assert rc == 0
            assert all(s["state"] == "complete" for s in json.loads(out)["segments"])
            assert r.cli["again"][0] == 0
            assert "nothing to recover" in r.cli["again"][1]
        else:
            reports = salvaged[r.session.name]
        assert {x["segment"] for x in reports} == set(recovered), (r.trial, reports, list(recovered))
        assert len(recovered) == 1, (r.trial, list(recovered))  # the segment being written
        for rep in reports:
            seg = recovered[rep["segment"]]
            assert seg.recovery is not None  # (a recovered segment)
            original = r.session / (rep["segment"] + ".torn")
            scan = SegmentScan(original, 0)
            held = sum(1 for rec in scan_segment(original, scan) if type(rec).__name__ == "Message")
            assert rep["torn_bytes"] == scan.torn_bytes == int(seg.recovery["torn_bytes"])
            assert scan.good_bytes + scan.torn_bytes == original.stat().st_size
            assert int(seg.recovery["messages"]) == held == seg.messages  # nothing dropped silently
            if "messages" in rep:
                assert rep["messages"] == held
            if r.torn_appended:
                assert original.read_bytes().endswith(r.torn_appended)
                assert rep["torn_bytes"] >= len(r.torn_appended), rep
                assert "torn" in rep["problem"], rep
                appended += 1
            total_torn += rep["torn_bytes"]
        assert segment_paths(r.session)[-1].name in recovered or not r.kill_ns
    assert appended >= 1
    print(
        f"\ntorn tail bytes reported over {TRIALS} kills: {total_torn} "
        f"({appended} power-cut tails of 786 B appended)"
    )
