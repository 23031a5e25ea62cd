"""GMR (numba, indexed) against the brute-force numpy oracle and finite differences."""

import numpy as np
import pytest
from sklearn.mixture import GaussianMixture as SkGMM

from gmmgp_app.config import MappingConfig
from gmmgp_app.stages.gmr import (DEFAULT_FAR_GROWTH, GMRError, GMRField, condition_on_xyz,
                                  far_growth_distance, gmr_bruteforce)
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
    assert 0.6 * DEFAULT_FAR_GROWTH < slope < 1.4 * DEFAULT_FAR_GROWTH
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
    with pytest.raises(GMRError, match="far_growth_floor >= 0, found -0.1"):
        GMRField(sphere_mix, far_growth_floor=-0.1)
    with pytest.raises(GMRError, match="cache_entries >= 1, found 0"):
        GMRField(sphere_mix, cache_entries=0)
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


# ------------------------------------------------------------- the cell cache
def test_cache_is_exact_in_many_cells_whatever_the_batch_order(sphere_mix):
    rng = np.random.default_rng(7)
    q = np.vstack([near_queries(3000, seed=8, band=0.8), rng.uniform(-2, 2, size=(1500, 3))])
    for j, cut in ((16, 6.0), (3, 2.5)):
        mb, vb, gb = gmr_bruteforce(sphere_mix, q, True, n_active=j, mahalanobis_cut=cut)
        f = GMRField(sphere_mix, n_active=j, mahalanobis_cut=cut, cell_size=0.15)
        # cells built by earlier, overlapping batches are reused by later ones
        parts = [f.predict(q[s:s + 700], return_grad=True) for s in range(0, len(q), 700)]
        assert f.cells_cached > 200
        m, v, g = (np.concatenate(p) for p in zip(*parts))
        np.testing.assert_allclose(m, mb, atol=1e-12)
        np.testing.assert_allclose(v, vb, atol=1e-12, rtol=1e-10)
        np.testing.assert_allclose(g, gb, atol=1e-10)
        # a warm cache answers the whole batch again, building nothing, same values
        m2, v2, g2 = f.predict(q[::-1], return_grad=True)
        assert f.info["cells_built"] == 0
        np.testing.assert_array_equal(m2, m[::-1])
        np.testing.assert_array_equal(v2, v[::-1])


def test_cache_bound_empties_and_stays_exact(sphere_mix):
    q = near_queries(2000, seed=9, band=0.5)
    f = GMRField(sphere_mix, cell_size=0.1, cache_entries=500)
    mb, vb = gmr_bruteforce(sphere_mix, q, n_active=16, mahalanobis_cut=6.0)
    for s in range(0, len(q), 250):
        m, v = f.predict(q[s:s + 250])
        np.testing.assert_allclose(m, mb[s:s + 250], atol=1e-12)
        np.testing.assert_allclose(v, vb[s:s + 250], rtol=1e-10)
        # bounded, except that one batch's own cells are always kept
        assert len(f._idx) <= max(500, f.info["cells_built"] * len(sphere_mix.weights))


def test_queries_outside_the_grid_use_the_top_j_of_all(sphere_mix):
    rng = np.random.default_rng(11)
    d = rng.normal(size=(300, 3))
    q = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(20, 1e4, size=(300, 1))
    f = GMRField(sphere_mix)
    m, v = f.predict(q)
    # no cell is built for them: they lie outside every component's candidate ball
    assert f.cells_cached == 0 and f.info["n_fallback"] == len(q)
    mb, vb = gmr_bruteforce(sphere_mix, q, n_active=16, mahalanobis_cut=6.0)
    np.testing.assert_allclose(m, mb, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(v, vb, rtol=1e-9)


# ----------------------------------------------------- far-field variance growth
def test_far_growth_distance_is_the_distance_to_the_box():
    # a component along x (sd 2) on a thin z axis: half-sides 4, 1, 0.2 with D0 = 2
    axes = np.eye(3)[None]
    half = np.array([[4.0, 1.0, 0.2]])
    dx = np.array([[0.0, 0.0, 0.0], [3.9, 0.9, 0.1], [5.0, 0.0, 0.0], [0.0, 0.0, -0.5],
                   [7.0, -5.0, 1.2]])[:, None, :]
    want = np.array([0.0, 0.0, 1.0, 0.3, np.sqrt(3.0 ** 2 + 4.0 ** 2 + 1.0 ** 2)])
    np.testing.assert_allclose(far_growth_distance(dx, axes, half)[:, 0], want)
    # rotated box: same distances for rotated offsets
    rot = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))[0]
    np.testing.assert_allclose(far_growth_distance(dx @ rot.T, rot.T[None], half)[:, 0],
                               want, atol=1e-12)


def plane_patch_mixture(seed=0):
    """A 4 x 4 m ground patch (x, y in [-4, 0] x [-2, 2]) with virtual points."""
    rng = np.random.default_rng(seed)
    xy = np.c_[rng.uniform(-4, 0, 6000), rng.uniform(-2, 2, 6000)]
    pts = np.c_[xy, 0.004 * rng.normal(size=len(xy))]
    rows = np.vstack([np.c_[pts, np.zeros(len(pts))],
                      np.c_[pts + [0, 0, 0.25], np.full(len(pts), 0.25)],
                      np.c_[pts - [0, 0, 0.25], np.full(len(pts), -0.25)]])
    return fit_mixture(rows, 6, seed=seed)


def test_variance_is_continuous_across_the_data_edge_and_grows_outside():
    mix = plane_patch_mixture()
    x = np.arange(-1.0, 1.5001, 0.01)                 # data end at x = 0
    for z in (0.0, 0.2):
        q = np.c_[x, np.zeros_like(x), np.full_like(x, z)]
        _, v = GMRField(mix).predict(q)
        _, v0 = GMRField(mix, far_variance_growth=0.0).predict(q)
        sd = np.sqrt(v)
        sd0 = np.sqrt(v0)
        # no jump: e(x) is 1-Lipschitz, so the std of neighbours 1 cm apart differs by
        # at most gamma * 1 cm beyond the GMR's own change, and by a factor < 3 here
        # (GMR std ~4 mm); the old growth went from 1e-2 to several metres within 10 cm
        step = np.abs(np.diff(sd)) - np.abs(np.diff(sd0))
        assert np.max(step) <= DEFAULT_FAR_GROWTH * 0.01 * 1.0001
        assert np.max(np.maximum(sd[1:] / sd[:-1], sd[:-1] / sd[1:])) < 3.0
        inside = x <= -0.5
        # inside the data and the +-0.25 m band, the GMR variance stands
        np.testing.assert_allclose(v[inside], v0[inside], rtol=1e-6)
        # outside it grows, roughly gamma per metre at 1.5 m from the edge
        assert sd[-1] > 0.5 * DEFAULT_FAR_GROWTH * 1.0
        assert np.all(np.diff(sd[x >= 0.6]) > 0)


def test_compact_lists_is_numpys_mask():
    """_compact_lists (one compiled pass) gives numpy's cumulative-sum pointers and
    masked int32 indices exactly: empty cells, cells losing every entry, all kept."""
    from gmmgp_app.stages.gmr import _compact_lists

    rng = np.random.default_rng(11)
    for n_cells, p_keep in ((1, 0.0), (7, 1.0), (50, 0.3), (400, 0.8)):
        lens = rng.integers(0, 9, n_cells)
        lens[::5] = 0
        ptr = np.zeros(n_cells + 1, dtype=np.int64)
        np.cumsum(lens, out=ptr[1:])
        idx = rng.integers(0, 2 ** 31 - 1, ptr[-1]).astype(np.int64)
        keep = rng.random(ptr[-1]) < p_keep
        ptr2, idx2 = _compact_lists(ptr, idx, keep)
        want_ptr = np.concatenate([[0], np.cumsum(keep, dtype=np.int64)])[ptr]
        np.testing.assert_array_equal(ptr2, want_ptr)
        assert ptr2.dtype == np.int64 and idx2.dtype == np.int32
        np.testing.assert_array_equal(idx2, idx[keep].astype(np.int32))
