"""The pass plan as GeoJSON (RFC 7946) for chart plotters, GIS and the helmsman (docs/architecture.md §8).

One FeatureCollection in WGS84 longitude/latitude with the ellipsoidal height as the optional
third coordinate (so that the lines convert back to the plan's LGF exactly):

- per pass a ``LineString`` from the line's start to its end, ``"kind": "line"``, with the pass
  id, sailing order, true heading, heading relative to the wall, speed, length, duration, the
  capture window (metres from the start and seconds after the start) and the side the targets
  are seen on;
- per pass a second ``LineString`` over the capture window only, ``"kind": "capture"``;
- per target a ``Point`` at its configured centre, ``"kind": "target"``.

The collection carries a foreign member ``"mls_plan"`` with the LGF reference, the wall azimuth
and the standoff. Coordinates keep 1e-10° (~0.01 mm) and heights 0.1 mm.
:func:`write_plan_geojson` writes it to a file (what ``mls plan --out`` does).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from calib.core import frames
from calib.io.site import Target
from calib.survey.passplan import PassPlan, PlannedPass

FORMAT = "marine-mls pass plan v1"


def _coords(frame: frames.LocalFrame, p_lgf_m) -> list[list[float]]:
    lat, lon, h = frame.to_geodetic(np.atleast_2d(np.asarray(p_lgf_m, float)))
    return [
        [round(float(x), 10), round(float(y), 10), round(float(z), 4)]
        for x, y, z in zip(lon, lat, h, strict=False)
    ]


def _pass_properties(p: PlannedPass) -> dict:
    cw = p.capture_window_s
    return {
        "pass_id": p.id,
        "order": p.order,
        "heading_deg": round(math.degrees(p.heading_rad), 6),
        "relative_heading_deg": round(math.degrees(p.relative_heading_rad), 6),
        "speed_mps": p.speed_mps,
        "length_m": round(p.length_m, 4),
        "duration_s": round(p.duration_s, 3),
        "capture_start_m": round(p.capture_start_m, 4),
        "capture_end_m": round(p.capture_end_m, 4),
        "capture_window_s": [round(cw[0], 3), round(cw[1], 3)],
        "targets_side": p.targets_side,
        "end_wall_distance_m": round(p.end_wall_distance_m, 3),
    } | ({} if p.standoff_m is None else {"standoff_m": round(p.standoff_m, 3)})


def plan_geojson(
    plan: PassPlan, frame: frames.LocalFrame, targets: Sequence[Target] = (), name: str | None = None
) -> dict:
    """The plan (lines in the LGF of ``frame``) as a GeoJSON FeatureCollection (a dict)."""
    features = []
    for p in plan.passes:
        props = _pass_properties(p)
        features.append(
            {
                "type": "Feature",
                "id": f"pass-{p.id}",
                "properties": {"kind": "line", **props},
                "geometry": {
                    "type": "LineString",
                    "coordinates": _coords(frame, [p.start_lgf_m, p.end_lgf_m]),
                },
            }
        )
        cap = p.position_at([p.capture_start_m, p.capture_end_m])
        features.append(
            {
                "type": "Feature",
                "id": f"pass-{p.id}-capture",
                "properties": {"kind": "capture", **props},
                "geometry": {"type": "LineString", "coordinates": _coords(frame, cap)},
            }
        )
    for t in targets:
        features.append(
            {
                "type": "Feature",
                "id": f"target-{t.name}",
                "properties": {
                    "kind": "target",
                    "name": t.name,
                    "width_m": t.width_m,
                    "height_m": t.height_along_slope_m,
                    "inclination_deg": round(math.degrees(t.inclination_rad), 6),
                    "facing_azimuth_deg": round(math.degrees(t.facing_azimuth_rad), 6),
                    "reflectivity": t.reflectivity,
                },
                "geometry": {"type": "Point", "coordinates": [t.lon_deg, t.lat_deg, t.height_m]},
            }
        )
    return {
        "type": "FeatureCollection",
        "name": name or "mls pass plan",
        "mls_plan": {
            "format": FORMAT,
            "reference": frame.as_dict(),
            "height_ref": "ellipsoid",
            "wall_azimuth_deg": round(math.degrees(plan.wall_azimuth_rad), 6),
            "water_azimuth_deg": round(math.degrees(plan.water_azimuth_rad), 6),
            "standoff_m": plan.standoff_m,
            "safe_wall_distance_m": plan.safe_wall_distance_m,
            "n_passes": len(plan.passes),
        },
        "features": features,
    }


def write_plan_geojson(
    path: str | Path,
    plan: PassPlan,
    frame: frames.LocalFrame,
    targets: Sequence[Target] = (),
    name: str | None = None,
) -> Path:
    """Write :func:`plan_geojson` to ``path`` (its folder created), UTF-8; returns the path."""
    path = Path(path)
    doc = plan_geojson(plan, frame, targets, name=name)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    return path
