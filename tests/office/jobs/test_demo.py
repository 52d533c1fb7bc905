"""``mls demo`` end to end, and the operator's checklist against the real thing.

One demo run, shorter than ``make demo``'s (lines 2–6 of 14 m, 2 s transits: all six passes
and both targets), is shared by two tests: the Textual checklist (headless, 80×24) follows it
live through the daemon's status socket — pre-checks red then green, the six passes accepted
one by one, the predicted σ shrinking, "calibrate now" running the real ``mls calib run`` on
the recorded session — with an SVG screenshot of each stage in ``$MLS_SCREENSHOT_DIR``
(default ``tests/screenshots/``, names ``live-NN-<stage>.svg``, listed in ``live-index.txt``);
then the demo's own result is checked (the boresight within 3σ of the truth, no process left
in its session). Two more runs are cut short: Ctrl-C, and a daemon that dies mid-survey; each
must name what happened and leave no process behind. ``mls demo`` runs in its own session
(``start_new_session``), so whatever it started is found by its session id in ``/proc``.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import signal
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

from office.jobs.demo_compare import comparison_rows
from tests import waiting
from tests.acquire.daemon_util import MLS, ROOT

SHOTS = Path(os.environ.get("MLS_SCREENSHOT_DIR") or Path(__file__).resolve().parents[2] / "screenshots")
SHORT = ("--line-m", "14", "--pass-gap-s", "2")  # 67 s of survey instead of make demo's 82 s
RELATIVE_HEADINGS = [0, 180, 45, 225, 315, 135]


# -- processes ----------------------------------------------------------------------------------


def session_processes(sid: int) -> list[tuple[int, str]]:
    """Live (non-zombie) processes of session ``sid``: (pid, command line)."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
        except OSError:
            continue
        fields = stat[stat.rfind(")") + 2 :].split()  # state ppid pgrp session ...
        if int(fields[3]) == sid and fields[0] != "Z":
            out.append((int(d.name), cmd))
    return out


def left_behind(sid: int, grace_s: float = 5.0) -> list[tuple[int, str]]:
    waiting.wait_until(
        lambda: not session_processes(sid), grace_s, "the processes to end", interval_s=0.1, fail=False
    )
    return session_processes(sid)


@dataclass
class DemoProcess:
    p: subprocess.Popen
    out: Path
    log: Path

    def output(self) -> str:
        return self.log.read_text(errors="replace")

    def kill_all(self) -> None:
        for pid, _ in session_processes(self.p.pid):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        if self.p.poll() is None:
            self.p.wait(10)


def start_demo(base: Path, *args: str, log_name: str = "demo.log") -> DemoProcess:
    out, log = base / "demo-out", base / log_name
    env = {**os.environ, "MLS_HISTORY_DB": str(base / "history.sqlite")}
    with open(log, "ab") as f:
        p = subprocess.Popen(
            [*MLS, "demo", "--out", str(out), *SHORT, *args],
            stdout=f,
            stderr=subprocess.STDOUT,
            cwd=ROOT,
            env=env,
            start_new_session=True,
        )
    return DemoProcess(p, out, log)


def wait_for(cond, timeout_s: float, what: str, demo: DemoProcess | None = None):
    def still_running() -> None:
        if demo is not None and demo.p.poll() is not None:
            raise AssertionError(f"{what}: mls demo ended ({demo.p.returncode}):\n{demo.output()[-3000:]}")

    return waiting.wait_until(
        cond,
        timeout_s,
        what,
        interval_s=0.05,
        between=still_running,
        detail=None if demo is None else (lambda: demo.output()[-3000:]),
    )


def daemon_status(out: Path) -> dict | None:
    from acquire.status.bus import read_snapshot

    try:
        st = read_snapshot(out / "run" / "status.sock", timeout_s=1.0).get("status") or {}
    except (OSError, ConnectionError, ValueError):
        return None
    return st if st.get("state") == "running" else None


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    d = start_demo(tmp_path_factory.mktemp("demo"))
    yield d
    d.kill_all()


# -- the checklist, live ------------------------------------------------------------------------


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.xdist_group("demo")
def test_checklist_follows_the_live_survey_and_calibrates_the_session(demo, monkeypatch):
    from rich.console import Console

    from acquire.status.feed import SocketFeed
    from acquire.ui.checklist_app import ChecklistApp

    monkeypatch.setenv("MLS_HISTORY_DB", str(demo.out.parent / "history.sqlite"))
    SHOTS.mkdir(parents=True, exist_ok=True)
    index = SHOTS / "live-index.txt"
    if index.exists():  # the previous run's screenshots
        for name in index.read_text().split():
            (SHOTS / name).unlink(missing_ok=True)
    shots: list[str] = []
    sock = demo.out / "run" / "status.sock"
    record: dict = {"accepted": [], "sigma": [], "captured": set()}

    async def main():
        app = ChecklistApp(
            SocketFeed(sock, retry_min_s=0.1, retry_max_s=0.2),
            session_root=str(demo.out / "run" / "sessions"),
        )

        def shot(name: str) -> None:
            fname = f"live-{len(shots) + 1:02d}-{name}.svg"
            app.save_screenshot(fname, str(SHOTS))
            shots.append(fname)

        def plain(wid: str) -> str:
            return app.query_one(wid).content.plain

        async def until(cond, timeout_s: float, what: str, live: bool = True):
            """Wait for ``cond``; with ``live``, fail early when the demo (its daemon) is gone."""
            deadline = time.monotonic() + timeout_s
            while time.monotonic() < deadline:
                if cond():
                    return
                if live and demo.p.poll() is not None and not app.state.link_up:
                    raise AssertionError(
                        f"{what}: mls demo ended ({demo.p.returncode}):\n{demo.output()[-3000:]}"
                    )
                await pilot.pause(0.05)
            red = [f"{c.get('label')}: {c.get('detail')}" for c in app.state.checks() if not c.get("ok")]
            raise AssertionError(
                f"timed out after {timeout_s} s waiting for {what}; red checks: {red}; "
                f"demo output:\n{demo.output()[-2000:]}"
            )

        async with app.run_test(size=(80, 24)) as pilot:
            # 1. the daemon has started: its checks are red (the clock is not locked yet)
            await until(
                lambda: app.state.link_up and app.state.checklist.get("prechecks"),
                90,
                "the daemon's guidance",
            )
            checks = {c["name"]: c for c in app.state.checks()}
            assert checks["clock_locked"]["ok"] is not True, checks["clock_locked"]
            text = plain("#prechecks")
            assert text.splitlines()[0][0] in "✘…" and "Clock LOCKED" in text
            assert "daemon running" in plain("#header")
            shot("prechecks-red")
            # 2. the INS navigates, the PPS labels lock the clock: every check green
            await until(
                lambda: (
                    len(app.state.checks()) >= 11
                    and all(c.get("ok") is True for c in app.state.checks())
                    and "clock LOCKED" in plain("#header")
                ),
                40,
                "green checks",
            )
            names = {c["name"] for c in app.state.checks()}
            assert {
                "ins_navigating",
                "gnss_fix",
                "pps_locked",
                "clock_locked",
                "latency_in_band",
                "disk_space",
                "mount_targets",
                "ins_pps",
                "profiler_data",
            } <= names
            assert "✘" not in plain("#prechecks")
            shot("prechecks-green")
            # 3. the passes, accepted one by one in the plan's order
            deadline = time.monotonic() + 150
            while len(record["accepted"]) < 6:
                assert time.monotonic() < deadline, (
                    f"passes so far: {record['accepted']}\n{demo.output()[-2000:]}"
                )
                msg = app.state.checklist
                passes = msg.get("passes") or []
                bad = [p for p in passes if p["status"] == "rejected"]
                assert not bad, f"pass {bad[0]['id']} rejected: {bad[0]['reasons']}"
                a = msg.get("active") or {}
                if a.get("state") == "capture" and "along_m" in a:
                    c0, c1 = a["capture_m"]
                    if a["pass_id"] not in record["captured"] and a["along_m"] >= 0.5 * (c0 + c1):
                        live = plain("#live")
                        assert f"pass {a['pass_id']}" in live and "CAPTURE" in live and "XTE" in live
                        record["captured"].add(a["pass_id"])
                        shot(f"pass-{a['pass_id']}-capture")
                accepted = [p["id"] for p in passes if p["status"] == "accepted"]
                if len(accepted) > len(record["accepted"]):
                    k = len(record["accepted"]) + 1
                    assert accepted == [p["id"] for p in passes[:k]], accepted  # one by one, in order
                    assert msg["accepted"] == k
                    await until(
                        lambda accepted=accepted: (
                            (app.state.checklist.get("sigma") or {}).get("current", {}).get("passes")
                            == accepted
                        ),
                        20,
                        f"the σ prediction of {k} passes",
                    )
                    cur = app.state.checklist["sigma"]["current"]
                    record["sigma"].append(cur)
                    record["accepted"] = accepted
                    assert plain("#sigma").startswith(f"σ({k})")
                    assert app.query_one("#passes").border_subtitle == f"{k}/6 accepted"
                    row = plain("#passes").splitlines()[k]
                    assert "accepted" in row and row[1:3].strip() == str(accepted[-1])
                    shot(f"pass-{accepted[-1]}-accepted")
                await pilot.pause(0.05)
            assert record["captured"] == set(range(1, 7))
            assert [
                round(p["relative_heading_deg"]) for p in app.state.checklist["passes"]
            ] == RELATIVE_HEADINGS
            # 4. the demo stops the daemon (the session closes); then "calibrate now"
            await until(
                lambda: (app.state.topics.get("status") or {}).get("state") == "stopped",
                30,
                "the daemon's orderly stop",
            )
            await pilot.press("c")
            await until(lambda: app.calibration is not None, 180, "the calibration", live=False)
            await until(
                lambda: (
                    len(app.screen_stack) > 1
                    and app.screen.query("#modal-body")
                    and app.screen.query_one("#modal-body").region.height > 0
                ),
                10,
                "the result screen",
                live=False,
            )
            await pilot.pause(0.2)  # laid out: let it paint before the screenshot
            outcome = app.calibration
            assert outcome.ok, outcome.message
            con = Console(width=80, record=True)
            con.print(app.screen.query_one("#modal-body").content)
            shown = con.export_text()
            for a in ("roll", "pitch", "yaw"):
                assert f"{outcome.result['boresight_deg'][a]:+.4f}" in shown
                assert f"{outcome.result['sigma_realistic_deg'][a]:.4f}" in shown
            shot("calibration-result")
            await pilot.press("escape")
            record["outcome"] = outcome

    asyncio.run(main())
    index.write_text("\n".join(shots) + "\n")
    assert len(shots) == 2 + 2 * 6 + 1
    for f in shots:
        assert (SHOTS / f).stat().st_size > 5000, f
    # the predicted σ after each accepted pass: the angles determined never go back to "not
    # observable", all three are determined at the end, and every determined angle's σ shrinks
    # with each new pass: the formal σ, and the realistic σ the screen shows (the GLS σ, the
    # inverse of an information that only grows as passes are added)
    sig = record["sigma"]
    determined = [{a for a, v in s["formal_deg"].items() if v is not None} for s in sig]
    assert all(b >= a for a, b in zip(determined, determined[1:])) and determined[-1] == {
        "roll",
        "pitch",
        "yaw",
    }
    for before, after in zip(sig, sig[1:]):
        for a, v in before["formal_deg"].items():
            if v is not None:
                assert after["formal_deg"][a] < v, (a, before, after)
        for a, v in before["realistic_deg"].items():
            if v is not None:
                assert after["realistic_deg"][a] <= v * (1.0 + 1e-9), (a, before, after)
    first_full = next(s for s, d in zip(sig, determined) if len(d) == 3)
    assert sig[-1]["worst_deg"] < first_full["worst_deg"]
    # "calibrate now" ran mls calib run on the session: its result, within 3σ of the truth
    outcome = record["outcome"]
    session = Path(outcome.out_dir).parent
    assert (
        session.parent == demo.out / "run" / "sessions" and (Path(outcome.out_dir) / "result.json").is_file()
    )
    truth = json.loads((demo.out / "run" / "scenario_truth.json").read_text())
    for r in comparison_rows(outcome.result, truth):
        assert abs(r.error_sigmas) <= 3, r


# -- the demo's own result ----------------------------------------------------------------------


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.xdist_group("demo")
def test_demo_recovers_the_boresight_within_3_sigma_and_leaves_no_process(demo):
    try:
        rc = demo.p.wait(400)
    except subprocess.TimeoutExpired:
        raise AssertionError(f"mls demo still running after 400 s:\n{demo.output()[-3000:]}") from None
    text = demo.output()
    assert rc == 0, text[-3000:]
    assert left_behind(demo.p.pid) == []
    flat = " ".join(text.split())
    accepted = re.findall(r"✔ pass (\d) \((\d+)°\) accepted: hits T1 \d+, T2 \d+", flat)
    assert [(int(i), int(h)) for i, h in accepted] == list(zip(range(1, 7), RELATIVE_HEADINGS))
    assert "6/6 passes accepted live" in flat and "✘" not in flat
    assert "recovered within 3σ (realistic) of the truth on every angle" in flat
    out = demo.out
    paths = {k: Path(v) for k, v in re.findall(r"^(result\.json|report\.md)\s+(\S+)$", text, re.M)}
    assert paths == {"result.json": out / "calib" / "result.json", "report.md": out / "calib" / "report.md"}
    assert all(p.is_file() for p in paths.values())
    plots = [Path(p) for p in re.findall(r"^plot\s+(\S+)$", text, re.M)]
    assert {p.name for p in plots} == {
        "residuals_by_pass.png",
        "residuals_by_plane.png",
        "residuals_time.png",
        "target_T1.png",
        "target_T2.png",
        "tie_patches.png",  # the default GLS adds planar patches of the quay wall
    }
    assert all(p.is_file() and p.stat().st_size > 10_000 for p in plots)
    wall = re.search(r"wall time (\d+\.\d) s\s*$", text)
    assert wall and float(wall.group(1)) < 180
    # the table's numbers are the result's, next to the truth the devices were fed
    result = json.loads(paths["result.json"].read_text())
    truth = json.loads((out / "run" / "scenario_truth.json").read_text())
    rows = comparison_rows(result, truth)
    for r in rows:
        name = r.angle if r.convention == "canonical" else f"thesis {r.angle}"
        assert (
            f"{name} {r.truth_deg:+.4f} {r.recovered_deg:+.4f} {r.error_deg:+.4f} "
            f"{r.sigma_formal_deg:.4f} {r.sigma_realistic_deg:.4f} {r.error_sigmas:+.2f}"
        ) in flat
        assert abs(r.error_deg) <= 3 * r.sigma_realistic_deg, r
    assert truth["boresight_deg"] == {"roll": 0.208, "pitch": 1.245, "yaw": 0.149}
    # every step left its log; the bundle holds the six passes
    assert {p.name for p in (out / "logs").iterdir()} == {
        "devices.log",
        "acquire.log",
        "export.log",
        "calib.log",
    }
    assert [p["id"] for p in result["passes"]] == [1, 2, 3, 4, 5, 6]


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.xdist_group("demo")
def test_the_demo_session_exports_for_foxglove_and_reads_back(demo, tmp_path):
    """``mls export SESSION --foxglove`` on the demo's recorded session: the read-back check of
    ``test_foxglove.py``, and every return of the demo's bundle (its own export and georeference)
    in the clouds, where calib puts it."""
    import numpy as np
    from scipy.spatial import cKDTree

    from acquire.log.read import iter_messages
    from calib.core.georef import georeference
    from calib.io.bundle import read_bundle
    from tests.office.jobs.test_foxglove import check_foxglove_file

    try:
        rc = demo.p.wait(400)
    except subprocess.TimeoutExpired:
        raise AssertionError(f"mls demo still running after 400 s:\n{demo.output()[-3000:]}") from None
    assert rc == 0, demo.output()[-3000:]
    (session,) = (demo.out / "run" / "sessions").iterdir()
    out = tmp_path / "demo.mcap"
    r = subprocess.run(
        [*MLS, "export", str(session), "--foxglove", str(out)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    flat = " ".join(r.stdout.split())
    m = re.search(
        r"([\d,]+) messages on 6 channels, [\d.]+ s from .*?; ([\d,]+) of ([\d,]+) returns in", flat
    )
    assert m, flat
    rb = check_foxglove_file(out, session)
    assert int(m.group(1).replace(",", "")) == sum(len(v) for v in rb.messages.values())
    assert m.group(2) == m.group(3)  # at 2 Hz no cloud of the demo is decimated
    assert len(rb.messages["/vessel/fix"]) > 5000 and len(rb.messages["/lidar/points"]) >= 20
    assert len(rb.messages["/clock"]) > 50 and len(rb.messages["/latency"]) > 50
    assert rb.messages["/clock"][-1][1]["state"] == "LOCKED"
    assert {"ins", "profiler"} <= set(rb.messages["/latency"][-1][1])
    levels = {m["level"] for _, m in rb.messages["/log"]}
    assert "INFO" in levels
    # every alarm the demo happened to raise or clear is one Log (check_foxglove_file matches each
    # to its event), and no Log claims an alarm the session does not hold; how many alarms a demo
    # raises depends on the host's timing, so their number is not asserted
    alarms = [e for e in iter_messages(session, {"/events"}) if e.payload.get("event") == "alarm"]
    assert sum(m["message"].startswith("alarm ") for _, m in rb.messages["/log"]) == len(alarms)
    # the bundle's returns, georeferenced by calib, are points of the clouds (within 1 mm)
    b = read_bundle(demo.out / "bundle")
    pts = b.points
    x_ned = georeference(pts.t_gps_s, pts.range_m, pts.scan_angle_rad, b.trajectory, b.site.mount)
    x_enu = np.column_stack([x_ned[:, 1], x_ned[:, 0], -x_ned[:, 2]])
    clouds = [rb.points(k)[0] for k in range(len(rb.messages["/lidar/points"]))]
    dist, _ = cKDTree(np.concatenate(clouds)).query(x_enu)
    assert dist.max() < 1e-3, dist.max()
    assert len(pts) >= 0.9 * sum(len(c) for c in clouds)  # the clouds are (mostly) the passes


# -- interrupted and failing runs ---------------------------------------------------------------


def _start_and_wait_for_the_daemon(tmp_path: Path, *args: str) -> tuple[DemoProcess, dict, dict]:
    """A demo whose daemon runs and which follows the survey."""
    demo = start_demo(tmp_path, *args)
    status = wait_for(lambda: daemon_status(demo.out), 90, "the daemon", demo)
    wait_for(lambda: "watch it with: mls checklist" in demo.output(), 30, "the survey", demo)
    devices = json.loads((demo.out / "run" / "devices.json").read_text())
    return demo, status, devices


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.xdist_group("demo")
def test_ctrl_c_stops_every_child_and_closes_the_session(tmp_path):
    from acquire.log.read import iter_messages

    demo, status, devices = _start_and_wait_for_the_daemon(tmp_path)
    pids = [status["pid"], devices["pid"], *devices["processes"].values()]
    try:
        assert all(os.path.exists(f"/proc/{p}") for p in pids)
        # a terminal's Ctrl-C signals the foreground process group: the demo's own, not the
        # children's (each in its own group)
        os.killpg(demo.p.pid, signal.SIGINT)
        rc = demo.p.wait(60)
        text = " ".join(demo.output().split())
        assert rc == 130, text
        assert "mls demo: interrupted (SIGINT); every child process was stopped" in text
        assert left_behind(demo.p.pid) == [] and not any(os.path.exists(f"/proc/{p}") for p in pids)
        # the daemon was stopped in order: its session ends with session_end (SIGTERM)
        (session,) = (demo.out / "run" / "sessions").iterdir()
        ends = [m.payload for m in iter_messages(session, {"/events"}) if m.payload["event"] == "session_end"]
        assert [e["reason"] for e in ends] == ["SIGTERM"]
    finally:
        demo.kill_all()


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.xdist_group("demo")
def test_a_failed_step_is_named_with_its_log_and_leaves_no_process(tmp_path):
    demo, status, devices = _start_and_wait_for_the_daemon(tmp_path)
    try:
        os.killpg(status["pid"], signal.SIGKILL)  # the daemon dies in the middle of the survey
        rc = demo.p.wait(60)
        text = " ".join(demo.output().split())
        assert rc == 1, text
        assert (
            "mls demo failed at step acquisition daemon (mls acquire): ended during the survey (exit code -9)"
        ) in text
        assert f"its log: {demo.out / 'logs' / 'acquire.log'}; all logs: {demo.out / 'logs'}" in text
        assert left_behind(demo.p.pid) == []
        assert not any(os.path.exists(f"/proc/{p}") for p in devices["processes"].values())
    finally:
        demo.kill_all()
    # a second demo in the same directory starts from an empty one; a bad scenario override
    # fails at the devices' step, with their log
    again = start_demo(tmp_path, "--set", "scanner.colour=red", log_name="again.log")
    try:
        rc = again.p.wait(60)
        text = " ".join(again.output().split())
        assert rc == 1, text
        assert (
            "mls demo failed at step simulated devices (mls sim devices): mls sim devices ended with exit code 2"
            in text
        )
        assert "unknown key 'colour'" in text
        assert f"its log: {again.out / 'logs' / 'devices.log'}" in text
        assert sorted(p.name for p in again.out.iterdir()) == [
            ".mls-demo",
            "logs",
        ]  # the first run's are gone
        assert left_behind(again.p.pid) == []
    finally:
        again.kill_all()
