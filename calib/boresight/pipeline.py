"""The calibration pipeline (docs/architecture.md §7): a bundle in, the boresight and its
uncertainties out.

    bundle ──► compare its passes with site.yaml's plan (a planned pass without points, points
               of an unplanned pass: a warning naming both files)
           ──► check the points (finite, ordered in time within each pass, covered by the
               trajectory; with ``skip_uncovered`` the points outside its coverage are dropped
               and counted per pass instead)
           ──► georeference every pass with the a-priori mount
           ──► extract each target of each pass (:mod:`calib.extraction.extract`), optional voxel
               subsampling
           ──► observations (:func:`calib.boresight.observations.build_observations`: trajectory at the
               point times, the trajectory's per-epoch σ or the site's), initial planes (each
               target's points over all passes combined, thesis §4.4.4; see
               :func:`calib.extraction.extract.initial_planes`)
           ──► the Gauss–Helmert adjustment (:func:`calib.boresight.adjust.adjust`)
           ──► the result.json document (:func:`calib.boresight.result.result_to_dict`)

:func:`calibrate` works on objects in memory (a site, a trajectory and raw scanner points,
optionally per-point POS observations or known target labels, as a simulator has them);
:func:`calibrate_bundle` reads a bundle directory; :func:`run_bundle` also writes
``result.json``, ``report.md`` and the plots (what ``mls calib run`` calls). Every step
reports through ``progress(stage, done, total)``.

Convergence is declared when no angle moves by more than 1e-6 rad and no offset by more than
10 µm (:class:`CalibrationOptions`; the adjustment's own defaults are 1000× stricter and cost
2–3 more iterations on noisy data for a boresight change below 1e-8 rad).

The realistic σ assumes first-order Gauss–Markov POS errors by default, with the correlation
time given by the caller, else the site's ``pos_sigmas.correlation_time_s``, else
:data:`calib.boresight.errormodel.DEFAULT_POS_CORRELATION_S` (and the report says it was assumed).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from calib.boresight.adjust import AdjustmentResult, adjust
from calib.boresight.errormodel import DEFAULT_POS_CORRELATION_S, ErrorModel
from calib.boresight.observations import AdjustOptions, Observations, build_observations, validate_input
from calib.boresight.result import estimator_doc, result_to_dict, write_result
from calib.boresight.scene_ties import patches_agree, tie_patches_from_points
from calib.boresight.tau import estimate_tau, tau_sensitivity
from calib.core import frames
from calib.core.errors import CalibError
from calib.core.georef import Mount
from calib.core.trajectory import Poses, Trajectory
from calib.core.version import software_version as _software_version
from calib.extraction.extract import (
    Extraction,
    ExtractOptions,
    extract,
    from_labels,
    initial_planes,
    subsample,
)
from calib.extraction.points import georeference_passes, pass_headings
from calib.io.bundle import ScanPoints, intensity_scale, read_bundle
from calib.io.site import Site

Progress = Callable[[str, float, float | None], None]
ERROR_MODELS = ("gauss_markov", "pass_bias", "white")
#: what ``--estimator`` offers: GLS over Gauss–Markov POS errors (the default), the thesis's
#: white weights, and the thesis's weights with per-pass trajectory offsets
ESTIMATORS = ("gls", "thesis", "pass_offsets")


class CalibrationError(CalibError, ValueError):
    """The input cannot be calibrated as given (the message says why and what to do)."""


@dataclass(frozen=True)
class CalibrationOptions:
    subsample_m: float | None = None  # voxel edge; None: every extracted point
    estimate: tuple[str, ...] = ()  # extra unknowns (calib.boresight.observations.ESTIMABLE)
    estimator: str = "gls"  # of ESTIMATORS
    tie_patches: str = "auto"  # "auto": add planar patches of the scene (gls only); "off"
    apriori_rad: tuple[float, float, float] | None = None  # overrides site.yaml's boresight
    error_model: str = "gauss_markov"  # of the POS errors, for sigma_realistic
    correlation_time_s: float | tuple[float, ...] | None = None  # overrides site.yaml's
    extraction: ExtractOptions = field(default_factory=ExtractOptions)
    outliers: str = "snooping"
    jackknife: bool = True
    #: convergence (calib.boresight.observations.AdjustOptions): absolute step tolerances, or every step
    #: below ``rel_tol`` of its formal σ, whichever comes first
    tol_angle_rad: float = AdjustOptions.tol_angle_rad
    tol_m: float = AdjustOptions.tol_m
    rel_tol: float = AdjustOptions.rel_tol
    #: iteration cap of the adjustment: reaching it unconverged is a warning in the result
    max_iterations: int = AdjustOptions.max_iterations

    def __post_init__(self):
        if self.estimator not in ESTIMATORS:
            raise CalibrationError(
                f"estimator {self.estimator!r} (--estimator): expected one of {', '.join(ESTIMATORS)}"
            )
        if self.tie_patches not in ("auto", "off"):
            raise CalibrationError(
                f"tie patches {self.tie_patches!r} (--tie-patches): expected 'auto' or 'off'"
            )
        if self.error_model not in ERROR_MODELS:  # first: an unknown name is named as such
            raise CalibrationError(
                f"error model {self.error_model!r}: expected one of {', '.join(ERROR_MODELS)}"
            )
        if self.estimator == "gls" and self.error_model != "gauss_markov":
            raise CalibrationError(
                f"error model {self.error_model!r} goes with --estimator thesis or pass_offsets: the "
                f"GLS estimator models the POS errors as Gauss–Markov processes"
            )
        self.adjust_options(ErrorModel("white"))  # unknown or refused extra unknowns: now
        if self.subsample_m is not None and not (np.isfinite(self.subsample_m) and self.subsample_m > 0):
            raise CalibrationError(
                f"subsampling voxel {self.subsample_m!r} m: expected a positive size in metres, e.g. 0.05"
            )
        if self.correlation_time_s is not None:
            tau = np.atleast_1d(np.asarray(self.correlation_time_s, float))
            if tau.size not in (1, 6) or not np.all(np.isfinite(tau) & (tau > 0)):
                raise CalibrationError(
                    f"correlation time {self.correlation_time_s!r} s: expected one positive number (or six)"
                )

    def adjust_options(self, model: ErrorModel) -> AdjustOptions:
        offsets = (
            ("pass_offsets",)
            if self.estimator == "pass_offsets" and "pass_offsets" not in self.estimate
            else ()
        )
        return AdjustOptions(
            estimate=tuple(self.estimate) + offsets,
            estimator="gls" if self.estimator == "gls" else "thesis",
            error_model=model,
            jackknife=self.jackknife,
            outliers=self.outliers,
            tol_angle_rad=self.tol_angle_rad,
            tol_m=self.tol_m,
            rel_tol=self.rel_tol,
            max_iterations=self.max_iterations,
        )


@dataclass
class CalibrationRun:
    """Everything a calibration produced (the report is written from it)."""

    source: str  # the bundle's path, or a description of the in-memory input
    site: Site
    frame: frames.LocalFrame
    mount_apriori: Mount
    options: CalibrationOptions
    extraction: Extraction
    observations: Observations
    planes_init: list[tuple[np.ndarray, float]]
    result: AdjustmentResult
    doc: dict  # result.json
    warnings: list[str]
    notes: list[str]  # assumptions the report states
    timings_s: dict[str, float]
    #: the thesis estimator on the same targets (beside the default GLS in the report)
    comparison: AdjustmentResult | None = None
    #: GLS: "estimate" (τ from the data), "sensitivity" (τ/3, τ, 3τ), "targets_only" (the
    #: solution before tie patches), "ties" (:class:`calib.boresight.scene_ties.TiePatches`)
    gls: dict = field(default_factory=dict)


# -- checks ---------------------------------------------------------------------------------


def check_points(points: ScanPoints, trajectory: Trajectory, time_offset_s: float = 0.0) -> None:
    """Refuse what cannot be georeferenced: non-finite times or observations, times going
    backwards within a pass, and points the trajectory does not cover (named by pass)."""
    t, pid = points.t_gps_s, points.pass_id
    bad = ~np.isfinite(t)
    if bad.any():
        i = int(np.argmax(bad))
        raise CalibrationError(
            f"{int(bad.sum())} point time(s) are NaN or infinite (first: "
            f"point {i}, pass {int(pid[i])}); fix or drop them"
        )
    for name, arr in (("range", points.range_m), ("scan angle", points.scan_angle_rad)):
        bad = ~np.isfinite(arr)
        if bad.any():
            i = int(np.argmax(bad))
            raise CalibrationError(
                f"{name} is NaN or infinite for {int(bad.sum())} point(s) "
                f"(first: point {i}, pass {int(pid[i])})"
            )
    back = (pid[1:] == pid[:-1]) & (np.diff(t) < 0)
    if back.any():
        i = int(np.argmax(back)) + 1
        raise CalibrationError(
            f"point times go backwards within pass {int(pid[i])} at point {i} "
            f"({t[i]:.6f} s after {t[i - 1]:.6f} s): the points of a pass "
            f"must be in time order"
        )
    uncovered = trajectory.uncovered(t + time_offset_s)
    if uncovered.any():
        parts = []
        for p in np.unique(pid[uncovered]):
            m = uncovered & (pid == p)
            parts.append(
                f"pass {int(p)}: {int(m.sum())} of {int(np.sum(pid == p))} points, "
                f"{t[m].min():.3f}…{t[m].max():.3f} s ({trajectory.where_uncovered(t[m] + time_offset_s)})"
            )
        raise CalibrationError(
            f"the trajectory does not cover the points: {trajectory.name} spans "
            f"{trajectory.t_gps_s[0]:.3f}…{trajectory.t_gps_s[-1]:.3f} s (gaps > "
            f"{trajectory.max_gap_s:g} s refused); {'; '.join(parts)}. Export the trajectory over "
            f"every pass, or drop these points with --skip-uncovered (mls calib run)."
        )


def drop_uncovered(
    points: ScanPoints, trajectory: Trajectory, time_offset_s: float = 0.0
) -> tuple[ScanPoints, np.ndarray, list[str]]:
    """The points the trajectory covers, their indices in ``points`` and one warning per pass
    that lost points (``--skip-uncovered``)."""
    bad = trajectory.uncovered(points.t_gps_s + time_offset_s)
    keep = np.flatnonzero(~bad)
    warnings = []
    for p in np.unique(points.pass_id[bad]):
        m = points.pass_id == p
        n, total = int(np.sum(bad & m)), int(np.sum(m))
        warnings.append(
            f"pass {int(p)}: dropped {n:,} of {total:,} points outside the trajectory's coverage "
            f"({trajectory.t_gps_s[0]:.3f}…{trajectory.t_gps_s[-1]:.3f} s, gaps > "
            f"{trajectory.max_gap_s:g} s) (--skip-uncovered)"
        )
    return points.select(keep), keep, warnings


# -- the steps ------------------------------------------------------------------------------


def error_model(options: CalibrationOptions, site: Site) -> tuple[ErrorModel, str]:
    """The POS error model for ``sigma_realistic`` and where its correlation time came from."""
    if options.error_model != "gauss_markov":
        return ErrorModel(options.error_model), "not used"
    if options.correlation_time_s is not None:
        tau = np.atleast_1d(np.asarray(options.correlation_time_s, float))
        source = "command line"
    elif site.pos_correlation_time_s is not None:
        tau = np.asarray(site.pos_correlation_time_s, float)
        source = "site.yaml pos_sigmas.correlation_time_s"
    else:
        tau = np.array([DEFAULT_POS_CORRELATION_S])
        source = "default (not configured)"
    value = float(tau[0]) if np.all(tau == tau[0]) else tuple(float(x) for x in tau)
    return ErrorModel("gauss_markov", value), source


def calibrate(
    site: Site,
    trajectory: Trajectory,
    points: ScanPoints,
    options: CalibrationOptions = CalibrationOptions(),
    *,
    poses: Poses | None = None,
    labels: np.ndarray | None = None,
    progress: Progress | None = None,
    source: str = "in memory",
    software_version: str | None = None,
    point_rows: np.ndarray | None = None,
    warnings: Sequence[str] = (),
    notes: Sequence[str] = (),
) -> CalibrationRun:
    """Calibrate the boresight from raw scanner ``points`` and the ``trajectory``.

    ``poses``: per-point POS observations that replace the trajectory's interpolation (a
    simulator's per-point POS errors); ``labels``: per point the index of the target it hit
    (−1 none) instead of the extraction; ``point_rows``: per point its row in the source file
    (outlier ids name those rows; default: the point's index); ``warnings`` and ``notes``: about
    the input, reported first. Raises :class:`CalibrationError`,
    :class:`calib.extraction.extract.ExtractionError` or :class:`calib.boresight.observations.AdjustmentError` (its
    :class:`~calib.boresight.observability.ObservabilityError` names the weak angles and the passes that would
    observe them) with a message that says what to do.
    """
    timings: dict[str, float] = {}
    clock = time.perf_counter()
    input_warnings, notes = list(warnings), list(notes)
    if not site.targets:
        raise CalibrationError(
            "site.yaml configures no targets: list the planar targets "
            "(name, centre, size, inclination, facing) under 'targets'"
        )
    mount = site.mount
    if options.apriori_rad is not None:
        mount = mount.with_boresight(np.asarray(options.apriori_rad, float))
    if len(points) == 0:
        raise CalibrationError("the bundle holds no points")
    if poses is not None and poses.p_lgf_m.shape != (len(points), 3):
        raise CalibrationError(f"per-point poses for {poses.p_lgf_m.shape[0]} points, expected {len(points)}")
    check_points(points, trajectory, mount.time_offset_s)
    frame = trajectory.frame
    rects = site.target_rectangles(frame)
    names = [r.name for r in rects]

    p, origin = georeference_passes(points, trajectory, mount, poses, progress)
    timings["georeference_s"] = time.perf_counter() - clock

    clock = time.perf_counter()
    if labels is None:
        ext = extract(
            p,
            points.intensity,
            points.pass_id,
            rects,
            options.extraction,
            origin,
            progress=None
            if progress is None
            else (lambda done, total: progress("extracting targets", done, total)),
        )
    else:
        lab = np.asarray(labels)
        if lab.shape != (len(points),):
            raise CalibrationError(f"labels for {lab.shape} points, expected ({len(points)},)")
        ext = from_labels(lab, points.pass_id, names)
    if options.subsample_m is not None:
        ext = subsample(ext, p, options.subsample_m)
    timings["extract_s"] = time.perf_counter() - clock
    run_warnings = input_warnings + list(ext.warnings)

    clock = time.perf_counter()
    idx, tgt = ext.indices()
    if idx.size == 0:
        raise CalibrationError(
            f"no target found in any pass ({', '.join(names)}): check the targets' centres "
            f"and sizes in site.yaml (search radius {options.extraction.search_radius_m:g} m "
            f"beyond each target), or try the automatic extraction"
        )
    pid = points.pass_id[idx]
    if poses is None:
        heading = trajectory.interpolate(points.t_gps_s[idx] + mount.time_offset_s).rpy_rad[:, 2]
    else:
        heading = poses.rpy_rad[idx, 2]
    headings = pass_headings(heading, pid, site.wall_azimuth_rad)
    obs = build_observations(
        trajectory,
        points.t_gps_s[idx],
        points.range_m[idx],
        points.scan_angle_rad[idx],
        tgt,
        pid,
        names,
        site.sigma_range_m,
        site.sigma_scan_angle_rad,
        site.sigma_position_m,
        site.sigma_attitude_rad,
        point_ids=idx if point_rows is None else np.asarray(point_rows)[idx],
        time_offset_s=mount.time_offset_s,
        pass_headings_rad=headings,
        sigma_range_per_m=site.sigma_range_per_m,
        beam_divergence_rad=site.beam_divergence_rad,
    )
    if poses is not None:
        obs.l[:, 0:3] = poses.p_lgf_m[idx]
        obs.l[:, 3:6] = poses.rpy_rad[idx]
        if poses.sigma_p_m is not None and poses.sigma_rpy_rad is not None:
            obs.sigma_l[:, 0:3] = poses.sigma_p_m[idx]
            obs.sigma_l[:, 3:6] = poses.sigma_rpy_rad[idx]
    if trajectory.has_sigmas:
        notes.append("POS σ per point from the trajectory's per-epoch sigmas")
    else:
        notes.append("POS σ from site.yaml pos_sigmas (the trajectory carries none)")
    validate_input(obs)  # a target with too few points, a single target: clear errors
    planes_or_none = initial_planes(ext, p, rects)
    unplaced = [name for name, plane in zip(names, planes_or_none) if plane is None]
    if unplaced:  # enough points over all passes, but fewer than 3 in every pass
        raise CalibrationError(
            f"target(s) {', '.join(unplaced)}: no pass holds 3 of its points, so it has no "
            f"a-priori plane; re-extract them (a smaller subsampling voxel) or remove them from the site"
        )
    planes = [plane for plane in planes_or_none if plane is not None]
    model, tau_source = error_model(options, site)
    gls = options.estimator == "gls"
    tau_doc: dict = {}
    if tau_source.startswith("default") and gls:
        if progress is not None:
            progress("estimating the POS correlation time", 0, None)
        est = estimate_tau(obs, mount, planes, options.adjust_options(model))
        model, tau_source = ErrorModel("gauss_markov", est.tau_s), "estimated from the data"
        tau_doc["estimate"] = {
            "tau_s": est.tau_s,
            "grid_s": list(est.grid_s),
            "neg2_log_lik": list(est.neg2_log_lik),
        }
        notes.append(
            f"no POS correlation time configured (site.yaml pos_sigmas.correlation_time_s): "
            f"estimated {est.tau_s:.1f} s from the data (restricted likelihood"
            f"{', at the edge of the searched range' if est.at_edge else ''}); the report shows "
            f"the boresight at τ/3, τ and 3τ"
        )
    elif tau_source.startswith("default"):
        notes.append(
            f"no POS correlation time configured (site.yaml pos_sigmas."
            f"correlation_time_s): sigma_realistic assumes {DEFAULT_POS_CORRELATION_S:g} "
            f"s"
        )
    timings["observations_s"] = time.perf_counter() - clock

    clock = time.perf_counter()
    if progress is not None:
        progress("adjusting", 0, 1)
    adjust_opts = options.adjust_options(model)
    ties_next = gls and options.tie_patches == "auto"
    res = adjust(obs, mount, planes, replace(adjust_opts, jackknife=adjust_opts.jackknife and not ties_next))
    comparison = None
    if gls:
        comparison = adjust(obs, mount, planes, replace(adjust_opts, estimator="thesis", jackknife=False))
        if options.tie_patches == "auto":
            if progress is not None:
                progress("choosing tie patches", 0, None)
            ties = tie_patches_from_points(obs, planes, res, site, mount, trajectory, points, poses, idx)
            if ties is not None and point_rows is not None:  # outlier ids name rows of the file
                n_t = len(obs)
                ties.observations.point_ids[n_t:] = np.asarray(point_rows)[ties.observations.point_ids[n_t:]]
            if ties is None:
                notes.append("tie patches: no planar patch of the scene seen from two headings; targets only")
            else:
                targets_only = res
                with_ties = adjust(
                    ties.observations, mount.with_boresight(res.boresight_rad), ties.planes, adjust_opts
                )
                check = patches_agree(targets_only, with_ties)
                tau_doc["patch_check"] = check
                if check["agree"]:
                    obs, planes, res = ties.observations, ties.planes, with_ties
                    tau_doc["targets_only"] = targets_only
                    tau_doc["ties"] = ties
                else:
                    run_warnings.append(
                        f"tie patches disagree with the targets (χ² = {check['chi2']:.1f} on 3 degrees of "
                        f"freedom, p = {check['p_value']:.2g}): the scene around the targets is not what "
                        f"the model assumes; the result uses the targets alone"
                    )
        if tau_source == "estimated from the data":
            tau_doc["sensitivity"] = tau_sensitivity(
                obs, mount.with_boresight(res.boresight_rad), planes, adjust_opts, float(model.tau_s(0))
            )
    if progress is not None:
        progress("adjusting", 1, 1)
    timings["adjust_s"] = time.perf_counter() - clock
    if not res.converged:
        run_warnings.append(
            f"the adjustment did not converge in {res.iterations} iterations: do "
            f"not use the result; check the a-priori boresight and the "
            f"extraction"
        )

    formal = res.sigma_formal_rad
    ratio = res.sigma_realistic_rad / formal
    extra = {
        "source": source,
        "extraction": {
            "mode": options.extraction.mode if labels is None else "labels",
            "subsample_m": options.subsample_m,
            "points_per_pass": {str(k): v for k, v in ext.counts().items()},
            "points_per_target": ext.totals(),
        },
        "realistic_correlation_time_source": tau_source,
        "sigma_realistic_over_formal": {a: float(r) for a, r in zip(("roll", "pitch", "yaw"), ratio)},
        "outlier_point_ids_refer_to": "0-based data rows of points.csv (after the header)",
        "warnings": run_warnings,
        "notes": notes,
    }
    extra.update(estimator_doc(options.estimator, options.tie_patches, tau_doc, comparison))
    doc = result_to_dict(res, mount.boresight_rad, software_version or _software_version(), extra)
    timings["total_s"] = sum(timings.values())
    return CalibrationRun(
        source,
        site,
        frame,
        mount,
        options,
        ext,
        obs,
        planes,
        res,
        doc,
        run_warnings,
        notes,
        timings,
        comparison,
        tau_doc,
    )


def calibrate_bundle(
    bundle_path: str | Path,
    options: CalibrationOptions = CalibrationOptions(),
    progress: Progress | None = None,
    max_gap_s: float = 1.0,
    skip_uncovered: bool = False,
) -> CalibrationRun:
    """Read a bundle directory (docs/architecture.md §4) and calibrate it; ``truth.json`` is never
    read. The passes of points.csv are compared with site.yaml's plan (warnings);
    ``skip_uncovered`` drops the points outside the trajectory's coverage (a warning per pass)
    instead of refusing them."""
    if progress is not None:
        progress("reading the bundle", 0, None)
    bundle = read_bundle(bundle_path, max_gap_s=max_gap_s)
    if not bundle.site.targets:  # (calibrate() says so too, without the file)
        raise CalibrationError(
            f"{bundle.path / 'site.yaml'}: targets: the site configures no targets: list the planar "
            f"targets (name, centre, size, inclination, facing) under 'targets'"
        )
    warnings = bundle.pass_warnings()
    scale = intensity_scale(bundle.points.intensity)
    notes = [f"{bundle.points_path.name} intensities: {scale.meaning} (one scale for the file)"]
    points, rows = bundle.points, None
    if skip_uncovered:
        offset_s = bundle.site.mount.time_offset_s
        points, rows, dropped = drop_uncovered(points, bundle.trajectory, offset_s)
        warnings += dropped
    return calibrate(
        bundle.site,
        bundle.trajectory,
        points,
        options,
        progress=progress,
        source=str(Path(bundle_path)),
        point_rows=rows,
        warnings=warnings,
        notes=notes,
    )


def write_outputs(run: CalibrationRun, out_dir: str | Path, plots: bool = True) -> list[Path]:
    """Write ``result.json``, ``report.md`` and (with ``plots``) the PNG plots; returns the
    paths written."""
    from calib.boresight.report import write_report
    from calib.io.outputs import make_output_dir

    out = make_output_dir(out_dir)
    return [write_result(out / "result.json", run.doc), *write_report(run, out, plots=plots)]


def run_bundle(
    bundle_path: str | Path,
    out_dir: str | Path | None = None,
    options: CalibrationOptions = CalibrationOptions(),
    progress: Progress | None = None,
    plots: bool = True,
    skip_uncovered: bool = False,
) -> tuple[CalibrationRun, list[Path]]:
    """What ``mls calib run`` does: calibrate a bundle and write its outputs into ``out_dir``
    (default ``BUNDLE/calib``; the command refuses one that holds files unless ``--force``)."""
    run = calibrate_bundle(bundle_path, options, progress, skip_uncovered=skip_uncovered)
    out = Path(bundle_path) / "calib" if out_dir is None else Path(out_dir)
    if progress is not None:
        progress("writing the report", 0, None)
    return run, write_outputs(run, out, plots=plots)
