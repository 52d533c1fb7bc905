"""The calibration report: ``report.md`` and its PNG plots (matplotlib's Agg renderer, no
display needed).

Plots, all residuals in millimetres (signed distance of a point to its plane):

- ``residuals_by_plane.png``: histogram per target, with the normal density of its mean and σ;
- ``residuals_by_pass.png``: histogram per pass;
- ``residuals_time.png``: residuals along time, a panel per pass, a colour per target;
- ``target_<name>.png``: the target's points seen edge-on (along its plane: horizontal
  position on the target against the distance to the plane) before the calibration (a-priori
  mount, the initial plane) and after it (the estimated mount, the adjusted plane), one colour
  per pass: the passes' copies of the target, apart before, fall onto one plane after.

The narrative states the estimates, the four σ and by how much the formal σ is optimistic, the
χ² test, the correlations, the outliers, what the passes sailed can observe, and every
warning and assumption of the run.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calib.boresight.observability import ANGLE_NAMES, OBSERVING_PAIRS, sailed_headings
from calib.boresight.report_gls import estimator_section, realistic_sigma_lines, tie_patch_plot
from calib.boresight.result import OFFSET_COMPONENTS
from calib.core import frames
from calib.core.georef import Mount, georeference_poses
from calib.core.trajectory import Poses

PLOT_DPI = 110


def _deg(x_rad) -> float:
    return float(np.degrees(x_rad))


def _fmt(x: float, digits: int = 4) -> str:
    return "—" if x is None or not np.isfinite(x) else f"{x:.{digits}f}"


def _sig(x: float) -> str:
    """A σ in degrees with three significant digits."""
    return "—" if x is None or not np.isfinite(x) else f"{x:.3g}"


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name)


# -- geometry for the plots -------------------------------------------------------------------


def _used(run) -> np.ndarray:
    """Mask of the observations the adjustment kept (outliers removed)."""
    return np.isin(run.observations.point_ids, run.result.used_point_ids)


def _poses(obs) -> Poses:
    rpy = obs.l[:, 3:6]
    return Poses(obs.l[:, 0:3], rpy, frames.attitude_matrix(*rpy.T))


def _removed_group_mask(run) -> np.ndarray:
    """Mask of the observations in target groups removed by the group test."""
    obs = run.observations
    out = np.zeros(len(obs), bool)
    for g in run.result.removed_groups:
        if g.get("removed") and g["plane"] in obs.plane_names and g["pass_id"] in obs.pass_ids:
            j, k = obs.plane_names.index(g["plane"]), obs.pass_ids.index(g["pass_id"])
            out |= (obs.plane_index == j) & (obs.pass_index == k)
    return out


def edge_on(run) -> dict[str, dict]:
    """Per target, for the kept points and those of removed groups (``removed``): horizontal
    position on the plane (m) and distance to the plane (m), before (a-priori mount, initial
    plane) and after (estimated mount and extras, adjusted plane), and each point's pass
    index."""
    obs, res = run.observations, run.result
    shown = _used(run) | _removed_group_mask(run)
    removed = _removed_group_mask(run)[shown]
    poses = _poses(obs)
    st = res.state
    after_mount = Mount(
        st.lever_arm_m,
        run.mount_apriori.nominal_rad,
        st.boresight_rad,
        st.range_offset_m,
        st.scan_angle_offset_rad,
    )
    p0 = georeference_poses(poses, obs.l[:, 6], obs.l[:, 7], run.mount_apriori)[shown]
    p1 = georeference_poses(poses, obs.l[:, 6], obs.l[:, 7], after_mount)[shown]
    plane_index, pass_index = obs.plane_index[shown], obs.pass_index[shown]
    p1 += st.pass_offsets_m[pass_index]
    out = {}
    for j, name in enumerate(obs.plane_names):
        if j in obs.patch_planes:  # tie patches: in their own table and plot
            continue
        m = plane_index == j
        n0, d0 = run.planes_init[j]
        horiz = np.cross([0.0, 0.0, 1.0], n0)
        horiz = horiz / np.linalg.norm(horiz) if np.linalg.norm(horiz) > 1e-6 else np.eye(3)[0]
        q0, q1 = p0[m], p1[m]
        centre = q1[~removed[m]].mean(axis=0) if (~removed[m]).any() else q1.mean(axis=0)
        out[name] = {
            "along_before_m": (q0 - centre) @ horiz,
            "before_m": q0 @ n0 + d0,
            "along_after_m": (q1 - centre) @ horiz,
            "after_m": q1 @ st.normals[j] + st.d_lgf_m[j],
            "pass_index": pass_index[m],
            "removed": removed[m],
        }
    return out


# -- plots --------------------------------------------------------------------------------------


#: the colour of a target group removed as a gross error (the passes take the tab10 colours)
REMOVED_COLOUR = "black"


def _figure(n_panels: int, width_in: float = 4.2, height_in: float = 3.0):
    from matplotlib.figure import Figure

    cols = min(n_panels, 3)
    rows = -(-n_panels // cols)
    w, h = width_in * cols, height_in * rows + 0.4
    fig = Figure(figsize=(w, h))
    # fixed margins (in inches): a constrained layout would cost a second per figure
    fig.subplots_adjust(
        left=0.75 / w, right=1 - 0.2 / w, bottom=0.55 / h, top=1 - 0.75 / h, wspace=0.35, hspace=0.55
    )
    axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False).ravel())
    for ax in axes[n_panels:]:
        ax.set_visible(False)
    return fig, axes


def _histograms(values_mm: list[np.ndarray], titles: list[str], path: Path, suptitle: str):
    fig, axes = _figure(len(values_mm))
    for ax, v, title in zip(axes, values_mm, titles, strict=False):
        if v.size:
            mean, std = float(v.mean()), float(v.std())
            dens, edges = np.histogram(v, bins=min(60, max(10, v.size // 20)), density=True)
            ax.stairs(dens, edges, fill=True, color="tab:blue", alpha=0.75)  # one artist: fast
            if std > 0:
                x = np.linspace(v.min(), v.max(), 200)
                ax.plot(
                    x,
                    np.exp(-0.5 * ((x - mean) / std) ** 2) / (std * np.sqrt(2 * np.pi)),
                    "k-",
                    lw=1,
                    label=f"mean {mean:+.2f}, σ {std:.2f} mm",
                )
                ax.legend(fontsize=8)
        ax.set_title(f"{title} ({v.size} points)", fontsize=10)
        ax.set_xlabel("residual (mm)")
    fig.suptitle(suptitle)
    fig.savefig(path, dpi=PLOT_DPI)
    return path


def _pass_colours(n: int):
    from matplotlib import colormaps

    cmap = colormaps["tab10"]
    return [cmap(k % 10) for k in range(n)]


def _residuals_along_time(run, used: np.ndarray, path: Path) -> Path:
    """Residuals along time, one panel per pass (passes last seconds, the gaps between them
    minutes), one colour per target: a drift within a pass is the POS error the formal σ
    ignores."""
    obs, r_mm = run.observations, run.result.residual_m * 1e3
    plane_index, pass_index = obs.plane_index[used], obs.pass_index[used]
    t = obs.t_gps_s[used]
    colours = _pass_colours(max(len(obs.pass_ids), len(obs.plane_names)))
    fig, axes = _figure(len(obs.pass_ids), 4.2, 2.8)
    for ax, k, pid in zip(axes, range(len(obs.pass_ids)), obs.pass_ids, strict=False):
        m = pass_index == k
        t0 = float(t[m].min()) if m.any() else 0.0
        for j, name in enumerate(obs.plane_names):
            mj = m & (plane_index == j)
            ax.plot(t[mj] - t0, r_mm[mj], ".", ms=2, color=colours[j], label=name)
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_title(f"pass {pid}", fontsize=10)
        ax.set_xlabel("time in the pass (s)")
        ax.set_ylabel("residual (mm)")
    axes[0].legend(fontsize=7, markerscale=4)
    fig.suptitle("Residuals along time")
    fig.savefig(path, dpi=PLOT_DPI)
    return path


def _edge_on_panel(ax, e: dict, key: str, pass_ids, colours, removed: list[dict]) -> None:
    """One target's points edge-on (``key``: "before" or "after" the adjustment), by pass; the
    points of its groups ``removed`` as gross errors marked apart."""
    for k, pid in enumerate(pass_ids):
        m = (e["pass_index"] == k) & ~e["removed"]
        if not m.any():
            continue
        ax.plot(
            e[f"along_{key}_m"][m], e[f"{key}_m"][m] * 1e3, ".", ms=2, color=colours[k], label=f"pass {pid}"
        )
    for g in removed:
        m = e["removed"] & (e["pass_index"] == pass_ids.index(g["pass_id"]))
        ax.plot(
            e[f"along_{key}_m"][m],
            e[f"{key}_m"][m] * 1e3,
            "x",
            ms=3,
            color=REMOVED_COLOUR,
            label=f"removed: pass {g['pass_id']} (group test T = {g['statistic']:.0f}, {100 * g['offset_m']:+.1f} cm)",
        )


def _edge_on_plots(run, out_dir: Path) -> list[Path]:
    """Each target seen edge-on before (a-priori boresight) and after (estimated) the adjustment."""
    obs = run.observations
    colours = _pass_colours(len(obs.pass_ids))
    removed_by_target: dict[str, list[dict]] = {}
    for g in run.result.removed_groups:
        if g.get("removed"):
            removed_by_target.setdefault(g["plane"], []).append(g)
    paths = []
    for name, e in edge_on(run).items():
        fig, axes = _figure(2, 5.0, 3.4)
        for ax, key, title in (
            (axes[0], "before", "before: a-priori boresight"),
            (axes[1], "after", "after: estimated boresight"),
        ):
            _edge_on_panel(ax, e, key, obs.pass_ids, colours, removed_by_target.get(name, []))
            ax.set_title(title, fontsize=10)
            ax.set_xlabel("along the target (m)")
            ax.set_ylabel("distance to the plane (mm)")
        axes[1].legend(fontsize=7, markerscale=4)
        fig.suptitle(f"Target {name} seen edge-on")
        path = out_dir / f"target_{_safe(name)}.png"
        fig.savefig(path, dpi=PLOT_DPI)
        paths.append(path)
    return paths


def write_plots(run, out_dir: Path) -> list[Path]:
    """The PNG plots of ``run`` into ``out_dir``: residuals per target, per pass and along
    time, the tie patches (when any) and each target edge-on; returns their paths."""
    obs, res = run.observations, run.result
    used = _used(run)
    r_mm = res.residual_m * 1e3
    plane_index, pass_index = obs.plane_index[used], obs.pass_index[used]
    paths = [
        _histograms(
            [r_mm[plane_index == j] for j in range(len(obs.plane_names))],
            list(obs.plane_names),
            out_dir / "residuals_by_plane.png",
            "Residuals per target (distance to the adjusted plane)",
        ),
        _histograms(
            [r_mm[pass_index == k] for k in range(len(obs.pass_ids))],
            [f"pass {p}" for p in obs.pass_ids],
            out_dir / "residuals_by_pass.png",
            "Residuals per pass",
        ),
        _residuals_along_time(run, used, out_dir / "residuals_time.png"),
    ]
    patches_png = tie_patch_plot(run, out_dir)
    if patches_png is not None:
        paths.append(patches_png)
    return paths + _edge_on_plots(run, out_dir)


# -- the narrative ------------------------------------------------------------------------------


def _chi2_sentence(res) -> str:
    c = res.chi2_test()
    s0 = res.sigma0_squared
    head = (
        f"σ̂0² = {s0:.3f} with {c['df']} degrees of freedom; the two-sided χ² test at 5 % "
        f"accepts [{c['lower']:.3f}, {c['upper']:.3f}]: "
    )
    if c["passed"]:
        return head + "**passed** — the observation sigmas agree with the residuals."
    if s0 > c["upper"]:
        return head + (
            f"**failed (high)** — the residuals are {np.sqrt(s0):.2f}× larger than "
            f"the sigmas say: the sigmas are optimistic, or something is not "
            f"modelled (range offset, lever arm, latency, a poor extraction). The "
            f"scaled σ accounts for it."
        )
    return head + (
        f"**failed (low)** — the residuals are {np.sqrt(s0):.2f}× the sigmas: the "
        f"sigmas are pessimistic (or the POS errors are correlated in time, which "
        f"within a pass the residuals do not show)."
    )


def _observability(run) -> list[str]:
    obs, res = run.observations, run.result
    sailed = sailed_headings(obs)
    lines = []
    headings = ", ".join(
        f"{pid} ({round(np.degrees(obs.pass_headings_rad[pid])) % 360}°)"
        for pid in obs.pass_ids
        if pid in obs.pass_headings_rad
    )
    lines.append(f"Passes and their headings relative to the wall: {headings}.")
    for i, angle in enumerate(ANGLE_NAMES):
        label, pairs = OBSERVING_PAIRS[i]
        have = [f"{a}°/{b}°" for a, b in pairs if a in sailed and b in sailed]
        lines.append(
            f"- {angle}: observed best by {label}; "
            + (f"sailed: {', '.join(have)}." if have else "**none sailed**.")
        )
    corr = res.correlation
    for i in range(3):
        for j in range(i + 1, 3):
            if abs(corr[i, j]) > 0.7:
                lines.append(
                    f"- {ANGLE_NAMES[i]} and {ANGLE_NAMES[j]} are strongly correlated "
                    f"(ρ = {corr[i, j]:+.2f}): the targets and passes do not separate "
                    f"them well."
                )
    if len(obs.plane_names) <= 2 and int(np.argmax(res.sigma_realistic_rad)) == 1:
        lines.append(
            "- pitch is the weakest angle here: with the targets at one range and "
            "height, an along-track POS position error (or lever-arm x error) looks "
            "like a pitch rotation. A third target at another range or height (the "
            "design study) separates them."
        )
    return lines


def extras_table(extras: dict) -> list[str]:
    """The extra unknowns of result.json's ``extras`` as a table: value, formal and realistic
    σ, and the correlation with each boresight angle; a pass offset gets a row per component
    (north, east, down)."""
    L = [
        "| unknown | value | σ formal | σ realistic | ρ roll | ρ pitch | ρ yaw |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]

    def row(label, value, sigma, sigma_real, c):
        return (
            f"| {label} | {value:+.6g} | {sigma:.3g} | **{_sig(sigma_real)}** | "
            f"{c['roll']:+.2f} | {c['pitch']:+.2f} | {c['yaw']:+.2f} |"
        )

    for name, e in extras.items():
        real = e.get("sigma_realistic")
        c = e["correlation_with_boresight"]
        if isinstance(e["value"], list):  # pass<id>_offset_m: north, east, down
            for k, comp in enumerate(OFFSET_COMPONENTS):
                L.append(
                    row(
                        f"{name} {comp}",
                        e["value"][k],
                        e["sigma"][k],
                        None if real is None else real[k],
                        c[comp],
                    )
                )
        else:
            L.append(row(name, e["value"], e["sigma"], real, c))
    L.append("")
    L.append(
        "ρ: correlation with the boresight angle (formal covariance); |ρ| near 1 means the "
        "unknown and that angle trade against each other. Judge whether an unknown "
        "differs from zero by its realistic σ: the formal σ is as optimistic for it as "
        "for the boresight when POS errors are correlated in time."
    )
    return L


def _verdict_section(run) -> list[str]:
    v = run.verdict
    L = ["## Verdict", "", f"**{v.status}**" + (": do not use this result." if v.status == "refused" else "")]
    L.append("")
    L.extend(f"- {r}" for r in v.reasons)
    L.extend(f"- {n}" for n in v.notes)
    if v.reasons or v.notes:
        L.append("")
    return L


def _lost_and_removed(run) -> list[str]:
    """Targets the extraction lost per pass, and target groups the group test removed."""
    L: list[str] = []
    lost = [f for f in run.extraction.found if f.n_points == 0]
    if lost:
        L += ["## Targets lost in a pass", "", "| target | pass | status | reason |", "|---|---:|---|---|"]
        L += [f"| {f.target} | {f.pass_id} | {f.status} | {f.note} |" for f in lost]
        L.append("")
    groups = run.result.removed_groups
    L += ["## Gross errors per group", ""]
    if not groups:
        L.append(
            "No target group (a target in one pass) failed the group test (offset and tilt from the "
            "adjusted plane, family-wise false-rejection rate 0.1 %)."
        )
    else:
        L += [
            "| target | pass | points | T | df | p | offset (cm) | action |",
            "|---|---:|---:|---:|---:|---:|---:|---|",
        ]
        L += [
            f"| {g['plane']} | {g['pass_id']} | {g['n_points']} | {g['statistic']:.1f} | {g['df']} | "
            f"{g['p_value']:.2g} | {100 * g['offset_m']:+.1f} | {'removed' if g['removed'] else g['reason']} |"
            for g in groups
        ]
    L.append("")
    return L


def _header(run) -> list[str]:
    """The title and what was calibrated: bundle, survey, software, a-priori boresight."""
    res, doc, obs = run.result, run.doc, run.observations
    survey = frames.gps_ns_to_utc(frames.seconds_to_gps_ns(float(obs.t_gps_s.min())))
    when = survey.strftime("%Y-%m-%d %H:%M UTC")
    ap = np.degrees(run.mount_apriori.boresight_rad)
    return [
        f"# Boresight calibration — {run.site.vessel}",
        "",
        f"- Bundle: `{run.source}`",
        f"- Survey: {when}; {len(obs.pass_ids)} passes, {len(obs.plane_names)} targets "
        f"({', '.join(obs.plane_names)})",
        f"- Software: {doc['software_version']}; adjustment {res.runtime_s:.2f} s, whole "
        f"run {run.timings_s.get('total_s', float('nan')):.2f} s",
        f"- A-priori boresight (canonical): roll {ap[0]:.4f}°, pitch {ap[1]:.4f}°, yaw {ap[2]:.4f}°",
        "",
    ]


def _boresight_section(run) -> list[str]:
    """The estimate with its σ (formal, scaled, realistic, jackknife), which σ to use, the χ²
    test and the convergence."""
    res, obs = run.result, run.observations
    formal, scaled = res.sigma_formal_rad, res.sigma_scaled_rad
    real = res.sigma_realistic_rad
    jack = None if res.cov_jackknife is None else np.sqrt(np.diag(res.cov_jackknife))
    thesis = frames.boresight_to_thesis(*res.boresight_rad)
    ratio = real / formal
    L = [
        "## Boresight",
        "",
        "Canonical convention (docs/architecture.md §3: rotations about the body's forward, starboard "
        "and down axes); the thesis convention negates pitch.",
        "",
        "| angle | estimate (°) | thesis conv. (°) | σ formal (°) | σ scaled (°) | "
        "σ realistic (°) | σ jackknife (°) | realistic / formal |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for i, a in enumerate(ANGLE_NAMES):
        L.append(
            f"| {a} | {_fmt(_deg(res.boresight_rad[i]))} | {_fmt(_deg(thesis[i]))} | "
            f"{_sig(_deg(formal[i]))} | {_sig(_deg(scaled[i]))} | "
            f"**{_sig(_deg(real[i]))}** | "
            f"{_sig(_deg(jack[i])) if jack is not None else '—'} | {ratio[i]:.1f} |"
        )
    L.append("")
    L.extend(realistic_sigma_lines(res, run.doc))
    L.append("")
    L.append(_chi2_sentence(res))
    L.append("")
    conv = "converged" if res.converged else "**did not converge**"
    opts = run.options
    L.append(
        f"The adjustment {conv} in {res.iterations} iterations (steps below "
        f"{opts.tol_angle_rad:g} rad and {opts.tol_m * 1e3:g} mm, or below "
        f"{opts.rel_tol:g} of each unknown's σ; {len(obs)} observations, "
        f"{res.n_points} kept)."
    )
    L.append("")
    return L


def _correlations_section(run) -> list[str]:
    """The boresight angles' correlations, and the extra unknowns when estimated."""
    res = run.result
    L = ["## Correlations", "", "| | roll | pitch | yaw |", "|---|---:|---:|---:|"]
    for i, a in enumerate(ANGLE_NAMES):
        L.append(f"| {a} | " + " | ".join(f"{res.correlation[i, j]:+.3f}" for j in range(3)) + " |")
    if res.extras:
        L.extend(["", "## Extra unknowns", ""])
        L.extend(extras_table(run.doc["extras"]))
    return L


def _targets_section(res) -> list[str]:
    """Each target's points, RMS and adjusted plane (the tie patches have their own section)."""
    L = [
        "## Targets",
        "",
        "| target | points | RMS (mm) | normal (N, E, D) | d (m) |",
        "|---|---:|---:|---|---:|",
    ]
    for p in res.plane_stats:
        if p.get("kind") == "tie patch":
            continue
        n = ", ".join(f"{x:+.4f}" for x in p["normal"])
        L.append(f"| {p['name']} | {p['n_points']} | {p['rms_m'] * 1e3:.2f} | {n} | {p['d']:.4f} |")
    L.append("")
    return L


def _passes_section(run) -> list[str]:
    """Each pass: its heading, the points extracted per target, kept, RMS; the extraction mode."""
    res = run.result
    counts = run.extraction.counts()
    names = run.extraction.target_names
    L = [
        "## Passes",
        "",
        "| pass | heading vs wall (°) | "
        + " | ".join(f"{n} extracted" for n in names)
        + " | kept | RMS (mm) |",
        "|---:|---:|" + "---:|" * len(names) + "---:|---:|",
    ]
    for p in res.pass_stats:
        h = "—" if p["heading_deg"] is None else f"{p['heading_deg']:.1f}"
        row = counts.get(p["id"], {})
        L.append(
            f"| {p['id']} | {h} | "
            + " | ".join(str(row.get(n, 0)) for n in names)
            + f" | {p['n_points']} | {p['rms_m'] * 1e3:.2f} |"
        )
    ex = run.doc.get("extraction", {})
    L.append("")
    L.append(
        f"Extraction: {ex.get('mode', '?')}; "
        + (
            f"voxel subsampling {ex['subsample_m']:g} m (one point per voxel, the nearest its centre)."
            if ex.get("subsample_m")
            else "no subsampling."
        )
    )
    L.append("")
    return L


def _outliers_section(res) -> list[str]:
    """The points the data snooping removed (their rows in points.csv)."""
    L = ["## Outliers", ""]
    n_out = res.outlier_point_ids.size
    if n_out:
        ids = ", ".join(str(int(i)) for i in res.outlier_point_ids[:50])
        more = f" … and {n_out - 50} more" if n_out > 50 else ""
        L.append(
            f"{n_out} point(s) failed the data-snooping test on normalized residuals and "
            f"were removed (0-based data rows of points.csv): {ids}{more}."
        )
    else:
        L.append("No point failed the data-snooping test on normalized residuals.")
    return L


def _closing(run, plot_names: list[str] | None) -> list[str]:
    """The warnings and assumptions, then the plots."""
    L = []
    if run.warnings or run.notes:
        L.extend(["", "## Warnings and assumptions", ""])
        L.extend(f"- ⚠ {w}" for w in run.warnings)
        L.extend(f"- {n}" for n in run.notes)
    if plot_names:
        L.extend(["", "## Plots", ""])
        L.extend(f"![{Path(p).stem}]({Path(p).name})" for p in plot_names)
    L.append("")
    return L


def report_markdown(run, plot_names: list[str] | None = None) -> str:
    """report.md: the calibration ``run`` section by section (``plot_names``: the plots beside it)."""
    L = _header(run)
    L.extend(_verdict_section(run))
    L.extend(_boresight_section(run))
    L.extend(estimator_section(run))
    L.append("")
    L.extend(_correlations_section(run))
    L.extend(["", "## Observability", ""])
    L.extend(_observability(run))
    L.extend(["", *_targets_section(run.result)])
    L.extend(_passes_section(run))
    L.extend(_lost_and_removed(run))
    L.extend(_outliers_section(run.result))
    L.extend(_closing(run, plot_names))
    return "\n".join(L)


def write_report(run, out_dir: str | Path, plots: bool = True) -> list[Path]:
    """Write ``report.md`` (and the plots) into ``out_dir``; returns the paths written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    pngs = write_plots(run, out) if plots else []
    md = out / "report.md"
    md.write_text(report_markdown(run, [p.name for p in pngs]), encoding="utf-8")
    return [md, *pngs]
