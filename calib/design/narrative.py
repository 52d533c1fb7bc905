"""``summary.md`` of the design study (:mod:`calib.design.summary` writes it): the study in
words — the thesis's findings checked on it, the visibility criteria, the predicted σ, the
recommended site and why it differs from the thesis's.
"""

from __future__ import annotations

import math

import numpy as np

from calib.design.criteria import best_inclinations, is_angular
from calib.design.prediction import ANGLES, ESTIMATOR_MODEL, MODELS
from calib.design.scenes import ground_based, surface_inclination_deg
from calib.design.study import Recommendation, StudyResult
from calib.design.yawlines import yaw_lines_markdown
from calib.sim.scenario import Scenario


def _deg3(row: dict, model: str) -> str:
    return ", ".join(f"{a} {row[f'sigma_{model}_{a}_deg']:.4f}°" for a in ANGLES)


def _best(rows, key="sigma_white_total_deg"):
    """The observable row of the smallest ``key`` (None: none observable)."""
    rows = [r for r in rows if r["observable"]]
    return min(rows, key=lambda r: r[key]) if rows else None


def _pass_findings(result: StudyResult) -> list[dict]:
    """All six passes are best, under white noise and (GLS) the realistic σ."""
    out = []
    passes = result.rows("passes")
    if passes:
        b = _best(passes)
        out.append(
            {
                "name": "all six passes give the smallest σ (one vertical plane, white)",
                "holds": len(b["passes"]) == max(len(r["passes"]) for r in passes),
                "ours": f"best subset {b['passes']}: {b['sigma_white_total_deg']:.4f}°",
            }
        )
    for g, what in (("passes", "one vertical plane"), ("site_passes", "the scenario's targets")):
        rows = result.rows(g)
        if rows:
            br = _best(rows, "realistic_total_deg")
            out.append(
                {
                    "name": f"… realistic σ (time-correlated POS errors, GLS), {what}",
                    "holds": len(br["passes"]) == max(len(r["passes"]) for r in rows),
                    "ours": f"best subset {br['passes']}: {br['realistic_total_deg']:.4f}°",
                }
            )
    return out


def _single_plane_findings(result: StudyResult) -> list[dict]:
    """A vertical plane is the best single plane; σ decreases with the plane's size."""
    out = []
    inc = result.rows("inclination")
    if inc:
        b = _best(inc)
        out.append(
            {
                "name": "a vertical plane is best among single planes (white)",
                "holds": abs(b["inclinations_deg"][0]) == 90.0,
                "ours": f"best {b['label']}: {b['sigma_white_total_deg']:.4f}°",
            }
        )
    size = sorted(result.rows("size"), key=lambda r: r["sizes_m"][0][0])
    if len(size) > 1:
        s = [r["sigma_white_total_deg"] for r in size]
        out.append(
            {
                "name": "σ decreases with the plane size",
                "holds": all(a > b for a, b in zip(s, s[1:], strict=False)),
                "ours": ", ".join(f"{r['label']}: {r['sigma_white_total_deg']:.4f}°" for r in size),
            }
        )
    return out


def _three_plane_findings(result: StudyResult) -> list[dict]:
    """Three planes 90/60/30 near the best triple, 90/30 within 20 %, under each model."""
    planes = {tuple(r["inclinations_deg"]): r for r in result.rows("planes") if r["observable"]}
    k3, k2 = (90.0, 60.0, 30.0), (90.0, 30.0)
    if k3 not in planes or k2 not in planes:
        return []
    out = []
    for model, key in (
        ("white", "sigma_white_total_deg"),
        ("per-pass biases, thesis adjustment", "sigma_pass_bias_total_deg"),
        ("Gauss–Markov, thesis adjustment", "sigma_gauss_markov_total_deg"),
        ("Gauss–Markov, GLS", "sigma_gls_total_deg"),
    ):
        triples = [r for k, r in planes.items() if len(k) == 3]
        b = min(triples, key=lambda r: r[key])
        r3, r2 = planes[k3][key], planes[k2][key]
        out.append(
            {
                "name": f"three planes 90/60/30 near the best, 90/30 within 20% ({model})",
                "holds": r3 <= 1.10 * b[key] and r2 <= 1.20 * r3,
                "ours": f"best triple {b['label']} {b[key]:.4f}°, 90/60/30 {r3:.4f}° "
                f"(×{r3 / b[key]:.2f}), 90/30 {r2:.4f}° (×{r2 / r3:.2f} of 90/60/30)",
            }
        )
    return out


def _invisible_findings(result: StudyResult) -> list[dict]:
    """A Z lever-arm error is invisible; roll and the scan-angle offset are one."""
    out = []
    vis = [v for v in result.visibility if v["error"] == "lever_arm_z"]
    if vis:
        out.append(
            {
                "name": "a Z lever-arm error is invisible in every configuration",
                "holds": not any(v["visible"] for v in vis),
                "ours": f"largest pass-to-pass spread {max(v['distance_spread_m'] for v in vis):.2e} m, "
                f"{max(v['angle_spread_deg'] for v in vis):.2e}°",
            }
        )
    out.append(
        {
            "name": "roll boresight and scan-angle offset strongly correlated",
            "holds": result.roll_scan_correlation > 0.99,
            "ours": f"|ρ| = {result.roll_scan_correlation:.6f}",
        }
    )
    return out


def findings(result: StudyResult) -> list[dict]:
    """The thesis's qualitative findings, checked on this study (name, thesis, ours, holds)."""
    return (
        _pass_findings(result)
        + _single_plane_findings(result)
        + _three_plane_findings(result)
        + _invisible_findings(result)
    )


_MODEL_NAMES = {
    "white": "white noise (formal)",
    "gls": "Gauss–Markov POS errors, GLS estimator (= CRLB)",
    "pass_bias": "per-pass POS biases, thesis adjustment",
    "pass_bias_offsets": "per-pass POS biases, with pass offsets",
    "gauss_markov": "Gauss–Markov POS errors, thesis adjustment",
    "gauss_markov_offsets": "Gauss–Markov POS errors, with pass offsets",
}


#: how summary.md names the calibration's estimators
ESTIMATOR_NAMES = {
    "gls": "GLS estimator",
    "thesis": "thesis adjustment",
    "pass_offsets": "thesis adjustment with pass offsets",
}


def tau_text(row: dict) -> str:
    """The correlation times of a row, each once (s, slash-separated)."""
    return "/".join(f"{t:g}" for t in dict.fromkeys(row["correlation_time_s"]))


def _why_model(rec: Recommendation, sc: Scenario) -> list[str]:
    """Why correlated POS errors change the design, and how the estimator copes with them."""
    gls = rec.estimator_name == "gls"
    txt = [
        "Under white noise (the thesis's model) a site's σ is set by how many points its "
        "targets return and how different their normals are, and the thesis's site (targets of "
        "different inclinations — vertical and 45° at Montreal — a few metres apart at one "
        "height and range) looks excellent. But INS "
        "errors are correlated in time: during the few seconds a pass sees the targets, the "
        "position error is nearly a constant translation of that pass's points, and seen from "
        f"{sc.standoff_m:g} m a translation of a centimetre looks like a boresight rotation of "
        "a few hundredths of a degree."
    ]
    if gls:
        txt.append(
            "The GLS estimator estimates the POS errors (Gauss–Markov processes with the "
            "trajectory's correlation times) together with the boresight: what is left is the "
            "part of a rotation that a slowly drifting POS error can imitate on these targets, "
            "and a layout is good when its targets make a rotation move them in ways no "
            "translation or drift of the vessel does."
        )
    else:
        txt.append(
            "Adjusting per-pass trajectory offsets removes a translation only where the targets "
            "can tell it from a rotation: with two targets of different normals a per-pass "
            "translation explains both targets' offsets at once, so the offsets take the "
            "boresight's signal with them."
        )
    return txt


def _why_geometry(rec: Recommendation) -> list[str]:
    """What the recommended targets' placement does against the POS errors."""
    tg, p = rec.layout.targets, rec.layout.params
    same_normal = len({round(surface_inclination_deg(t), 6) for t in tg}) == 1
    txt = []
    if rec.estimator and same_normal:
        txt.append(
            "The recommended targets share one normal: a translation moves both alike, "
            "a rotation moves them by amounts that grow with their lever from the scanner, "
            "so the per-pass offsets absorb the POS error and leave the rotation."
        )
    if p.get("spread_m", 1.0) == 0.0 and p.get("stagger_m", 0.0) > 0:
        txt.append(
            f"They stand one above the other ({p['stagger_m']:g} m apart): every profile "
            "crosses both at the same instant, so the POS error's drift within a pass "
            "cancels between them too (targets spread along the wall or in range are "
            "crossed seconds apart, and the drift over those seconds — half the POS σ for "
            f"correlation times of {tau_text(rec.row)} s — corrupts exactly the difference "
            "the design relies on)."
        )
    if p.get("stagger_m", 0.0) > 0:
        txt.append(
            f"The height difference ({p['stagger_m']:g} m) turns roll (a displacement across the "
            "track proportional to the height) and pitch (along the track, proportional "
            "to the height, seen at 45° by the oblique passes) into differences between "
            "the targets that no translation produces."
        )
    if p.get("setback_m", 0.0) > 0:
        txt.append(
            f"One target is set back {p['setback_m']:g} m: a yaw moves points along the "
            "track in proportion to their horizontal range, a translation does not."
        )
    return txt


def _why_result(rec: Recommendation) -> list[str]:
    """The weakest angle and the σ against the scenario's own site."""
    txt = []
    r, b = rec.row, rec.baseline_row
    real = ESTIMATOR_MODEL[rec.estimator_name]
    if max(ANGLES, key=lambda a: r[f"sigma_{real}_{a}_deg"]) == "yaw":
        txt.append(
            "Yaw stays the weakest angle: a profiler's yaw moves points along the track "
            "by their horizontal range, as an along-track POS error moves them, so only "
            "differences in range, the targets' own extent and the pass headings separate "
            "it from an along-track translation."
        )
    if b:
        txt.append(
            f"Predicted realistic σ ({ESTIMATOR_NAMES[rec.estimator_name]}): "
            f"{r['realistic_total_deg']:.4f}° against {b['realistic_total_deg']:.4f}° for the "
            "scenario's own site."
        )
    return txt


def _why(rec: Recommendation, sc: Scenario) -> str:
    """Where and why the recommended layout differs from the thesis's site (physics, with the
    layout's own parameters)."""
    return " ".join(_why_model(rec, sc) + _why_geometry(rec) + _why_result(rec))


def _own_site_name(sc: Scenario) -> str:
    return "the thesis's site (montreal)" if sc.name == "montreal" else f"the scenario's own site ({sc.name})"


def _crlb_comparison(rec: Recommendation, sc: Scenario) -> list[str]:
    """summary.md: the recommended site and the scenario's own (the thesis's, for montreal)
    under the GLS estimator, whose predicted σ is the Cramér–Rao bound, beside the thesis's
    adjustments."""
    rows = [("recommended site", rec.row)] + (
        [(_own_site_name(sc), rec.baseline_row)] if rec.baseline_row else []
    )
    if not all(math.isfinite(r.get("sigma_gls_total_deg", math.inf)) for _, r in rows):
        return []
    L = [
        "",
        "### Under the GLS estimator (the calibration's default)",
        "",
        "For the GLS model the predicted σ is the covariance of the GLS estimator — the inverse "
        "of the Fisher information of the Gauss–Markov POS error model, linearized at the "
        "truth — so it **is** the Cramér–Rao bound (CRLB): no unbiased estimator does better "
        "with these targets, passes and sigmas, and the GLS estimator attains it (its formal σ "
        "is its realistic σ). The thesis's adjustments under the same POS errors beside it:",
        "",
        "| site | GLS σ = CRLB: roll | pitch | yaw | total | thesis adjustment total | with pass offsets total |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, r in rows:
        L.append(
            f"| {name} | "
            + " | ".join(f"{r[f'sigma_gls_{a}_deg']:.4f}°" for a in ANGLES)
            + f" | {r['sigma_gls_total_deg']:.4f}° | {r['sigma_gauss_markov_total_deg']:.4f}° | "
            f"{r['sigma_gauss_markov_offsets_total_deg']:.4f}° |"
        )
    if len(rows) == 2:
        a, b = rows[0][1]["sigma_gls_total_deg"], rows[1][1]["sigma_gls_total_deg"]
        L += [
            "",
            f"The recommended site's CRLB is {a:.4f}° against {b:.4f}° (×{a / b:.2f}) for "
            f"{rows[1][0]}; on that site the GLS estimator is "
            f"×{rows[1][1]['sigma_gauss_markov_total_deg'] / b:.1f} better than the thesis's "
            f"adjustment and ×{rows[1][1]['sigma_gauss_markov_offsets_total_deg'] / b:.1f} better "
            "than the one with pass offsets.",
        ]
    return L


def _study_header(result: StudyResult) -> list[str]:
    """The title, the scenario, its passes, the profiler and the sigmas assumed."""
    sc, sg = result.scenario, result.sigmas
    L = [
        f"# Site design study — {sc.name}",
        "",
        f"{sc.description.strip()}",
        "",
        f"Standoff {sc.standoff_m:g} m, passes "
        + ", ".join(f"{p.id} ({np.degrees(p.relative_heading_rad) % 360:g}°)" for p in sc.passes)
        + f"; profiler at {sc.scanner.effective_profile_rate_hz:.0f} profiles/s × "
        f"{sc.scanner.effective_points_per_360} points/360°. Sigmas assumed: range "
        f"{sg.scanner.sigma_range_m * 1e3:g} mm (+ beam divergence "
        f"{sg.scanner.beam_divergence_rad * 1e3:g} mrad), scan angle "
        f"{np.degrees(sg.scanner.sigma_scan_angle_rad):g}°, POS position "
        f"{', '.join(f'{x * 100:g}' for x in sg.position_m)} cm, attitude "
        f"{', '.join(f'{x:g}' for x in np.degrees(sg.attitude_rad))}°. "
        f"Study time {result.runtime_s:.1f} s.",
        "",
    ]
    return L


def _visibility_section(result: StudyResult) -> list[str]:
    """Which inclination sees each error best (thesis Table 3.2); none without the criteria."""
    if not result.visibility:
        return []
    sc, spec = result.scenario, result.spec
    L = [
        "",
        "## Visibility criteria (thesis Table 3.2)",
        "",
        "Each error alone at the thesis's magnitude, a level vessel, one "
        f"{spec.criteria_size_m:g} m target per inclination, georeferenced with the "
        "error-free mount. An error is visible where the passes' copies disagree (a "
        "plane-based adjustment sees nothing else); the best inclination is chosen among "
        f"those whose mean Type I reaches {spec.type1_threshold:g}.",
        "",
        "| error | magnitude | best inclination (distance) | spread | best inclination (angle) | spread |",
        "|---|---|---|---|---|---|",
    ]

    def incl(v):  # the thesis's Chapter 3 angle beside ours on a ground-based site
        tilt = f" (thesis {v['thesis_tilt_deg']:g}°)" if ground_based(sc) else ""
        return f"{v['inclination_deg']:g}°{tilt}"

    for e in dict.fromkeys(v["error"] for v in result.visibility):
        vs = [v for v in result.visibility if v["error"] == e]
        bd, ba = best_inclinations(vs, e, spec.type1_threshold)
        mag = f"{np.degrees(spec.magnitudes[e]):g}°" if is_angular(e) else f"{spec.magnitudes[e] * 100:g} cm"
        if not any(v["visible"] for v in vs):
            L.append(
                f"| {e} | {mag} | invisible | {bd['distance_spread_m']:.1e} m | invisible | "
                f"{ba['angle_spread_deg']:.1e}° |"
            )
            continue
        L.append(
            f"| {e} | {mag} | {incl(bd)} | {bd['distance_spread_m'] * 1e3:.1f} mm | "
            f"{incl(ba)} | {ba['angle_spread_deg']:.3f}° |"
        )
    L += [
        "",
        "A Z lever-arm error moves every point of every pass by the same vertical "
        "vector (the vessel is level), which the plane's own offset absorbs: no plane, "
        "inclination or pass pattern sees it (thesis C.2.5); measure it by survey. A "
        "scan-angle offset is a rotation about the scanner's x axis, i.e. a boresight "
        f"rotation: |ρ(roll, scan-angle offset)| = {result.roll_scan_correlation:.6f}; the "
        "boresight absorbs it.",
    ]
    return L


def _sigma_section(result: StudyResult) -> list[str]:
    """The best configuration of each group under white noise and realistically, and the
    models."""
    L: list[str] = []
    L += [
        "",
        "## Predicted σ (thesis Fig. 4.12)",
        "",
        "Per group the configuration with the smallest white-noise σ and the one with the "
        "smallest realistic σ (σ total = √(σ_roll² + σ_pitch² + σ_yaw²)).",
        "",
        "| group | best (white) | σ white | best (realistic) | σ realistic | adjustment |",
        "|---|---|---|---|---|---|",
    ]
    for g in result.spec.groups:
        rows = [r for r in result.rows(g) if r["observable"]]
        if not rows:
            continue
        bw = min(rows, key=lambda r: r["sigma_white_total_deg"])
        br = min(rows, key=lambda r: r["realistic_total_deg"])
        lab = (lambda r: str(r["passes"])) if g.endswith("passes") else (lambda r: r["label"])
        L.append(
            f"| {g} | {lab(bw)} | {bw['sigma_white_total_deg']:.4f}° | {lab(br)} | "
            f"{br['realistic_total_deg']:.4f}° | {br['estimator'] or '—'} |"
        )
    if result.sigma:
        L += [
            "",
            "Models: *white* treats every observation as independent (the thesis's "
            "implicit model, the adjustment's formal σ); *Gauss–Markov* correlates the POS "
            "errors in time with the trajectory's correlation times "
            f"({tau_text(result.sigma[0])} s for north, east, down, roll, pitch, heading), "
            "across passes too; *per-pass biases* hold them constant within a pass and "
            "independent between passes (the Gauss–Markov model's limit of an infinite "
            "correlation time, which misses the POS drift within a pass). The realistic σ — "
            "what the recommendation minimizes — is the GLS estimator's under the "
            "Gauss–Markov errors (the calibration's default, `--estimator gls`: the POS errors "
            "estimated as processes with the boresight); its predicted σ is the Cramér–Rao "
            "bound of that model. The thesis's adjustment (`--estimator thesis`, white "
            "weights) and the one with per-pass trajectory offsets (`--estimator "
            "pass_offsets`) are predicted beside it under the same errors, and under per-pass "
            "biases, for comparison.",
        ]
    return L


def _recommendation_section(result: StudyResult) -> list[str]:
    """The recommended site: its targets, its σ under each model, why it differs."""
    rec = result.recommendation
    if rec is None:
        return []
    sc = result.scenario
    L: list[str] = []
    c, r, b = rec.constraint, rec.row, rec.baseline_row
    L += [
        "",
        "## Recommended site",
        "",
        f"Constraint: {c.n_targets} target(s) of at most {c.max_size_m:g} m, passes "
        f"{', '.join(map(str, c.passes))}. Adjust with the "
        f"{ESTIMATOR_NAMES[rec.estimator_name]} (`mls calib run --estimator {rec.estimator_name}`).",
        "",
        "| target | inclination | size | along the wall | out from the wall line | above the scanner |",
        "|---|---|---|---|---|---|",
    ]
    for s in rec.layout.targets:
        L.append(
            f"| {s.name} | {surface_inclination_deg(s):g}° | {s.width_m:g} × {s.height_m:g} m "
            f"| {s.along_m + 0.0:+.2f} m | {s.out_m + 0.0:+.2f} m | {s.up_m:.2f} m |"
        )
    L += ["", "| model | recommended | scenario's own site |", "|---|---|---|"]
    for m in MODELS:
        L.append(
            f"| {_MODEL_NAMES[m]} | {_deg3(r, m)} (total {r[f'sigma_{m}_total_deg']:.4f}°) | "
            + (f"{_deg3(b, m)} (total {b[f'sigma_{m}_total_deg']:.4f}°) |" if b else "— |")
        )

    def corr(x):
        pairs = (("roll", "pitch"), ("roll", "yaw"), ("pitch", "yaw"))
        return ", ".join(f"{a}–{c} {x[f'corr_realistic_{a}_{c}']:+.2f}" for a, c in pairs)

    L.append(f"| correlation (realistic) | {corr(r)} | {corr(b) if b else '—'} |")
    L += _crlb_comparison(rec, sc)
    L += ["", "### Why it differs from the thesis's site", "", _why(rec, sc)]
    return L


def summary_markdown(result: StudyResult, empirical: dict | None) -> str:
    """summary.md of a design study (``empirical``: the Monte Carlo check, when run)."""
    L = _study_header(result)
    L += ["## Thesis findings on this model", "", "| finding | holds | ours |", "|---|---|---|"]
    L += [f"| {f['name']} | {'yes' if f['holds'] else '**no**'} | {f['ours']} |" for f in findings(result)]
    L += _visibility_section(result)
    L += _sigma_section(result)
    L += _recommendation_section(result)
    if "yaw_lines" in result.spec.groups:
        L += yaw_lines_markdown(result.yaw_lines, result.yaw_lines_note)
    if empirical:
        L += ["", "## Monte Carlo check", "", empirical.get("text", "")]
    L += [
        "",
        "## Files",
        "",
        "`criteria.csv` (per error, inclination and pass), `visibility.csv` (per error and "
        "inclination), `sigma.csv` (per configuration and pass subset; σ in degrees under "
        "each model — the search's layouts under white noise and the three Gauss–Markov "
        "adjustments (GLS, thesis, pass offsets) only, the recommended one under all; "
        "`estimator` names the calibration estimator of `realistic_total_deg`), "
        "`recommendation.json`, "
        "`criteria_<error>.png`, `sigma_<group>.png`; `yaw_lines.csv` (per line set and "
        "feature set, σ in degrees).",
    ]
    return "\n".join(L) + "\n"
