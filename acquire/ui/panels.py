"""The panels of ``mls checklist`` as Rich renderables: pure functions of the latest status
messages (:class:`ChecklistState`) and of the room the panel has (``width`` × ``rows`` cells).

Nothing the operator must read is cut: a label too wide takes a short form from
:data:`acquire.ui.fit.SHORT_FORMS` (only then), free text wraps (:mod:`acquire.ui.fit`); what
does not fit a panel's rows is summed up in a last line that says how to see it (``d``, ``↑/↓``,
Enter).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rich import box
from rich.cells import cell_len
from rich.console import Group
from rich.table import Table
from rich.text import Text

from acquire.status.feed import LINK, SNAPSHOT_END, guidance_of
from acquire.ui.fit import abbreviate, fit_parts, hanging, runs

OK, FAIL, WAIT = "✔", "✘", "…"
#: Labels of the daemon's pre-survey check names (acquire.daemon.reports.StatusReporter.presurvey);
#: a name not here shows as itself, its underscores as spaces.
CHECK_LABELS = {
    "ins_navigating": "INS nav+fine",
    "gnss_fix": "GNSS fix",
    "ins_pps": "INS PPS+UTC",
    "pps_locked": "PPS locked",
    "profiler_data": "Profiler data",
    "receive_buffer": "Receive buffer",
    "devices_connected": "Devices connected",
    "clock_locked": "Clock LOCKED",
    "latency_in_band": "Latency",
    "disk_space": "Disk space",
    "mount_configured": "Mount",
    "mount_targets": "Mount+targets",
    "mount_watch": "Mount watch",
}
PRECHECK_ROWS = 7
PASS_ROWS = 7
LIVE_ROWS = 6
#: The label column of the pre-survey checks: at least this many cells, at most a third of the
#: panel (a longer label takes its short form).
LABEL_MIN = 13
STATUS_STYLE = {"accepted": "green", "rejected": "red", "capturing": "yellow", "pending": "dim"}


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
        it knows the plan), then the mount watch's verdict (its ``mount`` section: ok while
        steady, failing after a shift, waiting before the first pair of opposite lines)."""
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
        watch = c.get("mount")
        if isinstance(watch, dict) and "verdict" in watch:
            merged["mount_watch"] = {
                "name": "mount_watch",
                "label": CHECK_LABELS["mount_watch"],
                "ok": watch.get("ok"),
                "detail": str(watch.get("verdict", "")),
            }
        return list(merged.values())

    def alarms(self) -> list[dict]:
        """The active alarms (``status.alarms``)."""
        return [a for a in (self.topics.get("status") or {}).get("alarms") or [] if isinstance(a, dict)]

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


def _lines(lines: list[Text]) -> Text:
    return Text("\n", no_wrap=True).join(lines)


def render_header(st: ChecklistState, width: int = 80) -> Text:
    status = st.topics.get("status") or {}
    clock = st.topics.get("clock") or {}
    vessel = status.get("vessel") or st.checklist.get("vessel_name") or "?"
    state = status.get("state", "—")
    parts = [
        (" mls checklist ", "bold reverse"),
        (f" {vessel} ", ""),
        (f"daemon {state} ", "red" if state == "lost" else ""),
    ]
    if cs := clock.get("state"):
        parts.append((f"clock {cs} ", "green" if cs == "LOCKED" else "red"))
    if n_alarms := len(status.get("alarms") or []):
        parts.append((f"{n_alarms} alarm{'s' if n_alarms > 1 else ''} ", "bold red"))
    parts.append(("● link", "green") if st.link_up else ("○ no link", "bold red"))
    t = fit_parts(parts, width)
    t.no_wrap, t.overflow = True, "ellipsis"
    return t


def _mark(c: dict) -> tuple[str, str]:
    ok = c.get("ok")
    return (OK, "green") if ok else (WAIT, "yellow") if ok is None else (FAIL, "bold red")


def render_prechecks(st: ChecklistState, width: int = 38, rows: int = PRECHECK_ROWS) -> Text:
    """The checks, failing ones first, each detail whole (wrapped under itself); the checks that
    do not fit ``rows`` are summed up in the last row."""
    checks = st.checks()
    if not checks:
        return Text("waiting for the daemon's checklist…", "dim")
    checks = sorted(checks, key=lambda c: c.get("ok") is True)  # stable: failing first
    labels = [str(c.get("label", c.get("name", "?"))) for c in checks]
    lw = min(max(cell_len(x) for x in labels), max(LABEL_MIN, width // 3))
    groups: list[list[Text]] = []
    for c, label in zip(checks, labels, strict=True):
        mark, style = _mark(c)
        label = abbreviate(label, lw)
        head = Text(f"{mark} ", style)
        head.append(label, "bold" if not c.get("ok") else "")
        detail, dstyle = str(c.get("detail", "")), "" if c.get("ok") else style
        if cell_len(label) > lw:  # no short form fits: the label on its own line
            groups.append([head, *hanging(Text(" " * (lw + 3)), detail, dstyle, width)])
        else:
            head.append(" " * (lw + 1 - cell_len(label)))
            g = hanging(head, detail, dstyle, width)
            if len(g) > 2:  # a long detail (an OS error): its continuation lines under the label
                g = hanging(head, detail, dstyle, width, indent=2)
            groups.append(g)
    if sum(map(len, groups)) <= rows:
        return _lines([ln for g in groups for ln in g])
    shown: list[Text] = []
    n = 0
    for g in groups:
        if len(shown) + len(g) > rows - 1:
            break
        shown += g
        n += 1
    if n == 0:  # one check's detail is taller than the panel: as much as fits, then "d"
        shown = [*groups[0][: max(rows - 2, 1)], Text(" " * (lw + 3)) + Text("… (d: all of it)", "dim")]
        n = 1
    rest = checks[n:]
    n_ok = sum(c.get("ok") is True for c in rest)
    last = runs(
        [
            (
                f"{OK} {n_ok} more ok"
                if n_ok == len(rest)
                else f"… {len(rest)} more ({len(rest) - n_ok} not ok)",
                "green" if n_ok == len(rest) else "yellow",
            ),
            (" — d: all", "dim"),
        ]
    )
    return _lines([*shown, last])


def _pass_groups(
    st: ChecklistState, width: int, selected: int, every_reason: bool
) -> tuple[Text, list[list[Text]]]:
    """The header line and, per pass, its row and its first rejection reason: on the row when it
    fits, else wrapped under it (with ``every_reason``) or "why: ⏎" (Enter shows it; the
    guidance shows the active pass's)."""
    passes = st.checklist.get("passes") or []
    active = (st.checklist.get("active") or {}).get("pass_id")
    names = list((passes[0].get("hits") or {}).keys()) or [
        x["name"] for x in (st.checklist.get("plan") or {}).get("targets", [])
    ]
    cw = max([5, *(cell_len(n) for n in names[:2])])
    k = min(2, len(names), max((width - 19) // (cw + 1), 0))  # target columns that fit
    header = Text(f"  # rel°  status    {' '.join(n.rjust(cw) for n in names[:k])}", "dim")
    groups = []
    for i, p in enumerate(passes):
        arrow = "▶" if p["id"] == active else " "
        hits = p.get("hits") or {}
        row = runs(
            [
                (f"{arrow}{p['id']:>2} {p['relative_heading_deg']:>4.0f} ", ""),
                (f"{p.get('status', '?'):<10}", STATUS_STYLE.get(p.get("status"), "")),
                (" ".join(str(hits.get(n, "·")).rjust(cw) for n in names[:k]), ""),
            ]
        )
        if i == selected:
            row.stylize("reverse")
        group = [row]
        reasons = p.get("reasons") or []
        if reasons:
            why = reasons[0] + (f" (+{len(reasons) - 1} more: ⏎)" if len(reasons) > 1 else "")
            if row.cell_len + 1 + cell_len(why) <= width:
                row.append(" ").append(why, "red")
            elif every_reason:
                group += hanging(Text("    "), why, "red", width)
            elif row.cell_len + 7 <= width:
                row.append(" ").append("why: ⏎", "red")
        groups.append(group)
    return header, groups


def render_passes(st: ChecklistState, selected: int = 0, width: int = 38, rows: int = PASS_ROWS) -> Text:
    """The passes with their status, hits and first rejection reason (wrapped under the pass
    when every reason fits ``rows``, else "why: ⏎"); when the passes do not fit, the ones around
    the selected (and the active) pass, the others counted (↑/↓ moves)."""
    passes = st.checklist.get("passes") or []
    if not passes:
        return Text("no pass plan yet", "dim")
    header, groups = _pass_groups(st, width, selected, every_reason=True)
    if sum(map(len, groups)) > rows - 1:
        header, groups = _pass_groups(st, width, selected, every_reason=False)
    budget = rows - 1
    if sum(map(len, groups)) <= budget:
        return _lines([header, *(ln for g in groups for ln in g)])
    active = (st.checklist.get("active") or {}).get("pass_id")
    ia = next((i for i, p in enumerate(passes) if p["id"] == active), selected)
    selected = min(max(selected, 0), len(groups) - 1)

    def window(s: int) -> int:
        """The end of the window from pass ``s`` (its "more" lines counted)."""
        room = budget - (s > 0)
        e = s
        while e < len(groups) and len(groups[e]) + (e + 1 < len(groups)) <= room:
            room -= len(groups[e])
            e += 1
        return e

    spans = [(s, window(s)) for s in range(len(groups))]
    s, e = next(
        ((s, e) for s, e in spans if s <= min(selected, ia) and e > max(selected, ia)),
        next(((s, e) for s, e in spans if s <= selected < e), (selected, selected + 1)),
    )

    def more(arrow: str, hidden: list[dict]) -> Text:
        by = {x: sum(p.get("status") == x for p in hidden) for x in STATUS_STYLE}
        text = f"{arrow} {len(hidden)} more: " + ", ".join(f"{n} {x}" for x, n in by.items() if n)
        return Text(abbreviate(text, width), "dim")

    lines = [header, more("↑", passes[:s])] if s > 0 else [header]
    lines += [ln for g in groups[s:e] for ln in g][: budget - (s > 0) - (e < len(groups))]
    if e < len(groups):
        lines.append(more("↓", passes[e:]))
    return _lines(lines)


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


def render_sigma(st: ChecklistState, width: int = 38, rows: int = 3) -> Text:
    """The predicted σ, the next best pass and, when ``rows`` leave room for a third line, the
    weakest angle with the pass that helps it most."""
    sig = st.checklist.get("sigma")
    if not sig:
        return Text("σ after the first accepted pass", "dim")
    cur = sig.get("current") or {}
    n = len(cur.get("passes") or [])
    first = fit_parts([(f"σ({n}) ", "bold"), (_sigma_line(cur) if n else "no pass accepted yet", "")], width)
    second = Text()
    if nb := sig.get("next_best"):
        plan = {p["id"]: p for p in (st.checklist.get("plan") or {}).get("passes", [])}
        rel = plan.get(nb["pass_id"], {}).get("relative_heading_deg")
        worst = nb.get("worst_deg")
        second = fit_parts(
            [
                ("next best: ", "dim"),
                (f"pass {nb['pass_id']}" + (f" ({rel:.0f}°)" if rel is not None else ""), "bold"),
                (
                    f" → σ ≤ {worst:.3f}°"
                    if worst is not None
                    else f" → {3 - nb.get('undetermined', 3)}/3 angles",
                    "",
                ),
            ],
            width,
        )
    elif st.checklist.get("calibration_ready"):
        second = Text("ready: press c to calibrate", "bold green")
    weak = _weakest_line(sig.get("weakest"), width) if rows >= 3 else Text()
    return _lines([first, second, weak] if weak.plain else [first, second])


def _weakest_line(w: dict | None, width: int) -> Text:
    """The angle determined worst and the pass that sharpens it most (only while one is left)."""
    if not w or w.get("best_pass") is None:
        return Text()
    now, then = w.get("realistic_deg"), w.get("best_deg")
    return fit_parts(
        [
            (f"weakest {w['angle']} ", "dim"),
            (_fmt(now, ".3f", "°", "n/o"), ""),
            (f": pass {w['best_pass']} → {_fmt(then, '.3f', '°', 'n/o')}", ""),
        ],
        width,
    )


def render_live(st: ChecklistState, width: int = 38, rows: int = LIVE_ROWS) -> Text:
    """The active pass: its state and progress, XTE with the side to steer, heading error,
    speed, range and hits to the targets; when it was rejected, why (until it is sailed again)."""
    a = st.checklist.get("active")
    v = st.checklist.get("vessel")
    tol = st.checklist.get("tolerances") or {}
    if not a:
        return Text("all passes accepted" if st.checklist.get("passes") else "no active pass", "dim")
    state = a.get("state", "approach")
    parts = [(f"pass {a['pass_id']} ", "bold")]
    if "heading_deg" in a:
        parts.append((f"hdg {a['heading_deg']:.0f}° ", ""))
    parts.append((state.upper() + " ", "bold yellow" if state == "capture" else "cyan"))
    lines: list[Text] = []
    if "along_m" in a:
        parts.append(_window_progress(a, state))
        lines += _steering_lines(a, tol)
        if hits := a.get("hits"):
            lines += _hits_lines(hits, tol.get("min_points_per_target", 0), width)
    elif v is None:
        lines.append(Text("no navigation", "red"))
    first = fit_parts(parts, width)
    first.rstrip()
    lines.insert(0, first)
    entry: dict = next((p for p in st.checklist.get("passes") or [] if p["id"] == a["pass_id"]), {})
    if entry.get("status") == "rejected" and entry.get("reasons") and state != "capture":
        lines += _rejection_lines(entry["reasons"], len(lines), width, rows)
    return _lines(lines)


def _window_progress(a: dict, state: str) -> tuple[str, str]:
    """Metres sailed in the capture window, to it, or that it is passed."""
    c0, c1 = a.get("capture_m", (0, 0))
    to_window = a.get("to_capture_m", 0.0)
    if state == "capture":
        return (f"{max(a['along_m'] - c0, 0):.0f}/{c1 - c0:.0f} m", "")
    if to_window >= 0:
        return (f"window in {to_window:.0f} m", "")
    return ("window passed", "")


def _steering_lines(a: dict, tol: dict) -> list[Text]:
    """XTE with the side to steer, heading error and speed (red: out of tolerance), range."""
    xte, he = a["xte_m"], a["heading_error_deg"]
    sp, plan_sp = a.get("speed_mps"), a.get("planned_speed_mps")
    bad_xte = abs(xte) > tol.get("max_xte_m", math.inf)
    bad_he = abs(he) > tol.get("max_heading_error_deg", math.inf)
    bad_sp = (
        plan_sp is not None
        and sp is not None
        and abs(sp - plan_sp) > tol.get("max_speed_error_mps", math.inf)
    )
    return [
        runs(
            [
                ("XTE ", ""),
                (f"{xte:+6.2f} m", "bold red" if bad_xte else "bold green"),
                (f" steer {'L' if xte > 0 else 'R'}" if abs(xte) >= 0.05 else " on line", ""),
            ]
        ),
        runs(
            [
                ("HDG err ", ""),
                (f"{he:+5.1f}°", "bold red" if bad_he else "bold green"),
                ("  SOG ", ""),
                (_fmt(sp, ".2f", " m/s"), "bold red" if bad_sp else "bold green"),
            ]
        ),
        Text(f"range to targets {a.get('range_to_targets_m', math.nan):.1f} m"),
    ]


def _hits_lines(hits: dict, need: int, width: int) -> list[Text]:
    """The hits per target, whole "name count" items wrapped under "hits" (yellow: too few)."""
    lines: list[Text] = []
    row: list[tuple[str, str]] = [("hits", "")]
    for name, n in hits.items():
        item = [(f" {name}", ""), (f" {n}", "green" if n >= need else "yellow")]
        if sum(cell_len(x) for x, _ in row + item) > width:
            lines.append(runs(row))
            row = [("   ", "")]
        row += item
    lines.append(runs(row))
    return lines


def _rejection_lines(reasons: list, shown: int, width: int, rows: int) -> list[Text]:
    """Why the pass was rejected (the first reason), cut to the ``rows - shown`` left."""
    why = reasons[0] + (f" (+{len(reasons) - 1} more: ⏎)" if len(reasons) > 1 else "")
    more = hanging(Text(f"{FAIL} ", "red"), why, "red", width)
    if shown + len(more) > rows:  # taller than the panel: what fits, then Enter
        more = [*more[: max(rows - shown - 1, 0)], Text("  … ⏎ on the pass: all", "dim")]
    return more


_VERDICT_STYLE = {"trusted": "bold green", "questionable": "bold yellow", "refused": "bold red"}


def _verdict_text(result: dict) -> Text:
    """The calibration's verdict and its reasons (an older result has none)."""
    status = result.get("verdict")
    if status is None:
        return Text("verdict: none (an older result: its reliability was not checked)", "yellow")
    out = Text(f"verdict: {status}", _VERDICT_STYLE.get(status, "bold"))
    if status == "refused":
        out.append(" — do not use this result", "bold red")
    for reason in result.get("verdict_reasons") or []:
        out.append(f"\n  · {reason}", "")
    return out


def render_result(outcome) -> Group | Text:
    """The calibration result (a :class:`acquire.ui.checklist_app.CalibrationOutcome`): the
    boresight table, then the fit's figures and the output directory as text that wraps."""
    if not outcome.ok or not outcome.result:
        return Text(f"calibration failed: {outcome.message}", "bold red")
    r = outcome.result
    tab = Table(box=box.ROUNDED, expand=False, padding=(0, 1))
    for col in ("", "estimate", "σ realistic", "σ formal"):
        tab.add_column(col, justify="right")
    b, sr, sf = (r.get(k) or {} for k in ("boresight_deg", "sigma_realistic_deg", "sigma_deg"))
    for a in ("roll", "pitch", "yaw"):
        tab.add_row(a, _fmt(b.get(a), "+.4f"), _fmt(sr.get(a), ".4f"), _fmt(sf.get(a), ".4f"))
    chi = r.get("chi2_test") or {}
    figures = Text(
        f"σ0² {_fmt(r.get('sigma0_squared'), '.2f')} "
        f"(χ² {'passed' if chi.get('passed') else 'FAILED'}) · "
        f"{r.get('n_points', '?')} points · {r.get('iterations', '?')} it · "
        f"{_fmt(r.get('runtime_s'), '.2f', ' s')}",
        "dim",
    )
    parts: list = [_verdict_text(r), Text("boresight (canonical, degrees)", "italic"), tab, figures]
    if outcome.out_dir:  # on a line of its own: a path longer than the line folds
        parts += [Text("written to", "dim"), Text(outcome.out_dir, "dim")]
    return Group(*parts)


def render_check_details(st: ChecklistState) -> Text:
    """Every check with its full label and detail, then the active alarms with their messages
    (the modal wraps them)."""
    body = Text()
    for c in st.checks():
        mark, style = _mark(c)
        body.append(f"{mark} {c.get('label', c.get('name', '?'))}: ", "bold")
        body.append(f"{c.get('detail')}\n", "" if c.get("ok") else style)
    for a in st.alarms():
        body.append(
            f"{a.get('severity', '?')} alarm {a.get('name')} ({a.get('device')}): {a.get('message', '')}\n",
            "red",
        )
    body.rstrip()
    return body
