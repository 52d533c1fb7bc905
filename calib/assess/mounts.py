"""The mounts an assessment compares: the one a calibration result describes (*after*) and the
true one of a simulated bundle (truth.json); *before* is the site config's own.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from calib.assess.results import ANGLES, AssessError
from calib.core.georef import Mount


def mount_from_result(apriori: Mount, result: dict, source: str = "result") -> tuple[Mount, list[str]]:
    """The mount a calibration result describes: the a-priori one with the estimated boresight
    and the estimated extras (range offset, lever arm x/y, latency) applied; plus notes on what
    was not applied (per-pass trajectory offsets correct the trajectory, not the mount)."""
    from calib.assess.history import validate_result

    bs = validate_result(result, source)["boresight_deg"]
    mount = apriori.with_boresight(np.radians([bs[a] for a in ANGLES]))
    notes = []
    extras = result.get("extras") or {}
    if not isinstance(extras, dict):
        raise AssessError(f"{source}: extras is {extras!r}, expected an object")

    def value(key):
        e = extras[key]
        v = e.get("value") if isinstance(e, dict) else None
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise AssessError(f"{source}: extras.{key}.value is {v!r}, expected a finite number")
        return float(v)

    lever = mount.lever_arm_m.copy()
    kw = {}
    for key in extras:
        if key == "range_offset_m":
            kw["range_offset_m"] = value(key)
        elif key == "scan_angle_offset_deg":
            kw["scan_angle_offset_rad"] = float(np.radians(value(key)))
        elif key == "lever_arm_x_m":
            lever[0] = value(key)
        elif key == "lever_arm_y_m":
            lever[1] = value(key)
        elif key == "latency_s":
            kw["time_offset_s"] = value(key)
        elif not (key.startswith("pass") and key.endswith("_offset_m")):
            notes.append(f"{source}: extra {key!r} is not a mount parameter; not applied")
    if any(k.startswith("pass") and k.endswith("_offset_m") for k in extras):
        notes.append(
            "the result's per-pass trajectory offsets are not applied (they correct "
            "the calibration passes' trajectory, not the mount)"
        )
    return replace(mount, lever_arm_m=lever, **kw), notes


def mount_from_truth(truth: dict, apriori: Mount) -> Mount:
    """The true mount of a simulated bundle (truth.json, docs/architecture.md §4)."""
    try:
        bs = truth["boresight_deg"]
        return Mount(
            lever_arm_m=np.asarray(truth.get("lever_arm_m", apriori.lever_arm_m), float),
            nominal_rad=np.radians(truth.get("nominal_deg", np.degrees(apriori.nominal_rad))),
            boresight_rad=np.radians([float(bs[a]) for a in ANGLES]),
            range_offset_m=float(truth.get("range_offset_m", 0.0)),
            scan_angle_offset_rad=float(np.radians(truth.get("scan_angle_offset_deg", 0.0))),
            time_offset_s=float(truth.get("time_offset_s", 0.0)),
        )
    except (KeyError, TypeError, ValueError) as e:
        raise AssessError(f"truth.json: no usable true mount ({e!r})") from None
