"""The console against the real thing (issue 28): ``mls sim devices`` (the demo's montreal survey
at ×1, the INS unplugged for 2 s between the first and the second capture window) → the real
``mls acquire`` with a ``web`` section → Debian's Chromium under Playwright.

One observer page follows the whole survey with the plan's ``follow`` off, so the vessel moves
across a fixed plan; the page records what each render drew (``window.mlsConsole.history``), so
each test below reads the part of the survey it needs whatever order the tests run in. Other pages
take the screenshots (1920×1080, a bridge monitor; 1024×768, a tablet: kept in
``$MLS_SCREENSHOT_DIR``, default ``tests/screenshots/``) and try the actions.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import socket
import textwrap
import time
import urllib.request
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import pytest
from playwright.sync_api import Page

from tests.acquire.daemon_util import MLS, Proc, free_port, wait_until
from tests.waiting import wait_until as wait_for

# realtime: the simulated devices run at ×1 (the clock model locks only on a PPS once per host
# second, and the guidance accepts a pass only with the clock LOCKED), so every wait below is on
# the survey's own pace; browser: Chromium
pytestmark = [pytest.mark.realtime, pytest.mark.integration, pytest.mark.browser, pytest.mark.slow]

SHOTS = Path(os.environ.get("MLS_SCREENSHOT_DIR") or Path(__file__).resolve().parents[2] / "screenshots")
TOKEN = "bridge-console-test-token"
UNPLUG_AT_S, UNPLUG_S = 15.0, 2.0  # between pass 1's capture window (8-14 s) and pass 2's
SURVEY_S = 150.0  # the survey (~87 s) and the start, with room on a loaded machine
DRAWN = "window.mlsConsole.drawn !== null && window.mlsConsole.sigmaPoints > 0"
SIZES = {"bridge": (1920, 1080), "tablet": (1024, 768)}


@dataclass
class Live:
    url: str
    vessel: str
    sessions: Path
    daemon: Proc
    page: Page  # the observer
    foxglove_port: int


def _devices(tmp: Path, run: Path, config: Path) -> Proc:
    from office.jobs.demo import DemoSettings, scenario_overrides

    faults = tmp / "faults.yaml"
    faults.write_text(f"faults:\n  - {{at_s: {UNPLUG_AT_S}, kind: serial_unplug, duration_s: {UNPLUG_S}}}\n")
    settings = DemoSettings(out=tmp, line_m=14.0, pass_gap_s=6.0)
    return Proc(
        [
            *MLS,
            *("sim", "devices", "--scenario", "montreal", "--speed", "1"),
            *("--devices", "ins,profiler,pps", "--run-dir", str(run), "--faults", str(faults)),
            *("--write-config", str(config), "--lead-s", "4"),
            *(a for o in scenario_overrides(settings) for a in ("--set", o)),
        ],
        tmp / "devices.log",
    )


def _add_web_section(config: Path, port: int, foxglove_port: int) -> None:
    token = config.parent / "web-token.yaml"
    token.write_text(f"token: {TOKEN}\n")
    token.chmod(0o600)
    with config.open("a") as f:
        f.write(
            textwrap.dedent(f"""\
            web:
              port: {port}
              credentials_file: {token.name}
              foxglove_port: {foxglove_port}
            """)
        )


def _complete(config: Path) -> bool:
    from acquire.daemon.config import VesselConfigError, load_vessel_config
    from calib.io.configfile import ConfigError

    try:
        return config.is_file() and load_vessel_config(config).site_file is not None
    except (VesselConfigError, ConfigError, OSError):
        return False


def _serving(url: str) -> bool:
    try:
        with urllib.request.urlopen(url + "api/session", timeout=2) as r:
            return r.status == 200
    except OSError:
        return False


@pytest.fixture(scope="module")
def live(tmp_path_factory, chromium):
    tmp = tmp_path_factory.mktemp("console")
    run, config = tmp / "run", tmp / "vessel.yaml"
    procs: list[Proc] = []
    try:
        devices = _devices(tmp, run, config)
        procs.append(devices)
        wait_until(lambda: _complete(config), 120, "the simulated devices' vessel config", devices)
        port, foxglove_port = free_port(socket.SOCK_STREAM), free_port(socket.SOCK_STREAM)
        _add_web_section(config, port, foxglove_port)
        from acquire.daemon.config import load_vessel_config

        cfg = load_vessel_config(config)
        daemon = Proc([*MLS, "acquire", "--config", str(config)], tmp / "daemon.log")
        procs.append(daemon)
        url = f"http://127.0.0.1:{port}/"
        wait_until(lambda: _serving(url), 60, "the console", daemon)
        page = chromium.new_page(viewport={"width": 1920, "height": 1080})
        page.goto(url)
        page.uncheck("#follow")  # a fixed plan: the vessel moves across it
        yield Live(url, cfg.vessel, cfg.session_dir, daemon, page, foxglove_port)
    finally:
        for p in reversed(procs):
            p.signal(signal.SIGTERM)
            try:
                p.wait(30)
            except Exception:  # noqa: BLE001 — killed below whatever went wrong
                p.kill()


def _history(live: Live) -> list[dict]:
    return live.page.evaluate("window.mlsConsole.history")


def test_the_page_loads_with_the_daemons_state(live):
    page = live.page
    wait_for(lambda: page.text_content("#vessel") == live.vessel, 30, "the vessel's name on the page")
    wait_for(lambda: page.locator("#devices tbody tr").count() == 3, 30, "the three devices")
    assert page.text_content("#link") == "live"
    assert page.text_content("#mode") == "read-only"
    assert page.locator("button.act").first.is_disabled()


def test_foxglove_live_serves_every_channel_of_the_survey(live):
    """A WebSocket client subscribed to every channel the daemon's Foxglove server advertises
    receives each, the fixes where the survey is."""
    from acquire.foxglove.channels import TOPICS
    from tests.foxglove_client import FoxgloveClient

    async def receive() -> FoxgloveClient:
        client = await FoxgloveClient.connect(f"ws://127.0.0.1:{live.foxglove_port}")
        try:
            end = time.monotonic() + SURVEY_S
            while client.topics() != set(TOPICS) and time.monotonic() < end:
                await client.poll(0.5)
        finally:
            await client.close()
        return client

    with ThreadPoolExecutor(1) as pool:  # Playwright's sync API holds this thread's event loop
        client = pool.submit(asyncio.run, receive()).result()
    assert client.topics() == set(TOPICS), f"only {sorted(client.topics())}"
    fix = client.messages["/vessel/fix"][-1][1]
    assert abs(fix["latitude"] - 45.5) < 0.1 and abs(fix["longitude"] + 73.55) < 0.1  # montreal
    assert all(len(m["data"]) // 16 <= 50_000 for _, m in client.messages["/lidar/points"])
    assert any(c["state"] in ("LOCKED", "HOLDOVER", "UNLOCKED") for _, c in client.messages["/clock"])


def test_the_vessel_moves_on_the_plan(live):
    def moved() -> bool:
        drawn = [h for h in _history(live) if h["x"] is not None]
        return len(drawn) > 1 and any(
            abs(h["x"] - drawn[0]["x"]) + abs(h["y"] - drawn[0]["y"]) > 20 for h in drawn
        )

    wait_for(moved, SURVEY_S, "the vessel to move 20 px on the plan", interval_s=0.5)
    canvas = live.page.locator("#plan")
    assert int(canvas.get_attribute("data-frames")) > 1


def test_a_pass_is_accepted_and_the_sigma_plot_grows_a_point(live):
    def grew() -> bool:
        h = _history(live)
        return bool(h) and max(x["sigma_points"] for x in h) > h[0]["sigma_points"] and h[-1]["accepted"] >= 1

    wait_for(grew, SURVEY_S, "an accepted pass and a new point of the predicted σ", interval_s=0.5)
    page = live.page
    assert page.locator('#passes tr[data-status="accepted"]').count() >= 1
    assert int(page.get_attribute("#sigma", "data-points")) >= 1


def test_an_alarm_appears_when_the_ins_is_unplugged_and_clears_when_it_is_back(live):
    key = "device_unavailable/ins"

    def raised_and_cleared() -> bool:
        seen = [key in h["alarms"].split() for h in _history(live)]
        return True in seen and False in seen[seen.index(True) :]

    wait_for(raised_and_cleared, SURVEY_S, f"{key} raised and cleared on the page", interval_s=0.5)


def test_screenshots_at_a_bridge_monitor_and_a_tablet_size(live, chromium):
    wait_for(lambda: _history(live)[-1]["accepted"] >= 4, SURVEY_S, "four accepted passes", interval_s=0.5)
    SHOTS.mkdir(parents=True, exist_ok=True)
    for name, (w, h) in SIZES.items():
        page = chromium.new_page(viewport={"width": w, "height": h})
        page.goto(live.url)
        wait_for(  # (the page's CSP forbids Playwright's string predicates: evaluated from here)
            partial(page.evaluate, DRAWN),
            30,
            f"the {name} page drawn",
            interval_s=0.2,
        )
        path = SHOTS / f"console-{name}-{w}x{h}.png"
        page.screenshot(path=str(path))
        assert path.stat().st_size > 10_000
        page.close()


def _web_events(sessions: Path) -> list[dict]:
    """The ``/events`` entries with ``source: web`` in the complete chunks of the live session."""
    from mcap.records import Channel, Message

    from acquire.log.recover import scan_segment, segment_paths

    out = []
    for session in sorted(p for p in sessions.iterdir() if p.is_dir()):
        for path in segment_paths(session):
            channels: dict[int, str] = {}
            for rec in scan_segment(path):
                if isinstance(rec, Channel):
                    channels[rec.id] = rec.topic
                elif isinstance(rec, Message) and channels.get(rec.channel_id) == "/events":
                    doc = json.loads(rec.data)["data"]  # the envelope's data: the event
                    if doc.get("source") == "web":
                        out.append(doc)
    return out


def test_an_action_without_the_token_is_refused_and_with_it_recorded_in_the_session(live, chromium):
    page = chromium.new_page(viewport={"width": 1024, "height": 768})
    page.goto(live.url)
    status = page.evaluate(
        """async () => (await fetch('/api/action/mark', {method: 'POST',
             body: JSON.stringify({text: 'no token'})})).status"""
    )
    assert status == 401
    page.fill("#token", "not-the-operator-token")
    page.click("#token-use")
    page.fill("#mark-text", "wrong token")
    page.click("#mark")
    page.wait_for_selector('#action-result[data-code="403"]')
    assert page.text_content("#mode") == "read-only"  # a refused token is forgotten
    page.fill("#token", TOKEN)
    page.click("#token-use")
    page.fill("#mark-text", "quay wall seen from the bridge")
    page.click("#mark")
    page.wait_for_selector('#action-result[data-status="ok"]')
    wait_for(
        lambda: [e for e in _web_events(live.sessions) if e["event"] == "mark"],
        30,
        "the mark in the session's /events",
        interval_s=0.5,
    )
    marks = [e for e in _web_events(live.sessions) if e["event"] == "mark"]
    assert [m["text"] for m in marks] == ["quay wall seen from the bridge"]
    refused = [e for e in _web_events(live.sessions) if e["event"] == "command_refused"]
    assert refused == []  # a missing or wrong token is refused before the command's checks
    page.close()
