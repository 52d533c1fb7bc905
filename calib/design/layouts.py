"""The design study's specification and its candidate layouts: which targets, inclinations,
sizes, standoffs, heights and pass subsets it predicts.

Sweeps (groups): pass subsets on one vertical plane (``passes``) and on the scenario's own
targets (``site_passes``), single-plane inclination (``inclination``), plane size (``size``),
two- and three-plane combinations (``planes``), standoff (``standoff``), target height
(``height``), and the recommendation search over layouts (``layout``: inclinations, spread
along the wall, height stagger, setback) under a constraint (number of targets, maximum size,
passes allowed); and the lines that make the yaw observable from the scene's piles
(``yaw_lines``, :mod:`calib.design.yawlines`).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from calib.design.criteria import SYSTEMATIC_ERRORS, THESIS_MAGNITUDES
from calib.design.prediction import DesignError
from calib.design.scenes import ground_based, scenario_targets, square_target
from calib.design.yawlines import DEFAULT_OFFSETS_M
from calib.sim.scenario import Scenario, Surface

GROUPS = (
    "passes",
    "site_passes",
    "inclination",
    "size",
    "planes",
    "standoff",
    "height",
    "layout",
    "yaw_lines",
)


# ---------------------------------------------------------------------------------------------
# The study's specification
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Constraint:
    """What the recommended site may use."""

    n_targets: int
    max_size_m: float
    passes: tuple[int, ...]

    def __post_init__(self):
        if self.n_targets < 1:
            raise DesignError(f"constraint: n_targets is {self.n_targets}, expected ≥ 1")
        if not self.max_size_m > 0:
            raise DesignError(f"constraint: max_size_m is {self.max_size_m}, expected > 0")
        if not self.passes:
            raise DesignError("constraint: at least one pass must be allowed")


@dataclass(frozen=True)
class StudySpec:
    """What the study computes (degrees and metres, as in its tables). :func:`default_spec`
    fills it from the scenario."""

    constraint: Constraint
    seed: int = 0
    groups: tuple[str, ...] = GROUPS
    errors: tuple[str, ...] = SYSTEMATIC_ERRORS
    magnitudes: dict = field(default_factory=lambda: dict(THESIS_MAGNITUDES))  # rad or m
    criteria_inclinations_deg: tuple[float, ...] = tuple(range(0, 91, 10))
    criteria_size_m: float = 1.0
    type1_threshold: float = 0.3  # raw selection on the mean Type I of an inclination
    plane_size_m: float = 1.0
    inclinations_deg: tuple[float, ...] = tuple(range(0, 91, 15))
    sizes_m: tuple[float, ...] = (0.25, 0.5, 0.75, 1.0)
    combo_inclinations_deg: tuple[float, ...] = tuple(range(0, 91, 15))
    spacing_m: float = 3.5
    standoffs_m: tuple[float, ...] = (10.0, 15.0, 20.0, 25.0, 30.0)
    height_shifts_m: tuple[float, ...] = (-4.0, -2.0, 0.0, 2.0, 4.0)
    layout_inclinations_deg: tuple[float, ...] = (90.0, 60.0, 45.0, 30.0)
    layout_spreads_m: tuple[float, ...] = (0.0, 3.5)  # 0: one above the other
    layout_staggers_m: tuple[float, ...] = (0.0, 4.0)
    layout_setbacks_m: tuple[float, ...] = (0.0, 6.0)
    yaw_line_offsets_m: tuple[float, ...] = DEFAULT_OFFSETS_M  # beyond the standoff

    def __post_init__(self):
        bad = [g for g in self.groups if g not in GROUPS]
        if bad:
            raise DesignError(f"unknown study group(s) {', '.join(bad)}; expected {', '.join(GROUPS)}")
        bad = [e for e in self.errors if e not in SYSTEMATIC_ERRORS]
        if bad:
            raise DesignError(f"unknown systematic error(s) {', '.join(bad)}")


def default_spec(base: Scenario, **changes) -> StudySpec:
    """The study of ``base``: the thesis's sweeps scaled to its geometry; the constraint is its
    own site (number of targets, largest target dimension, all passes). ``changes`` override
    fields (``n_targets``, ``max_size_m`` and ``passes`` go to the constraint)."""
    tg = scenario_targets(base)
    cons: dict[str, Any] = {
        "n_targets": len(tg),
        "max_size_m": max(max(s.width_m, s.height_m) for s in tg),
        "passes": tuple(p.id for p in base.passes),
    }
    for k in list(cons):
        v = changes.pop(k, None)
        if v is not None:
            cons[k] = tuple(int(x) for x in v) if k == "passes" else v
    unknown = sorted(set(cons["passes"]) - {p.id for p in base.passes})
    if unknown:
        raise DesignError(
            f"constraint: pass(es) {', '.join(map(str, unknown))} are not in "
            f"scenario {base.name!r} (passes "
            f"{', '.join(str(p.id) for p in base.passes)})"
        )
    along = sorted(s.along_m for s in tg)
    spacing = (along[-1] - along[0]) / (len(along) - 1) if len(along) > 1 else 3.5
    S = base.standoff_m
    kw: dict = dict(
        spacing_m=max(spacing, 2.5),
        layout_spreads_m=(0.0, max(spacing, 2.5)),
        layout_setbacks_m=(0.0, round(0.4 * S, 1)),
        standoffs_m=tuple(round(S * f, 1) for f in (2 / 3, 1.0, 4 / 3, 5 / 3, 2.0)),
    )
    if ground_based(base):  # targets on the ground: the thesis's Chapter 3 sweep, raised stands
        kw.update(
            criteria_inclinations_deg=tuple(range(-90, 91, 10)),
            inclinations_deg=tuple(range(-75, 91, 15)),  # vertical once
            height_shifts_m=(0.0, 0.5, 1.0, 1.5, 2.0),
            layout_staggers_m=(0.0, round(0.25 * S, 1)),
        )
    else:
        kw.update(
            layout_staggers_m=(0.0, round(0.25 * S, 1)),
            height_shifts_m=tuple(round(f * S, 1) for f in (-0.25, -0.125, 0.0, 0.125, 0.25)),
        )
    kw.update(changes)
    return StudySpec(constraint=Constraint(**cons), **kw)


# ---------------------------------------------------------------------------------------------
# Configurations
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Layout:
    """One configuration of targets (site-frame surfaces) and the pass subsets to predict."""

    group: str
    label: str
    targets: tuple[Surface, ...]
    standoff_m: float
    pass_subsets: tuple[tuple[int, ...], ...]
    params: dict = field(default_factory=dict)  # spread_m, stagger_m, setback_m, height_m


def _row_positions(n: int, spacing: float) -> list[float]:
    return [(j - (n - 1) / 2) * spacing for j in range(n)]


def _plane_combinations(base: Scenario, spec: StudySpec, every) -> list[Layout]:
    """The "planes" group: two and three planes of different inclinations in a row along the
    wall."""
    size = spec.plane_size_m
    incs = sorted(set(spec.combo_inclinations_deg), reverse=True)
    out = []
    for k in (2, 3):
        for combo in itertools.combinations(incs, k):
            tg = tuple(
                square_target(base, f"P{j + 1}", inc, size, x)
                for j, (inc, x) in enumerate(zip(combo, _row_positions(k, spec.spacing_m), strict=False))
            )
            out.append(Layout("planes", "/".join(f"{c:g}" for c in combo), tg, base.standoff_m, every))
    return out


def _height_shifts(own: tuple[Surface, ...], standoff_m: float, spec: StudySpec, every) -> list[Layout]:
    """The "height" group: the scenario's own targets raised or lowered together."""
    h0 = float(np.mean([t.up_m for t in own]))
    out = []
    for dh in spec.height_shifts_m:
        tg = tuple(replace(t, up_m=t.up_m + dh) for t in own)
        out.append(Layout("height", f"{h0 + dh:.2f} m", tg, standoff_m, every, {"height_m": h0 + dh}))
    return out


def layouts(base: Scenario, spec: StudySpec) -> list[Layout]:
    """All configurations of the study, group by group."""
    all_passes = tuple(p.id for p in base.passes)
    every = (all_passes,)
    subsets = tuple(c for k in range(1, len(all_passes) + 1) for c in itertools.combinations(all_passes, k))
    S, size = base.standoff_m, spec.plane_size_m
    own = tuple(scenario_targets(base))
    out: list[Layout] = []
    for g in spec.groups:
        if g == "passes":
            out.append(Layout(g, f"vertical {size:g} m", (square_target(base, "P", 90.0, size),), S, subsets))
        elif g == "site_passes":
            out.append(Layout(g, base.name, own, S, subsets))
        elif g == "inclination":
            out += [
                Layout(g, f"{i:g}°", (square_target(base, "P", i, size),), S, every)
                for i in spec.inclinations_deg
            ]
        elif g == "size":
            out += [
                Layout(g, f"{s:g} m", (square_target(base, "P", 90.0, s),), S, every) for s in spec.sizes_m
            ]
        elif g == "planes":
            out += _plane_combinations(base, spec, every)
        elif g == "standoff":
            out += [Layout(g, f"{s:g} m", own, s, every) for s in spec.standoffs_m]
        elif g == "height":
            out += _height_shifts(own, S, spec, every)
        elif g == "layout":
            out += _layout_candidates(base, spec)
    return out


def _overlap(targets: Sequence[Surface], size_m: float) -> bool:
    """Whether two targets of a layout would intersect (their centres closer than the size,
    with a 0.2 m gap, along the wall and in height, at the same setback)."""
    for a, b in itertools.combinations(targets, 2):
        if (
            abs(a.along_m - b.along_m) < size_m + 0.2
            and abs(a.up_m - b.up_m) < size_m + 0.2
            and abs(a.out_m - b.out_m) < size_m
        ):
            return True
    return False


def _layout_candidates(base: Scenario, spec: StudySpec) -> list[Layout]:
    """The recommendation's search space: inclinations (every assignment for ≤ 2 targets,
    combinations for more), spread along the wall (0: stacked), height stagger (odd targets
    raised) and setback (odd targets moved back), at the constraint's size and passes; layouts
    whose targets would overlap are left out."""
    c = spec.constraint
    n, size = c.n_targets, c.max_size_m
    incs = spec.layout_inclinations_deg
    combos = itertools.product(incs, repeat=n) if n <= 2 else itertools.combinations_with_replacement(incs, n)
    ground = ground_based(base)
    out = []
    for combo in combos:
        for spread, stagger, setback in itertools.product(
            spec.layout_spreads_m if n > 1 else (0.0,),
            spec.layout_staggers_m if n > 1 else (0.0,),
            spec.layout_setbacks_m if n > 1 else (0.0,),
        ):
            tg = []
            for j, (inc, x) in enumerate(zip(combo, _row_positions(n, spread / max(n - 1, 1)), strict=False)):
                high = j % 2 == 1
                lift = (stagger if high else 0.0) if ground else (stagger / 2 if high else -stagger / 2)
                tg.append(square_target(base, f"T{j + 1}", inc, size, x, lift, setback if high else 0.0))
            if _overlap(tg, size):
                continue
            label = (
                "/".join(f"{i:g}" for i in combo)
                + f" spread {spread:g} stagger {stagger:g} setback {setback:g}"
            )
            out.append(
                Layout(
                    "layout",
                    label,
                    tuple(tg),
                    base.standoff_m,
                    (c.passes,),
                    {"spread_m": spread, "stagger_m": stagger, "setback_m": setback},
                )
            )
    return out
