"""What ``mls demo`` prints while the survey runs (:mod:`office.jobs.demo`), pure functions of the
guidance messages: the live line (:func:`progress_line`), a line per pass verdict
(:func:`pass_events`) and per new σ prediction (:func:`sigma_events`)."""

from __future__ import annotations

import math

ANGLES = ("roll", "pitch", "yaw")


def _sigma_text(g: dict) -> str:
    """The predicted realistic σ of the accepted passes (n/o: not observable yet)."""
    cur = ((g.get("sigma") or {}).get("current")) or {}
    r = cur.get("realistic_deg") or {}
    if not cur.get("passes"):
        return "σ —"
    return "σ " + " ".join(f"{a} " + ("n/o" if r.get(a) is None else f"{r[a]:.3f}°") for a in ANGLES)


def progress_line(g: dict, clock_state: str | None, elapsed_s: float) -> str:
    """One line of at most ~80 characters: the elapsed time, the active pass and its state,
    XTE, accepted passes, predicted σ (realistic, roll pitch yaw, n/o: not observable yet) and
    the clock when it is not LOCKED."""
    passes = g.get("passes") or []
    a = g.get("active") or {}
    parts = [f"{int(elapsed_s) // 60:02d}:{int(elapsed_s) % 60:02d}"]
    if not g:
        parts.append("waiting for the guidance")
    else:
        if a:
            state = str(a.get("state", "approach"))
            if state == "capture" and "along_m" in a:
                c0, c1 = a.get("capture_m", (0.0, 0.0))
                state += f" {max(a['along_m'] - c0, 0.0):.0f}/{c1 - c0:.0f} m"
            parts.append(f"pass {a.get('pass_id')} {state}")
            if "xte_m" in a:
                parts.append(f"· XTE {a['xte_m']:+.2f} m")
        else:
            parts.append("all passes sailed" if passes else "no plan")
        parts.append(f"· {g.get('accepted', 0)}/{len(passes)} accepted")
        cur = ((g.get("sigma") or {}).get("current")) or {}
        r = cur.get("realistic_deg") or {}
        if cur.get("passes"):
            parts.append("· σ° " + " ".join("n/o" if r.get(x) is None else f"{r[x]:.3f}" for x in ANGLES))
    if clock_state != "LOCKED":
        parts.append(f"· clock {clock_state or '—'}")
    return " ".join(parts)


def pass_events(before: dict, after: dict) -> list[str]:
    """A line for every pass that got a new verdict between two guidance messages."""
    old = {p["id"]: p.get("attempts", 0) for p in (before.get("passes") or [])}
    out = []
    for p in after.get("passes") or []:
        if p.get("attempts", 0) <= old.get(p["id"], 0) or p.get("status") not in ("accepted", "rejected"):
            continue
        hits = ", ".join(f"{k} {v}" for k, v in (p.get("hits") or {}).items())
        st = p.get("stats") or {}
        if p["status"] == "accepted":
            line = (
                f"✔ pass {p['id']} ({p['relative_heading_deg']:.0f}°) accepted: hits {hits}; "
                f"max XTE {st.get('max_xte_m', math.nan):.2f} m"
            )
        else:
            line = f"✘ pass {p['id']} ({p['relative_heading_deg']:.0f}°) rejected: " + "; ".join(
                p.get("reasons") or []
            )
        out.append(line)
    return out


def _sigma_passes(g: dict) -> list:
    return list(((g.get("sigma") or {}).get("current") or {}).get("passes") or [])


def sigma_events(before: dict, after: dict) -> list[str]:
    """A line when the guidance has predicted the σ of a new set of accepted passes."""
    passes = _sigma_passes(after)
    if not passes or passes == _sigma_passes(before):
        return []
    line = f"  predicted {_sigma_text(after)} with passes {', '.join(str(p) for p in passes)}"
    rose = (after.get("sigma") or {}).get("current", {}).get("rose") or []
    if rose:  # see acquire.guidance.state.sigma_rises
        line += f" ({', '.join(rose)} σ rose: the pass's POS bias outweighs its geometry)"
    return [line]


def sigma_covers_accepted(g: dict) -> bool:
    """Whether the σ prediction includes every accepted pass."""
    accepted = sorted(p["id"] for p in g.get("passes") or [] if p.get("status") == "accepted")
    return sorted(_sigma_passes(g)) == accepted
