"""Scene ray casting: exact ray–rectangle hits, nearest hit wins, no return from
water or sky, and scan-plane sectors that contain every hit of a profile."""

from __future__ import annotations

import numpy as np
import pytest

from calib.core import frames
from calib.core.geometry import Rectangle
from calib.sim.scene import Scene


def _random_scene(rng, n_rect=12) -> Scene:
    rects = [
        Rectangle.from_orientation(
            f"R{i}",
            rng.uniform(-20, 20, 3),
            rng.uniform(0.5, 6),
            rng.uniform(0.5, 6),
            rng.uniform(-np.pi / 2, np.pi / 2),
            rng.uniform(0, 2 * np.pi),
            rng.uniform(0.1, 1),
        )
        for i in range(n_rect)
    ]
    return Scene(tuple(rects), ("other",) * n_rect)


def _reference_hits(scene: Scene, o, d, min_range, max_range):
    """Nearest hit by the Rectangle methods (plane offset d, contains), ray by ray."""
    best = np.full(d.shape[0], np.inf)
    surf = np.full(d.shape[0], -1)
    for j, r in enumerate(scene.rectangles):
        den = d @ r.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            rho = -(o @ r.normal + r.d) / den
        x = o + np.where(np.isfinite(rho), rho, 0.0)[:, None] * d
        ok = np.isfinite(rho) & (rho > min_range) & (rho <= max_range) & r.contains(x) & (rho < best)
        best[ok], surf[ok] = rho[ok], j
    return best, surf


def test_intersections_are_exact_and_the_nearest_hit_wins():
    rng = np.random.default_rng(7)
    scene = _random_scene(rng)
    o = rng.uniform(-5, 5, (20000, 3))
    # aim half of the rays at rectangle points so that many hit, some through several planes
    j = rng.integers(0, len(scene), 20000)
    aim = np.array([r.center_m for r in scene.rectangles])[j] + rng.normal(0, 0.5, (20000, 3))
    d = aim - o
    d /= np.linalg.norm(d, axis=1)[:, None]
    d[::2] = rng.normal(size=(10000, 3))
    d[::2] /= np.linalg.norm(d[::2], axis=1)[:, None]
    hits = scene.intersect(o, d, min_range_m=0.3, max_range_m=40.0)
    ref_range, ref_surf = _reference_hits(scene, o, d, 0.3, 40.0)
    assert hits.hit.sum() > 4000
    assert np.array_equal(hits.surface, ref_surf)
    h = hits.hit
    np.testing.assert_allclose(hits.range_m[h], ref_range[h], rtol=0, atol=1e-10)
    assert np.all(np.isnan(hits.range_m[~h]))
    # every hit point lies on its plane and inside its rectangle
    x = o[h] + hits.range_m[h, None] * d[h]
    for jj, r in enumerate(scene.rectangles):
        s = hits.surface[h] == jj
        assert np.abs(r.signed_distance(x[s])).max(initial=0) < 1e-12
        assert r.contains(x[s], margin_m=1e-12).all()
        np.testing.assert_allclose(hits.cos_incidence[h][s], np.abs(d[h][s] @ r.normal))


def test_target_occludes_the_wall_and_water_and_sky_give_nothing():
    wall = Rectangle.from_orientation(
        "wall", [0.0, 15.0, -5.0], 10.0, 4.0, np.pi / 2, np.radians(270.0), 0.25
    )
    target = Rectangle.from_orientation("T", [0.0, 14.9, -5.0], 1.0, 1.0, np.pi / 2, np.radians(270.0), 0.9)
    scene = Scene((wall, target), ("wall", "target"))
    # rays from the origin toward the wall plane at heights −7 … −3, along y = 15
    z = np.linspace(-7.5, -2.5, 101)
    p = np.column_stack([np.zeros_like(z), np.full_like(z, 15.0), z])
    d = p / np.linalg.norm(p, axis=1)[:, None]
    hits = scene.intersect(np.zeros(3), d)
    on_target = np.abs(z + 5.0) < 0.5 - 1e-9
    on_wall = (np.abs(z + 5.0) <= 2.0) & ~on_target
    assert np.all(hits.surface[on_target] == 1)
    assert np.all(hits.surface[on_wall & (np.abs(np.abs(z + 5.0) - 0.5) > 1e-3)] == 0)
    assert np.all(hits.surface[np.abs(z + 5.0) > 2.0 + 1e-9] == -1)  # sky above, water below
    # a ray parallel to the planes and a ray pointing away return nothing, without warnings
    with np.errstate(all="raise"):
        away = scene.intersect(np.zeros(3), [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    assert np.all(away.surface == -1)


def test_max_range_and_min_range_cut_returns():
    wall = Rectangle.from_orientation("wall", [0.0, 15.0, 0.0], 10.0, 10.0, np.pi / 2, np.radians(270.0))
    scene = Scene((wall,), ("wall",))
    d = np.array([[0.0, 1.0, 0.0]])
    assert scene.intersect(np.zeros(3), d, max_range_m=14.9).surface[0] == -1
    assert scene.intersect(np.zeros(3), d, max_range_m=15.0).surface[0] == 0
    assert scene.intersect([0.0, 14.9, 0.0], d, min_range_m=0.3).surface[0] == -1


def test_scan_sectors_contain_every_hit_of_the_plane():
    rng = np.random.default_rng(11)
    scene = _random_scene(rng, 15)
    P = 40
    origins = rng.uniform(-10, 10, (P, 3))
    R = frames.rotation_from_vector(rng.normal(0, 1.5, (P, 3)))
    sec = scene.scan_sectors(origins, R[:, :, 0], R[:, :, 1], R[:, :, 2])
    alpha = np.linspace(0, 2 * np.pi, 20000, endpoint=False)
    n_hits = 0
    for p in range(P):
        d = np.cos(alpha)[:, None] * R[p, :, 1] + np.sin(alpha)[:, None] * R[p, :, 2]
        for j in range(len(scene)):
            rho, inside = scene.hit_range(j, *np.broadcast_to(origins[p], d.shape).T, *d.T)
            hit = inside & (rho > 0)
            n_hits += hit.sum()
            if not sec.hit[p, j]:
                assert not hit.any()
                continue
            assert 0.0 <= sec.width_rad[p, j] < np.pi
            rel = np.mod(alpha[hit] - sec.start_rad[p, j], 2 * np.pi)
            assert np.all(rel <= sec.width_rad[p, j] + 1e-9)
            if sec.width_rad[p, j] > 1e-3:  # the sector is tight: rays inside it hit
                mid = sec.start_rad[p, j] + sec.width_rad[p, j] * np.array([0.01, 0.5, 0.99])
                dm = np.cos(mid)[:, None] * R[p, :, 1] + np.sin(mid)[:, None] * R[p, :, 2]
                r_m, in_m = scene.hit_range(j, *np.broadcast_to(origins[p], dm.shape).T, *dm.T)
                assert np.all(in_m) and np.all(r_m > 0)
    assert n_hits > 1000


def test_scene_rejects_bad_input():
    r = Rectangle.from_orientation("A", [0, 0, 0], 1, 1, 1.0, 0.0)
    with pytest.raises(ValueError, match="unique.*A"):
        Scene((r, r), ("target", "wall"))
    with pytest.raises(ValueError, match="kind 'roof'"):
        Scene((r,), ("roof",))
    with pytest.raises(ValueError, match="1 rectangles but 2 kinds"):
        Scene((r,), ("wall", "wall"))
    with pytest.raises(ValueError, match="1 rectangles but 2 shapes"):
        Scene((r,), ("wall",), (None, None))
