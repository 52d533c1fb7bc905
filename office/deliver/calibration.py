"""The calibrated mount a survey is georeferenced with, its covariance and its provenance.

``--calibration`` names a ``result.json`` (file or directory) or a calibration-history id
(``#12``, :func:`calib.assess.history.resolve_result`). The result's boresight replaces the
vessel config's a-priori one, and the extra unknowns it estimated are applied (range and scan-
angle offsets, latency, lever-arm x/y). The boresight covariance is the result's realistic σ
(the GLS formal σ; else the scaled σ) with its correlation; the lever arm's is the estimated
components' realistic σ (components not estimated: 0 — the lever arm as measured is taken as
exact). Without ``--calibration`` the a-priori boresight is used and its uncertainty is not in
the per-point σ: a warning says so. A result whose verdict is not ``trusted`` (or that has none)
is used as given, with a warning naming its verdict and reasons; the provenance records it.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field, replace

import numpy as np

from calib.boresight.checks.verdict import untrusted_warning
from calib.core.georef import Mount
from calib.core.tpu import MountCovariance, ScannerSigmas
from office.deliver.options import GeorefError

_EXTRAS = {  # result.json extras → Mount field, scale to SI
    "range_offset_m": ("range_offset_m", 1.0),
    "scan_angle_offset_deg": ("scan_angle_offset_rad", float(np.radians(1.0))),
    "latency_s": ("time_offset_s", 1.0),
}


@dataclass(frozen=True)
class Calibration:
    mount: Mount
    covariance: MountCovariance
    scanner: ScannerSigmas
    provenance: dict
    warnings: list[str] = field(default_factory=list)
    #: the warning of a result whose verdict is not trusted (also in ``warnings``); None else
    untrusted: str | None = None


def fingerprint(result: dict) -> str:
    """SHA-256 of the result's canonical JSON (what a tile's provenance names)."""
    return hashlib.sha256(json.dumps(result, sort_keys=True).encode("utf-8")).hexdigest()


def _covariance(result: dict) -> np.ndarray:
    sig = result.get("sigma_realistic_deg") or result["sigma_scaled_deg"]
    s = np.radians([float(sig[k]) for k in ("roll", "pitch", "yaw")])
    return np.asarray(result["correlation"], float) * np.outer(s, s)


def scanner_sigmas(site) -> ScannerSigmas:
    return ScannerSigmas(
        sigma_range_m=float(site.sigma_range_m),
        sigma_range_per_m=float(site.sigma_range_per_m),
        sigma_angle_rad=float(site.sigma_scan_angle_rad),
    )


def load_calibration(site, ref: str | None, software: str, db=None) -> Calibration:
    """The mount for ``site`` (its vessel's) calibrated by ``ref`` (module docstring)."""
    from calib.assess.history import HistoryError, ResultFormatError, resolve_result

    base = site.mount
    if ref is None:
        prov = {
            "calibration": None,
            "mount_id": site.vessel,
            "boresight_deg": [float(v) for v in np.degrees(base.boresight_rad)],
            "software": software,
        }
        return Calibration(
            base,
            MountCovariance(np.zeros((3, 3)), np.zeros((3, 3))),
            scanner_sigmas(site),
            prov,
            [
                "no --calibration: the vessel config's a-priori boresight is used and its "
                "uncertainty is not in sigma_h_m / sigma_v_m"
            ],
        )
    try:
        found, label = resolve_result(ref, db=db, which="--calibration")
    except (HistoryError, ResultFormatError) as e:
        raise GeorefError(str(e)) from None
    result = found if isinstance(found, dict) else found.result
    mount_id = site.vessel if isinstance(found, dict) else found.mount_id
    b = result["boresight_deg"]
    mount = base.with_boresight(np.radians([float(b[k]) for k in ("roll", "pitch", "yaw")]))
    extras = result.get("extras") or {}
    lever = mount.lever_arm_m.copy()
    lever_var = np.zeros(3)
    applied = []
    for key, extra in extras.items():
        if key in _EXTRAS:
            attr, scale = _EXTRAS[key]
            mount = replace(mount, **{attr: float(extra["value"]) * scale})
            applied.append(key)
        elif key in ("lever_arm_x_m", "lever_arm_y_m"):
            i = 0 if key == "lever_arm_x_m" else 1
            lever[i] = float(extra["value"])
            lever_var[i] = float(extra.get("sigma_realistic", extra["sigma"])) ** 2
            applied.append(key)
    mount = replace(mount, lever_arm_m=lever)
    cov = MountCovariance(_covariance(result), np.diag(lever_var))
    prov = {
        "calibration": label,
        "result_fingerprint": fingerprint(result),
        "mount_id": mount_id,
        "boresight_deg": [float(b[k]) for k in ("roll", "pitch", "yaw")],
        "boresight_sigma_deg": [float(v) for v in np.degrees(np.sqrt(np.diag(cov.boresight_cov_rad2)))],
        "extras_applied": applied,
        "calibration_software": result.get("software_version"),
        "calibration_verdict": result.get("verdict"),
        "calibration_verdict_reasons": [str(r) for r in result.get("verdict_reasons") or []],
        "software": software,
    }
    warning = untrusted_warning(result, label)
    return Calibration(mount, cov, scanner_sigmas(site), prov, [] if warning is None else [warning], warning)
