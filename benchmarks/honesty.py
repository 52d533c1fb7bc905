"""Boresight calibration honesty over randomized geometry: is a result the calibration calls
"trusted" within its σ, whatever the mount tilt, wall azimuth, standoff, target layout,
reflectivity contrast, wall waviness, lever arm, boresight and POS noise?

Each draw N: ``calib.sim.simulate.simulate("random", N).write(bundle)`` (what ``mls sim dataset
--scenario random --seed N --out BUNDLE`` calls; the geometry ``calib.sim.randomdraw`` draws from
the seed, recorded in truth.json ``settings.random_draw``), then
``calib.boresight.pipeline.calibrate_bundle(bundle, CalibrationOptions())`` (what ``mls calib run
BUNDLE --no-history --no-plots`` calls; its ``run.doc`` is result.json), in worker processes as
benchmarks/accuracy.py does. The verdict is result.json's ``verdict`` ("trusted", "questionable"
or "refused"; a result without one counts as trusted); a calibration that stops with the
project's error (``MlsError``: too few target points, unobservable angles, …) counts as refused,
any other exception as crashed (a bug). σ is ``sigma_realistic_deg``; the CRLB is the targets-only
Cramér–Rao bound at the truth (benchmarks/_crlb.py, as accuracy.py computes it, from a second
run with ``tie_patches="off"``).

Goals, among trusted results: angle estimates outside 3σ ≤ 1 %, coverage at 2σ in [92 %, 98 %];
refused ≤ 5 % of the draws; RMS / CRLB per angle ≤ 1.2 (accuracy.py's goal, printed for
reference). A benchmark reports: exit 0 whatever the figures. Each draw gets one line; the
worst trusted draws are listed at the end with the command that reproduces them.

    .venv/bin/python benchmarks/honesty.py [--draws 200] [--jobs 2] [--quick] [--first-seed 0]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import _onecore  # noqa: F401  (first: BLAS on one thread)

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
from _crlb import ANGLES, angles_rad, targets_only_crlb_rad, true_correlation_time_s  # noqa: E402

VERDICTS = ("trusted", "questionable", "refused", "crashed")
OUTSIDE_3SIGMA_GOAL = 0.01
COVERAGE_2SIGMA_GOAL = (0.92, 0.98)
REFUSED_GOAL = 0.05
RMS_OVER_CRLB_GOAL = 1.2


# --------------------------------------------------------------------------- one draw


def geometry_of(draw: dict) -> dict:
    """The key geometry of a draw (truth.json ``settings.random_draw``) for the draw's line."""
    return {
        "nominal_deg": [round(x, 1) for x in draw["nominal_deg"][:2]],
        "wall_azimuth_deg": round(draw["wall_azimuth_deg"], 0),
        "standoff_m": round(draw["standoff_m"], 1),
        "targets": [f"{t['inclination_deg']:.0f}°/{100 * t['proud_m']:.0f}cm" for t in draw["targets"]],
        "contrast": round(draw["contrast"], 2),
        "waviness_mm": round(1e3 * draw["wall_waviness_m"], 1),
        "lever_arm_m": [round(x, 2) for x in draw["lever_arm_m"]],
        "boresight_deg": [round(x, 2) for x in draw["boresight_deg"]],
        "sigma_pos_cm": round(100 * draw["sigma_position_m"], 1),
        "sigma_att_mdeg": round(1e3 * draw["sigma_attitude_deg"], 1),
        "tau_s": [round(draw["tau_position_s"], 0), round(draw["tau_attitude_s"], 0)],
        "capture_margin_m": round(draw["placement"]["capture_margin_m"], 1),
        "piles": len(draw.get("piles", [])),
    }


def _crlb_rad(bundle: Path, truth: dict):
    """The targets-only CRLB (rad), or None when the targets-only run fails."""
    from calib.boresight.pipeline import CalibrationOptions, calibrate_bundle
    from calib.core.errors import MlsError

    try:
        off = calibrate_bundle(bundle, CalibrationOptions(tie_patches="off"))
        return targets_only_crlb_rad(truth, off.observations, true_correlation_time_s(truth)).tolist()
    except MlsError:
        return None


def run_draw(seed: int) -> dict:
    """One randomized simulation + calibration: verdict, errors, σ and CRLB (rad)."""
    from calib.boresight.pipeline import CalibrationOptions, calibrate_bundle
    from calib.core.errors import MlsError
    from calib.sim.simulate import simulate

    t0 = time.perf_counter()
    row: dict = {"seed": seed, "geometry": None, "err": None, "sigma": None, "crlb": None}
    try:
        with tempfile.TemporaryDirectory(prefix="mls-honesty-") as tmp:
            bundle = Path(tmp) / "bundle"
            simulate("random", seed).write(bundle)
            truth = json.loads((bundle / "truth.json").read_text())
            row["geometry"] = geometry_of(truth["settings"]["random_draw"])
            try:
                doc = calibrate_bundle(bundle, CalibrationOptions()).doc
            except MlsError as e:
                row.update(verdict="refused", reasons=[f"{type(e).__name__}: {e}"])
            else:
                true_b = angles_rad(truth["boresight_deg"])
                only = doc.get("targets_only", doc)  # no tie patch chosen: the default is targets-only
                row.update(
                    verdict=doc.get("verdict", "trusted"),
                    reasons=list(doc.get("verdict_reasons", [])),
                    err=(angles_rad(doc["boresight_deg"]) - true_b).tolist(),
                    sigma=angles_rad(doc["sigma_realistic_deg"]).tolist(),
                    err_targets_only=(angles_rad(only["boresight_deg"]) - true_b).tolist(),
                    sigma_targets_only=angles_rad(only["sigma_realistic_deg"]).tolist(),
                    n_points=int(doc["n_points"]),
                    n_patches=len(doc.get("tie_patches") or []),
                    n_cylinders=len(doc.get("tie_cylinders") or []),
                    crlb=_crlb_rad(bundle, truth),
                )
    except Exception as e:  # noqa: BLE001  (a crash is reported, not fatal)
        row.update(verdict="crashed", reasons=[f"{type(e).__name__}: {e}"])
    row["wall_s"] = time.perf_counter() - t0
    return row


def draw_line(r: dict) -> str:
    g = r["geometry"]
    if g is None:
        geo = "(simulation failed)"
    else:
        geo = (
            f"tilt {g['nominal_deg'][0]:+5.1f}/{g['nominal_deg'][1]:+5.1f}° az {g['wall_azimuth_deg']:3.0f}° "
            f"so {g['standoff_m']:4.1f} m tg {','.join(g['targets'])} c {g['contrast']:.2f} "
            f"wav {g['waviness_mm']:4.1f} mm τ {g['tau_s'][0]:.0f}/{g['tau_s'][1]:.0f} s"
        )
    if r["err"] is not None:
        z = np.asarray(r["err"]) / np.asarray(r["sigma"])
        zs = " ".join(f"{a[0]} {z[i]:+6.2f}" for i, a in enumerate(ANGLES))
        errs = " ".join(f"{np.degrees(r['err'][i]):+.4f}" for i in range(3))
        fig = f"err/σ {zs} (err° {errs})"
    else:
        fig = "—"
    why = f"  [{'; '.join(r['reasons'])[:160]}]" if r["reasons"] and r["verdict"] != "trusted" else ""
    return f"seed {r['seed']:4d} {geo} | {fig} | {r['verdict']}{why}"


# --------------------------------------------------------------------------- summary


def pass_fail(ok: bool) -> str:
    return "PASS" if ok else "FAIL"


def verdict_lines(rows: list[dict]) -> list[str]:
    n = len(rows)
    counts = {v: sum(r["verdict"] == v for r in rows) for v in VERDICTS}
    out = ["verdicts: " + ", ".join(f"{v} {counts[v]} ({100 * counts[v] / n:.1f} %)" for v in VERDICTS)]
    refused = counts["refused"] / n
    out.append(
        f"  refused {100 * refused:.1f} % of {n} draws   goal ≤ {100 * REFUSED_GOAL:.0f} %  {pass_fail(refused <= REFUSED_GOAL)}"
    )
    out.append(f"  questionable {100 * counts['questionable'] / n:.1f} %   (no goal)")
    if counts["crashed"]:
        out.append(f"  crashed {counts['crashed']} (a bug: the calibration must refuse, not crash)")
    return out


def refusal_lines(rows: list[dict]) -> list[str]:
    """Why draws were refused or crashed, grouped (numbers and target names left out)."""
    import re
    from collections import Counter

    why = Counter(
        re.sub(r"\bT\d\b|[-+]?\d+(\.\d+)?", "#", r["reasons"][0] if r["reasons"] else "no reason")[:110]
        for r in rows
        if r["verdict"] in ("refused", "crashed")
    )
    return [f"  {n:3d} × {text}" for text, n in why.most_common()]


def honesty_lines(label: str, rows: list[dict], goals: bool, which: str = "") -> list[str]:
    """Outside-3σ fraction, 2σ coverage and RMS/CRLB per angle among ``rows`` with a result
    (``which``: "" for the default estimate, "_targets_only" for result.json's targets-only one)."""
    rows = [r for r in rows if r["err"] is not None]
    if not rows:
        return [f"{label}: no result"]
    e, s = np.array([r["err" + which] for r in rows]), np.array([r["sigma" + which] for r in rows])
    z = np.abs(e) / s
    out3, cov2 = float(np.mean(z > 3)), float(np.mean(z <= 2))
    out = [f"{label}: {len(rows)} results, {3 * len(rows)} angle estimates"]
    g3 = (
        f"goal ≤ {100 * OUTSIDE_3SIGMA_GOAL:.0f} %  {pass_fail(out3 <= OUTSIDE_3SIGMA_GOAL)}" if goals else ""
    )
    lo, hi = COVERAGE_2SIGMA_GOAL
    g2 = f"goal {100 * lo:.0f}–{100 * hi:.0f} %  {pass_fail(lo <= cov2 <= hi)}" if goals else ""
    out.append(f"  outside 3σ {100 * out3:5.1f} %   {g3}")
    out.append(f"  coverage 2σ {100 * cov2:5.1f} %   {g2}")
    with_crlb = [r for r in rows if r["crlb"] is not None]
    crlb = np.array([r["crlb"] for r in with_crlb]) if with_crlb else None
    out.append(
        f"  {'angle':<7}{'out 3σ':>8}{'cov 2σ':>8}{'RMS °':>9}{'mean σ °':>10}{'CRLB °':>9}{'RMS/CRLB':>9}"
    )
    for i, a in enumerate(ANGLES):
        rms = np.degrees(np.sqrt(np.mean(e[:, i] ** 2)))
        if crlb is not None:
            ec = np.array([r["err" + which][i] for r in with_crlb])
            rms_c = np.degrees(np.sqrt(np.mean(ec**2)))
            crlb_i = np.degrees(np.sqrt(np.mean(crlb[:, i] ** 2)))
            ratio = rms_c / crlb_i
            tail = f"{crlb_i:>9.4f}{ratio:>9.2f}"
            if goals:
                tail += f"  goal ≤ {RMS_OVER_CRLB_GOAL} {pass_fail(ratio <= RMS_OVER_CRLB_GOAL)}"
        else:
            tail = f"{'—':>9}{'—':>9}"
        out.append(
            f"  {a:<7}{100 * np.mean(z[:, i] > 3):>7.1f}%{100 * np.mean(z[:, i] <= 2):>7.1f}%"
            f"{rms:>9.4f}{np.degrees(np.mean(s[:, i])):>10.4f}{tail}"
        )
    return out


def worst_lines(rows: list[dict], n: int = 10) -> list[str]:
    """The trusted draws most outside their σ (> 3σ), with what reproduces them."""
    bad = [r for r in rows if r["verdict"] == "trusted" and r["err"] is not None]
    bad = [(float(np.max(np.abs(np.asarray(r["err"]) / np.asarray(r["sigma"])))), r) for r in bad]
    bad = sorted([b for b in bad if b[0] > 3], key=lambda b: -b[0])[:n]
    if not bad:
        return ["no trusted draw outside 3σ"]
    out = [
        f"trusted draws outside 3σ (worst {len(bad)}; reproduce: mls sim dataset --scenario random --seed N --out DIR):"
    ]
    for zmax, r in bad:
        out.append(f"  max |err|/σ {zmax:.1f}: {draw_line(r)}")
        out.append(f"      geometry {json.dumps(r['geometry'], ensure_ascii=False)}")
    return out


# --------------------------------------------------------------------------- main


def run_all(seeds: list[int], jobs: int, keep) -> None:
    if jobs > 1:
        from multiprocessing import get_context

        with get_context("spawn").Pool(jobs) as pool:
            for r in pool.imap_unordered(run_draw, seeds):
                keep(r)
    else:
        for s in seeds:
            keep(run_draw(s))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=200, help="randomized draws (default 200)")
    ap.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    ap.add_argument("--quick", action="store_true", help="20-draw smoke run")
    ap.add_argument("--first-seed", type=int, default=0, help="seed of the first draw (default 0)")
    ap.add_argument("--json", type=Path, help="also write every draw's figures to this file (JSON lines)")
    args = ap.parse_args()
    n = 20 if args.quick else args.draws
    seeds = list(range(args.first_seed, args.first_seed + n))
    t0 = time.perf_counter()
    print(
        f"calibration honesty over randomized geometry: {n} draws (seeds {seeds[0]}…{seeds[-1]}), "
        f"{args.jobs} processes; simulate('random', seed) + calibrate_bundle() (mls sim dataset "
        f"--scenario random / mls calib run, default options)",
        flush=True,
    )
    rows: list[dict] = []
    sink = args.json.open("w") if args.json else None

    def keep(r: dict) -> None:
        rows.append(r)
        print(draw_line(r), flush=True)
        if sink:
            sink.write(json.dumps(r, default=float) + "\n")
            sink.flush()

    run_all(seeds, args.jobs, keep)
    if sink:
        sink.close()
    rows.sort(key=lambda r: r["seed"])
    lines = ["", *verdict_lines(rows)]
    lines += refusal_lines(rows)
    trusted = [r for r in rows if r["verdict"] == "trusted"]
    lines += honesty_lines("trusted (default: GLS + tie patches)", trusted, goals=True)
    lines += honesty_lines(
        "trusted, targets-only GLS (result.json targets_only)", trusted, True, "_targets_only"
    )
    piled = [r for r in trusted if r["geometry"]["piles"]]
    chosen = sum(1 for r in piled if r.get("n_cylinders"))
    lines += honesty_lines(
        f"trusted with piles in the scene ({chosen} chose tie cylinders)", piled, goals=False
    )
    lines += honesty_lines(
        "trusted without piles", [r for r in trusted if not r["geometry"]["piles"]], goals=False
    )
    lines += honesty_lines(
        "questionable (for reference)", [r for r in rows if r["verdict"] == "questionable"], goals=False
    )
    lines += ["", *worst_lines(rows)]
    lines.append(f"\n{time.perf_counter() - t0:.0f} s, {np.mean([r['wall_s'] for r in rows]):.1f} s per draw")
    print("\n".join(line.rstrip() for line in lines))
    sys.exit(0)


if __name__ == "__main__":
    main()
