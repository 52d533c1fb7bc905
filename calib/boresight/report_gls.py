"""The parts of ``report.md`` about the estimator: which σ to use under which POS error model,
the default beside the thesis estimator, the POS correlation time (estimated, and the
boresight at τ/3, τ and 3τ) and the tie patches (a table and a plan view,
``tie_patches.png``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calib.boresight.observability import ANGLE_NAMES

PLOT_DPI = 110


def _row(label: str, b_deg, s_deg) -> str:
    cells = " | ".join(f"{b:.4f} ± {s:.4f}" for b, s in zip(b_deg, s_deg, strict=False))
    return f"| {label} | {cells} |"


def _pos_model_phrase(res, doc: dict) -> str:
    """The POS error model the realistic σ assumes, in words (τ and where it came from)."""
    em = res.error_model
    if em.kind == "gauss_markov":
        tau = em.correlation_time_s
        tau_s = (
            f"{tau:g} s"
            if isinstance(tau, float)
            else "/".join(f"{x:g}" for x in tau) + " s (N/E/D/roll/pitch/heading)"
        )
        return (
            f"first-order Gauss–Markov POS errors with correlation time {tau_s} "
            f"(from {doc.get('realistic_correlation_time_source', 'the caller')})"
        )
    if em.kind == "pass_bias":
        return "POS errors constant within each pass and independent between passes"
    return "independent POS errors per point (the formal model itself)"


def realistic_sigma_lines(res, doc: dict) -> list[str]:
    """Markdown lines: which σ to use and why (the estimator and the POS error model), and what
    the jackknife σ is."""
    model = _pos_model_phrase(res, doc)
    ratio = res.sigma_realistic_rad / res.sigma_formal_rad
    if doc.get("estimator") == "gls":
        L = [
            f"**Use the realistic σ** — for the GLS estimator it is its formal σ: the model "
            f"holds {model}, so the correlation of the POS errors is estimated, not ignored."
        ]
    elif res.error_model.kind == "white":
        L = [
            "**Use the realistic σ** — here it equals the formal σ, because the white "
            "error model was chosen: POS errors correlated in time would make it "
            "optimistic."
        ]
    else:
        L = [
            f"**Use the realistic σ.** The formal σ (σ0 = 1) assumes every point's POS "
            f"error is independent; it is optimistic by a factor of {ratio[0]:.1f} for "
            f"roll, {ratio[1]:.1f} for pitch and {ratio[2]:.1f} for yaw (realistic / "
            f"formal). The realistic σ propagates {model} through the estimator: within "
            f"a pass such errors act almost as a bias, which more points do not average "
            f"out."
        ]
    if res.cov_jackknife is not None:
        L.append("")
        L.append(
            "The delete-one-pass jackknife σ is an empirical check from the spread of the "
            "estimates without each pass (few passes: itself uncertain by ±30–50 %)."
        )
    return L


def estimator_section(run) -> list[str]:
    """Markdown lines: the estimators side by side, τ, the tie patches."""
    doc, res = run.doc, run.result
    L = ["## Estimator", ""]
    if doc.get("estimator") != "gls":
        L.append(
            f"Estimator: {doc.get('estimator', 'thesis')} (white weights as in the thesis; the realistic σ "
            f"propagates the POS error model through it). The default, `--estimator gls`, models the POS "
            f"errors as Gauss–Markov processes and is several times more precise on correlated POS errors."
        )
        return L
    L.append(
        "GLS (the default): each POS channel's error is a first-order Gauss–Markov process on the "
        "trajectory's epochs (knots; the exact AR(1) prior between them), estimated jointly with the "
        "boresight and the planes, and the knots are eliminated with a banded factorization — O(n) in "
        "the points. Its formal σ is its realistic σ. The thesis estimator (white weights) on the same "
        "targets is beside it for comparison."
    )
    L.append("")
    L.append("| estimator | " + " | ".join(f"{a} (°)" for a in ANGLE_NAMES) + " |")
    L.append("|---|" + "---:|" * 3)
    L.append(_row("**GLS (default)**", np.degrees(res.boresight_rad), np.degrees(res.sigma_realistic_rad)))
    for key, label in (("targets_only", "GLS, targets only"), ("thesis_estimator", "thesis (white weights)")):
        if key in doc:
            L.append(_row(label, doc[key]["boresight_deg"], doc[key]["sigma_realistic_deg"]))
    L.append("")
    if "tau_estimate" in doc:
        t = doc["tau_estimate"]
        L.append(
            f"**τ was not configured** (site.yaml `pos_sigmas.correlation_time_s`): estimated "
            f"{t['tau_s']:.1f} s from the data by restricted likelihood over "
            f"{', '.join(f'{x:g}' for x in t['grid_s'])} s. Configure it when you know it."
        )
        L.append("")
    if "tau_sensitivity" in doc:
        L.append("| τ (s) | " + " | ".join(f"{a} (°)" for a in ANGLE_NAMES) + " |")
        L.append("|---:|" + "---:|" * 3)
        for r in doc["tau_sensitivity"]:
            L.append(_row(f"{r['tau_s']:.1f}", r["boresight_deg"], r["sigma_deg"]))
        L.append("")
    L.extend(_patch_lines(run))
    L.extend(crlb_lines(run.doc))
    check = doc.get("tie_patch_check")
    if check is not None:
        L.append("")
        L.append(
            f"Do the patches agree with the targets? The boresight moved by χ² = {check['chi2']:.2f} "
            f"({check['dof']} degrees of freedom, p = {check['p_value']:.2g}) when they were added "
            f"(a Hausman test: the difference of two efficient estimates has covariance Σ_targets − "
            f"Σ_patches); below p = {check['alpha']:g} they are refused and the targets alone give the "
            f"result — " + ("**refused**." if not check["agree"] else "accepted.")
        )
    return L


def crlb_lines(doc: dict) -> list[str]:
    """What each kind of scene feature adds to each angle, against the Cramér–Rao bound."""
    rows = doc.get("crlb_by_features_deg")
    if not rows:
        return []
    L = [
        "",
        "Cramér–Rao σ of each angle with the features added one kind at a time (the bound at the "
        "solution, flat features; yaw is the angle the scene's piles and corners carry):",
        "",
        "| features | roll (mdeg) | pitch (mdeg) | yaw (mdeg) |",
        "|---|---:|---:|---:|",
    ]
    for label, sig in rows.items():
        L.append(f"| {label} | " + " | ".join(f"{x * 1e3:.1f}" for x in sig) + " |")
    return L


def _patch_lines(run) -> list[str]:
    doc = run.doc
    if doc.get("tie_patches_mode") == "off":
        return ["Tie patches: off (`--tie-patches off`)."]
    patches = doc.get("tie_patches")
    rough = {p["name"]: p.get("roughness_m") for p in run.result.plane_stats}
    if not patches:
        return [
            "Tie patches: none chosen (no planar surface seen from two headings besides the targets)."
        ] + _cylinder_lines(doc, rough)
    cand = doc.get("tie_patch_candidates", {})
    L = [
        f"Tie patches: {len(patches)} of {cand.get('found', '?')} candidate cells of "
        f"{cand.get('size_m', float('nan')):g} m (rejected cells: "
        + ", ".join(f"{k} {v}" for k, v in cand.get("rejected_cells", {}).items())
        + "), chosen by their gain in the boresight's information; each has its own plane and a "
        "roughness σ estimated from its residuals, so a wall that is not flat widens σ instead of "
        "bending the boresight.",
        "",
        "| patch | points | passes | centre N, E, D (m) | normal | roughness (mm) | info gain |",
        "|---|---:|---|---|---|---:|---:|",
    ]
    for p in patches:
        r = rough.get(p["name"])
        L.append(
            f"| {p['name']} | {p['n_points']} | {', '.join(map(str, p['passes']))} | "
            + ", ".join(f"{x:.2f}" for x in p["center_lgf_m"])
            + " | "
            + ", ".join(f"{x:+.3f}" for x in p["normal"])
            + f" | {'—' if r is None else f'{r * 1e3:.1f}'} | {p['info_gain']:.3f} |"
        )
    return L + _cylinder_lines(doc, rough)


def _cylinder_lines(doc: dict, rough: dict) -> list[str]:
    """The chosen tie cylinders (piles, posts): a yaw moves a point along the track, and on a
    cylinder that changes its distance from the axis, so they carry what a flat wall does not."""
    cyls = doc.get("tie_cylinders") or []
    found = doc.get("tie_cylinder_candidates", {}).get("found", 0)
    leaning = doc.get("tie_cylinder_candidates", {}).get("rejected", {}).get("leaning", 0)
    why = f"; {leaning} rejected as leaning: the adjustment models upright piles" if leaning else ""
    if not cyls:
        return ["", f"Tie cylinders: none chosen ({found} vertical cylinders found near the targets{why})."]
    L = [
        "",
        f"Tie cylinders: {len(cyls)} of {found} vertical cylinders (piles, posts) found near the "
        "targets; each has its own axis and radius and a roughness σ like a patch.",
        "",
        "| cylinder | points | passes | axis N, E (m) | radius (m) | roughness (mm) | info gain |",
        "|---|---:|---|---|---:|---:|---:|",
    ]
    for c in cyls:
        r = rough.get(c["name"])
        L.append(
            f"| {c['name']} | {c['n_points']} | {', '.join(map(str, c['passes']))} | "
            + ", ".join(f"{x:.2f}" for x in c["axis_center_lgf_m"][:2])
            + f" | {c['radius_m']:.3f} | {'—' if r is None else f'{r * 1e3:.1f}'} | {c['info_gain']:.3f} |"
        )
    return L


def tie_patch_plot(run, out_dir: Path) -> Path | None:
    """Plan view (east, north) of the targets' and the tie patches' points, one colour per
    plane, the patches labelled: where the information beside the targets came from."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    obs, res = run.observations, run.result
    if not obs.patch_planes:
        return None
    fig, axes = plt.subplots(1, 2, figsize=(10.0, 4.2), constrained_layout=True)
    ax_plan, ax_face = axes
    state = res.state
    for j, name in enumerate(obs.plane_names):
        patch = j in obs.patch_planes
        c = state.centers_m[j]
        ax_plan.plot(
            c[1], c[0], "s" if patch else "o", ms=6 if patch else 9, color="tab:blue" if patch else "tab:red"
        )
        ax_face.plot(
            c[1], -c[2], "s" if patch else "o", ms=6 if patch else 9, color="tab:blue" if patch else "tab:red"
        )
        ax_face.annotate(name, (c[1], -c[2]), fontsize=6, xytext=(2, 2), textcoords="offset points")
    for ax, ylab, title in ((ax_plan, "north (m)", "plan"), (ax_face, "up (m)", "seen from the water")):
        ax.set_xlabel("east (m)")
        ax.set_ylabel(ylab)
        ax.set_title(title, fontsize=10)
        ax.set_aspect("equal", adjustable="datalim")
    fig.suptitle("Targets (red) and tie patches (blue): plane centres in the local frame")
    path = out_dir / "tie_patches.png"
    fig.savefig(path, dpi=PLOT_DPI)
    plt.close(fig)
    return path
