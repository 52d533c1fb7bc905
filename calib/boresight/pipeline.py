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
from calib.boresight.checks.inputs import (
    CalibrationError,
    check_input,
    check_points,
    check_within_reach,
    drop_uncovered,
)
from calib.boresight.checks.verdict import Verdict, evidence, judge
from calib.boresight.errormodel import ErrorModel
from calib.boresight.observations import (
    MIN_POINTS_PER_PLANE,
    AdjustOptions,
    Observations,
    build_observations,
    validate_input,
)
from calib.boresight.result import GlsDiagnostics, calibration_doc, write_result
from calib.boresight.scene_ties import TieSearch, crlb_by_features, with_tie_patches
from calib.boresight.tau import (
    TauChoice,
    choose_tau,
    error_model,  # noqa: F401  (where calib.watch and the tests take it)
    tau_sensitivity,
)
from calib.core import frames
from calib.core.georef import Mount
from calib.core.trajectory import Poses, Trajectory
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


@dataclass(kw_only=True)
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
    #: GLS: τ from the data, the boresight at τ/3, τ and 3τ, the tie patches and their check
    diagnostics: GlsDiagnostics = field(default_factory=GlsDiagnostics)
    #: trusted, questionable or refused, with the reasons (:mod:`calib.boresight.checks.verdict`)
    verdict: Verdict = field(default_factory=lambda: Verdict("trusted", [], []))


# -- the steps ------------------------------------------------------------------------------


def _extract_targets(
    p, origin, points: ScanPoints, rects, options: CalibrationOptions, labels, progress
) -> Extraction:
    """The targets' points of every pass: the extraction, or the given labels."""
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
        ext = from_labels(lab, points.pass_id, [r.name for r in rects])
    if options.subsample_m is not None:
        ext = subsample(ext, p, options.subsample_m)
    return ext


def _target_observations(
    site: Site, trajectory: Trajectory, points: ScanPoints, mount: Mount, ext: Extraction, poses, point_rows
) -> Observations:
    """The adjustment's observations of the extracted targets' points."""
    idx, tgt = ext.indices()
    if idx.size == 0:
        raise CalibrationError(
            f"no target found in any pass ({', '.join(ext.target_names)}): check the targets' centres "
            f"and sizes in site.yaml (search radius beyond each target: see the warnings), or try the "
            f"automatic extraction"
        )
    pid = points.pass_id[idx]
    if poses is None:
        heading = trajectory.interpolate(points.t_gps_s[idx] + mount.time_offset_s).rpy_rad[:, 2]
    else:
        heading = poses.rpy_rad[idx, 2]
    obs = build_observations(
        trajectory,
        points.t_gps_s[idx],
        points.range_m[idx],
        points.scan_angle_rad[idx],
        tgt,
        pid,
        ext.target_names,
        site.sigma_range_m,
        site.sigma_scan_angle_rad,
        site.sigma_position_m,
        site.sigma_attitude_rad,
        point_ids=idx if point_rows is None else np.asarray(point_rows)[idx],
        time_offset_s=mount.time_offset_s,
        pass_headings_rad=pass_headings(heading, pid, site.wall_azimuth_rad),
        sigma_range_per_m=site.sigma_range_per_m,
        beam_divergence_rad=site.beam_divergence_rad,
    )
    if poses is not None:
        obs.l[:, 0:3] = poses.p_lgf_m[idx]
        obs.l[:, 3:6] = poses.rpy_rad[idx]
        if poses.sigma_p_m is not None and poses.sigma_rpy_rad is not None:
            obs.sigma_l[:, 0:3] = poses.sigma_p_m[idx]
            obs.sigma_l[:, 3:6] = poses.sigma_rpy_rad[idx]
    validate_input(obs)  # a target with too few points, a single target: clear errors
    return obs


def _without_unseen_targets(ext: Extraction, rects, warnings: list[str]):
    """The extraction and rectangles without the targets seen too little to be adjusted (fewer
    than the adjustment's minimum points, or never 3 in one pass), as long as two targets remain
    (else the adjustment's own error names them); each dropped target is a warning, and the
    verdict counts it lost in every pass."""
    counts, totals = ext.counts(), ext.totals()
    unseen = [
        name
        for name in ext.target_names
        if totals[name] < MIN_POINTS_PER_PLANE or max(c[name] for c in counts.values()) < 3
    ]
    if not unseen or len(ext.target_names) - len(unseen) < 2:
        return ext, rects
    for name in unseen:
        warnings.append(
            f"target {name} is left out of the adjustment: {totals[name]} points over all passes "
            f"(the extraction did not find it; see its passes above)"
        )
    return ext.without(unseen), [r for r in rects if r.name not in unseen]


def _planes(ext: Extraction, p, rects) -> list[tuple[np.ndarray, float]]:
    planes_or_none = initial_planes(ext, p, rects)
    unplaced = [name for name, plane in zip(ext.target_names, planes_or_none, strict=False) if plane is None]
    if unplaced:  # enough points over all passes, but fewer than 3 in every pass
        raise CalibrationError(
            f"target(s) {', '.join(unplaced)}: no pass holds 3 of its points, so it has no "
            f"a-priori plane; re-extract them (a smaller subsampling voxel) or remove them from the site"
        )
    return [plane for plane in planes_or_none if plane is not None]


@dataclass(kw_only=True)
class _Adjusted:
    obs: Observations
    planes: list[tuple[np.ndarray, float]]
    result: AdjustmentResult
    comparison: AdjustmentResult | None


def _adjust_with_ties(
    options: CalibrationOptions,
    search: TieSearch,
    obs: Observations,
    planes: list[tuple[np.ndarray, float]],
    tau: TauChoice,
    gls: GlsDiagnostics,
    warnings: list[str],
    notes: list[str],
    progress: Progress | None,
) -> _Adjusted:
    """The default estimator, the thesis comparison and (GLS, ``tie_patches='auto'``) the
    scene's tie patches (:func:`calib.boresight.scene_ties.with_tie_patches`); with τ
    estimated, the boresight at τ/3, τ and 3τ (into ``gls``)."""
    if progress is not None:
        progress("adjusting", 0, 1)
    mount = search.mount
    adjust_opts = options.adjust_options(tau.model)
    is_gls = options.estimator == "gls"
    ties_next = is_gls and options.tie_patches == "auto"
    res = adjust(obs, mount, planes, replace(adjust_opts, jackknife=adjust_opts.jackknife and not ties_next))
    if not is_gls:
        return _Adjusted(obs=obs, planes=planes, result=res, comparison=None)
    comparison = adjust(obs, mount, planes, replace(adjust_opts, estimator="thesis", jackknife=False))
    if ties_next:
        if progress is not None:
            progress("choosing tie patches", 0, None)
        tied = with_tie_patches(search, obs, planes, res, adjust_opts, warnings, notes)
        obs, planes, res = tied.obs, tied.planes, tied.result
        gls.patch_check, gls.targets_only, gls.ties = tied.check, tied.targets_only, tied.ties
        if tied.ties is not None:
            gls.crlb_by_features_deg = crlb_by_features(obs, res.state, mount, adjust_opts)
    if tau.estimated:
        gls.sensitivity = tau_sensitivity(
            obs, mount.with_boresight(res.boresight_rad), planes, adjust_opts, float(tau.model.tau_s(0))
        )
    return _Adjusted(obs=obs, planes=planes, result=res, comparison=comparison)


def _scaled_by_variance_factor(res: AdjustmentResult) -> AdjustmentResult:
    """The realistic covariance scaled by σ̂0² when that exceeds 1: a misfit the model does
    not explain widens σ instead of being ignored."""
    f = max(1.0, float(res.sigma0_squared))
    return replace(res, cov_realistic=res.cov_realistic * f)


class _Laps:
    """How long each stage of a calibration took (s), each from the end of the one before."""

    def __init__(self) -> None:
        self.timings_s: dict[str, float] = {}
        self._since = time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.timings_s[name] = now - self._since
        self._since = now

    def with_total(self) -> dict[str, float]:
        return {**self.timings_s, "total_s": sum(self.timings_s.values())}


@dataclass(frozen=True, kw_only=True)
class _Georeferenced:
    """The checked input's points georeferenced with the a-priori mount."""

    mount: Mount  # the a-priori mount (site.yaml's, or the options' boresight)
    rects: list  # the site's targets (calib.core.geometry.Rectangle) in the trajectory's frame
    p_lgf_m: np.ndarray  # (n, 3) every point, local frame
    origin: np.ndarray


def _checked_and_georeferenced(
    site: Site, trajectory: Trajectory, points: ScanPoints, options: CalibrationOptions, poses, progress
) -> _Georeferenced:
    """Check the input (points, their times, the targets within reach of the trajectory) and
    georeference every pass with the a-priori mount."""
    check_input(site, points, poses)
    mount = (
        site.mount
        if options.apriori_rad is None
        else site.mount.with_boresight(np.asarray(options.apriori_rad, float))
    )
    check_points(points, trajectory, mount.time_offset_s)
    rects = site.target_rectangles(trajectory.frame)
    check_within_reach(trajectory, rects)
    p, origin = georeference_passes(points, trajectory, mount, poses, progress)
    return _Georeferenced(mount=mount, rects=rects, p_lgf_m=p, origin=origin)


def _finished(
    adj: _Adjusted, options: CalibrationOptions, warnings: list[str], progress: Progress | None
) -> _Adjusted:
    """The adjustment's result as reported: the GLS σ widened by σ̂0² > 1, a warning when it
    did not converge."""
    if progress is not None:
        progress("adjusting", 1, 1)
    if options.estimator == "gls":
        adj = replace(adj, result=_scaled_by_variance_factor(adj.result))
    if not adj.result.converged:
        warnings.append(
            f"the adjustment did not converge in {adj.result.iterations} iterations: do "
            f"not use the result; check the a-priori boresight and the "
            f"extraction"
        )
    return adj


def _pos_sigma_note(trajectory: Trajectory) -> str:
    """Where the POS σ of each point came from (a note of the report)."""
    if trajectory.has_sigmas:
        return "POS σ per point from the trajectory's per-epoch sigmas"
    return "POS σ from site.yaml pos_sigmas (the trajectory carries none)"


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
    observe them) with a message that says what to do. The run's verdict
    (:mod:`calib.boresight.checks.verdict`) is in ``doc["verdict"]``.
    """
    laps = _Laps()
    notes = list(notes)
    geo = _checked_and_georeferenced(site, trajectory, points, options, poses, progress)
    laps.lap("georeference_s")
    ext = _extract_targets(geo.p_lgf_m, geo.origin, points, geo.rects, options, labels, progress)
    laps.lap("extract_s")
    run_warnings = list(warnings) + list(ext.warnings)
    used, used_rects = _without_unseen_targets(ext, geo.rects, run_warnings)
    obs = _target_observations(site, trajectory, points, geo.mount, used, poses, point_rows)
    notes.append(_pos_sigma_note(trajectory))
    planes = _planes(used, geo.p_lgf_m, used_rects)
    tau = choose_tau(options, site, obs, geo.mount, planes, notes, progress)
    gls = GlsDiagnostics(estimate=tau.estimate)
    laps.lap("observations_s")
    search = TieSearch(
        site=site,
        mount=geo.mount,
        trajectory=trajectory,
        points=points,
        poses=poses,
        target_rows=ext.indices()[0],
        point_rows=point_rows,
    )
    adj = _adjust_with_ties(options, search, obs, planes, tau, gls, run_warnings, notes, progress)
    adj = _finished(adj, options, run_warnings, progress)
    laps.lap("adjust_s")
    verdict = judge(evidence(adj.result, ext.lost_passes(), gls.patch_check, gls.sensitivity))
    doc = calibration_doc(
        adj.result,
        geo.mount,
        options,
        ext,
        labels,
        tau,
        gls,
        adj.comparison,
        verdict,
        source,
        software_version,
    )
    doc["warnings"], doc["notes"] = run_warnings, notes
    return CalibrationRun(
        source=source,
        site=site,
        frame=trajectory.frame,
        mount_apriori=geo.mount,
        options=options,
        extraction=ext,
        observations=adj.obs,
        planes_init=adj.planes,
        result=adj.result,
        doc=doc,
        warnings=run_warnings,
        notes=notes,
        timings_s=laps.with_total(),
        comparison=adj.comparison,
        diagnostics=gls,
        verdict=verdict,
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
