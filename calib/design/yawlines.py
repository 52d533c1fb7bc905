"""Lines for yaw (docs/architecture.md §7 "Lines for yaw"): which extra lines make the boresight
yaw observable from the scene's piles, and how much each buys, against the limit.

A yaw error δψ turns every profile about the vertical: a feature at range ρ moves along the
track by ρ·δψ. Targets on a wall seen from one standoff tell that apart from a POS position
error only through their small spread of range; a pile standing in front of the wall, seen from
lines at several standoffs, is moved by ρ₁·δψ on one and ρ₂·δψ on the other — the difference
is yaw alone. The study adds to the scenario's own passes, at each offset, a pair of lines
parallel to the wall (0° and 180°) that much farther out, and predicts the GLS σ of each angle
(its Cramér–Rao bound under Gauss–Markov POS errors: :func:`calib.boresight.covariance.predict_covariance`)
for the own passes and each addition, with the targets alone and with the targets and piles —
one noise-free simulation of the scenario's targets and piles serving every row.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from calib.boresight.covariance import predict_covariance
from calib.boresight.errormodel import ErrorModel
from calib.design.prediction import ANGLES, DesignError, Sigmas, feature_observations, select_passes
from calib.io.site import PassSpec
from calib.sim.noise import PosNoise, ScannerNoise
from calib.sim.scenario import Scenario
from calib.sim.simulate import SimulationError, simulate
from calib.survey.passplan import PassPlanError

#: Pairs of parallel lines this far beyond the scenario's standoff (metres).
DEFAULT_OFFSETS_M = (20.0, 40.0, 60.0)
#: What a pile's surface departs from a cylinder (RMS, metres): added to its points' range σ.
PILE_SHAPE_SIGMA_M = 0.005
FEATURE_SETS = ("targets", "targets+piles")
YAW_LINE_COLUMNS = (
    ["lines", "passes", "added_lines", "added_time_s", "features", "n_points", "n_piles"]
    + [f"sigma_{a}_deg" for a in ANGLES]
    + ["yaw_gain"]
)


@dataclass(frozen=True)
class LineSet:
    """The scenario's own passes and some of the added pairs."""

    label: str
    pass_ids: tuple[int, ...]
    added: tuple[PassSpec, ...]

    @property
    def added_time_s(self) -> float:
        return float(sum(p.length_m / p.speed_mps for p in self.added))


def yaw_scenario(base: Scenario, offsets_m: Sequence[float]) -> tuple[Scenario, list[LineSet]]:
    """``base`` with only its targets and piles, no noise, every scan angle recorded, and at each
    offset a pair of lines parallel to the wall that much beyond its standoff; the line sets to
    predict: the own passes, with each pair, with every pair."""
    if any(not off > 0 for off in offsets_m):
        raise DesignError(f"yaw lines: offsets {list(offsets_m)} m, expected each > 0")
    own = base.passes
    first = max(p.id for p in own) + 1
    pairs = [
        tuple(
            PassSpec(first + 2 * k + j, h, own[0].length_m, own[0].speed_mps, base.standoff_m + off)
            for j, h in enumerate((0.0, np.pi))
        )
        for k, off in enumerate(offsets_m)
    ]
    targets = tuple(s for s in base.surfaces if s.kind == "target")
    sc = replace(
        base,
        surfaces=targets,
        scanner_noise=ScannerNoise(),
        pos_noise=PosNoise("none"),
        scanner=replace(base.scanner, angular_windows_rad=()),
        passes=own + tuple(p for pair in pairs for p in pair),
    )
    own_ids = tuple(p.id for p in own)
    sets = [LineSet("own passes", own_ids, ())]
    sets += [
        LineSet(f"+ 2 lines at {base.standoff_m + off:g} m", own_ids + (a.id, b.id), (a, b))
        for off, (a, b) in zip(offsets_m, pairs, strict=True)
    ]
    if len(pairs) > 1:
        every = tuple(p for pair in pairs for p in pair)
        far = ", ".join(f"{base.standoff_m + off:g}" for off in offsets_m)
        sets.append(LineSet(f"+ {len(every)} lines at {far} m", own_ids + tuple(p.id for p in every), every))
    return sc, sets


def predict_yaw_lines(
    base: Scenario,
    sigmas: Sigmas,
    offsets_m: Sequence[float] = DEFAULT_OFFSETS_M,
    seed: int = 0,
    shape_sigma_m: float = PILE_SHAPE_SIGMA_M,
) -> list[dict]:
    """One row per line set and feature set (:data:`YAW_LINE_COLUMNS`): the GLS σ (deg) of each
    angle; ``yaw_gain`` is the own passes' yaw σ with the targets alone over the row's."""
    sc, sets = yaw_scenario(base, offsets_m)
    sim = simulate(sc, seed)
    obs, features = feature_observations(sim, sigmas, shape_sigma_m)
    n_targets = len(sim.site.targets)
    model = ErrorModel("gauss_markov", tuple(sigmas.correlation_time_s))
    kinds = FEATURE_SETS if len(features) > n_targets else FEATURE_SETS[:1]
    rows = []
    for line_set in sets:
        for kind in kinds:
            keep = obs.plane_index < (n_targets if kind == "targets" else len(features))
            o, f = select_passes(obs.select(keep), features, line_set.pass_ids)
            cov = predict_covariance(o, sim.mount_true, f, (), model, estimator="gls")["realistic"]
            rows.append(_row(line_set, kind, o, len(f) - n_targets, np.degrees(np.sqrt(np.diag(cov)))))
    reference = rows[0]["sigma_yaw_deg"]
    for r in rows:
        r["yaw_gain"] = reference / r["sigma_yaw_deg"]
    return rows


def yaw_lines_or_why(
    base: Scenario, sigmas: Sigmas, offsets_m: Sequence[float] = DEFAULT_OFFSETS_M, seed: int = 0
) -> tuple[list[dict], str]:
    """:func:`predict_yaw_lines`, or no rows and why they cannot be predicted (a line that cannot
    be sailed, a scene the passes do not see)."""
    try:
        return predict_yaw_lines(base, sigmas, offsets_m, seed), ""
    except (PassPlanError, SimulationError, DesignError) as e:
        return [], str(e)


def _row(line_set: LineSet, kind: str, obs, n_piles: int, sigma_deg: np.ndarray) -> dict:
    return {
        "lines": line_set.label,
        "passes": line_set.pass_ids,
        "added_lines": len(line_set.added),
        "added_time_s": line_set.added_time_s,
        "features": kind,
        "n_points": len(obs),
        "n_piles": max(n_piles, 0),
        **{f"sigma_{a}_deg": float(s) for a, s in zip(ANGLES, sigma_deg, strict=True)},
    }


def best_for_yaw(rows: Sequence[dict]) -> dict:
    """The row of the smallest yaw σ; of rows within 10 % of it, the one that adds the fewest
    lines (a pair of lines costs a few minutes of the vessel)."""
    best = min(r["sigma_yaw_deg"] for r in rows)
    near = [r for r in rows if r["sigma_yaw_deg"] <= 1.1 * best]
    return min(near, key=lambda r: (r["added_lines"], r["sigma_yaw_deg"]))


def yaw_lines_markdown(rows: Sequence[dict], note: str = "") -> list[str]:
    """summary.md's section: the table of :func:`predict_yaw_lines` and the lines to sail."""
    L = ["", "## Lines for yaw", ""]
    if not rows:
        return L + [f"Not predicted: {note}" if note else "Not predicted."]
    L += [
        "The GLS σ of each angle (its Cramér–Rao bound under the Gauss–Markov POS errors) with "
        "the scenario's passes and with pairs of lines parallel to the wall farther out: a "
        "yaw error moves a pile along the track by range × δψ, so lines at two standoffs "
        f"disagree by Δrange × δψ. Pile points weighted with {1000 * PILE_SHAPE_SIGMA_M:g} mm of "
        "shape beside the scanner's noise (`yaw_lines.csv`, `sigma_yaw_lines.png`).",
        "",
        "| lines | added | features | points | σ roll | σ pitch | σ yaw | yaw gain |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        L.append(
            f"| {r['lines']} | {r['added_lines']} ({r['added_time_s']:.0f} s) | {r['features']} "
            f"| {r['n_points']} | {_mdeg(r['sigma_roll_deg'])} | {_mdeg(r['sigma_pitch_deg'])} "
            f"| {_mdeg(r['sigma_yaw_deg'])} | ×{r['yaw_gain']:.2f} |"
        )
    best = best_for_yaw(rows)
    L += [
        "",
        f"For yaw: sail **{best['lines']}** and use the {best['features']}: σ yaw {_mdeg(best['sigma_yaw_deg'])}.",
    ]
    if not any(r["n_piles"] for r in rows):
        L.append("The scene has no pile the passes see: only the targets observe yaw here.")
    return L


def _mdeg(v: float) -> str:
    return f"{1000 * v:.1f} mdeg"


def plot_yaw_lines(rows: Sequence[dict], path, title: str = ""):
    """σ yaw per line set, the targets alone beside the targets and piles."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sets = list(dict.fromkeys(r["lines"] for r in rows))
    fig, ax = plt.subplots(figsize=(max(6.0, 1.6 * len(sets)), 4.5))
    x = np.arange(len(sets))
    for k, kind in enumerate(FEATURE_SETS):
        ys = [
            next(
                (1000 * r["sigma_yaw_deg"] for r in rows if r["lines"] == s and r["features"] == kind), np.nan
            )
            for s in sets
        ]
        ax.bar(x + (k - 0.5) * 0.38, ys, 0.38, label=kind)
    ax.set_xticks(x)
    ax.set_xticklabels(sets, fontsize=8)
    ax.set_ylabel("σ yaw (mdeg, GLS = Cramér–Rao bound)")
    ax.set_title(f"{title}lines for yaw", fontsize=10)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
