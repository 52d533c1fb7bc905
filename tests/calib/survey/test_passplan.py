"""The six-fold pass-plan generator: headings relative to the wall, closest approach
at the standoff on the water side, length, order, safe distance from the wall for the oblique
passes, and a capture window around the targets."""

from __future__ import annotations

import numpy as np
import pytest

from calib.core import frames
from calib.core.geometry import Rectangle
from calib.core.georef import Mount
from calib.io.site import PassSpec, Site, Target, six_fold_passes
from calib.survey.passplan import PassPlanError, plan_passes, plan_site, water_azimuth

WALL_AZ = np.radians(215.0)
WATER_AZ = WALL_AZ - np.pi / 2  # to the left of the wall direction


def _targets(wall_az=WALL_AZ, facing=None):
    facing = wall_az - np.pi / 2 if facing is None else facing
    a = np.array([np.cos(wall_az), np.sin(wall_az), 0.0])
    w = np.array([np.cos(facing), np.sin(facing), 0.0])
    return [
        Rectangle.from_orientation("T1", -1.75 * a + 0.03 * w + [0, 0, -5.0], 1.23, 1.22, np.pi / 2, facing),
        Rectangle.from_orientation("T2", 1.75 * a + 0.3 * w + [0, 0, -5.0], 1.23, 0.76, np.pi / 4, facing),
    ]


def _line_distance(p, a, b):
    """Horizontal distance of point p from the infinite line through a and b."""
    h = (b - a)[:2] / np.linalg.norm((b - a)[:2])
    q = (p - a)[:2]
    return abs(q[0] * h[1] - q[1] * h[0])


def test_six_fold_headings_order_and_standoff():
    targets = _targets()
    plan = plan_passes(
        targets,
        WALL_AZ,
        15.0,
        six_fold_passes(60.0, 2.0),
        track_down_m=1.65,
        safe_wall_distance_m=5.0,
        capture_margin_m=2.0,
    )
    rel = [np.degrees(p.relative_heading_rad) for p in plan.passes]
    assert rel == [0.0, 180.0, 45.0, 225.0, 315.0, 135.0]
    assert [p.order for p in plan.passes] == [1, 2, 3, 4, 5, 6]
    assert [p.id for p in plan.passes] == [1, 2, 3, 4, 5, 6]
    aim = np.mean([t.center_m for t in targets], axis=0)
    for p in plan.passes:
        assert np.degrees(p.heading_rad) == pytest.approx(
            (215.0 + np.degrees(p.relative_heading_rad)) % 360.0, abs=1e-9
        )
        # the line heads along the heading and lies at the track height
        d = p.end_lgf_m - p.start_lgf_m
        assert np.degrees(np.arctan2(d[1], d[0])) % 360 == pytest.approx(np.degrees(p.heading_rad), abs=1e-9)
        assert p.start_lgf_m[2] == p.end_lgf_m[2] == 1.65
        assert p.length_m == pytest.approx(60.0, abs=1e-9)
        assert p.duration_s == pytest.approx(30.0)
        # closest approach at the standoff, inside the segment, on the water side
        assert _line_distance(aim, p.start_lgf_m, p.end_lgf_m) == pytest.approx(15.0, abs=1e-9)
        s_cpa = (p.closest_approach_lgf_m - p.start_lgf_m) @ p.direction
        assert 0.0 < s_cpa < p.length_m
        w = np.array([np.cos(WATER_AZ), np.sin(WATER_AZ), 0.0])
        assert (p.closest_approach_lgf_m - aim) @ w > 10.0


def test_a_line_with_its_own_standoff_keeps_it_and_the_others_the_plans():
    """Lines at several offsets from the scene's features (what makes yaw observable): a pass's
    own standoff_m moves its closest approach; the plan's standoff holds for the rest."""
    passes = (
        PassSpec(1, 0.0, 80.0),
        PassSpec(2, np.pi, 80.0, standoff_m=27.5),
        PassSpec(3, 0.0, 80.0, standoff_m=9.0),
    )
    plan = plan_passes(_targets(), WALL_AZ, 15.0, passes, safe_wall_distance_m=5.0, capture_margin_m=2.0)
    aim = np.mean([t.center_m for t in _targets()], axis=0)
    got = [_line_distance(aim, p.start_lgf_m, p.end_lgf_m) for p in plan.passes]
    np.testing.assert_allclose(got, [15.0, 27.5, 9.0], atol=1e-9)
    assert [p.standoff_m for p in plan.passes] == pytest.approx([15.0, 27.5, 9.0])
    with pytest.raises(PassPlanError, match="pass 4: its closest approach is only"):
        plan_passes(_targets(), WALL_AZ, 15.0, (PassSpec(4, 0.0, standoff_m=3.0),), safe_wall_distance_m=5.0)


def test_oblique_passes_keep_the_safe_distance_and_parallel_passes_are_centred():
    plan = plan_passes(
        _targets(), WALL_AZ, 15.0, six_fold_passes(60.0, 2.0), safe_wall_distance_m=5.0, capture_margin_m=2.0
    )
    for p in plan.passes:
        ends = plan.wall_distance(np.array([p.start_lgf_m, p.end_lgf_m]))
        assert ends.min() == pytest.approx(p.end_wall_distance_m, abs=1e-9)
        if np.degrees(p.relative_heading_rad) in (0.0, 180.0):
            # parallel: the CPA is the middle, both ends at the standoff from the wall line
            mid = 0.5 * (p.start_lgf_m + p.end_lgf_m)
            np.testing.assert_allclose(mid, p.closest_approach_lgf_m, atol=1e-9)
            assert ends.min() > 14.0
        else:
            # oblique: the segment was slid back so that its wall end is exactly the safe distance
            assert ends.min() == pytest.approx(5.0, abs=1e-9)
    # the wall line is the back of the targets (T1's face 3 cm and T2's top edge 3 cm out)
    corners = np.concatenate([t.corners() for t in _targets()])
    assert plan.wall_distance(corners).min() == pytest.approx(0.0, abs=1e-12)


def test_capture_window_covers_the_targets_and_sides_alternate():
    targets = _targets()
    plan = plan_passes(targets, WALL_AZ, 15.0, six_fold_passes(60.0, 2.0), capture_margin_m=2.0)
    corners = np.concatenate([t.corners() for t in targets])
    for p in plan.passes:
        s = (corners - p.start_lgf_m) @ p.direction
        assert p.capture_start_m == pytest.approx(s.min() - 2.0, abs=1e-9)
        assert p.capture_end_m == pytest.approx(s.max() + 2.0, abs=1e-9)
        assert 0.0 <= p.capture_start_m < p.capture_end_m <= p.length_m
        t0, t1 = p.capture_window_s
        assert (t0, t1) == pytest.approx((p.capture_start_m / 2.0, p.capture_end_m / 2.0))
        # which side the targets are on, from the cross product of heading and line of sight
        los = np.mean(corners, axis=0) - p.closest_approach_lgf_m
        cross_down = p.direction[0] * los[1] - p.direction[1] * los[0]
        assert p.targets_side == ("starboard" if cross_down > 0 else "port")
    assert [p.targets_side for p in plan.passes] == ["starboard", "port"] * 3


def test_plan_follows_the_side_the_targets_face_and_wraps_azimuths():
    # targets facing east of a wall running north: the water is on the right this time
    east = _targets(0.0, facing=np.pi / 2)
    assert np.degrees(water_azimuth(east, 0.0)) == pytest.approx(90.0)
    plan = plan_passes(east, 0.0, 15.0, six_fold_passes())
    for p in plan.passes:
        assert p.closest_approach_lgf_m[1] - east[0].center_m[1] > 10.0
    # horizontal targets only: the site convention, water to the left of the wall direction
    flat = [Rectangle.from_orientation("H", [0, 0, 0], 1, 1, 0.0, 0.0)]
    assert np.degrees(water_azimuth(flat, 0.0)) == pytest.approx(270.0)
    a = plan_passes(_targets(np.radians(350.0)), np.radians(350.0), 15.0, six_fold_passes())
    b = plan_passes(_targets(np.radians(-10.0)), np.radians(-10.0), 15.0, six_fold_passes())
    assert np.degrees(a.passes[1].heading_rad) == pytest.approx(170.0)
    for pa, pb in zip(a.passes, b.passes):
        np.testing.assert_allclose(pa.start_lgf_m, pb.start_lgf_m, atol=1e-9)
        assert pa.heading_rad == pytest.approx(pb.heading_rad)


def test_also_capture_widens_the_window_within_the_line():
    targets = _targets()
    a = np.array([np.cos(WALL_AZ), np.sin(WALL_AZ), 0.0])
    tower = Rectangle.from_orientation("V", 25.0 * a + [0, 0, -20.0], 2.0, 40.0, np.pi / 2, WATER_AZ)
    base = plan_passes(targets, WALL_AZ, 15.0, six_fold_passes(100.0, 2.0))
    wide = plan_passes(targets, WALL_AZ, 15.0, six_fold_passes(100.0, 2.0), also_capture=[tower])
    p0, w0 = base.passes[0], wide.passes[0]
    assert w0.capture_start_m == p0.capture_start_m
    s = (tower.corners() - w0.start_lgf_m) @ w0.direction
    assert w0.capture_end_m == pytest.approx(min(s.max() + 3.0, w0.length_m))
    for p in wide.passes:
        assert 0.0 <= p.capture_start_m < p.capture_end_m <= p.length_m + 1e-9


def test_impossible_plans_are_refused_with_the_reason():
    targets = _targets()
    with pytest.raises(PassPlanError, match="pass 7: relative heading 90° points straight"):
        plan_passes(targets, WALL_AZ, 15.0, [PassSpec(7, np.pi / 2)])
    with pytest.raises(PassPlanError, match=r"pass 3 .*capture window .* does not fit"):
        plan_passes(targets, WALL_AZ, 15.0, six_fold_passes(60.0), safe_wall_distance_m=10.0)
    with pytest.raises(PassPlanError, match="only .* m from the wall"):
        plan_passes(targets, WALL_AZ, 4.0, six_fold_passes(60.0), safe_wall_distance_m=5.0)
    with pytest.raises(PassPlanError, match="at least one target"):
        plan_passes([], WALL_AZ, 15.0, six_fold_passes())


def test_plan_site_uses_the_site_config():
    frame = frames.LocalFrame(45.5, -73.55, 0.0)
    rects = _targets()
    targets = []
    for r in rects:
        lat, lon, h = frame.to_geodetic(r.center_m[None])
        targets.append(
            Target(
                r.name,
                float(lat[0]),
                float(lon[0]),
                float(h[0]),
                r.width_m,
                r.height_m,
                r.inclination_rad,
                float(WATER_AZ),
            )
        )
    site = Site(
        mount=Mount(),
        targets=tuple(targets),
        reference=frame,
        wall_azimuth_rad=float(WALL_AZ),
        standoff_m=12.0,
        passes=six_fold_passes(70.0, 1.5),
    )
    plan = plan_site(site, capture_margin_m=2.0)
    ref = plan_passes(rects, WALL_AZ, 12.0, six_fold_passes(70.0, 1.5), capture_margin_m=2.0)
    for p, q in zip(plan.passes, ref.passes):
        np.testing.assert_allclose(p.start_lgf_m, q.start_lgf_m, atol=1e-6)
        np.testing.assert_allclose(p.end_lgf_m, q.end_lgf_m, atol=1e-6)
        assert p.speed_mps == 1.5
