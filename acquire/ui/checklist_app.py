"""``mls checklist``: the operator's screen during the calibration survey (docs/architecture.md §8), a Textual
app that fits an 80 × 24 terminal and works over SSH.

It reads the daemon's status bus (:mod:`acquire.status.feed`: the local socket by default, MQTT
when asked) and shows

- the pre-survey checks with pass/fail and the reason (the ``checklist`` message's
  ``prechecks``, made by :func:`acquire.guidance.prechecks.prechecks` in the daemon);
- the passes with their status (pending, capturing, accepted, rejected) and the first reason
  of a rejection (Enter on a pass shows them all);
- a braille plan view of the active line, its capture window, the targets and the vessel;
- live cross-track error (with the side to steer), heading error, speed, progress, range to the
  targets and target hits;
- the predicted boresight σ of the accepted passes and the pass that would help most;
- "calibrate now" (``c``): runs the injected calibrator (by default ``mls calib run`` on the
  session, in a worker thread) and shows the result.

Everything drawn comes from pure functions of the latest messages and of each panel's size
(:class:`ChecklistState` and the ``render_*`` functions of :mod:`acquire.ui.panels`), so the
screen is testable without a terminal. Nothing is cut (:mod:`acquire.ui.fit`): a label too wide
takes a short form from a fixed table, free text (details, alarm messages, OS errors, reasons)
wraps, a dialog taller than the terminal scrolls.
"""

from __future__ import annotations

import datetime as _dt
import json
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from rich.text import Text
from textual.app import App, ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical, VerticalScroll
from textual.screen import ModalScreen
from textual.widgets import Footer, Static
from textual.worker import Worker, WorkerState

from acquire.ui.panels import (
    LIVE_ROWS,
    PASS_ROWS,
    PRECHECK_ROWS,
    ChecklistState,
    render_check_details,
    render_header,
    render_live,
    render_passes,
    render_prechecks,
    render_result,
    render_sigma,
)
from acquire.ui.planview import render_plan
from calib.boresight.checks.verdict import REFUSED_EXIT_STATUS

# =============================================================================================
# Calibration runner
# =============================================================================================


@dataclass(frozen=True)
class CalibrationOutcome:
    ok: bool
    message: str
    result: dict | None = None  # result.json
    out_dir: str | None = None


Calibrator = Callable[[str | None], CalibrationOutcome]


def run_calib_cli(session: str | None) -> CalibrationOutcome:
    """The default calibrator: ``mls calib run SESSION --out SESSION/calib-<UTC>`` in a
    subprocess, then its ``result.json``."""
    if not session:
        return CalibrationOutcome(
            False,
            "no session directory: the daemon publishes none in "
            "its status; start mls checklist with --session DIR",
        )
    stamp = _dt.datetime.now(_dt.UTC).strftime("%Y%m%dT%H%M%SZ")
    out = Path(session) / f"calib-{stamp}"
    cmd = [sys.executable, "-m", "cli.app", "calib", "run", str(session), "--out", str(out)]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=3600)
    except (OSError, subprocess.TimeoutExpired) as e:
        return CalibrationOutcome(False, f"mls calib run failed to run: {e}")
    if proc.returncode not in (0, REFUSED_EXIT_STATUS):  # a refused result is shown with its reasons
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        return CalibrationOutcome(False, f"mls calib run exited with {proc.returncode}: " + " / ".join(tail))
    try:
        result = json.loads((out / "result.json").read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        return CalibrationOutcome(False, f"{out / 'result.json'}: {e}", out_dir=str(out))
    return CalibrationOutcome(True, str(result.get("verdict", "calibrated")), result, str(out))


# =============================================================================================
# The app
# =============================================================================================


class TextScreen(ModalScreen):
    """A modal with one renderable, scrolled when taller than the terminal; its hint line
    inside the frame. Escape or Enter closes it."""

    BINDINGS = [Binding("escape,enter,q", "dismiss", "close")]
    DEFAULT_CSS = """
    TextScreen { align: center middle; }
    TextScreen > #modal { width: 76; max-width: 100%; height: auto; max-height: 100%;
                          border: thick $accent; padding: 0 1; background: $surface; }
    TextScreen #modal-scroll { height: auto; }
    TextScreen #modal-body { height: auto; }
    TextScreen #modal-hint { height: 1; width: 100%; text-align: right; color: $text-muted; }
    """
    HINT, SCROLL_HINT = "Esc to close", "↑/↓ scroll · Esc to close"

    def __init__(self, title: str, body, name: str | None = None):
        super().__init__(name=name)
        self._title, self._body = title, body

    def compose(self) -> ComposeResult:
        with Vertical(id="modal") as frame:
            frame.border_title = self._title
            with VerticalScroll(id="modal-scroll"):
                yield Static(self._body, id="modal-body")
            yield Static(self.HINT, id="modal-hint")

    def on_mount(self) -> None:
        self._fit()

    def on_resize(self, event) -> None:
        self._fit()

    def _fit(self) -> None:
        """The body's room: the terminal less the frame and the hint line."""
        self.query_one("#modal-scroll").styles.max_height = max(self.size.height - 3, 1)
        self.call_after_refresh(self._hint)

    def _hint(self) -> None:
        scroll = self.query_one("#modal-scroll", VerticalScroll)
        self.query_one("#modal-hint", Static).update(
            self.SCROLL_HINT if scroll.max_scroll_y > 0 else self.HINT
        )


class ChecklistApp(App):
    """See the module docstring. ``feed`` is an async-iterable of ``(topic, data)``
    (:class:`acquire.status.feed.SocketFeed` or :class:`~acquire.status.feed.MqttFeed`);
    ``calibrator(session_dir) -> CalibrationOutcome`` runs "calibrate now" (in a thread);
    ``session`` overrides the session the daemon reports, ``session_root`` is the directory
    its session names are under (the vessel config's ``session.directory``)."""

    TITLE = "mls checklist"
    CSS = """
    Screen { layout: vertical; }
    #header { height: 1; background: $boost; }
    #body { height: 1fr; }
    #left { width: 40; }
    #right { width: 1fr; }
    .box { border: round $primary-darken-1; padding: 0 0; text-wrap: nowrap;
           text-overflow: ellipsis; }
    #header { text-wrap: nowrap; text-overflow: ellipsis; }
    #prechecks { height: 9; }
    #passes { height: 9; }
    #sigma { height: 1fr; }
    #plan { height: 1fr; }
    #live { height: 8; }
    """
    BINDINGS = [
        Binding("c", "calibrate", "calibrate now"),
        Binding("up,k", "move(-1)", "pass ↑", show=False),
        Binding("down,j", "move(1)", "pass ↓", show=False),
        Binding("enter", "pass_details", "pass details"),
        Binding("d", "check_details", "checks"),
        Binding("q", "quit", "quit"),
    ]

    def __init__(
        self,
        feed,
        calibrator: Calibrator = run_calib_cli,
        session: str | None = None,
        session_root: str | None = None,
    ):
        super().__init__()
        self.feed = feed
        self.calibrator = calibrator
        self.session = session
        self.session_root = session_root
        self.state = ChecklistState()
        self.selected = 0
        self.messages_seen = 0
        self.calibration: CalibrationOutcome | None = None
        self._calibrating = False

    def compose(self) -> ComposeResult:
        yield Static(id="header")
        with Horizontal(id="body"):
            with Vertical(id="left"):
                yield Static(id="prechecks", classes="box")
                yield Static(id="passes", classes="box")
                yield Static(id="sigma", classes="box")
            with Vertical(id="right"):
                yield Static(id="plan", classes="box")
                yield Static(id="live", classes="box")
        yield Footer()

    def on_mount(self) -> None:
        titles = {
            "prechecks": "pre-survey",
            "passes": "passes",
            "sigma": "predicted σ",
            "plan": "plan view",
            "live": "guidance",
        }
        for wid, title in titles.items():
            self.query_one(f"#{wid}", Static).border_title = title
        self.refresh_view()
        self.run_worker(self._consume(), name="feed", exclusive=True)

    async def _consume(self) -> None:
        async for topic, data in self.feed:
            self.state.apply(topic, data)
            self.messages_seen += 1
            self.refresh_view()

    # -- drawing ----------------------------------------------------------------------------

    def refresh_view(self) -> None:
        if not self.is_running:  # shutting down: the widgets are being removed
            return
        st = self.state
        header = self.query_one("#header", Static)
        header.update(render_header(st, header.size.width or self.size.width))
        pre = self.query_one("#prechecks", Static)
        pre.update(render_prechecks(st, pre.size.width or 38, pre.size.height or PRECHECK_ROWS))
        checks = st.checks()
        n_ok = sum(bool(c.get("ok")) for c in checks)
        pre.border_subtitle = f"{n_ok}/{len(checks)} ok" if checks else ""
        passes = st.checklist.get("passes") or []
        self.selected = min(self.selected, max(len(passes) - 1, 0))
        ps = self.query_one("#passes", Static)
        ps.update(render_passes(st, self.selected, ps.size.width or 38, ps.size.height or PASS_ROWS))
        ps.border_subtitle = f"{st.checklist.get('accepted', 0)}/{len(passes)} accepted"
        sig = self.query_one("#sigma", Static)
        sig.update(
            Text("calibrating…", "bold yellow")
            if self._calibrating
            else render_sigma(st, sig.size.width or 38, sig.size.height or 3)
        )
        live = self.query_one("#live", Static)
        live.update(render_live(st, live.size.width or 38, live.size.height or LIVE_ROWS))
        plan_w = self.query_one("#plan", Static)
        plan = st.checklist.get("plan")
        if plan:
            w = max(plan_w.size.width, 10)
            h = max(plan_w.size.height, 4)
            active = (st.checklist.get("active") or {}).get("pass_id")
            text, m_per_dot = render_plan(plan, st.checklist.get("vessel"), active, w, h)
            plan_w.update(text)
            plan_w.border_subtitle = f"N↑ {m_per_dot:.2g} m/dot"
        else:
            plan_w.update(Text("no plan yet", "dim"))

    def on_resize(self, event) -> None:
        """A taller or wider terminal gives the left column's panels more room (80 × 24: the
        CSS sizes), then each panel is drawn again for its new size."""
        w, h = self.size
        self.query_one("#left").styles.width = 40 if w < 100 else min(w * 2 // 5, 60)
        self.query_one("#prechecks").styles.height = 9 + max(h - 24, 0) // 2
        self.query_one("#passes").styles.height = 9 + max(h - 24, 0) // 4
        self.refresh_view()
        self.call_after_refresh(self.refresh_view)

    # -- actions ----------------------------------------------------------------------------

    def action_move(self, step: int) -> None:
        self.selected = max(self.selected + step, 0)
        self.refresh_view()

    def action_pass_details(self) -> None:
        passes = self.state.checklist.get("passes") or []
        if not passes:
            return
        p = passes[self.selected]
        body = Text()
        body.append(
            f"pass {p['id']} ({p['relative_heading_deg']:.0f}° to the wall, heading "
            f"{p['heading_deg']:.1f}°): {p['status']}, {p['attempts']} attempt(s)\n",
            "bold",
        )
        for r in p.get("reasons") or []:
            body.append(f"✘ {r}\n", "red")
        for k, v in (p.get("stats") or {}).items():
            if not k.startswith("t_"):
                body.append(f"  {k}: {v}\n")
        for name, n in (p.get("hits") or {}).items():
            body.append(f"  hits {name}: {n}\n")
        body.rstrip()
        self.push_screen(TextScreen(f"pass {p['id']}", body))

    def action_check_details(self) -> None:
        body = render_check_details(self.state)
        self.push_screen(TextScreen("pre-survey checks", body if body.plain else "no checks yet"))

    def action_calibrate(self) -> None:
        if self._calibrating:
            self.notify("a calibration is already running")
            return
        self._calibrating = True
        self.refresh_view()
        session = self.session or self.state.session_dir(self.session_root)
        self.run_worker(lambda: self.calibrator(session), name="calibrate", thread=True, exit_on_error=False)

    def on_worker_state_changed(self, event: Worker.StateChanged) -> None:
        w = event.worker
        if w.name != "calibrate" or event.state not in (WorkerState.SUCCESS, WorkerState.ERROR):
            return
        self._calibrating = False
        if event.state == WorkerState.SUCCESS:
            self.calibration = w.result
        else:
            self.calibration = CalibrationOutcome(False, f"{type(w.error).__name__}: {w.error}")
        self.refresh_view()
        self.push_screen(TextScreen("calibration result", render_result(self.calibration)))
