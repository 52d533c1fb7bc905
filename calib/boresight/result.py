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
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from calib.boresight.adjust import AdjustmentResult
from calib.boresight.checks.verdict import Verdict, as_doc
from calib.boresight.observability import ANGLE_NAMES
from calib.core.frames import boresight_to_thesis
from calib.core.version import software_version

if TYPE_CHECKING:  # (annotations only)
    from calib.boresight.scene_ties import TiePatches
    from calib.boresight.tau import TauChoice, TauEstimate
    from calib.core.georef import Mount
    from calib.extraction.extract import Extraction

_EXTRA_UNITS = {
    "range_offset": ("range_offset_m", 1.0),
    "scan_angle_offset": ("scan_angle_offset_deg", float(np.degrees(1.0))),
    "lever_arm_x": ("lever_arm_x_m", 1.0),
    "lever_arm_y": ("lever_arm_y_m", 1.0),
    "latency": ("latency_s", 1.0),
}


def _angles_deg(v_rad) -> dict:
    return {name: float(np.degrees(x)) for name, x in zip(ANGLE_NAMES, v_rad, strict=False)}


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
                "correlation_with_boresight": dict(
                    zip(ANGLE_NAMES, e["correlation_with_boresight"], strict=False)
                ),
            }
        else:  # pass<id>_offset_m: metres already, one correlation row per component
            out[name] = {
                **e,
                "correlation_with_boresight": {
                    c: dict(zip(ANGLE_NAMES, row, strict=False))
                    for c, row in zip(OFFSET_COMPONENTS, e["correlation_with_boresight"], strict=False)
                },
            }
    return out


def write_result(path: str | Path, doc: dict) -> Path:
    p = Path(path)
    p.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    return p


@dataclass(kw_only=True)
class GlsDiagnostics:
    """What the GLS calibration found beside its result, filled in stage by stage: τ from the
    data, the boresight at τ/3, τ and 3τ, the tie patches and whether they agree with the
    targets (:attr:`calib.boresight.pipeline.CalibrationRun.diagnostics`)."""

    estimate: TauEstimate | None = None  # τ estimated from the data (none configured)
    sensitivity: list[dict] | None = None  # rows of calib.boresight.tau.tau_sensitivity
    patch_check: dict | None = None  # calib.boresight.scene_ties.patches_agree
    targets_only: AdjustmentResult | None = None  # the solution before the (accepted) patches
    ties: TiePatches | None = None  # the accepted tie patches
    #: Cramér–Rao σ (deg) of roll, pitch, yaw by feature set (calib.boresight.scene_ties.crlb_by_features)
    crlb_by_features_deg: dict[str, list[float]] | None = None


def _brief(r: AdjustmentResult) -> dict:
    return {
        "boresight_deg": [float(x) for x in np.degrees(r.boresight_rad)],
        "sigma_realistic_deg": [float(x) for x in np.degrees(r.sigma_realistic_rad)],
    }


def _tie_patch_docs(t: TiePatches) -> dict:
    """The chosen tie features (patches, cylinders) and what the search found."""
    out: dict = {"tie_patches": [], "tie_cylinders": []}
    n_p = t.n_patch_candidates
    for j, g in zip(t.chosen, t.gain, strict=True):
        if j < n_p:
            out["tie_patches"].append(_patch_doc(t.candidates, j, g))
        else:
            out["tie_cylinders"].append(_cylinder_doc(t.cylinders, j - n_p, g))
    c = t.candidates
    if c is not None:
        out["tie_patch_candidates"] = {
            "found": len(c.names),
            "size_m": float(c.size_m),
            "rejected_cells": dict(c.rejected),
        }
    if t.cylinders is not None:
        out["tie_cylinder_candidates"] = {"found": len(t.cylinders), "rejected": dict(t.cylinders.rejected)}
    return out


def _patch_doc(c, j: int, gain: float) -> dict:
    return {
        "name": c.names[j],
        "n_points": int(c.n_points[j]),
        "passes": [int(x) for x in c.passes[j]],
        "normal": [float(x) for x in c.normals[j]],
        "center_lgf_m": [float(x) for x in c.centers_m[j]],
        "rms_m": float(c.rms_m[j]),
        "info_gain": gain,
    }


def _cylinder_doc(c, k: int, gain: float) -> dict:
    return {
        "name": c.names[k],
        "n_points": int(c.n_points[k]),
        "passes": [int(x) for x in c.passes[k]],
        "axis_center_lgf_m": [float(x) for x in c.centers_m[k]],
        "radius_m": float(c.radius_m[k]),
        "height_m": float(c.height_m[k]),
        "rms_m": float(c.rms_m[k]),
        "info_gain": gain,
    }


def estimator_doc(
    estimator: str, tie_patches: str, gls: GlsDiagnostics, comparison: AdjustmentResult | None
) -> dict:
    """What result.json says about the estimator, τ, the thesis comparison and the tie patches."""
    out: dict = {"estimator": estimator, "tie_patches_mode": tie_patches}
    if comparison is not None:
        out["thesis_estimator"] = _brief(comparison)
    if gls.targets_only is not None:
        out["targets_only"] = _brief(gls.targets_only)
    if gls.ties is not None:
        out.update(_tie_patch_docs(gls.ties))
    if gls.patch_check is not None:
        out["tie_patch_check"] = gls.patch_check
    if gls.crlb_by_features_deg is not None:
        out["crlb_by_features_deg"] = gls.crlb_by_features_deg
    if gls.estimate is not None:
        out["tau_estimate"] = gls.estimate.as_dict()
    if gls.sensitivity is not None:
        out["tau_sensitivity"] = gls.sensitivity
    return out


def calibration_doc(
    res: AdjustmentResult,
    mount: Mount,
    options,  # calib.boresight.pipeline.CalibrationOptions
    ext: Extraction,
    labels,
    tau: TauChoice,
    gls: GlsDiagnostics,
    comparison: AdjustmentResult | None,
    verdict: Verdict,
    source: str,
    version: str | None,
) -> dict:
    """result.json of a calibration (:func:`calib.boresight.pipeline.calibrate`; its warnings and
    notes are added by the caller): the adjustment's result, the verdict, the extraction, where
    τ came from and the estimator's diagnostics."""
    ratio = res.sigma_realistic_rad / res.sigma_formal_rad
    extra = {
        "source": source,
        **as_doc(verdict),
        "removed_groups": list(res.removed_groups),
        "extraction": {
            "mode": options.extraction.mode if labels is None else "labels",
            "subsample_m": options.subsample_m,
            "points_per_pass": {str(k): v for k, v in ext.counts().items()},
            "points_per_target": ext.totals(),
            "lost": [
                {"target": f.target, "pass_id": int(f.pass_id), "status": f.status, "reason": f.note}
                for f in ext.found
                if f.n_points == 0
            ],
        },
        "realistic_correlation_time_source": tau.source.text,
        "sigma_realistic_over_formal": {
            a: float(r) for a, r in zip(("roll", "pitch", "yaw"), ratio, strict=False)
        },
        "outlier_point_ids_refer_to": "0-based data rows of points.csv (after the header)",
    }
    extra.update(estimator_doc(options.estimator, options.tie_patches, gls, comparison))
    return result_to_dict(res, mount.boresight_rad, version or software_version(), extra)
