"""The pairs of passes an assessment compares: the sailed heading of each pass, the reciprocal
pairs found from them, or the pairs the user names.
"""

from __future__ import annotations

import numpy as np

from calib.assess.results import AssessError
from calib.extraction.points import line_headings

#: Passes are reciprocal when their sailed headings differ by 180° within this tolerance.
RECIPROCAL_TOLERANCE_DEG = 20.0


def pass_headings_deg(bundle) -> dict[int, float]:
    """Sailed heading of each pass (circular mean of the trajectory at its covered returns)."""
    pts, traj = bundle.points, bundle.trajectory
    covered = pts.select(~traj.uncovered(pts.t_gps_s))
    return {p: float(np.degrees(h)) for p, h in line_headings(covered, traj, 0.0).items()}


def _heading_gap_deg(a: float, b: float) -> float:
    """How far two headings are from opposite: |((a − b) mod 360°) − 180°|."""
    return abs((a - b) % 360.0 - 180.0)


def reciprocal_pairs(
    headings_deg: dict[int, float], tolerance_deg: float = RECIPROCAL_TOLERANCE_DEG
) -> list[tuple[int, int]]:
    """Pairs of passes sailed in opposite directions (each pass in at most one pair, the closest
    to 180° first), lower pass id first."""
    ids = sorted(headings_deg)
    cands = sorted(
        (_heading_gap_deg(headings_deg[a], headings_deg[b]), a, b)
        for i, a in enumerate(ids)
        for b in ids[i + 1 :]
    )
    used, pairs = set(), []
    for gap, a, b in cands:
        if gap <= tolerance_deg and a not in used and b not in used:
            pairs.append((a, b))
            used |= {a, b}
    return sorted(pairs)


def parse_pairs(text: str) -> list[tuple[int, int]]:
    """``"1:2,5:6"`` → [(1, 2), (5, 6)] (compared pass first, reference second)."""
    out = []
    for item in text.split(","):
        item = item.strip()
        a, sep, b = item.partition(":")
        if not sep or not a.strip().isdigit() or not b.strip().isdigit():
            raise AssessError(f"pair {item!r}: expected two pass ids A:B, e.g. 1:2")
        pa, pb = int(a), int(b)
        if pa == pb:
            raise AssessError(f"pair {item!r}: a pass cannot be compared with itself")
        out.append((pa, pb))
    if not out:
        raise AssessError(f"pairs {text!r}: expected A:B[,C:D…]")
    return out
