"""``mls checklist``, headless: the Textual app in an 80×24 terminal reads a status
stream from a real Unix socket (:class:`acquire.status.bus.StatusServer`). The stream is the
guidance's own output over a simulated survey (:mod:`tests.acquire.guidance_sim`): pre-checks
fail, then go green; the passes are sailed one by one (one is rejected when the clock drops to
HOLDOVER and is sailed again at the end) and the predicted σ shrinks; "calibrate now" runs an
injected calibrator (the real adjustment of the simulated returns) and shows its result.

An SVG screenshot of each stage goes to ``$MLS_SCREENSHOT_DIR`` (default ``tests/screenshots/``).
"""

from __future__ import annotations

import asyncio
import math
import os
from dataclasses import replace
from pathlib import Path

import pytest
from rich.console import Console

from acquire.guidance.prechecks import prechecks
from acquire.status.bus import StatusBus, StatusServer
from acquire.status.feed import SocketFeed
from acquire.ui.checklist_app import CalibrationOutcome, ChecklistApp, run_calib_cli
from acquire.ui.panels import ChecklistState, render_live, render_passes, render_prechecks, render_sigma
from acquire.ui.planview import render_plan
from calib.boresight.result import result_to_dict
from drivers.hydrins.nav import status_words
from tests.acquire.guidance_sim import adjust_simulated, run_survey

SHOTS = Path(os.environ.get("MLS_SCREENSHOT_DIR") or Path(__file__).resolve().parents[2] / "screenshots")


@pytest.fixture(scope="module")
def survey():
    return run_survey(3, holdover_pass=3)


def _plain(app, wid: str) -> str:
    return app.query_one(wid).content.plain


async def _until(pilot, cond, what: str, timeout_s: float = 10.0) -> None:
    for _ in range(int(timeout_s / 0.05)):
        if cond():
            return
        await pilot.pause(0.05)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


def _calibrator(survey, calls: list):
    """The injected "calibrate now": the real adjustment of the simulated returns."""

    def run(session):
        calls.append(session)
        res = adjust_simulated(survey.sim)
        mount = survey.sim.site.mount
        return CalibrationOutcome(
            True, "calibrated", result_to_dict(res, mount.boresight_rad, "test"), f"{session}/calib"
        )

    return run


def _failing(survey) -> tuple[dict, list]:
    """The daemon's presurvey section and the guidance's checks before the INS is aligned and
    the clock locked."""
    alg, sys_ = status_words(alignment=True, gps_received=True, gps_valid=True, utc_detected=True)
    aligning = replace(survey.guidance.last_nav, algorithm_status=alg, system_status=sys_)
    checks = prechecks(
        aligning,
        {"state": "UNLOCKED", "last_edge_age_s": None},
        {
            "ins": {"latency_mean_ms": 12.0, "latency_p99_ms": 14.0},
            "profiler": {"latency_mean_ms": 3.0, "latency_p99_ms": 4.5},
        },
        {"ins": (0.0, 30.0), "profiler": (0.0, 20.0)},
        free_bytes=80 * 10**9,
        needed_bytes=10 * 10**9,
        mount_configured=True,
        n_targets=2,
    )
    presurvey = {
        "profiler_data": {"ok": True, "detail": "63 profiles/s"},
        "ins_pps": {"ok": False, "detail": "INS time source: none"},
    }
    return presurvey, [c.as_dict() for c in checks]


def test_checklist_app_through_a_simulated_survey(survey, tmp_path):
    SHOTS.mkdir(parents=True, exist_ok=True)
    index = SHOTS / "index.txt"
    if index.exists():  # the previous run's screenshots (their names may change)
        for name in index.read_text().split():
            (SHOTS / name).unlink(missing_ok=True)
    shots: list[str] = []
    calls: list = []
    sock = tmp_path / "status.sock"
    stages = survey.stages

    async def main():
        server = StatusServer(sock)
        await server.start()
        bus = StatusBus([server])
        status = {
            "state": "running",
            "vessel": "sim-montreal",
            "session": "20190709T140000Z_sim-montreal",
            "alarms": [],
        }
        alarm = {
            "severity": "critical",
            "name": "pps_flag_lost",
            "device": "ins",
            "message": "the INS reports no PPS",
        }
        bus.publish("status", {**status, "alarms": [alarm]})
        bus.publish("clock", {"state": "UNLOCKED"})
        presurvey, failing = _failing(survey)
        start = dict(stages[0][1])
        bus.publish("checklist", {"presurvey": presurvey, "guidance": {**start, "prechecks": failing}})
        app = ChecklistApp(
            SocketFeed(sock), calibrator=_calibrator(survey, calls), session_root=str(tmp_path)
        )

        def shot(name: str) -> None:
            fname = f"{len(shots) + 1:02d}-{name}.svg"
            app.save_screenshot(fname, str(SHOTS))
            shots.append(fname)

        async with app.run_test(size=(80, 24)) as pilot:
            # 1. pre-checks fail, each with its reason, failing ones first
            await _until(pilot, lambda: len(app.state.checks()) == 9, "the pre-survey checks")
            text = _plain(app, "#prechecks")
            assert text.splitlines()[0].startswith("✘ ")
            assert "INS nav+fine  aligning" in text and "Clock LOCKED  UNLOCKED" in text
            assert "PPS locked    no PPS: INS, no edges" in text
            assert "INS PPS+UTC   INS time source: none" in text
            assert text.splitlines()[-1].startswith("✔ 3 more ok")
            assert "clock UNLOCKED" in _plain(app, "#header") and "1 alarm" in _plain(app, "#header")
            shot("prechecks-failing")
            await pilot.press("d")  # every check in full, and the active alarms
            await _until(pilot, lambda: len(app.screen_stack) > 1, "the checks in full")
            body = app.screen.query_one("#modal-body").content.plain
            assert "✘ PPS locked: no PPS: INS, no edges" in body
            assert "✔ Disk space: 80 GB free ≥ 10 GB" in body
            assert "critical alarm pps_flag_lost (ins): the INS reports no PPS" in body
            shot("prechecks-details")
            await pilot.press("escape")
            await _until(pilot, lambda: len(app.screen_stack) == 1, "details closed")
            bus.publish("status", status)
            # 2. the daemon locks the clock, the INS aligns: all green
            bus.publish("clock", {"state": "LOCKED"})
            presurvey["ins_pps"] = {"ok": True, "detail": "INS time source: UTC+PPS"}
            bus.publish("checklist", {"presurvey": presurvey, "guidance": start})
            await _until(pilot, lambda: all(c["ok"] for c in app.state.checks()), "green checks")
            text = _plain(app, "#prechecks")
            # "INS time source: UTC+PPS" wraps under itself: one check fewer fits, summed up
            assert "✘" not in text and text.count("✔") == 6 and "4 more ok" in text
            assert "INS PPS+UTC   INS time source:\n                UTC+PPS" in text
            assert "pass 1" in _plain(app, "#live")
            shot("prechecks-green")
            # 3. the passes, one by one
            worst, determined, accepted = [], [], 0
            for name, msg in stages[1:]:
                bus.publish("checklist", {"presurvey": presurvey, "guidance": msg})
                await _until(
                    pilot,
                    lambda msg=msg: (
                        app.state.checklist is not None
                        and app.state.checklist.get("passes") == msg["passes"]
                        and app.state.checklist.get("active") == msg["active"]
                    ),
                    name,
                )
                pid = int(name.split("-")[1])
                live, passes = _plain(app, "#live"), _plain(app, "#passes")
                row = next(r for r in passes.splitlines()[1:] if r[1:3].strip() == str(pid))
                if name.endswith("capture"):
                    assert f"pass {pid}" in live and "CAPTURE" in live
                    assert "XTE" in live and "hits T1" in live
                    assert "capturing" in row
                elif name.endswith("rejected"):
                    # the reason is too long for the row: the guidance shows it whole, until the
                    # pass is sailed again
                    assert "rejected" in row and row.endswith(" why: ⏎")
                    assert "✘ clock HOLDOVER during the window\n  (must stay LOCKED)" in live
                else:
                    accepted += 1
                    assert "accepted" in row
                    assert _plain(app, "#sigma").startswith(f"σ({accepted})")
                    assert app.query_one("#passes").border_subtitle == f"{accepted}/6 accepted"
                    cur = msg["sigma"]["current"]
                    worst.append(cur["worst_deg"] if cur["worst_deg"] is not None else math.inf)
                    determined.append(sum(cur["observable"].values()))
                shot(name)
                if name == "pass-3-rejected":
                    await pilot.press("down", "down", "enter")  # the rejected pass's details
                    await _until(
                        pilot,
                        lambda: app.screen.id != "_default" and len(app.screen_stack) > 1,
                        "pass details",
                    )
                    body = app.screen.query_one("#modal-body").content.plain
                    assert "pass 3" in body and "✘ clock HOLDOVER during the window" in body
                    shot("pass-3-details")
                    await pilot.press("escape")
                    await _until(pilot, lambda: len(app.screen_stack) == 1, "details closed")
            assert accepted == 6
            # the predicted σ: never worse after a pass; once every angle is determined, smaller
            # after each accepted pass; every angle determined at the end
            assert determined == sorted(determined) and determined[-1] == 3
            assert all(b <= a for a, b in zip(worst, worst[1:]))
            finite = [w for w in worst if math.isfinite(w)]
            assert len(finite) >= 3 and all(b < a for a, b in zip(finite, finite[1:]))
            sig = _plain(app, "#sigma")
            assert "n/o" not in sig and "ready: press c to calibrate" in sig
            # 4. calibrate now
            await pilot.press("c")
            await _until(pilot, lambda: app.calibration is not None, "the calibration")
            await _until(
                pilot,
                lambda: (
                    len(app.screen_stack) > 1
                    and app.screen.query("#modal-body")
                    and app.screen.query_one("#modal-body").region.height > 0
                ),
                "the result screen",
            )
            await pilot.pause(0.2)  # laid out: let it paint before the screenshot
            assert calls == [str(tmp_path / "20190709T140000Z_sim-montreal")]
            res = app.calibration.result
            table = app.screen.query_one("#modal-body").content
            con = Console(width=80, record=True)
            con.print(table)
            out = con.export_text()
            for a in ("roll", "pitch", "yaw"):
                assert f"{res['boresight_deg'][a]:+.4f}" in out
                assert f"{res['sigma_realistic_deg'][a]:.4f}" in out
            assert "χ²" in out
            shot("calibration-result")
            await pilot.press("escape")
        await server.close()

    asyncio.run(main())
    assert len(shots) == 3 + (len(stages) - 1) + 2
    for f in shots:
        assert (SHOTS / f).stat().st_size > 5000
    index.write_text("\n".join(shots) + "\n")


def test_calibrate_now_failures_are_shown(tmp_path):
    async def main():
        sock = tmp_path / "s.sock"
        server = StatusServer(sock)
        await server.start()

        def broken(session):
            raise RuntimeError("no bundle in the session")

        app = ChecklistApp(SocketFeed(sock), calibrator=broken)
        async with app.run_test(size=(80, 24)) as pilot:
            await pilot.press("c")
            await _until(pilot, lambda: app.calibration is not None, "the calibration")
            await _until(pilot, lambda: len(app.screen_stack) > 1, "the result screen")
            body = app.screen.query_one("#modal-body").content.plain
            assert body == "calibration failed: RuntimeError: no bundle in the session"
        await server.close()

    asyncio.run(main())
    out = run_calib_cli(None)
    assert not out.ok and "start mls checklist with --session" in out.message


def test_app_shows_a_lost_link(tmp_path):
    async def main():
        app = ChecklistApp(SocketFeed(tmp_path / "nobody.sock"))
        async with app.run_test(size=(80, 24)) as pilot:
            await _until(pilot, lambda: "no link" in _plain(app, "#header"), "the link state")
            assert "waiting for the daemon" in _plain(app, "#prechecks")
            assert app.state.link_detail.startswith(str(tmp_path / "nobody.sock"))

    asyncio.run(main())


def test_a_message_arriving_while_the_app_closes_is_ignored(tmp_path):
    """The feed runs until the app is torn down; a message it yields after the widgets are gone
    must not fail the app (Textual would re-raise it from run_test / on exit)."""

    async def main():
        app = ChecklistApp(SocketFeed(tmp_path / "nobody.sock"))
        async with app.run_test(size=(80, 24)) as pilot:
            await _until(pilot, lambda: "no link" in _plain(app, "#header"), "the link state")
        app.state.apply("status", {"state": "stopped"})
        app.refresh_view()  # what the feed worker does with it: nothing, quietly

    asyncio.run(main())


# -- the pure rendering ---------------------------------------------------------------------------


def test_render_live_tells_the_side_to_steer(survey):
    msg = dict(next(m for n, m in survey.stages if n == "pass-2-capture"))
    st = ChecklistState()
    for xte, word in ((1.4, "steer L"), (-0.8, "steer R"), (0.02, "on line")):
        st.apply("checklist", {**msg, "active": {**msg["active"], "xte_m": xte}})
        assert word in render_live(st).plain
    st.apply("checklist", {**msg, "active": {**msg["active"], "xte_m": 2.5}})
    text = render_live(st)
    span = next(s for s in text.spans if "red" in str(s.style))
    assert text.plain[span.start : span.end].strip() == "+2.50 m"  # beyond the 2 m tolerance


def test_render_passes_and_sigma_before_anything_is_sailed(survey):
    st = ChecklistState()
    assert render_passes(st).plain == "no pass plan yet"
    assert render_sigma(st).plain == "σ after the first accepted pass"
    st.apply("checklist", survey.stages[0][1])
    rows = render_passes(st).plain.splitlines()
    assert len(rows) == 7 and rows[1].startswith("▶ 1    0 pending")
    sig = render_sigma(st).plain
    assert sig.startswith("σ(0) no pass accepted yet") and "next best: pass " in sig


def test_a_sigma_that_rose_with_the_last_pass_is_marked():
    st = ChecklistState()
    st.apply(
        "checklist",
        {
            "guidance": {
                "sigma": {
                    "current": {
                        "passes": [1, 2, 3],
                        "rose": ["roll"],
                        "realistic_deg": {"roll": 0.062, "pitch": 0.04, "yaw": None},
                    }
                }
            }
        },
    )
    assert render_sigma(st).plain.splitlines()[0] == "σ(3) r 0.062°↑ p 0.040° y n/o"


def test_the_weakest_angle_and_the_pass_that_helps_it_are_shown():
    st = ChecklistState()
    weakest = {"angle": "yaw", "realistic_deg": 0.0312, "best_pass": 7, "best_deg": 0.0145}
    sigma = {"current": {"passes": [1, 2], "realistic_deg": {"roll": 0.01, "pitch": 0.02, "yaw": 0.0312}}}
    st.apply("checklist", {"guidance": {"sigma": {**sigma, "weakest": weakest}}})
    assert render_sigma(st, width=60).plain.splitlines()[-1] == "weakest yaw 0.031°: pass 7 → 0.015°"
    assert "weakest" not in render_sigma(st, width=60, rows=2).plain  # a panel of two rows: not cut, left out
    st.apply("checklist", {"guidance": {"sigma": {**sigma, "weakest": {**weakest, "best_pass": None}}}})
    assert "weakest" not in render_sigma(st, width=60).plain  # nothing left to sail


def test_prechecks_overflow_is_summed_up():
    st = ChecklistState()
    st.apply("checklist", {"presurvey": {f"c{i}": {"ok": i != 4, "detail": f"d{i}"} for i in range(10)}})
    lines = render_prechecks(st).plain.splitlines()
    assert len(lines) == 7 and lines[0].startswith("✘ c4")
    assert lines[-1] == "✔ 4 more ok — d: all"


def test_plan_view_draws_the_vessel_where_it_is():
    plan = {
        "passes": [{"id": 1, "start_ne_m": [0.0, 0.0], "end_ne_m": [0.0, 76.0], "capture_m": [30.0, 40.0]}],
        "targets": [
            {
                "name": "T1",
                "center_ne_m": [15.0, 38.0],
                "corners_ne_m": [[15.0, 37.0], [15.0, 39.0], [15.5, 39.0], [15.5, 37.0]],
            }
        ],
    }
    text, m = render_plan(plan, {"n_m": -2.0, "e_m": 10.0, "heading_deg": 90.0}, 1, 38, 10)
    lines = text.plain.splitlines()
    assert len(lines) == 10 and all(len(ln) == 38 for ln in lines)
    # the east-west line is one row of braille; the targets lie north of it, the vessel south

    def row_of(style):
        return {text.plain[: s.start].count("\n") for s in text.spans if s.style == style}

    assert max(row_of("bold red")) < min(row_of("cyan")) <= max(row_of("bold yellow"))
    # 76 m of east span over 2 × 38 dots, with an 8 % margin each side
    assert m == pytest.approx(1.16)
