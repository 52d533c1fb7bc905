"""Cloud-to-cloud distances (calib.assess.c2c) against analytic values and an independent per-point
implementation of CloudCompare's C2C '-MODEL LS KNN k' semantics."""

from __future__ import annotations

import numpy as np
import pytest

from calib.assess.c2c import C2CError, c2c, distance_stats, smallest_eigenvector
from calib.core.geometry import Rectangle

DENSITY = 100.0  # points per m²


def plane_points(rng, n, half_m=5.0):
    return np.c_[rng.uniform(-half_m, half_m, n), rng.uniform(-half_m, half_m, n), np.zeros(n)]


def interior(p, half_m=5.0, margin_m=0.5):
    return (np.abs(p[:, 0]) < half_m - margin_m) & (np.abs(p[:, 1]) < half_m - margin_m)


def poisson_nn_median(offset_m, density_per_m2):
    """Median distance to the nearest point of a planar Poisson cloud of the given density, for a
    query at ``offset_m`` from the plane: P(r ≤ R) = 1 − exp(−λπR²) for the in-plane distance."""
    return np.sqrt(offset_m**2 + np.log(2.0) / (np.pi * density_per_m2))


# -- analytic values on constructed surfaces ------------------------------------------------


def test_offset_20mm_at_100_points_per_m2_local_plane_vs_nearest_neighbour():
    rng = np.random.default_rng(1)
    n = int(DENSITY * 100)
    ref = plane_points(rng, n)
    cmp_ = plane_points(rng, n) + [0.0, 0.0, 0.020]
    r = c2c(cmp_, ref, k=6)
    inside = interior(cmp_)
    # the local plane recovers the offset exactly on a noise-free plane, edges included
    np.testing.assert_allclose(r.distance_m, 0.020, atol=1e-9)
    assert r.has_model.all() and r.n_fallback == 0
    # the plain nearest neighbour is biased by the point spacing, as the Poisson law predicts
    nn_median = float(np.median(r.nn_distance_m[inside]))
    expected_nn = poisson_nn_median(0.020, DENSITY)  # 0.0511 m
    assert expected_nn == pytest.approx(0.0511, abs=5e-4)
    assert nn_median == pytest.approx(expected_nn, rel=0.03)
    assert nn_median - 0.020 > 0.025  # more than 25 mm of bias, against < 1e-9 m for C2C


def test_offset_20mm_noisy_planes_median_within_1mm():
    rng = np.random.default_rng(2)
    n, sigma = int(DENSITY * 100), 0.003
    ref = plane_points(rng, n)
    ref[:, 2] += rng.normal(0, sigma, n)
    cmp_ = plane_points(rng, n)
    cmp_[:, 2] += 0.020 + rng.normal(0, sigma, n)
    r = c2c(cmp_, ref, k=6, orient_direction=[0, 0, 1])
    s, ss, nn = r.stats(), r.stats(signed=True), r.nn_stats()
    assert abs(s.median_m - 0.020) < 0.001
    assert abs(ss.mean_m - 0.020) < 0.0003  # signed distances are unbiased (SE ≈ 0.04 mm)
    # the spread: compared noise plus the prediction error of a 6-point plane fit
    assert sigma < ss.std_m < 2 * sigma
    assert nn.median_m > 0.045  # the nearest neighbour is biased by > 25 mm
    assert r.n_ambiguous_sign == 0


@pytest.mark.parametrize(
    ("incl_deg", "az_deg", "offset_m"), [(90, 270, 0.05), (30, 45, -0.03), (60, 200, 0.2), (0, 0, 0.011)]
)
def test_tilted_planes_exact_unsigned_and_signed(incl_deg, az_deg, offset_m):
    rng = np.random.default_rng(3)
    rect = Rectangle.from_orientation(
        "P", [100.0, -50.0, -12.0], 5.0, 5.0, np.radians(incl_deg), np.radians(az_deg)
    )

    def on_plane(m):
        ab = rng.uniform(-2.5, 2.5, (m, 2))
        return rect.center_m + ab[:, :1] * rect.u_axis + ab[:, 1:] * rect.v_axis

    ref = on_plane(2500)
    cmp_ = on_plane(2000) + offset_m * rect.normal
    r = c2c(cmp_, ref, k=6)
    np.testing.assert_allclose(r.distance_m, abs(offset_m), atol=1e-9)
    # unit normals, parallel to the plane's
    np.testing.assert_allclose(np.abs(r.normal @ rect.normal), 1.0, atol=1e-9)
    for orient, sign in (
        ({"orient_direction": rect.normal}, 1.0),
        ({"orient_direction": -rect.normal}, -1.0),
        ({"orient_toward_m": rect.center_m + 30.0 * rect.normal}, 1.0),
    ):
        rs = c2c(cmp_, ref, k=6, **orient)
        np.testing.assert_allclose(rs.signed_distance_m, sign * offset_m, atol=1e-9)
        np.testing.assert_allclose(rs.normal @ rect.normal, sign, atol=1e-9)


def test_sphere_patch_curvature_is_small_at_dense_sampling():
    """A 5 m sphere sampled at 2500 points/m²: the local plane's chord error (ρ²/2R ≈ 0.06 mm
    for a 6-point neighbourhood) keeps the C2C value within 0.2 mm of the radial offset; the
    nearest neighbour is biased by several mm."""
    rng = np.random.default_rng(4)
    R, density, theta_max = 5.0, 2500.0, np.radians(15.0)
    area = 2 * np.pi * R**2 * (1 - np.cos(theta_max))

    def cap(m, radius):
        ct = rng.uniform(np.cos(theta_max), 1.0, m)
        st, ph = np.sqrt(1 - ct**2), rng.uniform(0, 2 * np.pi, m)
        return radius * np.c_[st * np.cos(ph), st * np.sin(ph), ct]

    ref = cap(int(density * area), R)
    for delta in (0.010, -0.010):
        cmp_ = cap(4000, R + delta)
        away = np.arccos(cmp_[:, 2] / np.linalg.norm(cmp_, axis=1)) < theta_max - 0.02
        r = c2c(cmp_[away], ref, k=6, orient_toward_m=[0, 0, 100.0])  # normals outward
        assert abs(r.stats().median_m - abs(delta)) < 2e-4
        assert abs(r.stats(signed=True).median_m - delta) < 2e-4
        assert r.nn_stats().median_m == pytest.approx(poisson_nn_median(delta, density), rel=0.05)
        assert r.nn_stats().median_m - abs(delta) > 0.003


# -- neighbourhood sizes and degenerate neighbourhoods --------------------------------------


@pytest.mark.parametrize("k", [3, 6, 12, 30])
def test_any_k_below_the_cloud_size_is_exact_on_a_plane(k):
    rng = np.random.default_rng(5)
    ref = plane_points(rng, 800, half_m=1.0)
    cmp_ = plane_points(rng, 300, half_m=1.0) + [0, 0, -0.007]
    r = c2c(cmp_, ref, k=k)
    assert r.k == k
    np.testing.assert_allclose(r.distance_m, 0.007, atol=1e-9)


def test_fewer_reference_points_than_k_uses_all_of_them():
    ref = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]])  # 4 points, k = 6
    cmp_ = np.array([[0.2, 0.3, 0.05], [0.9, 0.9, -0.02]])
    r = c2c(cmp_, ref, k=6)
    assert r.has_model.all()
    np.testing.assert_allclose(r.distance_m, [0.05, 0.02], atol=1e-12)


def test_fewer_than_three_reference_points_falls_back_to_nearest_neighbour():
    ref = np.array([[0, 0, 0], [1, 0, 0.0]])
    cmp_ = np.array([[0.2, 0.3, 0.05]])
    r = c2c(cmp_, ref, k=6)
    assert not r.has_model.any() and r.n_fallback == 1
    np.testing.assert_allclose(r.distance_m, np.sqrt(0.2**2 + 0.3**2 + 0.05**2))
    np.testing.assert_allclose(r.distance_m, r.nn_distance_m)


def test_collinear_neighbourhood_falls_back_to_nearest_neighbour():
    x = np.linspace(0, 10, 101)  # a line along x, 10 cm spacing
    ref = np.c_[x, 2 * x + 1.0, np.zeros_like(x)]
    cmp_ = np.array([[5.03, 11.0, 0.04], [2.0, 5.2, -0.1]])
    r = c2c(cmp_, ref, k=6)
    assert not r.has_model.any() and r.n_fallback == 2
    assert np.isnan(r.normal).all()
    nn = np.min(np.linalg.norm(cmp_[:, None, :] - ref[None], axis=2), axis=1)
    np.testing.assert_allclose(r.distance_m, nn, rtol=1e-12)
    # a signed request still gives a sign: the side of the nearest point along the orientation
    rs = c2c(cmp_, ref, k=6, orient_direction=[0, 0, 1])
    np.testing.assert_allclose(rs.signed_distance_m, [nn[0], -nn[1]], rtol=1e-12)


def test_nearly_collinear_scan_line_is_caught_by_a_larger_tolerance():
    rng = np.random.default_rng(6)
    x = np.linspace(0, 1, 51)  # 2 cm spacing, 0.1 mm of noise across: width/length ≈ 1e-3
    ref = np.c_[x, rng.normal(0, 1e-4, x.size), rng.normal(0, 1e-4, x.size)]
    cmp_ = np.array([[0.5, 0.0, 0.03]])
    assert c2c(cmp_, ref, k=6).has_model.all()  # a plane is fitted to the noise
    r = c2c(cmp_, ref, k=6, collinear_tol=0.05)
    assert not r.has_model.any()
    np.testing.assert_allclose(r.distance_m, r.nn_distance_m)


def test_coincident_reference_points_fall_back():
    ref = np.repeat([[1.0, 2.0, 3.0]], 10, axis=0)
    r = c2c(np.array([[1.0, 2.0, 3.5]]), ref, k=6)
    assert not r.has_model.any()
    np.testing.assert_allclose(r.distance_m, 0.5)


def test_distance_never_exceeds_the_nearest_neighbour_distance():
    """CloudCompare keeps the smaller of the model and nearest-neighbour distances: a spike in a
    flat reference barely tilts a 30-point local plane, which passes far below the spike; the
    point 2 cm above the spike gets the spike's distance, not the plane's."""
    g = np.arange(0, 1.0001, 0.05)
    gx, gy = np.meshgrid(g, g)
    ref = np.c_[gx.ravel(), gy.ravel(), np.zeros(gx.size)]
    ref = np.vstack([ref, [0.525, 0.525, 0.10]])
    q = np.array([[0.525, 0.525, 0.12]])
    r = c2c(q, ref, k=30)
    assert r.has_model.all()
    assert r.nearest_index[0] == ref.shape[0] - 1
    nb = ref[np.argsort(np.linalg.norm(ref - ref[-1], axis=1))[:30]]
    normal = np.linalg.eigh(np.cov(nb.T))[1][:, 0]
    assert abs((q[0] - nb.mean(axis=0)) @ normal) > 0.1  # what the plane alone would say
    np.testing.assert_allclose(r.distance_m, 0.02, atol=1e-12)


def test_max_distance_gives_the_bound_and_leaves_points_out_of_the_statistics():
    rng = np.random.default_rng(7)
    ref = plane_points(rng, 2000, half_m=2.0)
    cmp_ = np.vstack([plane_points(rng, 50, half_m=2.0) + [0, 0, 0.01], [[0, 0, 5.0], [10, 10, 0]]])
    r = c2c(cmp_, ref, k=6, max_distance_m=1.0, orient_direction=[0, 0, 1])
    assert r.within_max.sum() == 50
    np.testing.assert_allclose(r.distance_m[-2:], 1.0)  # CloudCompare's value beyond MAX_DIST
    assert (r.nearest_index[-2:] == -1).all() and np.isinf(r.nn_distance_m[-2:]).all()
    assert np.isnan(r.signed_distance_m[-2:]).all()
    s = r.stats()
    assert s.count == 50 and s.max_m == pytest.approx(0.01, abs=1e-9)


# -- the vectorized code against a per-point reference implementation -----------------------


def reference_c2c(cmp_, ref, k, tol=1e-5, direction=None):
    """CloudCompare's C2C LS semantics, one point at a time, with numpy's eigh."""
    out, signed, model = [], [], []
    for q in cmp_:
        d_all = np.linalg.norm(ref - q, axis=1)
        i = int(np.argmin(d_all))
        p = ref[i]
        nb = ref[np.argsort(np.linalg.norm(ref - p, axis=1), kind="stable")[: min(k, len(ref))]]
        c = nb.mean(axis=0)
        w, v = np.linalg.eigh((nb - c).T @ (nb - c))
        ok = len(nb) >= 3 and w[2] > 0 and np.sqrt(max(w[1], 0) / w[2]) >= tol
        d_nn = d_all[i]
        if ok:
            n = v[:, 0]
            if direction is not None and n @ direction < 0:
                n = -n
            side = (q - c) @ n
            d = min(d_nn, abs(side))
        else:
            side = (q - p) @ direction if direction is not None else 0.0
            d = d_nn
        out.append(d)
        signed.append(d if side >= 0 else -d)
        model.append(ok)
    return np.array(out), np.array(signed), np.array(model)


@pytest.mark.parametrize("k", [3, 4, 6, 10])
def test_matches_a_per_point_reference_implementation(k):
    rng = np.random.default_rng(10 + k)
    # a wavy noisy surface, a noisy blob and a collinear strip in one reference cloud
    xy = rng.uniform(0, 2, (500, 2))
    surf = np.c_[xy, 0.1 * np.sin(3 * xy[:, 0]) + rng.normal(0, 0.004, 500)]
    blob = rng.normal([1, 1, 0.5], 0.05, (80, 3))
    line = np.c_[np.linspace(3, 4, 30), np.full(30, 1.0), np.full(30, 0.2)]
    ref = np.vstack([surf, blob, line])
    cmp_ = np.vstack(
        [
            np.c_[rng.uniform(0, 2, (200, 2)), rng.normal(0.03, 0.02, 200)],
            rng.normal([1, 1, 0.5], 0.1, (50, 3)),
            np.c_[rng.uniform(3, 4, 20), rng.normal(1.0, 0.05, 20), rng.normal(0.2, 0.05, 20)],
        ]
    )
    direction = np.array([0.0, 0.0, 1.0])
    d, s, m = reference_c2c(cmp_, ref, k, direction=direction)
    r = c2c(cmp_, ref, k=k, orient_direction=direction, chunk_size=64)
    np.testing.assert_array_equal(r.has_model, m)
    assert (~m).sum() >= 10  # the collinear strip exercised the fallback
    np.testing.assert_allclose(r.distance_m, d, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(r.signed_distance_m, s, rtol=1e-9, atol=1e-12)


def test_block_size_does_not_change_the_result():
    rng = np.random.default_rng(11)
    ref = rng.normal(size=(3000, 3)) * [3, 3, 0.1]
    cmp_ = rng.normal(size=(2000, 3)) * [3, 3, 0.1]
    a = c2c(cmp_, ref, k=6, chunk_size=7)
    b = c2c(cmp_, ref, k=6)
    np.testing.assert_array_equal(a.distance_m, b.distance_m)
    np.testing.assert_array_equal(a.nearest_index, b.nearest_index)
    calls = []
    c2c(cmp_, ref, k=6, chunk_size=500, progress=lambda done, total: calls.append((done, total)))
    assert calls == [(500, 2000), (1000, 2000), (1500, 2000), (2000, 2000)]


def test_smallest_eigenvector_agrees_with_eigh():
    rng = np.random.default_rng(12)
    m = 20000
    # spectra from isotropic to very flat; λ3 well separated from λ2 (a defined normal)
    lam = np.sort(rng.uniform(0, 1, (m, 3)), axis=1)[:, ::-1] * 10.0 ** rng.uniform(-6, 3, (m, 1))
    lam[:, 1] = lam[:, 0] * 10.0 ** rng.uniform(-10, 0, m)
    lam[:, 2] = lam[:, 1] * rng.uniform(0, 0.5, m)
    Q = np.linalg.qr(rng.normal(size=(m, 3, 3)))[0]
    A = np.einsum("mij,mj,mkj->mik", Q, lam, Q)
    n = smallest_eigenvector(A[:, 0, 0], A[:, 1, 1], A[:, 2, 2], A[:, 0, 1], A[:, 0, 2], A[:, 1, 2])
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    sin_angle = np.linalg.norm(np.cross(n, Q[:, :, 2]), axis=1)
    bound = 4e-15 * lam[:, 0] / (lam[:, 1] - lam[:, 2]) + 1e-15  # ≈ 20 ε / separation, as LAPACK
    assert np.all(sin_angle <= bound)


# -- statistics and errors ------------------------------------------------------------------


def test_distance_stats_known_values():
    s = distance_stats([1.0, 2.0, 3.0, 4.0, np.nan])
    assert s.count == 4
    assert s.mean_m == 2.5 and s.median_m == 2.5
    assert s.rms_m == pytest.approx(np.sqrt(7.5))
    assert s.std_m == pytest.approx(np.sqrt(1.25))  # population standard deviation
    assert s.p95_m == pytest.approx(3.85)  # linear interpolation between 3 and 4
    assert s.max_m == 4.0
    signed = distance_stats([-3.0, 1.0])
    assert signed.mean_m == -1.0 and signed.max_m == 3.0 and signed.p95_m == pytest.approx(2.9)
    assert distance_stats([]).count == 0 and np.isnan(distance_stats([]).median_m)


@pytest.mark.parametrize(
    ("args", "kwargs", "message"),
    [
        ((np.zeros((0, 3)), np.zeros((5, 3))), {}, "compared cloud is empty"),
        ((np.zeros((5, 3)), np.zeros((0, 3))), {}, "reference cloud is empty"),
        ((np.zeros((5, 2)), np.zeros((5, 3))), {}, "expected an (n, 3) array"),
        ((np.zeros((5, 3)), np.array([[0, 0, 0], [1, np.nan, 0]])), {}, "point 1 has a non-finite"),
        ((np.zeros((5, 3)), np.zeros((5, 3))), {"k": 2}, "k ≥ 3"),
        ((np.zeros((5, 3)), np.zeros((5, 3))), {"max_distance_m": 0.0}, "positive distance"),
        ((np.zeros((5, 3)), np.zeros((5, 3))), {"orient_direction": [0, 0, 0]}, "zero vector"),
        (
            (np.zeros((5, 3)), np.zeros((5, 3))),
            {"orient_direction": [0, 0, 1], "orient_toward_m": [0, 0, 1]},
            "not both",
        ),
    ],
)
def test_bad_input_is_named(args, kwargs, message):
    with pytest.raises(C2CError, match=None) as e:
        c2c(*args, **kwargs)
    assert message in str(e.value)


def test_signed_stats_need_an_orientation():
    r = c2c(np.zeros((1, 3)), np.eye(3))
    assert r.signed_distance_m is None
    with pytest.raises(C2CError, match="orient_direction"):
        r.stats(signed=True)
