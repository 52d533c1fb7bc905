"""Nothing silent: the daemon against the simulated devices through a campaign of faults at random
times, 60 s of real time.

``mls acquire`` (its own process, started through :mod:`tests.acquire.daemon_proc` for the loop
stall, with ``--sim-host-clock``) reads ``mls sim devices`` (scenario montreal from pass 1, INS
NMEA 100 Hz on a pty, profiler ZFP1 and PPS over UDP, truth clock drifting 35 ppm, ×1). The fault
timeline is drawn from a seeded RNG (:func:`draw_plan`): each fault gets its own stretch of the
run, in a random order, at random times, with random parameters —

- **profiler port stolen**: another socket holds the profiler's UDP port when the daemon starts
  and lets it go at a random time; the daemon's transport keeps retrying in the background;
- **INS unplugged** (the emulator's ``serial_unplug``: pty and link removed, a new pty after
  1.5–3 s);
- **garbage** on the INS line (``garbage``: 16–400 random bytes between two epochs);
- **ZDA late by 0.8 s** for 1–3 s (``zda_late``);
- **event-loop stall** of 2 s inside the daemon (SIGUSR1 → the test-only handler of
  :mod:`tests.acquire.daemon_proc`), 5 ms after a pulse before its ZDA or at a random phase;
- **host clock step** (``host_clock_step``, ±0.5 s … ±1 h);
- **disk nearly full**: the session directory is on a 64 MiB tmpfs that a ballast file fills to
  below the ``disk_low`` warning or critical level for 2.5–4 s (where the test may not mount a
  tmpfs, the same ballast is subtracted from the free space the daemon reads:
  :mod:`tests.acquire.daemon_proc`).

Then every alarm each fault should raise was raised, and cleared, within the delay
:data:`DELAYS` states; no other alarm was raised; no record of the session carries a wrong GPS
second (INS time tags, profile ``t0``, log times and PPS labels against the emulators' truth
clock); every segment is readable and complete, and nothing the daemon received was lost.

The seed is fixed (``DEFAULT_SEED``) unless ``$MLS_FAULT_SEED`` gives one (``random`` draws a new
timeline, for a campaign by hand); every assertion message names it, and
``MLS_FAULT_SEED=<seed> pytest tests/acquire/daemon/test_fault_campaign.py`` replays the same
timeline. One module fixture runs it all, once per test session (:func:`run_once`).
"""

from __future__ import annotations

import json
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest

from acquire.daemon.supervisor import LOSS_CLEAR_S
from acquire.log.read import iter_messages
from acquire.log.recover import session_info
from acquire.timing.latency import ALARM_DELAYS_S
from tests.acquire.daemon.fault_campaign import (
    DELAYS,
    ENVIRONMENT,
    EVENT_CLEAR_S,
    HOST_STEP_S,
    MONITOR_S,
    NET_BACKOFF_S,
    NS,
    SERIAL_BACKOFF_S,
    SLACK_S,
    STALL_S,
    STATUS_PERIOD_S,
    ZDA_LATE_S,
    run_campaign,
)
from tests.acquire.daemon.latency_truth import replay_latency_alarms
from tests.acquire.daemon_util import MLS, ROOT, Recording, TruthClock, run_once

pytestmark = [
    pytest.mark.realtime,
    pytest.mark.integration,
    pytest.mark.slow,
    pytest.mark.xdist_group("fault-campaign"),
]


@pytest.fixture(scope="session")
def campaign(tmp_path_factory) -> dict:
    r = run_once(tmp_path_factory, "mls-fault-campaign", run_campaign)
    r["truth"] = TruthClock.read(Path(r["run_dir"]) / "truth_clock.json")
    r["sock"] = Recording.from_json(r["sock"])
    r["session"] = Path(r["sessions"][0])
    r["events"] = [(m.host_ns, m.payload) for m in iter_messages(r["session"], {"/events"})]
    return r


def _why(r: dict, text: str) -> str:
    seed = r["plan"]["seed"]
    return f"seed {seed} (replay: MLS_FAULT_SEED={seed} pytest {Path(__file__).relative_to(ROOT)}): {text}"


def _fault(r: dict, kind: str) -> dict:
    return next(f for f in r["faults"] if f["kind"] == kind)


def _late_zda_host_ns(r: dict) -> list[int]:
    """When each late ZDA left the emulator (a ZDA of a second in the window: its usual delay after
    the pulse + 0.8 s)."""
    from sim_devices.ins import InsSettings

    f, truth = _fault(r, "zda_late"), r["truth"]
    seconds = range(-(-f["start_gps_ns"] // NS) * NS, f["end_gps_ns"], NS)
    late = round((InsSettings().zda_delay_s + ZDA_LATE_S) * NS)
    return [truth.host_ns(s) + late for s in seconds]


def _instants(r: dict) -> dict[str, int]:
    """Host ns of what the faults did (the emulators' own record where they did it)."""
    applied = {a["kind"]: a["host_ns"] for a in r["sim_stats"]["ins"]["stats"]["applied"]}
    late = _late_zda_host_ns(r)
    start = next(h for h, e in r["events"] if e["event"] == "session_start")
    (stall0, stall1), *_ = r["stalls"]
    return {
        "daemon start (before READY=1)": start,
        "daemon start (the monitor's first look, before READY=1)": start,
        "the emulators' INS link appears": r["truth"].window["start_host_ns"],  # (made before it)
        "the other socket lets the port go": r["done"]["port_released"],
        "unplug (EIO seen at once by the reader thread)": applied["unplugged"],
        "unplug (the last record)": applied["unplugged"],
        "replug": applied["replugged"],
        "the first late ZDA": late[0],
        "the last late ZDA": late[-1],
        "the step": _fault(r, "host_clock_step")["start_host_ns"],
        "the ballast written": r["done"]["disk_filled"],
        "the ballast removed": r["done"]["disk_emptied"],
        "garbage": applied["garbage"],
        "stall start": stall0,
        "stall end": stall1,
        "start": r["truth"].window["start_host_ns"],
        "end": r["truth"].window["end_host_ns"],
    }


def _alarm_log(r: dict) -> list[tuple[int, int, dict]]:
    """Every alarm transition: (host ns in the daemon's /events, host ns the test's status-socket
    client received it or None, the alarm)."""
    received = {
        (a["action"], a["name"], a["device"], a["first_host_ns"], a["last_host_ns"]): x.host_ns
        for x in r["sock"].topic("alarms")
        for a in [x.data]
    }
    out = []
    for h, e in r["events"]:
        if e["event"] == "alarm":
            key = (e["action"], e["name"], e["device"], e["first_host_ns"], e["last_host_ns"])
            out.append((h, received.get(key), e))
    return out


def _due(r: dict, ref_ns: int, delay_s: float) -> int:
    """``ref_ns`` + ``delay_s`` + :data:`SLACK_S`, pushed back by the loop stall where it overlaps:
    a stalled loop publishes, clears, retries and counts nothing until it runs again (the faults
    are drawn at random times, so a stall may fall in another fault's delay, or a 10-s clear)."""
    due = ref_ns + round((delay_s + SLACK_S) * NS)
    for a, b in r["stalls"]:
        if a < due and b > ref_ns:
            due += b - a
    return due


def _first(log: list, action: str, name: str, device: str, from_ns: int) -> tuple | None:
    """The first ``action`` (raise, clear) of the alarm ``name``/``device`` at or after ``from_ns``."""
    return next(
        (
            x
            for x in log
            if x[0] >= from_ns and (x[2]["action"], x[2]["name"], x[2]["device"]) == (action, name, device)
        ),
        None,
    )


def _latency_truth_windows(r: dict) -> list[tuple[str, str, int, int, int | None]]:
    """The windows of the latency alarms the replay on the truth clock raises too (the comment
    above :data:`ENVIRONMENT`); cleared by None: the replay's alarm lasts to the end of the run."""
    vessel = Path(r["run_dir"]).parent / "vessel.yaml"
    out = []
    for name, device, on, off in replay_latency_alarms(r["session"], r["truth"], vessel):
        raise_s, clear_s = ALARM_DELAYS_S[name]
        lo = on - round((raise_s + SLACK_S) * NS)
        if off is None:
            end = _instants(r)["end"] + round(60 * NS)  # the daemon evaluates until it is stopped
            out.append(("devices' latency (truth clock)", f"{name}/{device}", lo, end, None))
        else:
            hi = max(_due(r, on, raise_s), off)
            out.append(("devices' latency (truth clock)", f"{name}/{device}", lo, hi, _due(r, off, clear_s)))
    return out


def _optional_windows(r: dict) -> list[tuple[str, str, int, int, int | None]]:
    """(fault, alarm/device, raised from, raised by, cleared by) of the alarms a fault may raise
    besides its own, of the alarms the devices' real latency raises (:func:`_latency_truth_windows`)
    and of the end of the run (the emulators stop: the devices go quiet and the INS pty goes away;
    the daemon is stopped 1.5 s later)."""
    t = _instants(r)

    def s(seconds: float) -> int:
        return round(seconds * NS)

    holdover = "clock_holdover/clock"
    # the next ZDA after the INS is back, or after the late ones, labels its pulse: LOCKED again
    unplug_by = _due(r, t["replug"], SERIAL_BACKOFF_S + 1.0 + MONITOR_S)
    zda_by = _due(r, t["the last late ZDA"], 1.0 + MONITOR_S)
    stall_by = _due(r, t["stall end"], MONITOR_S)
    # the first profile after the port is free may have begun before the daemon had it
    port_by = _due(r, t["the other socket lets the port go"], NET_BACKOFF_S + MONITOR_S)
    return [
        ("INS unplugged", holdover, t["unplug (the last record)"], unplug_by, unplug_by),
        ("ZDA late 0.8 s", holdover, t["the first late ZDA"] - s(1.0), zda_by, zda_by),
        ("2-s loop stall", holdover, t["stall start"], stall_by, stall_by),
        *(
            ("2-s loop stall", f"data_gap/{d}", t["stall start"], stall_by, stall_by)
            for d in ("ins", "profiler")
        ),
        (
            "profiler port stolen",
            "packet_loss/profiler",
            t["the other socket lets the port go"],
            port_by,
            _due(r, port_by, LOSS_CLEAR_S + MONITOR_S),
        ),
        *(
            ("end of the run", k, t["end"] - s(0.1), t["end"] + s(60), t["end"] + s(60))
            for k in ("device_unavailable/ins", "data_gap/ins", "data_gap/profiler", holdover)
        ),
        # the step leaves the host clock that far off GPS time: host_clock_offset stays raised
        (
            "host clock step",
            "host_clock_offset/clock",
            t["the step"],
            _due(r, t["the step"], HOST_STEP_S),
            None,
        ),
        *_latency_truth_windows(r),
    ]


def test_every_fault_raises_its_alarm_within_the_stated_delay_and_clears_it(campaign):
    r = campaign
    t = _instants(r)
    log = _alarm_log(r)
    rows, bad = [], []
    for (fault, key), d in DELAYS.items():
        name, device = key.split("/")
        what_r, delay_r = d["raise"]
        what_c, delay_c = d["clear"]
        ref_r, ref_c = t[what_r], t[what_c]
        startup = what_r.startswith("daemon start")
        lo = t["daemon start (before READY=1)"] if startup else ref_r - round(0.1 * NS)
        raised = _first(log, "raise", name, device, lo)
        if raised is None:
            bad.append(f"{fault}: {key} never raised")
            continue
        cleared = _first(log, "clear", name, device, raised[0] + 1)
        if delay_r == 0.0:  # from start-up: raised before READY=1 (the socket's client came after)
            late_r = raised[0] - r["ready_ns"]
            seen_r = late_r
        else:
            late_r = raised[0] - ref_r
            seen_r = None if raised[1] is None else raised[1] - ref_r
        row = {
            "fault": fault,
            "alarm": key,
            "raise_s": round(late_r / NS, 3),
            "raise_on_socket_s": None if seen_r is None else round(seen_r / NS, 3),
            "raise_limit_s": delay_r,
        }
        allowed = 0 if delay_r == 0.0 else _due(r, ref_r, delay_r) - ref_r
        if late_r > allowed or (seen_r is not None and seen_r > allowed):
            bad.append(
                f"{fault}: {key} raised {row['raise_on_socket_s'] or row['raise_s']} s after "
                + ("READY=1, expected before" if delay_r == 0.0 else f"{what_r}, limit {delay_r} s")
            )
        if cleared is None:
            bad.append(f"{fault}: {key} never cleared")
        else:
            late_c = cleared[0] - ref_c
            seen_c = None if cleared[1] is None else cleared[1] - ref_c
            row.update(
                clear_s=round(late_c / NS, 3),
                clear_on_socket_s=None if seen_c is None else round(seen_c / NS, 3),
                clear_limit_s=delay_c,
            )
            allowed = _due(r, ref_c, delay_c) - ref_c
            if late_c > allowed or (seen_c is not None and seen_c > allowed):
                bad.append(
                    f"{fault}: {key} cleared {row['clear_on_socket_s']} s after {what_c}, limit {delay_c} s"
                )
            if late_c < 0 and what_c != "the emulators' INS link appears":  # (made before the run starts)
                bad.append(f"{fault}: {key} cleared {-late_c / NS:.3f} s before {what_c}")
            if what_c == "the last late ZDA" and late_c < EVENT_CLEAR_S * NS:
                bad.append(f"{fault}: {key} cleared {late_c / NS:.3f} s after the last late ZDA, before 10 s")
        rows.append(row)
    print(f"\nfault campaign, seed {r['plan']['seed']}: {json.dumps(r['plan'])}")
    for row in rows:
        print("  " + json.dumps(row))
    assert not bad, _why(r, "; ".join(bad))


def test_no_alarm_is_raised_without_a_fault_and_none_is_left_raised(campaign):
    r = campaign
    t = _instants(r)
    log = _alarm_log(r)
    expected: list[tuple[str, int, int]] = []  # (alarm/device, raise window) of the table's alarms
    for (_, key), d in DELAYS.items():
        what_r, delay_r = d["raise"]
        lo = (
            t["daemon start (before READY=1)"]
            if what_r.startswith("daemon start")
            else t[what_r] - round(0.1 * NS)
        )
        hi = _due(r, r["ready_ns"] if delay_r == 0.0 else t[what_r], delay_r)
        expected.append((key, lo, hi))
    optional = _optional_windows(r)
    unexplained, hanging = [], []
    for h, _, a in log:
        if a["action"] != "raise" or a["name"] in ENVIRONMENT:
            continue
        key = f"{a['name']}/{a['device']}"
        if any(k == key and lo <= h <= hi for k, lo, hi in expected):
            continue
        window = next(((f, by) for f, k, lo, hi, by in optional if k == key and lo <= h <= hi), None)
        if window is None:
            unexplained.append(f"{key} {(h - t['start']) / NS:.3f} s into the run: {a['message']}")
            continue
        fault, deadline = window
        if fault != "end of the run" and deadline is not None:
            clear = _first(log, "clear", a["name"], a["device"], h + 1)
            if clear is None or clear[0] > deadline:
                hanging.append(
                    f"{key} raised by the {fault} not cleared by {(deadline - h) / NS:.2f} s after"
                )
    assert not unexplained, _why(r, "alarms without a fault to explain them: " + "; ".join(unexplained))
    assert not hanging, _why(r, "; ".join(hanging))


def test_faults_without_an_alarm_of_their_own_show_in_the_metrics(campaign):
    r = campaign
    t = _instants(r)
    metrics = [(x.host_ns, x.data) for x in r["sock"].topic("metrics")]
    # garbage: the INS decoder skipped exactly those bytes, counted within one status period
    n = r["plan"]["garbage_bytes"]
    skipped = [(h, m["devices"]["ins"]["decoder"]["skipped_bytes"]) for h, m in metrics]
    before = max((k for h, k in skipped if h < t["garbage"]), default=0)
    shown = next((h for h, k in skipped if h >= t["garbage"] and k >= before + n), None)
    assert shown is not None, _why(r, f"{n} garbage bytes never counted: {skipped[-1]}")
    assert shown <= _due(r, t["garbage"], STATUS_PERIOD_S), _why(
        r, f"garbage counted after {(shown - t['garbage']) / NS:.3f} s"
    )
    # the stall: the loop's lag, ≥ the stall, in the metrics within one status period after it
    (stall0, stall1), *_ = r["stalls"]
    assert len(r["stalls"]) == 1 and stall1 - stall0 >= STALL_S * NS, _why(r, f"stalls {r['stalls']}")
    lag = next(
        (
            (h, m["loop_lag_ms"])
            for h, m in metrics
            if h > stall1 and m["loop_lag_ms"] >= (STALL_S - MONITOR_S) * 1e3
        ),
        None,
    )
    assert lag is not None and lag[0] <= _due(r, stall1, STATUS_PERIOD_S), _why(
        r, f"loop lag after the stall: {lag}"
    )


def test_no_record_is_stamped_with_a_wrong_gps_second(campaign):
    """Against the emulators' truth clock (host monotonic → GPS): the INS time tags and each
    profiler packet's t0 (the GPS time of its first point) as logged, the log time of every
    record while the clock is LOCKED or in HOLDOVER, and every PPS label. A wrong second shows
    as ≥ 0.5 s (a whole second, as a rule); the bounds below are far tighter."""
    r = campaign
    truth, session = r["truth"], r["session"]
    bad = []
    nav = [
        (m.host_ns, m.payload["time_gps_ns"], m.payload["time_source"])
        for m in iter_messages(session, {"/ins/nav"})
    ]
    host = np.array([h for h, _, _ in nav], dtype=np.int64)
    late = (truth.gps_ns(host) - np.array([g for _, g, _ in nav], dtype=np.int64)) / NS
    if not (late.min() > -0.005 and late.max() < 0.25):
        bad.append(f"INS time tags off the truth by {late.min():+.4f} … {late.max():+.4f} s")
    raw = list(iter_messages(session, {"/lidar/raw"}))
    t0 = np.array([struct.unpack_from("<q", m.payload, 16)[0] for m in raw], dtype=np.int64)
    if any(m.device_ns is None or m.device_ns != t for m, t in zip(raw, t0.tolist())):
        bad.append("a profiler packet logged without its t0 as its device time")
    plate = (truth.gps_ns(np.array([m.host_ns for m in raw], dtype=np.int64)) - t0) / NS
    if not (plate.min() >= 0 and plate.max() < 0.25):
        bad.append(f"profiler t0 off the truth by {plate.min():+.4f} … {plate.max():+.4f} s")
    msgs = [m for m in iter_messages(session, {"/ins/raw", "/lidar/raw", "/ins/nav", "/pps"})]
    err = np.array([m.log_time_ns for m in msgs], dtype=np.int64) - truth.gps_ns(
        np.array([m.host_ns for m in msgs], dtype=np.int64)
    )
    state = np.array([m.clock for m in msgs])
    synced = state != "UNLOCKED"
    if np.abs(err[synced]).max() > 1_000_000:
        bad.append(
            f"log times off the truth by up to {np.abs(err[synced]).max() / 1e6:.3f} ms while the clock was synced"
        )
    # UNLOCKED: before the first lock only, on the system clock's seed (flagged, no claim of GPS
    # accuracy: the emulators' GPS time is the scenario's, a fraction of a second off this host's)
    states = [(h, e["to"]) for h, e in r["events"] if e["event"] == "clock_state"]
    locked = next((h for h, to in states if to == "LOCKED"), None)
    if locked is None or any(to == "UNLOCKED" for _, to in states):
        bad.append(f"the clock did not lock once and for all: {states}")
    elif any(m.host_ns > locked for m, s in zip(msgs, synced) if not s):
        bad.append("records stamped UNLOCKED after the clock locked")
    pps = [
        (m.payload["host_ns"], m.payload["gps_s"], m.payload["reason"])
        for m in iter_messages(session, {"/pps"})
    ]
    wrong = [(h, g) for h, g, _ in pps if g is not None and round(int(truth.gps_ns(h)) / NS) != g]
    if wrong:
        bad.append(f"PPS pulses labelled with a wrong second: {wrong}")
    zda = _fault(r, "zda_late")
    ambiguous = sorted(round(int(truth.gps_ns(h)) / NS) * NS for h, _, why in pps if why == "ambiguous")
    if ambiguous != list(range(-(-zda["start_gps_ns"] // NS) * NS, zda["end_gps_ns"], NS)):
        bad.append(f"pulses left ambiguous {ambiguous}, not the late ZDAs' seconds {zda}")
    t = _instants(r)
    other = [(h, why) for h, g, why in pps if g is None and why != "ambiguous"]
    # the pulses whose ZDA was due while the INS was away (from the second before the unplug to
    # the reconnection) have no time message: unlabelled, and only they
    unplug = (t["unplug (the last record)"] - NS, _due(r, t["replug"], SERIAL_BACKOFF_S + 1.0))
    # and likewise at start-up: the INS link appears with the emulators and the daemon's serial
    # transport opens it within its back-off, so the first pulses' ZDAs can precede the opening
    startup = (t["start"] - NS, _due(r, t["the emulators' INS link appears"], SERIAL_BACKOFF_S + 1.0))
    if any(not (unplug[0] <= h <= unplug[1] or startup[0] <= h <= startup[1]) for h, _ in other):
        bad.append(
            f"pulses unlabelled outside the INS start-up (… {(startup[1] - t['start']) / NS:.3f} s) and "
            f"unplug ({(unplug[0] - t['start']) / NS:.3f} … {(unplug[1] - t['start']) / NS:.3f} s): "
            f"{[(h - t['start']) / NS for h, _ in other]}"
        )
    print(
        f"\nINS tags {late.min() * 1e3:.2f}…{late.max() * 1e3:.2f} ms behind the truth ({len(nav)} epochs), "
        f"profiler t0 {plate.min() * 1e3:.2f}…{plate.max() * 1e3:.2f} ms ({len(raw)} packets), "
        f"log times ≤ {np.abs(err[synced]).max() / 1e3:.1f} µs off while synced ({int(synced.sum())} records), "
        f"{sum(g is not None for _, g, _ in pps)}/{len(pps)} pulses labelled, {len(wrong)} wrong"
    )
    assert not bad, _why(r, "; ".join(bad))


def test_every_segment_is_readable_and_nothing_received_is_lost(campaign):
    r = campaign
    session, t = r["session"], _instants(r)
    assert len(r["sessions"]) == 1, _why(r, f"sessions {r['sessions']}")
    out = subprocess.run(
        [*MLS, "logs", "info", "--json", str(session)], capture_output=True, text=True, cwd=ROOT, timeout=120
    )
    assert out.returncode == 0, _why(
        r, f"mls logs info exit {out.returncode}: {out.stdout[-2000:]}{out.stderr[-2000:]}"
    )
    info = session_info(session)
    assert len(info.segments) >= 3 and all(s.state == "complete" for s in info.segments), _why(
        r, f"segments {[(s.name, s.state, s.problem) for s in info.segments]}"
    )
    for seg in sorted(session.glob("seg-*.mcap")):  # each segment on its own, every message decoded
        alone = session.parent.parent / "one-segment" / seg.stem
        alone.mkdir(parents=True, exist_ok=True)
        shutil.copy(seg, alone / seg.name)
        assert sum(1 for _ in iter_messages(alone)) > 0, _why(r, f"{seg.name} holds no message")
    for topic, ch in info.channels.items():
        assert ch.missing == ch.duplicates == ch.backwards == 0, _why(r, f"{topic}: {ch}")
    status = [m.payload["log"] for m in iter_messages(session, {"/status"})]
    assert all(s["dropped"] == 0 and s["lost"] == 0 for s in status), _why(r, "the writer dropped records")
    # every PPS pulse the emulator sent is in /pps exactly once
    sent = [e["sequence"] for e in r["sim_stats"]["pps"]["stats"]["edges"]]
    logged = sorted(m.payload["sequence"] for m in iter_messages(session, {"/pps"}))
    assert logged == sent, _why(r, f"{len(sent)} pulses sent, {len(logged)} logged")
    # every INS epoch: its time tags on the 10-ms grid with one hole only, the unplug (and the
    # reconnection after it); an epoch cut by opening the pty (its time sentence lost) is timed by
    # the clock model (time_source "clock")
    truth = r["truth"]
    nav = [
        (m.host_ns, m.payload["time_gps_ns"], m.payload["time_source"])
        for m in iter_messages(session, {"/ins/nav"})
    ]
    tags = np.array([g for _, g, src in nav if src == "device"], dtype=np.int64)
    step = np.diff(tags)
    holes = np.flatnonzero(step != 10_000_000)
    assert len(holes) == 1, _why(r, f"INS epochs missing at {[(int(tags[i]), int(step[i])) for i in holes]}")
    (i,) = holes
    a, b = truth.host_ns(int(tags[i])), truth.host_ns(int(tags[i + 1]))
    assert a <= t["unplug (the last record)"] and b <= _due(r, t["replug"], SERIAL_BACKOFF_S), _why(
        r,
        f"INS hole {(a - t['start']) / NS:.3f} … {(b - t['start']) / NS:.3f} s into the run, not the unplug",
    )
    connects = [h for h, e in r["events"] if e["event"] == "connected" and e.get("device") == "ins"]
    cut = [h for h, _, src in nav if src != "device"]
    assert all(any(c <= h <= c + 100_000_000 for c in connects) for h in cut), _why(
        r, f"INS epochs without their time tag, not at a (re)connection: {cut}"
    )
    # ... and none missing but those: from the first epoch the emulator wrote after the daemon
    # first opened the pty (opening it flushes what waited) to the last
    opened = connects[0]
    before = round((int(tags[0]) - truth.window["start_gps_ns"]) / 10_000_000)
    assert before == 0 or truth.host_ns(int(tags[0]) - 10_000_000) < opened, _why(
        r, f"the first {before} INS epochs, written after the daemon opened the pty, are missing"
    )
    sent_epochs = r["sim_stats"]["ins"]["stats"]["epochs"]
    assert before + len(tags) + int(step[i] // 10_000_000) - 1 == sent_epochs, _why(
        r, f"{len(tags)} epochs logged of {sent_epochs}"
    )
    # every profiler datagram from the first the daemon received (after the port was freed) to the
    # last the emulator sent: complete profiles, each packet once
    pkts = [struct.unpack_from("<IHH", m.payload, 8) for m in iter_messages(session, {"/lidar/raw"})]
    first_host = min(m.host_ns for m in iter_messages(session, {"/lidar/raw"}))
    assert first_host > t["the other socket lets the port go"], _why(
        r, "profiler data before the port was freed"
    )
    count = r["devices"]["profiler"]["packets_per_profile"]
    c0, c1 = pkts[0][0] + (pkts[0][1] != 0), r["devices"]["profiler"]["profiles"] - 1
    have = sorted((c, k) for c, k, _ in pkts if c >= c0)
    assert have == [(c, k) for c in range(c0, c1 + 1) for k in range(count)], _why(
        r, f"profiler packets of profiles {c0}…{c1}: {len(have)} logged, {(c1 - c0 + 1) * count} sent"
    )
    final = r["sock"].topic("metrics")[-1].data["devices"]["profiler"]
    # (the first profile may have begun before the daemon had the port: packets of it "lost")
    assert final["packets_lost"] < count and final["profiles_lost"] == 0, _why(r, f"profiler losses {final}")


def test_the_daemon_ran_through_every_fault_and_stopped_cleanly(campaign):
    r = campaign
    assert r["daemon_rc"] == 0 and "Traceback" not in r["daemon_log"], _why(r, r["daemon_log"][-3000:])
    ends = [e for _, e in r["events"] if e["event"] == "session_end"]
    assert ends and ends[0]["reason"] == "SIGTERM", _why(r, f"{ends}")
    print(
        f"\nfault campaign seed {r['plan']['seed']}: {r['wall_s']:.1f} s wall time, disk "
        f"{'64 MiB tmpfs' if r['disk']['tmpfs'] else 'simulated in the daemon'}"
    )
