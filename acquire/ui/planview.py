"""A plan view of the active line in Unicode braille (2 × 4 dots per character cell), for the
checklist in an 80 × 24 terminal: north up, equal scale on both axes, fitted to the active line,
the targets and the vessel.

Layers, drawn in this order (a later layer owns a cell's colour): the other lines (dim), the
active line, its capture window, the targets, the vessel (a dot with a heading tick). Input is
the ``checklist`` message's ``plan`` block (LGF north/east metres) and ``vessel``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from rich.text import Text

#: Dot (column, row) within a cell → bit of the braille pattern (U+2800 + bits).
_BITS = ((0x01, 0x02, 0x04, 0x40), (0x08, 0x10, 0x20, 0x80))
STYLES = {
    "other": "grey37",
    "line": "cyan",
    "capture": "bold bright_cyan",
    "target": "bold red",
    "vessel": "bold yellow",
}


@dataclass
class Canvas:
    """Braille canvas of ``width`` × ``height`` cells; layers paint dots in metres (n, e)."""

    width: int
    height: int
    n0: float  # north of the top edge
    e0: float  # east of the left edge
    m_per_dot: float

    def __post_init__(self) -> None:
        self._bits: list[list[int]] = [[0] * self.width for _ in range(self.height)]
        self._style: list[list[str | None]] = [[None] * self.width for _ in range(self.height)]  # layer

    def _dot(self, x: int, y: int, style: str) -> None:
        if 0 <= x < 2 * self.width and 0 <= y < 4 * self.height:
            cx, cy = x // 2, y // 4
            self._bits[cy][cx] |= _BITS[x % 2][y % 4]
            self._style[cy][cx] = style

    def to_dots(self, n: float, e: float) -> tuple[int, int]:
        return (
            int(math.floor((e - self.e0) / self.m_per_dot)),
            int(math.floor((self.n0 - n) / self.m_per_dot)),
        )

    def point(self, n: float, e: float, style: str) -> None:
        self._dot(*self.to_dots(n, e), style)

    def line(self, a: tuple[float, float], b: tuple[float, float], style: str) -> None:
        x0, y0 = self.to_dots(*a)
        x1, y1 = self.to_dots(*b)
        steps = max(abs(x1 - x0), abs(y1 - y0), 1)
        if steps > 20000:  # far outside the view: clip by sampling the visible part only
            steps = 20000
        for i in range(steps + 1):
            f = i / steps
            self._dot(round(x0 + f * (x1 - x0)), round(y0 + f * (y1 - y0)), style)

    def polygon(self, pts: list[tuple[float, float]], style: str, fill: bool = True) -> None:
        for i in range(len(pts)):
            self.line(pts[i], pts[(i + 1) % len(pts)], style)
        if fill and pts:  # small targets: paint the cells their extent covers
            xs, ys = zip(*(self.to_dots(*p) for p in pts), strict=True)
            for x in range(min(xs), max(xs) + 1):
                for y in range(min(ys), max(ys) + 1):
                    self._dot(x, y, style)

    def render(self) -> Text:
        out = Text(no_wrap=True, overflow="crop")
        for row in range(self.height):
            for col in range(self.width):
                b, layer = self._bits[row][col], self._style[row][col]
                out.append(chr(0x2800 + b) if b else " ", STYLES.get(layer, "") if layer is not None else "")
            if row < self.height - 1:
                out.append("\n")
        return out


def fit(points: list[tuple[float, float]], width: int, height: int, margin_frac: float = 0.08) -> Canvas:
    """A canvas whose square dots show all ``points`` (n, e) with a margin."""
    ns = [p[0] for p in points] or [0.0]
    es = [p[1] for p in points] or [0.0]
    span_n = max(max(ns) - min(ns), 1.0)
    span_e = max(max(es) - min(es), 1.0)
    m = max(span_e / (2 * width), span_n / (4 * height)) * (1 + 2 * margin_frac)
    cn, ce = 0.5 * (max(ns) + min(ns)), 0.5 * (max(es) + min(es))
    return Canvas(width, height, cn + 2 * height * m, ce - width * m, m)


def render_plan(
    plan: dict, vessel: dict | None, active_id: int | None, width: int, height: int
) -> tuple[Text, float]:
    """The plan view as styled text and its scale (metres per dot)."""
    passes = {p["id"]: p for p in plan.get("passes", [])}
    targets = plan.get("targets", [])
    act = passes.get(active_id)
    cv = fit(_view_points(passes, targets, act, vessel), width, height)
    for pid, p in passes.items():
        if pid != active_id:
            cv.line(tuple(p["start_ne_m"]), tuple(p["end_ne_m"]), "other")
    if act is not None:
        _draw_active_line(cv, act)
    for t in targets:
        cv.polygon([tuple(c) for c in t["corners_ne_m"]], "target")
    if vessel is not None:
        _draw_vessel(cv, vessel)
    return cv.render(), cv.m_per_dot


def _view_points(
    passes: dict, targets: list, act: dict | None, vessel: dict | None
) -> list[tuple[float, float]]:
    """What the view shows whole: the active line (every line when none is active), the
    targets' corners and the vessel."""
    pts: list[tuple[float, float]] = []
    if act is not None:
        pts += [tuple(act["start_ne_m"]), tuple(act["end_ne_m"])]
    for t in targets:
        pts += [tuple(c) for c in t["corners_ne_m"]]
    if vessel is not None:
        pts.append((vessel["n_m"], vessel["e_m"]))
    if act is None:
        for p in passes.values():
            pts += [tuple(p["start_ne_m"]), tuple(p["end_ne_m"])]
    return pts


def _draw_active_line(cv: Canvas, act: dict) -> None:
    """The active line and, over it, its capture window."""
    a, b = act["start_ne_m"], act["end_ne_m"]
    cv.line(tuple(a), tuple(b), "line")
    length = math.hypot(b[0] - a[0], b[1] - a[1]) or 1.0
    u = ((b[0] - a[0]) / length, (b[1] - a[1]) / length)
    c0, c1 = act["capture_m"]
    cv.line((a[0] + c0 * u[0], a[1] + c0 * u[1]), (a[0] + c1 * u[0], a[1] + c1 * u[1]), "capture")


def _draw_vessel(cv: Canvas, vessel: dict) -> None:
    """The vessel: a 3 × 3 dot with a heading tick 4 dots long."""
    n, e = vessel["n_m"], vessel["e_m"]
    h = math.radians(vessel.get("heading_deg", 0.0))
    tick = 4 * cv.m_per_dot
    cv.line((n, e), (n + tick * math.cos(h), e + tick * math.sin(h)), "vessel")
    for dn in (-1, 0, 1):
        for de in (-1, 0, 1):
            cv.point(n + dn * cv.m_per_dot, e + de * cv.m_per_dot, "vessel")
