"""``result.json`` (docs/architecture.md §4): the calibration result as users and other tools read it.

Degrees at this edge (``_deg`` names); boresight angles in the canonical convention, with the
thesis convention beside them for comparison with published figures.

``extras`` holds the extra unknowns asked for (``--estimate``), keyed by name and unit:

- ``range_offset_m``, ``scan_angle_offset_deg``, ``lever_arm_x_m``, ``lever_arm_y_m``,
  ``latency_s``: ``value``; ``sigma`` (formal, σ0 = 1); ``sigma_realistic`` (the POS error
  model of ``realistic_error_model`` propagated through the estimator, as for
  ``sigma_realistic_deg``; equal to ``sigma`` under the white model): judge whether an extra
  differs from zero by this one, since under time-correlated POS errors the formal σ is as
  optimistic for an extra as for the boresight; ``correlation_with_boresight``
  ``{roll, pitch, yaw}`` (from the formal covariance).
- ``pass<id>_offset_m`` (``pass_offsets``: the translation of pass <id>'s trajectory in the
  LGF): ``value``, ``sigma`` and ``sigma_realistic`` as ``[north, east, down]`` in metres, and
  ``correlation_with_boresight`` as ``{north: {roll, pitch, yaw}, east: {…}, down: {…}}``
  (formal): a large |ρ| says that pass's translation and that angle trade against each other
  (the targets do not separate them).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from calib.boresight.adjust import AdjustmentResult
from calib.boresight.observability import ANGLE_NAMES
from calib.core.frames import boresight_to_thesis

_EXTRA_UNITS = {
    "range_offset": ("range_offset_m", 1.0),
    "scan_angle_offset": ("scan_angle_offset_deg", float(np.degrees(1.0))),
    "lever_arm_x": ("lever_arm_x_m", 1.0),
    "lever_arm_y": ("lever_arm_y_m", 1.0),
    "latency": ("latency_s", 1.0),
}


def _angles_deg(v_rad) -> dict:
    return {name: float(np.degrees(x)) for name, x in zip(ANGLE_NAMES, v_rad)}


def result_to_dict(
    res: AdjustmentResult, apriori_rad, software_version: str, extra: dict | None = None
) -> dict:
    """The result.json document for an adjustment result."""
    thesis = boresight_to_thesis(*res.boresight_rad)
    d = {
        "boresight_deg": _angles_deg(res.boresight_rad),
        "boresight_thesis_convention_deg": _angles_deg(thesis),
        "sigma_deg": _angles_deg(res.sigma_formal_rad),
        "sigma_scaled_deg": _angles_deg(res.sigma_scaled_rad),
        "sigma_realistic_deg": _angles_deg(res.sigma_realistic_rad),
        "sigma_jackknife_deg": None
        if res.cov_jackknife is None
        else _angles_deg(np.sqrt(np.diag(res.cov_jackknife))),
        "realistic_error_model": {
            "kind": res.error_model.kind,
            "correlation_time_s": (
                res.error_model.correlation_time_s
                if isinstance(res.error_model.correlation_time_s, float)
                else list(res.error_model.correlation_time_s)
            )
            if res.error_model.kind == "gauss_markov"
            else None,
        },
        "correlation": [[float(x) for x in row] for row in res.correlation],
        "sigma0_squared": float(res.sigma0_squared),
        "chi2_test": res.chi2_test(),
        "iterations": int(res.iterations),
        "converged": bool(res.converged),
        "planes": res.plane_stats,
        "passes": res.pass_stats,
        "n_points": int(res.n_points),
        "n_outliers": int(res.outlier_point_ids.size),
        "outlier_point_ids": [int(i) for i in res.outlier_point_ids],
        "extras": _extras(res),
        "runtime_s": float(res.runtime_s),
        "apriori_deg": _angles_deg(apriori_rad),
        "software_version": software_version,
    }
    if extra:
        d.update(extra)
    return d


OFFSET_COMPONENTS = ("north", "east", "down")


def _extras(res: AdjustmentResult) -> dict:
    out = {}
    for name, e in res.extras.items():
        if name in _EXTRA_UNITS:
            key, scale = _EXTRA_UNITS[name]
            out[key] = {
                "value": e["value"] * scale,
                "sigma": e["sigma"] * scale,
                "sigma_realistic": e["sigma_realistic"] * scale,
                "correlation_with_boresight": dict(zip(ANGLE_NAMES, e["correlation_with_boresight"])),
            }
        else:  # pass<id>_offset_m: metres already, one correlation row per component
            out[name] = {
                **e,
                "correlation_with_boresight": {
                    c: dict(zip(ANGLE_NAMES, row))
                    for c, row in zip(OFFSET_COMPONENTS, e["correlation_with_boresight"])
                },
            }
    return out


def write_result(path: str | Path, doc: dict) -> Path:
    p = Path(path)
    p.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    return p


def estimator_doc(estimator: str, tie_patches: str, gls: dict, comparison: AdjustmentResult | None) -> dict:
    """What result.json says about the estimator, τ, the thesis comparison and the tie patches
    (``gls``: :attr:`calib.boresight.pipeline.CalibrationRun.gls`)."""

    def brief(r: AdjustmentResult) -> dict:
        return {
            "boresight_deg": [float(x) for x in np.degrees(r.boresight_rad)],
            "sigma_realistic_deg": [float(x) for x in np.degrees(r.sigma_realistic_rad)],
        }

    out: dict = {"estimator": estimator, "tie_patches_mode": tie_patches}
    if comparison is not None:
        out["thesis_estimator"] = brief(comparison)
    if "targets_only" in gls:
        out["targets_only"] = brief(gls["targets_only"])
    if "ties" in gls:
        t = gls["ties"]
        c = t.candidates
        out["tie_patches"] = [
            {
                "name": c.names[j],
                "n_points": int(c.n_points[j]),
                "passes": [int(x) for x in c.passes[j]],
                "normal": [float(x) for x in c.normals[j]],
                "center_lgf_m": [float(x) for x in c.centers_m[j]],
                "rms_m": float(c.rms_m[j]),
                "info_gain": g,
            }
            for j, g in zip(t.chosen, t.gain)
        ]
        out["tie_patch_candidates"] = {
            "found": len(c.names),
            "size_m": float(c.size_m),
            "rejected_cells": dict(c.rejected),
        }
    if "patch_check" in gls:
        out["tie_patch_check"] = gls["patch_check"]
    if "estimate" in gls:
        out["tau_estimate"] = gls["estimate"]
    if "sensitivity" in gls:
        out["tau_sensitivity"] = gls["sensitivity"]
    return out
