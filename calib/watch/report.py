"""The mount watch's report for a finished survey: ``watch.json`` (every block, the test's state
after each, the alarm), ``watch.md`` (what a hydrographer reads: the verdict, then block by
block which lines and patches carried the information) and ``watch.png`` (the boresight
correction along time with ±σ, the running estimate, the test statistic and the alarm)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from calib.core.frames import gps_ns_to_utc
from calib.watch.block import BlockEstimate
from calib.watch.runner import WatchRun
from calib.watch.sequential import ANGLES, FAMILIES, MountAlarm

NS_PER_S = 1_000_000_000


def _utc(t_gps_s: float) -> str:
    return gps_ns_to_utc(int(round(t_gps_s * NS_PER_S))).strftime("%Y-%m-%d %H:%M:%S UTC")


WAITING = "waiting for a pair of opposite lines"
#: the running estimate's σ of an angle no block has observed yet stays near its 1° prior
UNSEEN_SIGMA_DEG = 0.5


def _pm(x_deg: float, s_deg: float) -> str:
    return f"{x_deg:+.3f} ± {s_deg:.3f}°"


def verdict(state: dict, alarm: MountAlarm | None, pending_lines: int, last: BlockEstimate | None) -> str:
    """The one-line verdict of a :meth:`calib.watch.sequential.MountTest.state`."""
    if alarm is not None:
        return f"MOUNT SHIFT: {alarm.message()} — recalibrate the mount"
    if state.get("blocks_ok"):
        est, sig = state["estimate_deg"], state["sigma_deg"]
        n = state["blocks_ok"]
        angles = ", ".join(
            f"{a} {_pm(est[i], sig[i])}" if sig[i] < UNSEEN_SIGMA_DEG else f"{a} not observed"
            for i, a in enumerate(ANGLES)
        )
        return f"mount steady: {angles} ({n} block{'s' if n != 1 else ''})"
    if last is not None and not last.ok:
        return f"{WAITING} with tie patches (last block: {last.status})"
    if pending_lines:
        return f"{WAITING} ({pending_lines} line{'s' if pending_lines != 1 else ''} so far)"
    return WAITING


def run_verdict(run: WatchRun) -> str:
    """The verdict of a finished watch (:func:`verdict` of its last state)."""
    last = run.blocks[-1] if run.blocks else None
    return verdict(run.states[-1] if run.states else {}, run.alarm, 0, last)


def as_document(run: WatchRun, meta: dict) -> dict:
    return {
        **meta,
        "design": run.test.design.as_dict(),
        "verdict": run_verdict(run),
        "alarm": None if run.alarm is None else run.alarm.as_dict(),
        "lines": run.line_order,
        "blocks": [b.as_dict() | {"family": f} for b, f in zip(run.blocks, run.families, strict=False)],
        "states": run.states,
    }


def write_report(run: WatchRun, out_dir: Path, meta: dict, plot: bool = True) -> list[Path]:
    """Write ``watch.json``, ``watch.md`` and (``plot``) ``watch.png`` into ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    doc = as_document(run, meta)
    p = out_dir / "watch.json"
    p.write_text(json.dumps(doc, indent=1, allow_nan=False, default=_json_default) + "\n", encoding="utf-8")
    written.append(p)
    p = out_dir / "watch.md"
    p.write_text(markdown(run, meta), encoding="utf-8")
    written.append(p)
    if plot and any(b.ok for b in run.blocks):
        p = out_dir / "watch.png"
        plot_watch(run, p)
        written.append(p)
    return written


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)


def markdown(run: WatchRun, meta: dict) -> str:
    d = run.test.design
    lines = [
        "# Mount watch",
        "",
        f"**{run_verdict(run)}**",
        "",
        *_calibration_lines(meta),
        f"- source: `{meta.get('source', '?')}`; calibration: `{meta.get('calibration') or 'the site a priori'}`",
        f"- test: CUSUM per angle and sign tuned to a {math.degrees(d.shift_rad):.3f}° change; "
        f"threshold h = {d.threshold:.2f} (≤ {d.false_alarms_per_hour:g} false alarms per hour at "
        f"≤ {d.max_blocks_per_hour:g} blocks per hour in each of {FAMILIES} families of blocks that share no "
        f"line); an angle a block resolves no better than {math.degrees(d.max_sigma_rad):.2f}° is not evidence",
        f"- lines: {len(run.line_order)}; blocks: {len(run.blocks)} ({sum(b.ok for b in run.blocks)} with an estimate)",
        "",
        "| block | family | lines | headings ° | start (UTC) | patches | roll ° | pitch ° | yaw ° | statistic |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for k, (b, s, f) in enumerate(zip(run.blocks, run.states, run.families, strict=False)):
        if b.delta_rad is not None:
            cells = [
                _angle_cell(x, sd, d.max_sigma_rad) for x, sd in zip(b.delta_rad, b.sigma_rad, strict=False)
            ]
        else:
            cells = [b.status, "", ""]
        stat = " / ".join(f"{x:.2f}" for x in s["statistic"])
        lines.append(
            f"| {k + 1} | {chr(ord('A') + f)} | {', '.join(map(str, b.pass_ids))} | {', '.join(f'{h:.0f}' for h in b.headings_deg)} | "
            f"{_utc(b.t_start_gps_s)} | {len(b.patches)} | {' | '.join(cells)} | {stat} |"
        )
    lines += ["", "## Where the information came from", ""]
    for k, b in enumerate(run.blocks):
        if not b.ok:
            continue
        top = sorted(b.patches, key=lambda p: -sum(p.info_rad2))[:5]
        share = _line_shares(b)
        lines.append(
            f"- block {k + 1}: lines "
            + ", ".join(f"{pid} ({100 * w:.0f} % of the patch points)" for pid, w in share.items())
            + "; strongest patches "
            + ", ".join(
                f"{p.name} at ({p.center_lgf_m[0]:.0f}, {p.center_lgf_m[1]:.0f}, {p.center_lgf_m[2]:.0f}) m"
                for p in top
            )
            + (f"; dropped as moving: {', '.join(b.moved_patches)}" if b.moved_patches else "")
        )
    return "\n".join(lines) + "\n"


def _angle_cell(delta_rad: float, sigma_rad: float, max_sigma_rad: float) -> str:
    """A block's correction of one angle, or "no verdict" when it resolves the angle no better
    than the test's bound (held at the calibrated value: its value is no evidence)."""
    if sigma_rad > max_sigma_rad:
        return f"no verdict (σ {math.degrees(sigma_rad):.3f})"
    return f"{math.degrees(delta_rad):+.3f} ± {math.degrees(sigma_rad):.3f}"


def _line_shares(b) -> dict[int, float]:
    counts: dict[int, float] = {}
    for p in b.patches:
        for pid in p.pass_ids:
            counts[pid] = counts.get(pid, 0.0) + p.n_points / len(p.pass_ids)
    total = sum(counts.values()) or 1.0
    return {pid: c / total for pid, c in sorted(counts.items())}


def plot_watch(run: WatchRun, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [(k, b) for k, b in enumerate(run.blocks) if b.delta_rad is not None]
    t0 = min(b.t_start_gps_s for b in run.blocks)
    fig, axes = plt.subplots(4, 1, figsize=(10, 10), sharex=True)
    tm = np.array([0.5 * (b.t_start_gps_s + b.t_end_gps_s) - t0 for _, b in ok]) / 60.0
    est = np.array([s["estimate_deg"] for s in (run.states[k] for k, _ in ok)])
    sd = np.array([s["sigma_deg"] for s in (run.states[k] for k, _ in ok)])
    for i, ax in enumerate(axes[:3]):
        d = np.array([math.degrees(b.delta_rad[i]) for _, b in ok])  # type: ignore[index]
        e = np.array([math.degrees(b.sigma_rad[i]) for _, b in ok])
        seen = e <= math.degrees(run.test.design.max_sigma_rad)
        ax.errorbar(tm[seen], d[seen], yerr=e[seen], fmt="o", ms=3, label="block ± σ")
        ax.plot(tm[~seen], d[~seen], "x", color="0.6", label="block (angle not resolved)")
        ax.plot(tm, est[:, i], "-", color="C1", label="running estimate")
        ax.fill_between(tm, est[:, i] - sd[:, i], est[:, i] + sd[:, i], color="C1", alpha=0.2)
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_ylabel(f"{ANGLES[i]} correction (°)")
        lim = max(0.05, float(np.nanmax(np.abs(d[seen]) + e[seen])) * 1.2) if seen.any() else 0.5
        ax.set_ylim(-lim, lim)
    stat = np.array([s["statistic"] for s in (run.states[k] for k, _ in ok)])
    for i in range(3):
        axes[3].step(tm, stat[:, i], where="post", label=ANGLES[i])
    axes[3].axhline(1.0, color="r", ls="--", lw=1, label="threshold")
    axes[3].set_ylabel("CUSUM / threshold")
    axes[3].set_xlabel("survey time (min)")
    if run.alarm is not None:
        for ax in axes:
            ax.axvline((run.alarm.t_gps_s - t0) / 60.0, color="r", lw=1)
            ax.axvline((run.alarm.since_gps_s - t0) / 60.0, color="r", lw=1, ls=":")
    axes[0].legend(loc="upper left", fontsize=8)
    axes[3].legend(loc="upper left", fontsize=8)
    axes[0].set_title(run_verdict(run), fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


#: what the watch says of a result.json written before calibrations carried a verdict
OLDER_CALIBRATION = "no verdict (older calibration)"


def _calibration_lines(meta: dict) -> list[str]:
    """Under the watch's verdict: the warning of a calibration not trusted, its verdict line."""
    warning, line = meta.get("calibration_warning"), meta.get("calibration_verdict")
    return ([f"> **Warning:** {warning}", ""] if warning else []) + ([f"- {line}"] if line else [])


def calibration_verdict(provenance: dict) -> str | None:
    """The calibration's verdict line for the watch's report from its provenance
    (:func:`office.deliver.calibration.load_calibration`); None without a calibration (the
    vessel's a-priori boresight: the calibration loader warns)."""
    if provenance.get("calibration") is None:
        return None
    verdict_ = provenance.get("calibration_verdict")
    if verdict_ is None:
        return f"calibration verdict: {OLDER_CALIBRATION}"
    reasons = provenance.get("calibration_verdict_reasons") or []
    return f"calibration verdict: {verdict_}" + (f" ({'; '.join(reasons)})" if reasons else "")
