"""Systematic-error visibility criteria (thesis §3.4.4, Appendix C): how strongly one of the
eight systematic errors of an MLS shows on a planar target, pass by pass.

A target is scanned with the error injected and georeferenced with the error-free (a-priori)
mount; each pass's point set is then compared with the true plane:

* **Type I** (raw selection, thesis Algorithm 2): ``planarity · (1 − z)`` with planarity
  ``(λ2 − λ3)/λ1`` of the point set's covariance and ``z`` the centroidal distance (from the
  point set's centroid to the target's centre) min–max normalized over the configurations
  compared (thesis eq. 3.4). Near 1: the pass gives a well-spread, well-placed copy of the plane.
* **Type II** (fine selection, thesis Algorithm 3): the angular deviation between the fitted and
  the true normal (in [0°, 90°]) and the signed orthogonal distance of the fitted centroid from
  the true plane.

An error is *visible* in a configuration when the passes disagree: a plane-based calibration
only sees differences between passes (whatever all passes share is absorbed by the plane's own
parameters). :func:`pass_spread` measures that disagreement: the largest angle between two
passes' normals and the range of their signed distances.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np

from calib.core.errors import CalibError
from calib.core.geometry import Rectangle, fit_plane
from calib.core.georef import georeference
from calib.sim.scenario import InjectedErrors
from calib.sim.simulate import SimResult

#: The eight systematic errors of the thesis (Table 3.2, Appendix C), in its order.
SYSTEMATIC_ERRORS = (
    "boresight_roll",
    "boresight_pitch",
    "boresight_yaw",
    "lever_arm_x",
    "lever_arm_y",
    "lever_arm_z",
    "range_offset",
    "scan_angle_offset",
)
ANGULAR_ERRORS = ("boresight_roll", "boresight_pitch", "boresight_yaw", "scan_angle_offset")

#: Below these pass-to-pass spreads (between the passes with a usable copy) an error is invisible.
VISIBLE_DISTANCE_M = 1e-3
VISIBLE_ANGLE_RAD = float(np.radians(0.01))
#: A pass's copy of a target takes part in the comparison with this many points and this
#: planarity (a single scan line is collinear: its normal is arbitrary).
MIN_CRITERIA_POINTS = 10
MIN_CRITERIA_PLANARITY = 0.1

#: The thesis's inserted magnitudes (rad or m): 2° per boresight angle, 10 cm per lever-arm
#: component and for the range offset, 1° for the scan-angle offset (Appendix C.2.7; its Table
#: 3.2 lists 2°, the appendix's analysis uses 1°).
THESIS_MAGNITUDES = {
    "boresight_roll": float(np.radians(2.0)),
    "boresight_pitch": float(np.radians(2.0)),
    "boresight_yaw": float(np.radians(2.0)),
    "lever_arm_x": 0.10,
    "lever_arm_y": 0.10,
    "lever_arm_z": 0.10,
    "range_offset": 0.10,
    "scan_angle_offset": float(np.radians(1.0)),
}


class CriteriaError(CalibError, ValueError):
    """A criterion cannot be computed for this input (the message says why)."""


def is_angular(error: str) -> bool:
    """Whether the error's magnitude is an angle (radians) rather than metres."""
    _check(error)
    return error in ANGULAR_ERRORS


def _check(error: str) -> None:
    if error not in SYSTEMATIC_ERRORS:
        raise CriteriaError(
            f"unknown systematic error {error!r}; expected one of {', '.join(SYSTEMATIC_ERRORS)}"
        )


def injected(error: str, magnitude: float, apriori_boresight_rad=None) -> InjectedErrors:
    """The simulator's truth with only ``error`` set to ``magnitude`` (rad or m): the true
    boresight is the a-priori one (default zero) plus the error."""
    _check(error)
    bs = np.zeros(3) if apriori_boresight_rad is None else np.asarray(apriori_boresight_rad, float).copy()
    lever = np.zeros(3)
    kw = {}
    axis = {"x": 0, "y": 1, "z": 2, "roll": 0, "pitch": 1, "yaw": 2}
    if error.startswith("boresight_"):
        bs[axis[error.split("_")[1]]] += magnitude
    elif error.startswith("lever_arm_"):
        lever[axis[error[-1]]] = magnitude
    elif error == "range_offset":
        kw["range_offset_m"] = float(magnitude)
    else:
        kw["scan_angle_offset_rad"] = float(magnitude)
    return InjectedErrors(boresight_rad=bs, lever_arm_error_m=lever, **kw)


@dataclass(frozen=True)
class PlaneCriteria:
    """Type I ingredients and Type II criteria of one pass's copy of a target."""

    n_points: int
    planarity: float  # (λ2 − λ3)/λ1
    centroidal_distance_m: float  # |centroid − target centre|
    angular_deviation_rad: float  # in [0, π/2]
    signed_distance_m: float  # of the centroid from the true plane, + on the normal's side
    normal: np.ndarray  # fitted unit normal, oriented like the true one

    @staticmethod
    def missing() -> PlaneCriteria:
        nan = float("nan")
        return PlaneCriteria(0, nan, nan, nan, nan, np.full(3, np.nan))


def plane_criteria(p_lgf_m, reference: Rectangle) -> PlaneCriteria:
    """Algorithms 1–3 of the thesis for one point set against the true ``reference``; fewer
    than 3 points give :meth:`PlaneCriteria.missing`."""
    p = np.asarray(p_lgf_m, float).reshape(-1, 3)
    if p.shape[0] < 3:
        return PlaneCriteria.missing()
    fit = fit_plane(p, orient_like=reference.normal)
    cross = np.linalg.norm(np.cross(fit.normal, reference.normal))
    return PlaneCriteria(
        n_points=int(p.shape[0]),
        planarity=fit.planarity,
        centroidal_distance_m=float(np.linalg.norm(fit.centroid_m - reference.center_m)),
        angular_deviation_rad=float(np.arctan2(cross, abs(fit.normal @ reference.normal))),
        signed_distance_m=float(reference.signed_distance(fit.centroid_m)),
        normal=fit.normal,
    )


def normalized(x) -> np.ndarray:
    """Min–max normalization to [0, 1] (thesis eq. 3.4), ignoring NaN; a constant input gives
    zeros."""
    x = np.asarray(x, float)
    lo, hi = np.nanmin(x), np.nanmax(x)
    if not hi > lo:
        return np.where(np.isnan(x), np.nan, 0.0)
    return (x - lo) / (hi - lo)


def type1(planarity, centroidal_distance_m) -> np.ndarray:
    """Type I criterion of each configuration, ``planarity · (1 − normalized distance)``; the
    normalization runs over the configurations given together. Missing passes (NaN) get 0."""
    v = np.asarray(planarity, float) * (1.0 - normalized(centroidal_distance_m))
    return np.nan_to_num(v, nan=0.0)


def pass_spread(normals, signed_distances_m) -> tuple[float, float]:
    """How much the passes disagree: (largest angle between two passes' normals in rad, range
    of the signed distances in m). Passes with NaN are ignored; fewer than two give (0, 0)."""
    n = np.asarray(normals, float).reshape(-1, 3)
    d = np.asarray(signed_distances_m, float).reshape(-1)
    ok = np.isfinite(d) & np.all(np.isfinite(n), axis=1)
    n, d = n[ok], d[ok]
    if d.size < 2:
        return 0.0, 0.0
    angle = max(float(np.arctan2(np.linalg.norm(np.cross(a, b)), a @ b)) for a, b in combinations(n, 2))
    return angle, float(d.max() - d.min())


def thesis_tilt_deg(inclination_deg: float) -> float:
    """The thesis Chapter 3 angle of a plane (0° vertical, −90° horizontal facing up, positive:
    leaning toward the scanner's side) from the design inclination (angle to the horizontal,
    negative: tilted the other way)."""
    return float(inclination_deg - 90.0 if inclination_deg >= 0 else inclination_deg + 90.0)


# ---------------------------------------------------------------------------------------------
# Tables of a study: per pass, per inclination
# ---------------------------------------------------------------------------------------------

CRITERIA_COLUMNS = (
    "scenario",
    "error",
    "magnitude_deg",
    "magnitude_m",
    "inclination_deg",
    "thesis_tilt_deg",
    "pass_id",
    "heading_deg",
    "n_points",
    "planarity",
    "centroidal_distance_m",
    "type1",
    "angular_deviation_deg",
    "signed_distance_m",
    "normal_n",
    "normal_e",
    "normal_d",
)
VISIBILITY_COLUMNS = (
    "scenario",
    "error",
    "inclination_deg",
    "thesis_tilt_deg",
    "passes_used",
    "type1_mean",
    "type1_min",
    "angle_spread_deg",
    "distance_spread_m",
    "visible",
)


def criteria_rows(sim: SimResult, error: str, magnitude: float, inclination_deg: float) -> list[dict]:
    """One row per pass (:data:`CRITERIA_COLUMNS`; Type I still NaN, see :func:`summarize`) for
    a simulation of one target with ``error`` injected: its returns georeferenced with the
    a-priori (error-free) mount and the true trajectory, compared with the true rectangle."""
    p = sim.points
    x = georeference(p.t_gps_s, p.range_m, p.scan_angle_rad, sim.trajectory_true, sim.site.mount)
    rect = sim.scene.rectangles[sim.scene.indices("target")[0]]
    rows = []
    for q in sim.plan.passes:
        c = plane_criteria(x[(sim.target_index == 0) & (p.pass_id == q.id)], rect)
        rows.append(
            {
                "scenario": sim.scenario.name,
                "error": error,
                "magnitude_deg": float(np.degrees(magnitude)) if is_angular(error) else "",
                "magnitude_m": "" if is_angular(error) else float(magnitude),
                "inclination_deg": float(inclination_deg),
                "thesis_tilt_deg": thesis_tilt_deg(inclination_deg),
                "pass_id": q.id,
                "heading_deg": float(np.degrees(q.relative_heading_rad)) % 360.0,
                "n_points": c.n_points,
                "planarity": c.planarity,
                "centroidal_distance_m": c.centroidal_distance_m,
                "type1": float("nan"),
                "angular_deviation_deg": float(np.degrees(c.angular_deviation_rad)),
                "signed_distance_m": c.signed_distance_m,
                "normal_n": float(c.normal[0]),
                "normal_e": float(c.normal[1]),
                "normal_d": float(c.normal[2]),
            }
        )
    return rows


def summarize(rows: list[dict]) -> list[dict]:
    """Fill Type I in every row (normalized per error over all its inclinations and passes,
    thesis eq. 3.4) and return, per error and inclination (:data:`VISIBILITY_COLUMNS`), how
    much the passes with a usable copy disagree."""
    out = []
    for error in dict.fromkeys(r["error"] for r in rows):
        sel = [r for r in rows if r["error"] == error]
        t1 = type1([r["planarity"] for r in sel], [r["centroidal_distance_m"] for r in sel])
        for r, v in zip(sel, t1, strict=False):
            r["type1"] = float(v)
        for inc in dict.fromkeys(r["inclination_deg"] for r in sel):
            here = [r for r in sel if r["inclination_deg"] == inc]
            used = [
                r
                for r in here
                if r["n_points"] >= MIN_CRITERIA_POINTS and r["planarity"] >= MIN_CRITERIA_PLANARITY
            ]
            ang, dist = pass_spread(
                [[r["normal_n"], r["normal_e"], r["normal_d"]] for r in used],
                [r["signed_distance_m"] for r in used],
            )
            t1s = [r["type1"] for r in here]
            out.append(
                {
                    "scenario": sel[0]["scenario"],
                    "error": error,
                    "inclination_deg": inc,
                    "thesis_tilt_deg": thesis_tilt_deg(inc),
                    "passes_used": tuple(r["pass_id"] for r in used),
                    "type1_mean": float(np.mean(t1s)),
                    "type1_min": float(np.min(t1s)),
                    "angle_spread_deg": float(np.degrees(ang)),
                    "distance_spread_m": dist,
                    "visible": bool(dist >= VISIBLE_DISTANCE_M or ang >= VISIBLE_ANGLE_RAD),
                }
            )
    return out


def best_inclinations(visibility, error: str, type1_threshold: float) -> tuple[dict, dict]:
    """The thesis's selection for one error: among the inclinations whose mean Type I reaches
    ``type1_threshold`` (all of them if none does), the one where the passes' signed distances
    differ most and the one where their normals do."""
    vs = [v for v in visibility if v["error"] == error]
    good = [v for v in vs if v["type1_mean"] >= type1_threshold] or vs
    return (max(good, key=lambda v: v["distance_spread_m"]), max(good, key=lambda v: v["angle_spread_deg"]))


#: Colours of the six passes in the thesis's order (0°, 180°, 45°, 225°, 315°, 135°).
PASS_COLOURS = ("tab:red", "tab:blue", "tab:green", "tab:orange", "tab:purple", "black")


def plot_criteria(rows, error: str, path, title: str = ""):
    """Thesis Fig. 3.13/3.14 style: Type I, signed distance and angular deviation against the
    inclination, one line per pass, for one error's rows of :func:`criteria_rows`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in rows if r["error"] == error]
    if not rows:
        raise CriteriaError(f"no criteria rows for {error!r}")
    passes = list(dict.fromkeys(r["pass_id"] for r in rows))
    fig, axes = plt.subplots(3, 1, figsize=(7.5, 8.5), sharex=True)
    for k, pid in enumerate(passes):
        sel = sorted((r for r in rows if r["pass_id"] == pid), key=lambda r: r["inclination_deg"])
        x = [r["inclination_deg"] for r in sel]
        kw = dict(
            color=PASS_COLOURS[k % 6],
            marker="o",
            ms=3,
            lw=1.2,
            label=f"pass {pid} ({sel[0]['heading_deg']:g}°)",
        )
        axes[0].plot(x, [r["type1"] for r in sel], **kw)
        axes[1].plot(x, [1e3 * r["signed_distance_m"] for r in sel], **kw)
        axes[2].plot(x, [r["angular_deviation_deg"] for r in sel], **kw)
    axes[0].set_ylabel("Type I")
    axes[1].set_ylabel("signed orthogonal\ndistance (mm)")
    axes[2].set_ylabel("angular deviation (°)")
    axes[2].set_xlabel("plane inclination (°, 90 = vertical)")
    mag = rows[0]["magnitude_deg"] if is_angular(error) else rows[0]["magnitude_m"]
    unit = "°" if is_angular(error) else " m"
    axes[0].set_title(f"{title}{error.replace('_', ' ')} {mag:g}{unit} — visibility criteria per pass")
    axes[0].legend(fontsize=7, ncol=3)
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.subplots_adjust(left=0.13, right=0.97, top=0.95, bottom=0.07, hspace=0.12)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
