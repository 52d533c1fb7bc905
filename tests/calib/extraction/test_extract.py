"""Target extraction (calib.extraction.extract): RANSAC, reflectivity and size, automatic mode, voxel
subsampling, and the extraction of the simulator's Montreal targets against its truth."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from calib.core.geometry import Rectangle
from calib.core.georef import georeference
from calib.extraction.extract import (
    ExtractionError,
    ExtractOptions,
    extract,
    extract_target,
    initial_planes,
    voxel_subsample,
)
from calib.extraction.segmentation import incidence_corrected, intensity_split, ransac_plane
from calib.sim.simulate import simulate


def _angle_deg(a, b) -> float:
    return float(np.degrees(np.arccos(min(1.0, abs(float(np.dot(a, b)))))))


# -- RANSAC -------------------------------------------------------------------------------------


def test_ransac_recovers_a_plane_among_outliers():
    rng = np.random.default_rng(1)
    n_true = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    basis = np.linalg.svd(n_true[None])[2][1:]  # two in-plane directions
    noise = rng.normal(0, 0.002, (700, 1)) * n_true
    on = rng.uniform(-1, 1, (700, 2)) @ basis + 2.0 * n_true + noise
    off = rng.uniform(-1.5, 3.5, (300, 3))  # 30 % gross outliers in a box around the plane
    far = np.abs(off @ n_true - 2.0) > 0.05
    p = np.vstack([on, off[far]])
    plane = ransac_plane(p, distance_m=0.01, rng=np.random.default_rng(0))
    assert _angle_deg(plane.normal, n_true) < 0.2
    assert abs(plane.d * np.sign(plane.normal @ n_true) + 2.0) < 0.002
    assert plane.inliers[:700].mean() > 0.99  # the plane's points
    assert not plane.inliers[700:].any()  # no outlier farther than 5 cm


def test_ransac_stops_when_98_percent_are_inliers_and_obeys_the_tilt_limit():
    rng = np.random.default_rng(2)
    wall = np.column_stack([rng.uniform(-3, 3, 2000), np.zeros(2000), rng.uniform(-1, 1, 2000)])
    plane = ransac_plane(wall, rng=rng)
    assert plane.inlier_fraction == 1.0 and plane.iterations == 128  # one batch was enough
    # a 45° panel with fewer points next to the wall: the hint selects it, not the wall
    s = rng.uniform(-0.5, 0.5, (400, 2))
    hint = np.array([0.0, np.sqrt(0.5), np.sqrt(0.5)])
    panel = np.column_stack([s[:, 0] + 5, -s[:, 1] * np.sqrt(0.5), s[:, 1] * np.sqrt(0.5)]) + hint
    both = np.vstack([wall, panel])
    free = ransac_plane(both, rng=np.random.default_rng(0))
    tilted = ransac_plane(both, rng=np.random.default_rng(0), normal_hint=hint, max_tilt_rad=np.radians(30))
    assert _angle_deg(free.normal, [0, 1, 0]) < 0.1
    assert _angle_deg(tilted.normal, hint) < 0.1 and tilted.normal @ hint > 0
    assert tilted.inliers[2000:].all() and tilted.inliers.sum() == 400


def test_ransac_needs_three_points():
    assert ransac_plane(np.zeros((2, 3))) is None


# -- reflectivity -----------------------------------------------------------------------------


def test_intensity_split_finds_two_materials_and_refuses_one():
    rng = np.random.default_rng(3)
    concrete = 0.25 * rng.uniform(0.7, 1.0, 3000)
    white = 0.9 * rng.uniform(0.7, 1.0, 800)
    split = intensity_split(np.concatenate([concrete, white]))
    assert 0.25 < split.threshold < 0.63 and split.contrast > 3.0
    assert intensity_split(white).threshold is None  # one material: incidence spread only


def test_incidence_correction_restores_the_contrast_of_an_oblique_target():
    """A 45° white target seen from below is barely brighter than the wall it hangs on;
    divided by the cosine of incidence the two materials separate again."""
    rng = np.random.default_rng(4)
    origin = np.array([0.0, 0.0, 0.0])
    u = rng.uniform(-0.6, 0.6, (600, 2))
    wall = np.column_stack([u[:, 0] * 4, np.full(600, 15.0), -5.0 + u[:, 1] * 3])
    n_t = np.array([0.0, -np.sqrt(0.5), -np.sqrt(0.5)])  # facing the water and up (NED)
    t_axis = np.array([0.0, np.sqrt(0.5), -np.sqrt(0.5)])
    target = np.array([0.0, 14.7, -5.0]) + u[:300, :1] * [1, 0, 0] + u[:300, 1:] * 0.6 * t_axis
    p = np.vstack([wall, target])
    beam = p / np.linalg.norm(p, axis=1, keepdims=True)
    normals = np.vstack([np.tile([0.0, -1.0, 0.0], (600, 1)), np.tile(n_t, (300, 1))])
    refl = np.r_[np.full(600, 0.25), np.full(300, 0.9)]
    intensity = refl * np.abs(np.einsum("ij,ij->i", beam, normals))
    assert intensity_split(intensity).contrast < 2.0  # raw: ambiguous
    corrected = incidence_corrected(p, intensity, np.tile(origin, (900, 1)))
    split = intensity_split(corrected)
    assert split.contrast > 3.0
    # (a few wall points next to the target get a mixed local normal)
    assert np.mean(corrected[600:] >= split.threshold) > 0.98
    assert np.mean(corrected[:600] < split.threshold) > 0.98


# -- one target against its wall ----------------------------------------------------------------


def _grid(rect: Rectangle, step: float, rng) -> np.ndarray:
    a = np.arange(-rect.width_m / 2, rect.width_m / 2, step)
    b = np.arange(-rect.height_m / 2, rect.height_m / 2, step)
    A, B = (x.ravel() for x in np.meshgrid(a, b))
    p = rect.center_m + A[:, None] * rect.u_axis + B[:, None] * rect.v_axis
    return p + rng.normal(0, 0.002, (p.shape[0], 1)) * rect.normal


def test_target_is_separated_from_its_wall_by_reflectivity_and_size():
    """A white 1.23 × 1.22 m target 3 cm in front of a concrete wall, a smaller white panel on
    the same wall 1.6 m away, the configured centre 0.4 m off: exactly the target's points."""
    rng = np.random.default_rng(5)
    az = np.radians(270.0)
    target = Rectangle.from_orientation("T1", [0.0, 14.97, -5.0], 1.23, 1.22, np.pi / 2, az, 0.9)
    panel = Rectangle.from_orientation("P", [0.0, 14.97, -5.0], 0.5, 0.5, np.pi / 2, az, 0.9)
    panel = panel.translated([2.2, 0.0, 0.0])
    wall = Rectangle.from_orientation("W", [0.0, 15.0, -5.0], 8.0, 3.0, np.pi / 2, az, 0.25)
    pw = _grid(wall, 0.03, rng)
    pw = pw[~target.contains(pw, 0.0) & ~panel.contains(pw, 0.0)]  # occluded by the boards
    pt, pp = _grid(target, 0.03, rng), _grid(panel, 0.03, rng)
    p = np.vstack([pw, pt, pp])
    origin = np.zeros_like(p)
    cos = np.abs(p @ wall.normal) / np.linalg.norm(p, axis=1)
    intensity = np.r_[np.full(len(pw), 0.25), np.full(len(pt) + len(pp), 0.9)] * cos
    configured = target.translated([0.3, 0.0, 0.25])  # approximate centre
    idx = np.arange(len(p))
    got = extract_target(
        p, intensity, idx, configured, 1, ExtractOptions(), np.random.default_rng(0), origin_m=origin
    )
    is_target = (idx >= len(pw)) & (idx < len(pw) + len(pt))
    assert got.n_points > 0 and is_target[got.indices].all()  # no wall, no panel
    # the 2 cm edge margin trims the rim only
    assert got.n_points >= 0.9 * is_target.sum()
    np.testing.assert_allclose(got.extent_m, [1.23, 1.22], atol=0.05)
    assert got.contrast > 3.0 and got.note == ""
    # the same scene without contrast (a white wall): geometry only, and the report says so
    flat = extract_target(
        p,
        np.full(len(p), 0.9) * cos,
        idx,
        configured,
        1,
        ExtractOptions(),
        np.random.default_rng(0),
        origin_m=origin,
    )
    assert "no reflectivity contrast" in flat.note


# -- the simulator's Montreal targets -----------------------------------------------------------


@pytest.fixture(scope="module")
def montreal():
    """Montreal with its Gauss–Markov POS errors, georeferenced with the a-priori mount (the
    true boresight is the thesis's 0.2°/1.2°/0.15°)."""
    r = simulate("montreal", 0)
    pts, traj, mount = r.points, r.trajectory_observed, r.site.mount
    p = georeference(pts.t_gps_s, pts.range_m, pts.scan_angle_rad, traj, mount)
    o = georeference(pts.t_gps_s, np.zeros(len(pts)), pts.scan_angle_rad, traj, mount)
    return r, p, o, r.site.target_rectangles(r.site.frame())


def _check_against_truth(r, ext, min_recall=0.85):
    idx, tgt = ext.indices()
    assert np.array_equal(r.target_index[idx], tgt)  # every extracted point is on its target
    for j, name in enumerate(ext.target_names):
        for pid in ext.pass_ids:
            n_true = np.sum((r.target_index == j) & (r.points.pass_id == pid))
            assert ext.counts()[pid][name] >= min_recall * n_true, (name, pid)


def test_seeded_extraction_matches_the_simulator_truth(montreal):
    r, p, o, rects = montreal
    ext = extract(p, r.points.intensity, r.points.pass_id, rects, ExtractOptions(), o)
    assert ext.warnings == []
    _check_against_truth(r, ext)


def test_automatic_mode_finds_the_configured_targets_without_their_centres(montreal):
    r, p, o, rects = montreal
    lost = [rr.translated([8.0, -6.0, 3.0]) for rr in rects]  # centres 10.4 m wrong
    seeded = extract(p, r.points.intensity, r.points.pass_id, lost, ExtractOptions(), o)
    assert sum(seeded.totals().values()) == 0 and len(seeded.warnings) == 12
    auto = extract(p, r.points.intensity, r.points.pass_id, lost, ExtractOptions(mode="auto"), o)
    assert auto.warnings == []
    _check_against_truth(r, auto)


def test_a_target_missing_from_a_pass_is_a_warning_naming_both(montreal):
    r, p, o, rects = montreal
    keep = ~((r.target_index == 1) & (r.points.pass_id == 3))  # T2 unseen in pass 3
    ext = extract(p[keep], r.points.intensity[keep], r.points.pass_id[keep], rects, ExtractOptions(), o[keep])
    missing = [w for w in ext.warnings if "missing" in w]
    assert len(missing) == 1 and missing[0].startswith("target T2 is missing from pass 3")
    assert ext.counts()[3]["T2"] == 0 and ext.counts()[3]["T1"] > 300


def test_initial_planes_survive_a_two_degree_misalignment():
    """Misaligned by 2° the passes' copies of a target no longer overlap; the initial plane
    (mean of the per-pass normals, combined centroid) stays within a degree of the truth."""
    r = simulate("montreal", 1, overrides={"truth.boresight_deg": [2.0, -2.0, 2.0]})
    pts = r.points
    p = georeference(pts.t_gps_s, pts.range_m, pts.scan_angle_rad, r.trajectory_observed, r.site.mount)
    o = georeference(pts.t_gps_s, np.zeros(len(pts)), pts.scan_angle_rad, r.trajectory_observed, r.site.mount)
    rects = r.site.target_rectangles(r.site.frame())
    ext = extract(p, pts.intensity, pts.pass_id, rects, ExtractOptions(), o)
    assert ext.warnings == []
    for (n, d), true in zip(initial_planes(ext, p, rects), r.scene.rectangles[:2]):
        assert _angle_deg(n, true.normal) < 1.5 and n @ true.normal > 0
        assert abs(d - true.d) < 0.3


def test_options_are_checked():
    with pytest.raises(ExtractionError, match="mode 'manual'"):
        ExtractOptions(mode="manual")
    with pytest.raises(ExtractionError, match="search_radius_m"):
        ExtractOptions(search_radius_m=0.0)
    with pytest.raises(ExtractionError, match="no targets"):
        extract(np.zeros((5, 3)), np.ones(5), np.ones(5), [])


# -- subsampling --------------------------------------------------------------------------------


def test_voxel_subsampling_keeps_the_point_nearest_each_voxel_centre():
    rng = np.random.default_rng(6)
    p = rng.uniform(-0.3, 0.7, (5000, 3))
    voxel = 0.1
    keep = voxel_subsample(p, voxel)
    cells = np.floor(p / voxel).astype(int)
    occupied = {tuple(c) for c in cells}
    kept = [tuple(c) for c in cells[keep]]
    assert len(kept) == len(set(kept)) == len(occupied)  # one point per occupied voxel
    assert np.all(np.diff(keep) > 0)  # original order
    dist = np.linalg.norm(p - (cells + 0.5) * voxel, axis=1)
    for i in keep[:200]:  # the kept point is the nearest its voxel's centre
        same = np.all(cells == cells[i], axis=1)
        assert dist[i] == dist[same].min()
    with pytest.raises(ExtractionError, match="positive size"):
        voxel_subsample(p, 0.0)


def test_subsampling_an_extraction_thins_each_pass_separately(montreal):
    from calib.extraction.extract import subsample

    r, p, o, rects = montreal
    ext = extract(p, r.points.intensity, r.points.pass_id, rects, ExtractOptions(), o)
    thin = subsample(ext, p, 0.05)
    for a, b in zip(ext.found, thin.found):
        assert 0 < b.n_points < a.n_points and set(b.indices) <= set(a.indices)
        assert len(voxel_subsample(p[b.indices], 0.05)) == b.n_points
    assert thin.subsample_m == 0.05 and replace(thin, subsample_m=None).pass_ids == ext.pass_ids


def _wall_and_target(proud_m: float, rng, target_seen: bool = True):
    """A 1.23 × 1.22 m target ``proud_m`` in front of an 8 × 3 m wall of the same
    reflectivity (no contrast at all), seen from the origin; the wall behind it occluded."""
    az = np.radians(270.0)
    target = Rectangle.from_orientation("T1", [0.0, 15.0 - proud_m, -5.0], 1.23, 1.22, np.pi / 2, az, 0.9)
    wall = Rectangle.from_orientation("W", [0.0, 15.0, -5.0], 8.0, 3.0, np.pi / 2, az, 0.9)
    pw = _grid(wall, 0.03, rng)
    shadow = target.translated(target.normal * -proud_m)  # about what the target hides
    pw = pw[~shadow.contains(pw, 0.0)]
    pt = _grid(target, 0.03, rng) if target_seen else np.empty((0, 3))
    p = np.vstack([pw, pt])
    return target, p, len(pw)


def test_a_target_proud_of_a_wall_without_contrast_is_found_on_its_own_plane():
    """No reflectivity contrast: the largest plane of the target's orientation is the wall;
    the target is the next plane, 30 cm in front, with a cluster of its size."""
    rng = np.random.default_rng(7)
    target, p, n_wall = _wall_and_target(0.3, rng)
    idx = np.arange(len(p))
    got = extract_target(
        p,
        np.full(len(p), 0.9),
        idx,
        target.translated([0.2, 0.0, 0.1]),
        1,
        ExtractOptions(),
        rng,
        origin_m=np.zeros_like(p),
    )
    assert got.status == "found" and got.n_points >= 0.85 * (len(p) - n_wall)
    assert np.all(got.indices >= n_wall)  # no wall point
    assert "no reflectivity contrast" in got.note


def test_a_wall_cluster_is_rejected_with_its_size_never_trimmed_to_a_box():
    """The target not hit at all (the pass saw only the wall around it) and no contrast:
    every cluster of its orientation is the wall, larger than the target: rejected, named."""
    rng = np.random.default_rng(8)
    target, p, _ = _wall_and_target(0.3, rng, target_seen=False)
    got = extract_target(
        p,
        np.full(len(p), 0.9),
        np.arange(len(p)),
        target,
        4,
        ExtractOptions(),
        rng,
        origin_m=np.zeros_like(p),
    )
    assert got.status == "rejected" and got.n_points == 0
    assert "against the configured 1.23 × 1.22 m: more than the target alone" in got.note
    ext = extract(p, np.full(len(p), 0.9), np.full(len(p), 4), [target], ExtractOptions(), np.zeros_like(p))
    assert ext.warnings[0].startswith("target T1 is rejected in pass 4: ")
