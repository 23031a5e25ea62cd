"""GMR (numba, indexed) against the brute-force numpy oracle and finite differences."""

import numpy as np
import pytest
from sklearn.mixture import GaussianMixture as SkGMM

from gmmgp_app.config import MappingConfig
from gmmgp_app.stages.gmr import GMRError, GMRField, condition_on_xyz, gmr_bruteforce
from gmmgp_app.types import GaussianMixture


def sphere_rows(n=600, r=1.0, noise=0.008, s=0.25, seed=0):
    """Hit points on a sphere (8 mm noise) and virtual points at +-s along the normal."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    pts = r * u + noise * rng.normal(size=(n, 1)) * u
    rows = np.vstack([np.c_[pts, np.zeros(n)], np.c_[pts + s * u, np.full(n, s)],
                      np.c_[pts - s * u, np.full(n, -s)]])
    return pts, u, rows


def fit_mixture(rows, k, seed=0):
    g = SkGMM(k, covariance_type="full", random_state=seed, reg_covar=1e-6).fit(rows)
    return GaussianMixture(g.weights_, g.means_, g.covariances_)


@pytest.fixture(scope="module")
def sphere_mix():
    _, _, rows = sphere_rows()
    return fit_mixture(rows, 24)


def near_queries(n=3000, seed=1, band=0.3):
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u * (1.0 + rng.uniform(-band, band, size=(n, 1)))


def test_matches_bruteforce_over_all_components_near_data(sphere_mix):
    q = near_queries()
    m, v, g = GMRField(sphere_mix).predict(q, return_grad=True)
    mb, vb, gb = gmr_bruteforce(sphere_mix, q, return_grad=True)
    assert np.max(np.abs(m - mb)) < 1e-6
    assert np.max(np.abs(v - vb)) < 1e-6
    assert np.max(np.abs(g - gb)) < 1e-4


def test_matches_bruteforce_with_same_selection_exactly(sphere_mix):
    rng = np.random.default_rng(3)
    q = np.vstack([near_queries(2000, seed=2, band=0.6), rng.uniform(-3, 3, size=(500, 3))])
    for j, cut in ((4, 2.0), (16, 6.0), (1, 1.0)):
        f = GMRField(sphere_mix, n_active=j, mahalanobis_cut=cut)
        m, v, g = f.predict(q, return_grad=True)
        mb, vb, gb = gmr_bruteforce(sphere_mix, q, True, n_active=j, mahalanobis_cut=cut)
        np.testing.assert_allclose(m, mb, atol=1e-12)
        np.testing.assert_allclose(v, vb, atol=1e-12, rtol=1e-10)
        np.testing.assert_allclose(g, gb, atol=1e-10)


def test_far_queries_fall_back_and_variance_grows(sphere_mix):
    dirs = np.array([[1.0, 0.3, -0.2]]) / np.linalg.norm([1.0, 0.3, -0.2])
    t = np.array([3.0, 6.0, 12.0, 24.0, 48.0])
    q = t[:, None] * dirs
    f = GMRField(sphere_mix)
    m, v = f.predict(q)
    assert f.info["n_fallback"] == len(q)
    mb, vb = gmr_bruteforce(sphere_mix, q, n_active=16, mahalanobis_cut=6.0)
    np.testing.assert_allclose(m, mb, atol=1e-10)
    np.testing.assert_allclose(v, vb, rtol=1e-10)
    assert np.all(np.diff(v) > 0)
    # std grows about gamma per metre far away
    slope = np.diff(np.sqrt(v))[-1] / np.diff(t)[-1]
    assert 0.3 < slope < 0.7
    # the paper's variance (gamma = 0) stays tiny: the reason for the growth term
    _, v0 = GMRField(sphere_mix, far_variance_growth=0.0).predict(q)
    assert np.sqrt(v0[-1]) < 0.3 * np.sqrt(v[-1])


def test_gradient_matches_finite_differences(sphere_mix):
    q = near_queries(200, seed=4)
    f = GMRField(sphere_mix, n_active=len(sphere_mix.weights))  # smooth: no set changes
    _, _, g = f.predict(q, return_grad=True)
    eps = 1e-6
    fd = np.stack([(f.predict(q + eps * e)[0] - f.predict(q - eps * e)[0]) / (2 * eps)
                   for e in np.eye(3)], axis=1)
    np.testing.assert_allclose(g, fd, atol=1e-6)


def test_sdf_of_a_plane_is_recovered():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-2, 2, size=(3000, 2))
    pts = np.c_[xy, np.zeros(len(xy))]
    rows = np.vstack([np.c_[pts, np.zeros(len(pts))],
                      np.c_[pts + [0, 0, 0.25], np.full(len(pts), 0.25)],
                      np.c_[pts - [0, 0, 0.25], np.full(len(pts), -0.25)]])
    mix = fit_mixture(rows, 8)
    q = np.c_[rng.uniform(-1.5, 1.5, size=(500, 2)), rng.uniform(-0.2, 0.2, size=500)]
    m, v, g = GMRField(mix).predict(q, return_grad=True)
    np.testing.assert_allclose(m, q[:, 2], atol=2e-3)
    np.testing.assert_allclose(g, np.tile([0, 0, 1.0], (len(q), 1)), atol=2e-2)
    assert np.all(v > 0)


def test_conditioning_matches_covariance_form(sphere_mix):
    c = condition_on_xyz(sphere_mix)
    cov = sphere_mix.covariances
    b = np.linalg.solve(cov[:, :3, :3], cov[:, :3, 3:])[..., 0]
    s2 = cov[:, 3, 3] - np.einsum("ki,ki->k", cov[:, :3, 3], b)
    np.testing.assert_allclose(c["b"], b, atol=1e-10)
    np.testing.assert_allclose(c["s2"], s2, rtol=1e-8)


def test_from_config_uses_gmr_section(sphere_mix):
    cfg = MappingConfig().replace({"gmr.n_active": 3, "gmr.far_variance_growth": 0.0})
    f = GMRField.from_config(sphere_mix, cfg.gmr)
    assert f.n_active == 3 and f.far_variance_growth == 0.0


def test_empty_queries(sphere_mix):
    m, v, g = GMRField(sphere_mix).predict(np.zeros((0, 3)), return_grad=True)
    assert m.shape == (0,) and v.shape == (0,) and g.shape == (0, 3)


def test_bad_inputs(sphere_mix):
    f = GMRField(sphere_mix)
    with pytest.raises(GMRError, match=r"shape \(K, 3\), found \(5, 2\)"):
        f.predict(np.zeros((5, 2)))
    q = np.zeros((4, 3))
    q[1, 2] = np.nan
    with pytest.raises(GMRError, match="finite query coordinates, found 1 rows"):
        f.predict(q)
    with pytest.raises(GMRError, match="finite query coordinates"):
        gmr_bruteforce(sphere_mix, q)
    mix3 = GaussianMixture(np.ones(2) / 2, np.zeros((2, 3)), np.tile(np.eye(3), (2, 1, 1)))
    with pytest.raises(GMRError, match="4D mixture .* found dimension 3"):
        GMRField(mix3)
    sing = GaussianMixture(np.ones(1), np.zeros((1, 4)), np.zeros((1, 4, 4)))
    with pytest.raises(GMRError, match="positive definite"):
        GMRField(sing)
    with pytest.raises(GMRError, match="n_active >= 1, found 0"):
        GMRField(sphere_mix, n_active=0)
    with pytest.raises(GMRError, match="positive finite mahalanobis_cut"):
        GMRField(sphere_mix, mahalanobis_cut=-1.0)
    with pytest.raises(GMRError, match="far_variance_growth >= 0"):
        GMRField(sphere_mix, far_variance_growth=-1.0)
    with pytest.raises(GMRError, match="Expected a GaussianMixture, found ndarray"):
        GMRField(np.zeros((3, 4)))
    bad = GaussianMixture(np.array([np.nan]), np.zeros((1, 4)), np.eye(4)[None])
    with pytest.raises(GMRError, match="finite mixture parameters"):
        GMRField(bad)
    neg = GaussianMixture(np.array([-1.0]), np.zeros((1, 4)), np.eye(4)[None])
    with pytest.raises(GMRError, match="non-negative weights"):
        GMRField(neg)
    with pytest.raises(GMRError, match="positive cell_size"):
        GMRField(sphere_mix, cell_size=0.0)
