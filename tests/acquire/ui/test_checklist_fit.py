"""Nothing the operator must read is cut: every screen state of ``mls checklist`` (the scripted
survey's: pre-checks failing and green, each pass captured / accepted / rejected, the details
dialogs, the calibration result and its failure; plus five long alarms with a device that does
not connect, its OS errors in a failing pre-check; and a lost link), rendered at 80 × 24 and at
120 × 40, read back from the compositor's lines. For each state:

- no line is wider than the terminal;
- every text widget shows all of its text (whitespace aside: wrapping only moves it); a
  scrolled dialog is read through its whole height;
- what the widgets were given is in them whole: each check's label (or its short form from
  :data:`acquire.ui.fit.SHORT_FORMS`) with its detail, else counted in the "n more" row; each
  rejection reason; the header's words; the guidance line; every alarm message and check in
  the details; the calibration figures and directory;
- each frame is intact: its top and bottom borders run corner to corner with nothing but the
  border and its title, its sides are unbroken (a dialog's hint sits inside its frame).
"""

from __future__ import annotations

import asyncio
import io
import re

import pytest
from rich.cells import cell_len
from rich.console import Console
from rich.text import Text
from textual._border import BORDER_CHARS
from textual.containers import ScrollableContainer
from textual.widgets import Footer, Static

from acquire.status.feed import LINK
from acquire.ui.checklist_app import CalibrationOutcome, ChecklistApp, TextScreen
from acquire.ui.fit import SHORT_FORMS, abbreviations
from acquire.ui.panels import render_result
from tests.acquire.guidance_sim import run_survey
from tests.acquire.ui.test_checklist_app import _failing

SIZES = [(80, 24), (120, 40)]
HEAVY_BOX = "━┃┏┓┗┛┣┫┳┻╋┡┩╇"
LONG_ALARMS = [
    (
        "device_unavailable",
        "profiler",
        "the profiler at 192.168.1.20:8110 does not answer: [Errno 113] No route to host; "
        "retrying every 5 s (37 attempts so far)",
    ),
    (
        "disk_low",
        "writer",
        "/srv/mls/sessions: 1.8 GiB free, below the 2 GiB floor; the session stops recording "
        "in about 4 minutes at the current rate",
    ),
    (
        "time_ambiguous",
        "clock",
        "the INS and the PPS labels disagree by exactly one second: the GPS-UTC offset is "
        "ambiguous until the next leap second announcement is received",
    ),
    (
        "leap_table_stale",
        "clock",
        "the leap-second table /usr/share/zoneinfo/leap-seconds.list expired on 2025-06-28; "
        "update the tzdata package",
    ),
    (
        "host_clock_step",
        "host",
        "the host clock stepped by -2.41 s (chrony or an operator set it); the clock model "
        "restarted its fit and holds its last estimate",
    ),
]
OS_ERROR = (
    "ins: [Errno 111] Connect call failed ('192.168.1.10', 8110); "
    "profiler: [Errno 113] Connect call failed ('192.168.1.20', 8110)"
)


class _Idle:
    """A feed that yields nothing: the test puts the messages in the state itself."""

    def __aiter__(self):
        return self

    async def __anext__(self):
        await asyncio.Event().wait()


def _squash(s: str) -> str:
    return re.sub(r"\s+", "", s)


def _screen_lines(app) -> list[list[str]]:
    """The screen as the compositor draws it (what export_screenshot draws), one list of cells a
    line (a wide character's second cell is "")."""
    w, h = app.size
    con = Console(width=w, height=h, file=io.StringIO(), record=True, legacy_windows=False, safe_box=False)
    con.print(app.screen._compositor.render_update(full=True, screen_stack=app._background_screens))
    lines = con.export_text().splitlines()
    assert len(lines) == h, f"{len(lines)} lines on a {h}-line terminal"
    for ln in lines:
        assert cell_len(ln) <= w, f"a line wider than {w} cells: {ln!r}"
    return [[c for ch in ln for c in ((ch,) if cell_len(ch) < 2 else (ch, ""))] for ln in lines]


def _crop(lines, region) -> list[str]:
    return ["".join(ln[region.x : region.right]) for ln in lines[region.y : region.bottom]]


def _content_text(w: Static, width: int) -> str:
    """What the widget was given, as text (a table or group rendered at the widget's width)."""
    c = w.content
    if isinstance(c, Text):
        return c.plain
    if isinstance(c, str):
        return c
    con = Console(width=width, file=io.StringIO(), record=True)
    con.print(c)
    return con.export_text()


def _check_frame(w, lines) -> None:
    """Top and bottom borders corner to corner, nothing in them but the border and its title;
    the sides unbroken."""
    edge = w.styles.border_top[0]
    (tl, t, tr), (ll, _, rr), (bl, b, br) = BORDER_CHARS[edge]
    r = w.region
    rows = _crop(lines, r)
    for row, (c0, mid, c1), label in (
        (rows[0], (tl, t, tr), w.border_title),
        (rows[-1], (bl, b, br), w.border_subtitle),
    ):
        assert row[0] == c0 and row[-1] == c1, f"{w}: border corners broken: {row!r}"
        inner = row[1:-1]
        if label:
            assert f" {label} " in inner, f"{w}: border title {label!r} cut: {row!r}"
            inner = inner.replace(f" {label} ", "", 1)
        assert set(inner) <= {mid}, f"{w}: border line broken: {row!r}"
    for row in rows[1:-1]:
        assert row[0] == ll and row[-1] == rr, f"{w}: side border broken: {row!r}"


async def _scrolled_text(pilot, scroll: ScrollableContainer) -> str:
    """The whole height of a scrolled container's content, read screen by screen."""
    region = scroll.scrollable_content_region  # without the scrollbar
    rows: dict[int, str] = {}
    for y in range(0, int(scroll.max_scroll_y) + 1):
        scroll.scroll_to(y=y, animate=False)
        await pilot.pause()
        for i, row in enumerate(_crop(_screen_lines(pilot.app), region)):
            rows[int(scroll.scroll_y) + i] = row
    scroll.scroll_to(y=0, animate=False)
    return "\n".join(rows[k] for k in sorted(rows))


async def _check_screen(pilot, expect: list[str]) -> str:
    """The checks of the module docstring on the active screen; ``expect``: texts that must be
    in it whole (whitespace aside), each a list of alternatives joined by "|" (short forms).
    Returns the screen's text."""
    app = pilot.app
    lines = _screen_lines(app)
    screen_text = "\n".join("".join(ln) for ln in lines)
    shown = {}
    for w in app.screen.query("*"):
        if not w.display or not w.region.area:
            continue
        if w.styles.border_top[0] not in ("", "none", "hidden"):
            _check_frame(w, lines)
        if isinstance(w, Static):
            scroll = next((a for a in w.ancestors if isinstance(a, ScrollableContainer)), None)
            if scroll is not None and scroll.max_scroll_y > 0:
                text = await _scrolled_text(pilot, scroll)
                assert "scroll" in _content_text(app.screen.query_one("#modal-hint", Static), 80)
            else:
                text = "\n".join(_crop(lines, w.content_region))
            given = _content_text(w, w.content_region.width)
            assert _squash(given) in _squash(text), f"#{w.id} cut:\n{given}\n--- shown:\n{text}"
            shown[w.id] = text
        if isinstance(w, Footer):
            for b in app.active_bindings.values():
                if b.binding.show:
                    assert b.binding.description in screen_text, f"footer: {b.binding.description!r} cut"
    everything = _squash("\n".join(shown.values()) + screen_text)
    for e in expect:
        alts = e.split("|")
        assert any(_squash(a) in everything for a in alts), f"not shown whole: {alts}\n{screen_text}"
    return screen_text


def _alarms(app) -> list[dict]:
    return (app.state.topics.get("status") or {}).get("alarms") or []


def _expected_main(app) -> list[str]:
    """What the main screen must show whole, from the messages it was given."""
    st = app.state
    status, clock = st.topics.get("status") or {}, st.topics.get("clock") or {}
    out = []
    if status:
        out += ["|".join(abbreviations(f"{status['vessel']} daemon {status['state']}"))]
    if clock.get("state"):
        out += ["|".join(abbreviations(f"clock {clock['state']}"))]
    if n := len(status.get("alarms") or []):
        out += ["|".join(abbreviations(f"{n} alarm{'s' if n > 1 else ''}"))]
    out += ["|".join(abbreviations("● link" if st.link_up else "○ no link"))]
    g = st.checklist
    for p in g.get("passes") or []:
        if (
            p.get("reasons")
            and (g.get("active") or {}).get("pass_id") == p["id"]
            and p["status"] == "rejected"
        ):
            out.append(p["reasons"][0])  # on the row, under it, or in the guidance
    a = g.get("active")
    if a and "along_m" in a:
        c0, c1 = a["capture_m"]
        to = a["to_capture_m"]
        prog = (
            f"{max(a['along_m'] - c0, 0):.0f}/{c1 - c0:.0f} m"
            if a["state"] == "capture"
            else f"window in {to:.0f} m"
            if to >= 0
            else "window passed"
        )
        out.append(
            "|".join(
                abbreviations(f"pass {a['pass_id']} hdg {a['heading_deg']:.0f}° {a['state'].upper()} {prog}")
            )
        )
        out += [f"{name} {n}" for name, n in (a.get("hits") or {}).items()]
    return out


def _check_prechecks(app) -> None:
    """Each check whole (label or short form, then the detail), or counted in the last row."""
    text = _squash(app.query_one("#prechecks").content.plain)
    checks = app.state.checks()
    whole = [
        c
        for c in checks
        if any(_squash(lab + str(c.get("detail", ""))) in text for lab in abbreviations(str(c["label"])))
    ]
    m = re.search(r"(\d+)more", text)
    assert len(whole) + (int(m.group(1)) if m else 0) == len(checks), (len(whole), text)


def _check_passes(app) -> None:
    """Each pass's row, or counted in an "n more" row; each rejection reason whole, or "why: ⏎"
    on its row (too long for it: Enter shows it, the guidance the active pass's)."""
    text = app.query_one("#passes").content.plain
    rows = {int(r[1:3]): r for r in text.splitlines() if r[0] in "▶ " and r[1:3].strip().isdigit()}
    more = sum(int(n) for n in re.findall(r"[↑↓] (\d+) more", text))
    passes = app.state.checklist.get("passes") or []
    assert len(rows) + more == len(passes), text
    for p in passes:
        if p["id"] in rows and p.get("reasons"):
            assert _squash(p["reasons"][0]) in _squash(text) or rows[p["id"]].endswith(" why: ⏎"), text


def _alarm_state(survey) -> list[tuple[str, dict]]:
    presurvey, failing = _failing(survey)
    presurvey = {
        "devices_connected": {"ok": False, "detail": OS_ERROR},
        "receive_buffer": {"ok": True, "detail": "profiler socket buffer 32.0 MiB"},
        **presurvey,
    }
    alarms = [{"severity": "critical", "name": n, "device": d, "message": m} for n, d, m in LONG_ALARMS]
    return [
        ("status", {"state": "running", "vessel": "sim-montreal", "alarms": alarms}),
        ("clock", {"state": "HOLDOVER"}),
        ("checklist", {"presurvey": presurvey, "guidance": {**survey.stages[0][1], "prechecks": failing}}),
    ]


RESULT = {
    "boresight_deg": {"roll": 0.1937, "pitch": 1.2424, "yaw": 0.1355},
    "sigma_realistic_deg": {"roll": 0.0354, "pitch": 0.1077, "yaw": 0.0472},
    "sigma_deg": {"roll": 0.0026, "pitch": 0.0071, "yaw": 0.0024},
    "chi2_test": {"passed": False},
    "sigma0_squared": 0.36,
    "n_points": 4097,
    "iterations": 5,
    "runtime_s": 0.09,
}
OUT_DIR = (
    "/tmp/pytest-of-root/pytest-38/popen-gw0/demo0/demo-out/run/sessions/"
    "20261202T095607Z_sim-montreal/calib-20261202T095716Z"
)
CALIB_ERROR = (
    "mls calib run exited with 2: extract: pass 3: target T2: 12 points on the plane, fewer than "
    "the 50 the fit needs / adjust: the yaw is not observable from passes 1, 2 / see "
    f"{OUT_DIR}/calib.log"
)


@pytest.mark.parametrize("size", SIZES, ids=lambda s: f"{s[0]}x{s[1]}")
def test_no_text_is_cut_in_any_screen_state(size):
    survey = run_survey(3, holdover_pass=3)
    presurvey, failing = _failing(survey)
    green = {
        "receive_buffer": {"ok": True, "detail": "profiler socket buffer 32.0 MiB"},  # "Rcv buf" at 80
        **presurvey,
        "ins_pps": {"ok": True, "detail": "INS time source: UTC+PPS"},
    }
    status = {"state": "running", "vessel": "sim-montreal", "session": "s", "alarms": []}
    pps_alarm = {
        "severity": "critical",
        "name": "pps_flag_lost",
        "device": "ins",
        "message": "the INS reports no PPS",
    }
    start = survey.stages[0][1]
    # (name, messages, dialogs to open on it)
    states = [
        ("no-link", [(LINK, {"up": False, "detail": "/run/mls/status.sock: [Errno 2] No such file"})], ["d"]),
        (
            "prechecks-failing",
            [
                ("status", {**status, "alarms": [pps_alarm]}),
                ("clock", {"state": "UNLOCKED"}),
                ("checklist", {"presurvey": presurvey, "guidance": {**start, "prechecks": failing}}),
            ],
            ["d"],
        ),
        ("long-alarms", _alarm_state(survey), ["d"]),
        (
            "prechecks-green",
            [
                ("status", status),
                ("clock", {"state": "LOCKED"}),
                ("checklist", {"presurvey": green, "guidance": start}),
            ],
            [],
        ),
    ]
    for name, msg in survey.stages[1:]:
        states.append(
            (
                name,
                [
                    ("status", status),
                    ("clock", {"state": "LOCKED"}),
                    ("checklist", {"presurvey": green, "guidance": msg}),
                ],
                ["enter"] if name == "pass-3-rejected" else [],
            )
        )
    states[-1][2].extend(["result", "failure"])

    async def main():
        app = ChecklistApp(_Idle())
        async with app.run_test(size=size) as pilot:
            await pilot.pause()
            for name, msgs, dialogs in states:
                app.state = type(app.state)()
                app.state.apply(LINK, {"up": True, "detail": "test"})
                for topic, data in msgs:
                    app.state.apply(topic, data)
                app.selected = 0
                app.refresh_view()
                await pilot.pause()
                await pilot.pause()
                try:
                    await _check_screen(pilot, _expected_main(app))
                    _check_prechecks(app)
                    _check_passes(app)
                except AssertionError as e:
                    raise AssertionError(f"{name} at {size}: {e}") from None
                for dialog in dialogs:
                    if dialog == "d":
                        app.action_check_details()
                        expect = [f"{c['label']}: {c['detail']}" for c in app.state.checks()]
                        expect += [f"alarm {a['name']} ({a['device']}): {a['message']}" for a in _alarms(app)]
                    elif dialog == "enter":
                        app.selected = next(
                            i for i, p in enumerate(app.state.checklist["passes"]) if p["reasons"]
                        )
                        app.action_pass_details()
                        expect = ["✘ " + r for r in app.state.checklist["passes"][app.selected]["reasons"]]
                    elif dialog == "result":
                        outcome = CalibrationOutcome(True, "calibrated", RESULT, OUT_DIR)
                        app.push_screen(TextScreen("calibration result", render_result(outcome)))
                        expect = [
                            "+1.2424",
                            "0.1077",
                            "0.0071",
                            "(χ² FAILED)",
                            "4097 points",
                            "0.09 s",
                            OUT_DIR,
                        ]
                    else:
                        app.push_screen(
                            TextScreen(
                                "calibration result", render_result(CalibrationOutcome(False, CALIB_ERROR))
                            )
                        )
                        expect = [CALIB_ERROR]
                    for _ in range(3):
                        await pilot.pause()
                    try:
                        assert isinstance(app.screen, TextScreen)
                        text = await _check_screen(pilot, expect)
                        # the hint inside the frame, not over it; box lines of one weight (a
                        # heavy head on a light table is drawn with broken joints)
                        frame = _crop(_screen_lines(app), app.screen.query_one("#modal").region)
                        assert any("Esc to close" in r[1:-1] for r in frame[1:-1]), frame
                        assert "Esc" not in frame[0] + frame[-1], frame
                        assert not set(text) & set(HEAVY_BOX), text
                    except AssertionError as e:
                        raise AssertionError(f"{name}, dialog {dialog} at {size}: {e}") from None
                    app.pop_screen()
                    await pilot.pause()

    asyncio.run(main())


def test_short_forms_are_used_only_when_the_width_demands_them():
    from acquire.ui.fit import abbreviate

    assert abbreviate("Receive buffer", 14) == "Receive buffer"
    assert abbreviate("Receive buffer", 13) == "Rcv buf"
    assert all(cell_len(short) < cell_len(long) for long, short in SHORT_FORMS)


def test_passes_that_do_not_fit_are_counted_around_the_selected_one():
    from acquire.ui.checklist_app import ChecklistState, render_passes

    reason = "too few target points (T1: 12, T2: 40; need 100)"
    passes = [
        {
            "id": i,
            "relative_heading_deg": 45.0 * i,
            "status": "rejected" if i == 3 else "accepted" if i < 3 else "pending",
            "reasons": [reason] if i == 3 else [],
            "hits": {"T1": 5, "T2": 6},
        }
        for i in range(1, 10)
    ]
    st = ChecklistState()
    st.apply("checklist", {"guidance": {"passes": passes, "active": {"pass_id": 3, "state": "approach"}}})
    for selected in range(9):
        lines = render_passes(st, selected, width=38, rows=7).plain.splitlines()
        assert len(lines) <= 7 and all(cell_len(ln) <= 38 for ln in lines)
        ids = [int(r[1:3]) for r in lines if r[0] in "▶ " and r[1:3].strip().isdigit()]
        hidden = sum(int(n) for n in re.findall(r"[↑↓] (\d+) more", "\n".join(lines)))
        assert selected + 1 in ids and len(ids) + hidden == 9, lines
    assert render_passes(st, 0, 38, 7).plain.splitlines()[3].endswith("rejected      5     6 why: ⏎")
    # room for it: the reason whole under its pass
    text = render_passes(st, 0, 38, 13).plain
    assert "▶ 3  135 rejected      5     6\n    too few target points (T1: 12, T2:\n    40; need 100)" in text
