"""The local projection model of a chunk (:mod:`office.deliver.projection`) against pyproj:
≤ 0.01 mm over the chunk's box on random chunks (UTM at its central meridian and far from it,
MTM, geographic), the fallback to pyproj when a box is too large for it, and the chunk's LAS
integers pyproj's or one unit (0.1 mm) away."""

from __future__ import annotations

import numpy as np
import pytest

from calib.core.frames import LocalFrame
from calib.io.laz import output_crs
from office.deliver import projection
from office.deliver.projection import fit_model, project_on_grid, tolerance

# (lat, lon, CRS): UTM 18N near its central meridian (−75°) and 3° from it (the zone's edge,
# ≈ 235 km east), high latitude, the southern hemisphere, MTM zone 8, geographic 3-D
CASES = [
    (45.5, -74.9, "utm"),
    (45.5, -72.01, "utm"),
    (70.2, -77.95, "utm"),
    (-33.9, 18.4, "utm"),
    (45.5, -73.55, "EPSG:2950"),
    (45.5, -73.55, "EPSG:4979"),
]


@pytest.mark.parametrize(("lat", "lon", "spec"), CASES)
def test_the_model_agrees_with_pyproj_over_random_chunks(lat, lon, spec):
    crs = output_crs(spec, LocalFrame(lat, lon, 12.0))
    rng = np.random.default_rng(abs(hash((lat, lon, spec))) % 2**32)
    for _ in range(6):
        centre = np.r_[rng.uniform(-20e3, 20e3, 2), rng.uniform(-40.0, 40.0)]
        half = np.r_[rng.uniform(5.0, 1500.0, 2), rng.uniform(1.0, 60.0)]
        lo, hi = centre - half, centre + half
        model, err = fit_model(crs, lo, hi)
        assert np.all(err <= tolerance(crs))
        p = rng.uniform(lo, hi, (20_000, 3))
        got = model.offsets(p) + model.origin
        # 0.01 mm (or its length in degrees) everywhere in the box, not only at the checks
        assert np.all(np.abs(got - crs.from_lgf(p)).max(axis=0) <= tolerance(crs))


def test_a_box_too_large_for_the_model_is_projected_by_pyproj(monkeypatch):
    crs = output_crs("utm", LocalFrame(45.5, -72.01, 0.0))
    rng = np.random.default_rng(7)
    p = np.asfortranarray(rng.uniform([-300e3, -300e3, -50.0], [300e3, 300e3, 50.0], (5000, 3)))
    _, err = fit_model(crs, p.min(axis=0), p.max(axis=0))
    assert np.any(err > tolerance(crs))  # 600 km: no cubic is exact to 0.01 mm
    want = np.round((crs.from_lgf(p) - np.asarray(crs.offsets)) / np.asarray(crs.scales)).T
    assert np.array_equal(project_on_grid(crs, p), want)


@pytest.mark.parametrize(("lat", "lon", "spec"), [*CASES, (45.5, -73.55, "lgf")])
def test_a_chunk_is_on_pyprojs_las_grid_or_one_unit_away(lat, lon, spec):
    crs = output_crs(spec, LocalFrame(lat, lon, 12.0))
    rng = np.random.default_rng(3)
    centre = np.r_[rng.uniform(-2e3, 2e3, 2), 0.0]
    p = np.asfortranarray(
        centre + rng.uniform([-150, -150, -5], [150, 150, 40], (3 * projection.BLOCK + 5, 3))
    )
    want = np.round((crs.from_lgf(p) - np.asarray(crs.offsets)) / np.asarray(crs.scales)).T
    got = project_on_grid(crs, p)
    assert np.abs(got - want).max() <= 1.0
    assert np.count_nonzero(got != want) <= 1e-3 * got.size  # only points next to a half unit
    if spec == "lgf":
        assert np.array_equal(got, want)  # an exact axis swap
