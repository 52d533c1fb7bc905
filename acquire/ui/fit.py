"""Fitting the checklist's text to its boxes without cutting any of it: what the operator must
read is shown whole.

- A label (a check's name, a word of the header or of the guidance line) that does not fit its
  width takes a short form from one fixed table, :data:`SHORT_FORMS`, and only then: a wider
  terminal shows the full words.
- Free text (a check's detail, an alarm message, an OS error, a rejection reason) wraps, at word
  boundaries when it can; a word longer than the width is folded, never dropped.

Widths are terminal cells (:func:`rich.cells.cell_len`).
"""

from __future__ import annotations

from rich.cells import cell_len
from rich.text import Text

#: The short forms, ``(long, short)``, in the order they are tried: a label too wide for its
#: place takes the first that applies, then the next, ... until it fits.
SHORT_FORMS: tuple[tuple[str, str], ...] = (
    # pre-survey check labels (panels.CHECK_LABELS, and the daemon's names as they are)
    ("Receive buffer", "Rcv buf"),
    ("receive buffer", "rcv buf"),
    ("Devices connected", "Devices conn"),
    ("devices connected", "devices conn"),
    # the header
    ("mls checklist", "mls"),
    ("daemon ", ""),
    ("clock ", "clk "),
    (" alarms", " alm"),
    (" alarm", " alm"),
    ("no link", "no lnk"),
    # the guidance line
    ("window in ", "win in "),
    ("window passed", "win passed"),
    ("APPROACH", "APPR"),
    ("hdg ", ""),
    # predicted σ
    ("next best: ", "next: "),
    (" angles", ""),
    # the passes' "n more" rows
    (" accepted", " acc"),
    (" rejected", " rej"),
    (" capturing", " capt"),
    (" pending", " pend"),
)


def abbreviations(text: str) -> list[str]:
    """``text`` and its successive short forms (each applies one more entry of the table)."""
    out = [text]
    for long, short in SHORT_FORMS:
        if long in out[-1]:
            out.append(out[-1].replace(long, short))
    return out


def abbreviate(text: str, width: int) -> str:
    """``text`` if it fits ``width`` cells, else its first short form that does (the shortest
    when none does: the caller wraps it)."""
    forms = abbreviations(text)
    return next((f for f in forms if cell_len(f) <= width), forms[-1])


def runs(parts: list[tuple[str, str]]) -> Text:
    """Styled pieces ``(text, style)`` as one Text, each piece's leading spaces moved to the end of
    the piece before (same text; librsvg, which turns the SVG screenshots into PNG, drops a
    styled run's leading spaces and so runs "CAPTURE" and "6/10 m" together)."""
    t = Text()
    for i, (p, s) in enumerate(parts):
        stripped = p.lstrip(" ")
        if i and stripped != p:
            t.append(p[: len(p) - len(stripped)], parts[i - 1][1])
            p = stripped
        t.append(p, s)
    return t


def fit_parts(parts: list[tuple[str, str]], width: int) -> Text:
    """Styled pieces ``(text, style)`` on one line: the table's short forms applied to the pieces,
    entry by entry, only while the line is wider than ``width``."""
    parts = list(parts)
    for long, short in SHORT_FORMS:
        if sum(cell_len(p) for p, _ in parts) <= width:
            break
        parts = [(p.replace(long, short), s) for p, s in parts]
    return runs(parts)


def _fold(word: str, width: int, first: int) -> list[str]:
    """A word wider than its line in pieces: the first at most ``first`` cells, the others
    at most ``width``."""
    pieces, cur, room = [], "", first
    for ch in word:
        if cur and cell_len(cur + ch) > room:
            pieces.append(cur)
            cur, room = "", width
        cur += ch
    return pieces + [cur]


def wrap(text: str, width: int, first: int | None = None) -> list[str]:
    """``text`` in lines of at most ``width`` cells (the first line: ``first``), broken at
    spaces, a longer word folded; its own newlines kept."""
    width = max(width, 1)
    room = width if first is None else max(first, 1)
    lines: list[str] = []
    for para in str(text).split("\n"):
        cur = ""
        for word in para.split(" "):
            if not word:
                continue
            cand = f"{cur} {word}" if cur else word
            if cell_len(cand) <= room:
                cur = cand
                continue
            if cur:
                lines.append(cur)
                room = width
            pieces = _fold(word, width, room)
            lines.extend(pieces[:-1])
            if len(pieces) > 1:
                room = width
            cur = pieces[-1]
        lines.append(cur)
        room = width
    return lines


def hanging(first: Text, text: str, style: str, width: int, indent: int | None = None) -> list[Text]:
    """``first`` followed by ``text`` wrapped in the rest of the line, its continuation lines
    indented by ``indent`` cells (default: the width of ``first``)."""
    indent = first.cell_len if indent is None else indent
    lines = wrap(text, width - indent, first=width - first.cell_len)
    out = [first.copy()]
    out[0].append(lines[0], style)
    out.extend(Text(" " * indent) + Text(ln, style) for ln in lines[1:])
    return out
