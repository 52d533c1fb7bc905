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

Everything drawn comes from pure functions of the latest messages (:class:`ChecklistState` and
the ``render_*`` functions), so the screen is testable without a terminal.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rich.table import Table
from rich.text import Text
from textual.app import App, ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.screen import ModalScreen
from textual.widgets import Footer, Static
from textual.worker import Worker, WorkerState

from acquire.status.feed import LINK, SNAPSHOT_END, guidance_of
from acquire.ui.planview import render_plan

OK, FAIL, WAIT = "✔", "✘", "…"
#: Short labels of the daemon's pre-survey check names (acquire.daemon.reports.StatusReports.presurvey).
CHECK_LABELS = {
    "ins_navigating": "INS nav+fine",
    "gnss_fix": "GNSS fix",
    "ins_pps": "INS PPS+UTC",
    "pps_locked": "PPS locked",
    "profiler_data": "Profiler data",
    "clock_locked": "Clock LOCKED",
    "latency_in_band": "Latency",
    "disk_space": "Disk space",
    "mount_configured": "Mount",
    "mount_targets": "Mount+targets",
}
PRECHECK_ROWS = 7
STATUS_STYLE = {"accepted": "green", "rejected": "red", "capturing": "yellow", "pending": "dim"}


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
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        return CalibrationOutcome(False, f"mls calib run exited with {proc.returncode}: " + " / ".join(tail))
    try:
        result = json.loads((out / "result.json").read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        return CalibrationOutcome(False, f"{out / 'result.json'}: {e}", out_dir=str(out))
    return CalibrationOutcome(True, "calibrated", result, str(out))


# =============================================================================================
# State and rendering (pure)
# =============================================================================================


@dataclass
class ChecklistState:
    """The latest message of each status topic (``alarms`` included: the active ones are in
    ``status``)."""

    topics: dict[str, Any] = field(default_factory=dict)
    link_up: bool = False
    link_detail: str = "connecting"

    def apply(self, topic: str, data: Any) -> None:
        if topic == LINK:
            self.link_up = bool(data.get("up"))
            self.link_detail = str(data.get("detail", ""))
        elif topic == SNAPSHOT_END:
            return
        else:
            self.topics[topic] = data

    @property
    def checklist(self) -> dict:
        """The guidance message (:meth:`acquire.guidance.state.Guidance.message`): the ``checklist``
        topic itself, or its ``guidance`` section when the daemon publishes sections."""
        return guidance_of(self.topics.get("checklist"))

    def checks(self) -> list[dict]:
        """The pre-survey checks: the daemon's ``presurvey`` section (``{name: {ok, detail}}``)
        merged with the guidance's own ``prechecks`` (a list; same name: the guidance's wins,
        it knows the plan)."""
        c = self.topics.get("checklist") or {}
        merged: dict[str, dict] = {}
        for name, v in (c.get("presurvey") or {}).items():
            if isinstance(v, dict):
                merged[name] = {
                    "name": name,
                    "label": CHECK_LABELS.get(name, name.replace("_", " ")),
                    "ok": v.get("ok"),
                    "detail": str(v.get("detail", "")),
                }
        for v in self.checklist.get("prechecks") or []:
            merged[v.get("name", v.get("label", "?"))] = dict(v)
        return list(merged.values())

    def session_dir(self, root: str | None = None) -> str | None:
        """The session directory "calibrate now" works on: the daemon's ``status.session``
        (a directory name, under ``root`` when given)."""
        s = (self.topics.get("status") or {}).get("session")
        if isinstance(s, dict):
            s = s.get("dir") or s.get("path")
        if not s:
            return None
        p = Path(str(s))
        return str(p if p.is_absolute() or root is None else Path(root) / p)


def _fmt(v, spec: str, unit: str = "", none: str = "—") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return none
    return f"{v:{spec}}{unit}"


def render_header(st: ChecklistState) -> Text:
    status = st.topics.get("status") or {}
    clock = st.topics.get("clock") or {}
    vessel = status.get("vessel") or st.checklist.get("vessel_name") or "?"
    state = status.get("state", "—")
    t = Text(no_wrap=True, overflow="ellipsis")
    t.append(" mls checklist ", "bold reverse")
    t.append(f" {vessel} ")
    t.append(f"daemon {state} ", "red" if state == "lost" else "")
    cs = clock.get("state")
    if cs:
        t.append(f"clock {cs} ", "green" if cs == "LOCKED" else "red")
    n_alarms = len(status.get("alarms") or [])
    if n_alarms:
        t.append(f"{n_alarms} alarm{'s' if n_alarms > 1 else ''} ", "bold red")
    t.append("● link" if st.link_up else "○ no link", "green" if st.link_up else "bold red")
    return t


def render_prechecks(st: ChecklistState, width: int = 38, rows: int = PRECHECK_ROWS) -> Text:
    """The checks, failing ones first; what does not fit is summed up in the last row."""
    checks = st.checks()
    t = Text(no_wrap=True, overflow="ellipsis")
    if not checks:
        t.append("waiting for the daemon's checklist…", "dim")
        return t
    shown = sorted(checks, key=lambda c: c.get("ok") is True)  # stable: failing first
    if len(shown) > rows:
        rest = shown[rows - 1 :]
        shown = shown[: rows - 1]
    else:
        rest = []
    for i, c in enumerate(shown):
        mark, style = (
            (OK, "green") if c.get("ok") else (WAIT, "yellow") if c.get("ok") is None else (FAIL, "bold red")
        )
        label = str(c.get("label", c.get("name", "?")))[:13]
        t.append(f"{mark} ", style)
        t.append(f"{label:<13} ", "bold" if not c.get("ok") else "")
        t.append(str(c.get("detail", ""))[: max(width - 16, 0)], "" if c.get("ok") else style)
        if i < len(shown) - 1 or rest:
            t.append("\n")
    if rest:
        n_ok = sum(c.get("ok") is True for c in rest)
        t.append(
            f"{OK} {n_ok} more ok"
            if n_ok == len(rest)
            else f"… {len(rest)} more ({len(rest) - n_ok} not ok)",
            "green" if n_ok == len(rest) else "yellow",
        )
        t.append(" — d: all", "dim")
    return t


def render_passes(st: ChecklistState, selected: int = 0) -> Text:
    passes = st.checklist.get("passes") or []
    active = (st.checklist.get("active") or {}).get("pass_id")
    t = Text(no_wrap=True, overflow="ellipsis")
    if not passes:
        t.append("no pass plan yet", "dim")
        return t
    names = list((passes[0].get("hits") or {}).keys()) or [
        x["name"] for x in (st.checklist.get("plan") or {}).get("targets", [])
    ]
    t.append(f"  # rel°  status    {' '.join(n[:5].rjust(5) for n in names[:2])}\n", "dim")
    for i, p in enumerate(passes):
        style = STATUS_STYLE.get(p.get("status"), "")
        arrow = "▶" if p["id"] == active else " "
        row = Text(f"{arrow}{p['id']:>2} {p['relative_heading_deg']:>4.0f} ")
        row.append(f"{p.get('status', '?'):<9}", style)
        hits = p.get("hits") or {}
        row.append(" " + " ".join(str(hits.get(n, "·")).rjust(5) for n in names[:2]))
        reasons = p.get("reasons") or []
        if reasons:
            row.append(" " + reasons[0], "red")
        if i == selected:
            row.stylize("reverse")
        t.append_text(row)
        if i < len(passes) - 1:
            t.append("\n")
    return t


def _sigma_line(d: dict | None) -> str:
    if not d:
        return "—"
    r = d.get("realistic_deg") or {}
    rose = set(d.get("rose") or ())  # ↑: the last pass made this angle's realistic σ larger
    parts = [
        f"{a[0]} {_fmt(r.get(a), '.3f', '°', 'n/o')}" + ("↑" if a in rose else "")
        for a in ("roll", "pitch", "yaw")
    ]
    return " ".join(parts)


def render_sigma(st: ChecklistState) -> Text:
    sig = st.checklist.get("sigma")
    t = Text(no_wrap=True, overflow="ellipsis")
    if not sig:
        t.append("σ after the first accepted pass", "dim")
        return t
    cur = sig.get("current") or {}
    n = len(cur.get("passes") or [])
    t.append(f"σ({n}) ", "bold")
    t.append(_sigma_line(cur) if n else "no pass accepted yet")
    nb = sig.get("next_best")
    t.append("\n")
    if nb:
        plan = {p["id"]: p for p in (st.checklist.get("plan") or {}).get("passes", [])}
        rel = plan.get(nb["pass_id"], {}).get("relative_heading_deg")
        t.append("next best: ", "dim")
        t.append(f"pass {nb['pass_id']}" + (f" ({rel:.0f}°)" if rel is not None else ""), "bold")
        worst = nb.get("worst_deg")
        t.append(
            f" → σ ≤ {worst:.3f}°" if worst is not None else f" → {3 - nb.get('undetermined', 3)}/3 angles"
        )
    elif st.checklist.get("calibration_ready"):
        t.append("ready: press c to calibrate", "bold green")
    return t


def render_live(st: ChecklistState) -> Text:
    a = st.checklist.get("active")
    v = st.checklist.get("vessel")
    tol = st.checklist.get("tolerances") or {}
    t = Text(no_wrap=True, overflow="ellipsis")
    if not a:
        t.append("all passes accepted" if st.checklist.get("passes") else "no active pass", "dim")
        return t
    state = a.get("state", "approach")
    t.append(f"pass {a['pass_id']} ", "bold")
    if "heading_deg" in a:
        t.append(f"hdg {a['heading_deg']:.0f}° ")
    t.append(state.upper(), "bold yellow" if state == "capture" else "cyan")
    if "along_m" in a:
        c0, c1 = a.get("capture_m", (0, 0))
        to_window = a.get("to_capture_m", 0.0)
        if state == "capture":
            t.append(f" {max(a['along_m'] - c0, 0):.0f}/{c1 - c0:.0f} m")
        elif to_window >= 0:
            t.append(f" window in {to_window:.0f} m")
        else:
            t.append(" window passed")
        xte = a["xte_m"]
        bad = abs(xte) > tol.get("max_xte_m", math.inf)
        t.append("\nXTE ")
        t.append(f"{xte:+6.2f} m", "bold red" if bad else "bold green")
        t.append(f" steer {'L' if xte > 0 else 'R'}" if abs(xte) >= 0.05 else " on line")
        he = a["heading_error_deg"]
        t.append("\nHDG err ")
        t.append(
            f"{he:+5.1f}°", "bold red" if abs(he) > tol.get("max_heading_error_deg", 1e9) else "bold green"
        )
        sp, plan_sp = a.get("speed_mps"), a.get("planned_speed_mps")
        t.append("  SOG ")
        bad_sp = (
            plan_sp is not None
            and sp is not None
            and abs(sp - plan_sp) > tol.get("max_speed_error_mps", math.inf)
        )
        t.append(_fmt(sp, ".2f", " m/s"), "bold red" if bad_sp else "bold green")
        t.append(f"\nrange to targets {a.get('range_to_targets_m', math.nan):.1f} m")
        hits = a.get("hits")
        if hits:
            need = tol.get("min_points_per_target", 0)
            t.append("\nhits ")
            for name, n in hits.items():
                t.append(f"{name} ")
                t.append(f"{n} ", "green" if n >= need else "yellow")
    elif v is None:
        t.append("\nno navigation", "red")
    return t


def render_result(outcome: CalibrationOutcome) -> Table | Text:
    if not outcome.ok or not outcome.result:
        return Text(f"calibration failed: {outcome.message}", "bold red")
    r = outcome.result
    tab = Table(title="boresight (canonical, degrees)", expand=False, padding=(0, 1))
    for col in ("", "estimate", "σ realistic", "σ formal"):
        tab.add_column(col, justify="right")
    b, sr, sf = (r.get(k) or {} for k in ("boresight_deg", "sigma_realistic_deg", "sigma_deg"))
    for a in ("roll", "pitch", "yaw"):
        tab.add_row(a, _fmt(b.get(a), "+.4f"), _fmt(sr.get(a), ".4f"), _fmt(sf.get(a), ".4f"))
    chi = r.get("chi2_test") or {}
    tab.caption = (
        f"σ0² {_fmt(r.get('sigma0_squared'), '.2f')} "
        f"(χ² {'passed' if chi.get('passed') else 'FAILED'}) · "
        f"{r.get('n_points', '?')} points · {r.get('iterations', '?')} it · "
        f"{_fmt(r.get('runtime_s'), '.2f', ' s')}" + (f"\n{outcome.out_dir}" if outcome.out_dir else "")
    )
    return tab


# =============================================================================================
# The app
# =============================================================================================


class TextScreen(ModalScreen):
    """A modal with one renderable; Escape or Enter closes it."""

    BINDINGS = [Binding("escape,enter,q", "dismiss", "close")]
    DEFAULT_CSS = """
    TextScreen { align: center middle; }
    TextScreen > Static { width: 76; max-height: 22; border: thick $accent; padding: 0 1;
                          background: $surface; }
    """

    def __init__(self, title: str, body, name: str | None = None):
        super().__init__(name=name)
        self._title, self._body = title, body

    def compose(self) -> ComposeResult:
        s = Static(self._body, id="modal-body")
        s.border_title = self._title
        s.border_subtitle = "Esc to close"
        yield s


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
        self.query_one("#header", Static).update(render_header(st))
        pre = self.query_one("#prechecks", Static)
        pre.update(render_prechecks(st))
        checks = st.checks()
        n_ok = sum(bool(c.get("ok")) for c in checks)
        pre.border_subtitle = f"{n_ok}/{len(checks)} ok" if checks else ""
        passes = st.checklist.get("passes") or []
        self.selected = min(self.selected, max(len(passes) - 1, 0))
        ps = self.query_one("#passes", Static)
        ps.update(render_passes(st, self.selected))
        ps.border_subtitle = f"{st.checklist.get('accepted', 0)}/{len(passes)} accepted"
        sig = self.query_one("#sigma", Static)
        sig.update(Text("calibrating…", "bold yellow") if self._calibrating else render_sigma(st))
        self.query_one("#live", Static).update(render_live(st))
        plan_w = self.query_one("#plan", Static)
        plan = st.checklist.get("plan")
        if plan:
            w = max(plan_w.size.width - 2, 10)
            h = max(plan_w.size.height - 2, 4)
            active = (st.checklist.get("active") or {}).get("pass_id")
            text, m_per_dot = render_plan(plan, st.checklist.get("vessel"), active, w, h)
            plan_w.update(text)
            plan_w.border_subtitle = f"N↑ {m_per_dot:.2g} m/dot"
        else:
            plan_w.update(Text("no plan yet", "dim"))

    def on_resize(self, event) -> None:
        self.refresh_view()

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
        self.push_screen(TextScreen(f"pass {p['id']}", body))

    def action_check_details(self) -> None:
        body = Text()
        for c in self.state.checks():
            mark = OK if c.get("ok") else WAIT if c.get("ok") is None else FAIL
            body.append(f"{mark} {c.get('label')}: ", "bold")
            body.append(f"{c.get('detail')}\n")
        for a in (self.state.topics.get("status") or {}).get("alarms") or []:
            body.append(
                f"{a.get('severity', '?')} alarm {a.get('name')} ({a.get('device')}): "
                f"{a.get('message', '')}\n",
                "red",
            )
        self.push_screen(TextScreen("pre-survey checks", body or "no checks yet"))

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
