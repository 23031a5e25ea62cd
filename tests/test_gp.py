"""Local GPs: exact dense GP oracle, variance bounds, accuracy on a sphere, persistence."""

import math

import numpy as np
import pytest
from sklearn.mixture import GaussianMixture as SkGMM

from gmmgp_app.config import GPConfig, concrete
from gmmgp_app.stages.gmr import GMRField
from gmmgp_app.stages.gp import (ConstantPrior, GPError, LocalGPField, fit_block,
                                 fit_local_gps, neighbourhood_residual,
                                 select_gp_points)
from gmmgp_app.stages.kernels import matern32_joint
from gmmgp_app.stages.octree import BlockGrid, OctreeError
from gmmgp_app.types import GaussianMixture


def sphere(n, r=1.0, noise=0.008, seed=0):
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return r * u + noise * rng.normal(size=(n, 1)) * u, u


@pytest.fixture(scope="module")
def sphere_scene():
    pts, nrm = sphere(1000)
    s = 0.25
    rows = np.vstack([np.c_[pts, np.zeros(len(pts))], np.c_[pts + s * nrm, np.full(len(pts), s)],
                      np.c_[pts - s * nrm, np.full(len(pts), -s)]])
    g = SkGMM(16, covariance_type="full", random_state=0, reg_covar=1e-6).fit(rows)
    mix = GaussianMixture(g.weights_, g.means_, g.covariances_)
    return pts, nrm, GMRField(mix)


def dense_gp(points, normals, prior, cfg, xs):
    """One exact GP over all points (numpy solve, no blocks, no Cholesky caching)."""
    m, v, g = prior.predict(points, return_grad=True)
    y = np.column_stack([-m, normals - g]).reshape(-1)
    S = np.repeat(np.sqrt(v), 4)
    K = S[:, None] * matern32_joint(points, points, cfg.length_scale) * S[None]
    K += np.diag(np.tile([cfg.value_noise] + [cfg.gradient_noise] * 3, len(points)))
    ms, vs, gs = prior.predict(xs, return_grad=True)
    Ss = np.repeat(np.sqrt(vs), 4)
    Ks = Ss[:, None] * matern32_joint(xs, points, cfg.length_scale) * S[None]
    post = Ks @ np.linalg.solve(K, y)
    kv = Ks[0::4]
    var = vs - np.einsum("ij,ji->i", kv, np.linalg.solve(K, kv.T)) + cfg.value_noise
    return ms + post[0::4], var, gs + post.reshape(-1, 4)[:, 1:]


def small_scene(seed=0):
    """40 points on the positive octant of the unit sphere: one 10 m block holds them."""
    pts, nrm = sphere(40, seed=seed)
    pts, nrm = np.abs(pts), np.abs(nrm)
    rng = np.random.default_rng(seed + 1)
    xs = rng.uniform(0.05, 1.1, size=(50, 3))
    return pts, nrm, xs


@pytest.mark.parametrize("prior", [ConstantPrior(0.05, 0.01), "gmr"])
def test_one_block_equals_dense_exact_gp(prior, sphere_scene):
    if prior == "gmr":
        prior = sphere_scene[2]
    pts, nrm, xs = small_scene()
    cfg = concrete(GPConfig(block_size=10.0, jitter=0.0, length_scale=0.1))
    field = fit_local_gps(pts, nrm, prior, cfg)
    assert field.info["n_blocks"] == 1
    m, v, g = field.predict(xs, return_grad=True)
    md, vd, gd = dense_gp(pts, nrm, prior, cfg, xs)
    np.testing.assert_allclose(m, md, atol=1e-9)
    np.testing.assert_allclose(v, vd, atol=1e-10)
    np.testing.assert_allclose(g, gd, atol=1e-7)


def test_gradient_is_derivative_of_mean_for_constant_prior():
    pts, nrm, xs = small_scene(3)
    field = fit_local_gps(pts, nrm, ConstantPrior(0.0, 0.01), concrete(GPConfig(block_size=10.0)))
    _, _, g = field.predict(xs, return_grad=True)
    eps = 1e-6
    fd = np.stack([(field.predict(xs + eps * e)[0] - field.predict(xs - eps * e)[0])
                   / (2 * eps) for e in np.eye(3)], axis=1)
    np.testing.assert_allclose(g, fd, atol=1e-5)


def test_posterior_variance_bounded_by_prior_plus_noise(sphere_scene):
    pts, nrm, prior = sphere_scene
    cfg = concrete(GPConfig(block_size=0.3))
    field = fit_local_gps(pts[:400], nrm[:400], prior, cfg)
    assert field.info["n_blocks"] > 10
    rng = np.random.default_rng(2)
    q = rng.uniform(-1.3, 1.3, size=(3000, 3))
    _, v = field.predict(q)
    _, vp = prior.predict(q)
    assert np.all(v <= vp + cfg.value_noise + 1e-12)
    assert np.all(v > 0)


def test_prior_alone_outside_every_block(sphere_scene):
    pts, nrm, prior = sphere_scene
    field = fit_local_gps(pts[:50], nrm[:50], prior, concrete(GPConfig()))
    q = np.array([[5.0, 5.0, 5.0], [-4.0, 3.0, 0.0]])
    m, v, g = field.predict(q, return_grad=True)
    mp, vp, gp = prior.predict(q, return_grad=True)
    np.testing.assert_array_equal(m, mp)
    np.testing.assert_array_equal(v, vp)
    np.testing.assert_array_equal(g, gp)


def test_gp_beats_gmr_on_a_sphere_near_the_surface(sphere_scene):
    pts, nrm, prior = sphere_scene
    mask = select_gp_points(prior.predict(pts)[0], concrete(GPConfig()).d_m)
    assert 0 < mask.sum() < len(pts)
    field = fit_local_gps(pts[mask], nrm[mask], prior, concrete(GPConfig()))
    rng = np.random.default_rng(5)
    u = rng.normal(size=(3000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    d = rng.uniform(-0.1, 0.1, size=3000)
    q = u * (1 + d[:, None])                          # exact SDF: |x| - 1 = d
    mg, vg = field.predict(q)
    mp, vp = prior.predict(q)
    rmse = lambda m: np.sqrt(np.mean((m - d) ** 2))  # noqa: E731
    ll = lambda m, v: np.mean(-0.5 * np.log(2 * np.pi * v) - 0.5 * (m - d) ** 2 / v)  # noqa
    assert rmse(mg) < 0.6 * rmse(mp)
    assert ll(mg, vg) > ll(mp, vp)


def test_save_load_round_trip(tmp_path, sphere_scene):
    pts, nrm, prior = sphere_scene
    cfg = concrete(GPConfig(block_size=0.4))
    field = fit_local_gps(pts[:300], nrm[:300], prior, cfg)
    np.savez(tmp_path / "gp.npz", **field.to_arrays())
    with np.load(tmp_path / "gp.npz", allow_pickle=False) as z:
        loaded = LocalGPField.from_arrays(dict(z), prior, cfg)
    q = np.random.default_rng(0).uniform(-1.2, 1.2, size=(500, 3))
    for a, b in zip(field.predict(q, return_grad=True), loaded.predict(q, return_grad=True)):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(GPError, match="fitted with length_scale=0.15, the config has 0.1"):
        LocalGPField.from_arrays(field.to_arrays(), prior, concrete(GPConfig(block_size=0.4,
                                                                    length_scale=0.1)))
    arrays = field.to_arrays()
    del arrays["gp_L"]
    with pytest.raises(GPError, match=r"missing \['gp_L'\]"):
        LocalGPField.from_arrays(arrays, prior, cfg)
    arrays = field.to_arrays()
    arrays["gp_alpha"] = arrays["gp_alpha"][:-1]
    with pytest.raises(GPError, match="inconsistent"):
        LocalGPField.from_arrays(arrays, prior, cfg)
    arrays = field.to_arrays()
    arrays["gp_L"] = arrays["gp_L"][:-1]
    with pytest.raises(GPError, match="inconsistent"):
        LocalGPField.from_arrays(arrays, prior, cfg)


def test_factors_are_stored_packed_and_square_factors_still_load(sphere_scene):
    """The saved factors are the lower triangles packed by rows (half the memory of
    square ones); a map saved with square factors (before packing) loads and predicts
    bitwise the same."""
    pts, nrm, prior = sphere_scene
    cfg = concrete(GPConfig(block_size=0.4))
    field = fit_local_gps(pts[:300], nrm[:300], prior, cfg)
    arrays = field.to_arrays()
    m = 4 * np.diff(arrays["gp_point_ptr"])
    assert len(arrays["gp_L"]) == np.sum(m * (m + 1) // 2)
    assert field.info["cholesky_bytes"] == 8 * len(arrays["gp_L"])
    square = np.concatenate([f.L.ravel() for f in field.blocks])
    for f in field.blocks:                             # unpacked: lower-triangular
        assert np.all(np.triu(f.L, 1) == 0) and np.all(np.diag(f.L) > 0)
    old = LocalGPField.from_arrays(dict(arrays, gp_L=square), prior, cfg)
    np.testing.assert_array_equal(old.to_arrays()["gp_L"], arrays["gp_L"])
    q = np.random.default_rng(1).uniform(-1.2, 1.2, size=(800, 3))
    for a, b in zip(field.predict(q, return_grad=True), old.predict(q, return_grad=True)):
        np.testing.assert_array_equal(a, b)


def test_block_cap_is_seeded_and_reported():
    pts, nrm = sphere(300, r=0.2)
    cfg = concrete(GPConfig(max_block_points=25, block_size=0.2))
    prior = ConstantPrior(0.0, 0.01)
    a = fit_local_gps(pts, nrm, prior, cfg, rng=np.random.default_rng(7))
    b = fit_local_gps(pts, nrm, prior, cfg, rng=np.random.default_rng(7))
    assert a.info["n_capped_blocks"] > 0 and a.info["n_points_dropped_by_cap"] > 0
    assert max(len(blk.X) for blk in a.blocks) == 25
    for x, y in zip(a.blocks, b.blocks):
        np.testing.assert_array_equal(x.X, y.X)


def test_jitter_raised_when_cholesky_fails():
    X = np.zeros((3, 3))                 # three identical points, no noise: singular
    fit = fit_block(X, np.ones(3), np.zeros((3, 4)), 0.1, 0.0, 0.0, 0.0)
    assert fit.jitter_raised >= 1 and fit.jitter > 0
    np.testing.assert_allclose(fit.L @ fit.L.T, matern32_joint(X, X, 0.1)
                               + fit.jitter * np.eye(12), atol=1e-9)


def test_neighbourhood_selection_keeps_a_misfitted_patch_whole_and_unbiased():
    """A plane z = 0 whose prior sits 12 mm behind it on one half (x < 0) and on it on the
    other; hits with 6 mm noise, d_m = 6 mm. Each point's own residual (eq. condition1)
    keeps a truncated sample of the misfitted half (its points lie on the free side: the
    noise that adds to the miss) and noise outliers of the fitted half; the mean over 16
    neighbours keeps the misfitted half whole (its mean offset the data's, about 0) and
    nothing of the fitted half."""
    rng = np.random.default_rng(3)
    n = 4000
    xy = rng.uniform(-1.0, 1.0, size=(n, 2))
    z = 0.006 * rng.normal(size=n)                  # the hits' noise along the normal
    pts = np.c_[xy, z]
    bias = np.where(xy[:, 0] < 0, 0.012, 0.0)       # prior's zero level 12 mm behind
    m = z + bias                                    # prior mean at the hits (free side +)
    own = select_gp_points(m, 0.006)
    near = select_gp_points(neighbourhood_residual(pts, m, 16), 0.006)
    left = xy[:, 0] < -0.1
    right = xy[:, 0] > 0.1
    assert own[left].mean() < 0.9 and own[right].mean() > 0.2
    assert z[own & left].mean() > 0.001            # the truncated sample: free side
    assert near[left].mean() > 0.99 and near[right].mean() < 0.01
    assert abs(z[near & left].mean()) < 0.0005
    np.testing.assert_array_equal(neighbourhood_residual(pts, m, 1), m)
    with pytest.raises(GPError, match="k >= 1"):
        neighbourhood_residual(pts, m, 0)
    with pytest.raises(GPError, match="one prior mean per hit point"):
        neighbourhood_residual(pts, m[:-1], 4)


def test_select_gp_points():
    m = np.array([0.0, 0.03, -0.05, 0.02, -0.01])
    np.testing.assert_array_equal(select_gp_points(m, 0.02), [False, True, True, False, False])
    with pytest.raises(GPError, match="d_m >= 0, found -1"):
        select_gp_points(m, -1.0)
    with pytest.raises(GPError, match="finite prior means, found 1 NaN"):
        select_gp_points(np.array([np.nan, 0.0]), 0.02)
    with pytest.raises(GPError, match=r"shape \(P,\), found \(5, 1\)"):
        select_gp_points(m[:, None], 0.02)


def test_octree_cover_matches_brute_force():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, size=(200, 3))
    grid = BlockGrid.from_points(pts, 0.5, 0.5)
    q = rng.uniform(-1.5, 1.5, size=(400, 3))
    qi, bi = grid.cover(q)
    got = set(zip(qi.tolist(), bi.tolist()))
    dist = np.abs(q[:, None, :] - grid.centres[None]).max(axis=2)
    want = set(zip(*np.nonzero(dist <= grid.half_extent)))
    assert got == {(int(a), int(b)) for a, b in want}
    with pytest.raises(OctreeError, match="positive block_size"):
        BlockGrid.from_points(pts, 0.0, 0.5)
    with pytest.raises(OctreeError, match="overlap >= 0"):
        BlockGrid(np.zeros((1, 3)), 1.0, -0.5)
    with pytest.raises(OctreeError, match="local frame"):
        BlockGrid(np.array([[5_000_000, 0, 0]]), 1.0, 0.5)


def test_octree_cover_hashed_equals_binary_search():
    """cover() looks the blocks up in a hash table: the same (point, block) pairs in
    the same order as the binary search of the sorted keys (``lookup``) it replaced,
    on blocks that share two of three coordinates (a hash of part of the key would
    pile them up), negative cells, cells at the +-2^20 limit and queries beyond it."""
    from gmmgp_app.stages.octree import _BIAS, _find, _hash_table, _hfind, _lookup
    rng = np.random.default_rng(3)
    line = np.c_[np.arange(-300, 300), np.full(600, 7), np.full(600, -2)]     # c0 only
    plane = np.stack(np.meshgrid(np.full(1, 4), np.arange(-20, 20), np.arange(-20, 20),
                                 indexing="ij"), -1).reshape(-1, 3)
    blob = rng.integers(-60, 60, size=(3000, 3))
    edge = np.array([[_BIAS - 1, 0, 0], [-_BIAS, -_BIAS, -_BIAS], [0, _BIAS - 1, -_BIAS]])
    keys = np.unique(np.concatenate([line, plane, blob, edge]), axis=0)
    grid = BlockGrid(keys, 0.5, 0.5)
    tk, tv = _hash_table(grid._packed)
    probe = np.concatenate([keys, rng.integers(-70, 70, size=(4000, 3)),
                            edge + 1, edge - 1, [[_BIAS, 0, 0], [0, -_BIAS - 1, 0]]])
    for c in probe:
        assert _hfind(tk, tv, *c) == _find(grid._packed, *c)
    h = grid.block_size
    q = np.concatenate([(keys[rng.integers(0, len(keys), 5000)] + rng.uniform(-0.3, 1.3, (5000, 3))) * h,
                        (edge + 0.5) * h, [[(_BIAS + 3) * h, 0.0, 0.0]]])
    qi, bi = grid.cover(q)
    half = grid.half_extent
    lo = np.ceil((q - half) / h - 0.5).astype(np.int64)
    hi = np.floor((q + half) / h - 0.5).astype(np.int64)
    pi_old, bi_old = [], []
    for i in range(len(q)):
        cells = np.stack(np.meshgrid(*[np.arange(lo[i, d], hi[i, d] + 1) for d in range(3)],
                                     indexing="ij"), -1).reshape(-1, 3)
        inside = np.all((cells >= -_BIAS) & (cells < _BIAS), axis=1)
        j = np.full(len(cells), -1)
        j[inside] = _lookup(grid._packed, np.ascontiguousarray(cells[inside]))
        j = j[j >= 0]
        pi_old.append(np.full(len(j), i))
        bi_old.append(j)
    pi_old, bi_old = np.concatenate(pi_old), np.concatenate(bi_old)
    o = np.argsort(bi_old, kind="stable")          # by block, then by point
    assert len(qi) > 5000
    assert np.array_equal(qi, pi_old[o]) and np.array_equal(bi, bi_old[o])


def test_octree_lookup_hashed_equals_binary_search():
    """BlockGrid.lookup goes through the hash table that cover() uses (built once): the
    same index as the binary search of the sorted keys (``_lookup``, the oracle) on every
    key, on random cells that mostly miss, next to the keys, and at and beyond the
    +-2^20 limit; the table is built once and shared with cover()."""
    from gmmgp_app.stages.octree import _BIAS, _lookup
    rng = np.random.default_rng(11)
    edge = np.array([[_BIAS - 1, 0, 0], [-_BIAS, -_BIAS, -_BIAS], [0, _BIAS - 1, -_BIAS]])
    keys = np.unique(np.concatenate([rng.integers(-40, 40, size=(5000, 3)),
                                     np.c_[np.arange(-500, 500), np.zeros((1000, 2), int)],
                                     edge]), axis=0)
    grid = BlockGrid(keys, 0.25, 0.5)
    assert grid._table is None
    probe = np.concatenate([keys[rng.permutation(len(keys))],
                            rng.integers(-80, 80, size=(20000, 3)),
                            keys[:3000] + rng.integers(-1, 2, size=(3000, 3)),
                            edge + 1, edge - 1,
                            [[_BIAS, 0, 0], [0, -_BIAS - 1, 0], [0, 0, 5 * _BIAS]]])
    got = grid.lookup(probe)
    want = _lookup(grid._packed, np.ascontiguousarray(probe, dtype=np.int64))
    assert np.array_equal(got, want)
    assert (want < 0).sum() > 15000 and (want >= 0).sum() > len(keys)   # hits and misses
    assert np.array_equal(grid.keys[got[:len(keys)]], probe[:len(keys)])
    table = grid._table
    grid.cover(np.zeros((4, 3)))
    assert grid._table is table                     # one table for lookup and cover
    assert np.array_equal(BlockGrid(keys, 0.25, 0.5).lookup(np.zeros((0, 3))),
                          np.zeros(0, np.int64))


def test_bad_inputs(sphere_scene):
    pts, nrm, prior = sphere_scene
    cfg = concrete(GPConfig())
    with pytest.raises(GPError, match=r"one normal per GP point \(\(10, 3\)\), found \(9, 3\)"):
        fit_local_gps(pts[:10], nrm[:9], prior, cfg)
    with pytest.raises(GPError, match="at least one GP training point, found 0"):
        fit_local_gps(np.zeros((0, 3)), np.zeros((0, 3)), prior, cfg)
    with pytest.raises(GPError, match=r"GP points with shape \(P, 3\), found \(10, 2\)"):
        fit_local_gps(pts[:10, :2], nrm[:10], prior, cfg)
    field = fit_local_gps(pts[:20], nrm[:20], prior, cfg)
    q = np.zeros((3, 3))
    q[2, 0] = np.nan
    with pytest.raises(GPError, match="finite query points, found 1 rows"):
        field.predict(q)
    with pytest.raises(GPError, match="positive variance"):
        ConstantPrior(0.0, 0.0)
    with pytest.raises(GPError, match="positive prior variance at every GP point"):
        fit_local_gps(pts[:5], nrm[:5], _ZeroVar(), cfg)
    with pytest.raises(GPError, match="not positive definite even with relative jitter"):
        fit_block(np.zeros((2, 3)), np.ones(2), np.zeros((2, 4)), 0.1, -10.0, -10.0, 0.0)


class _ZeroVar:
    def predict(self, xyz, return_grad=False):
        n = len(xyz)
        return np.zeros(n), np.zeros(n), np.zeros((n, 3))


def test_compiled_pair_predictor_matches_numpy_block_predictor():
    """_predict_pairs (numba) against predict_block (numpy) on random blocks."""
    from gmmgp_app.stages.gp import _predict_pairs, fit_block, predict_block

    rng = np.random.default_rng(5)
    fits = []
    for n in (1, 4, 9):
        X = rng.uniform(-0.1, 0.1, size=(n, 3))
        sp = rng.uniform(0.01, 0.05, size=n)
        t = rng.normal(scale=0.01, size=(n, 4))
        fits.append(fit_block(X, sp, t, 0.08, 4e-4, 5e-4, 1e-8))
    xs = rng.uniform(-0.15, 0.15, size=(7, 3))
    sig = rng.uniform(0.01, 0.05, size=7)
    qi = np.repeat(np.arange(7), 3)
    bi = np.tile(np.arange(3), 7)
    n = np.array([len(f.X) for f in fits])
    ptr = np.r_[0, np.cumsum(n)]
    loff = np.r_[0, np.cumsum(4 * n * (4 * n + 1) // 2)]     # packed lower triangles
    X = np.concatenate([f.X for f in fits])
    sp = np.concatenate([f.sigma_p for f in fits])
    L = np.concatenate([f.L[np.tril_indices(4 * len(f.X))] for f in fits])
    al = np.concatenate([f.alpha for f in fits])
    a = np.sqrt(3.0) / 0.08
    dm, red, dg = _predict_pairs(xs, sig, qi, bi, ptr, X, sp, L, loff, al, a, True)
    for b, f in enumerate(fits):
        mu, rd, gr = predict_block(f, xs, sig, 0.08, True)
        sel = bi == b
        np.testing.assert_allclose(dm[sel], mu, rtol=1e-10, atol=1e-14)
        np.testing.assert_allclose(red[sel], rd, rtol=1e-10, atol=1e-14)
        np.testing.assert_allclose(dg[sel], gr, rtol=1e-10, atol=1e-14)


def test_value_path_equals_the_pair_predictor(sphere_scene):
    """predict() without gradients solves each block once for all its queries
    (_value_blocks); with gradients it runs the compiled per-pair predictor: same mean
    and variance."""
    pts, nrm, prior = sphere_scene
    field = fit_local_gps(pts[:400], nrm[:400], prior, concrete(GPConfig(block_size=0.3)))
    q = np.random.default_rng(4).uniform(-1.2, 1.2, size=(3000, 3))
    m1, v1 = field.predict(q)
    m2, v2, _ = field.predict(q, return_grad=True)
    assert np.count_nonzero(m1 != prior.predict(q)[0]) > 500   # many queries in blocks
    np.testing.assert_allclose(m1, m2, rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(v1, v2, rtol=1e-10, atol=1e-13)


def _value_blocks_query_by_query(x, sig, qi, bi, starts, ends, ptr, X, sp, L, Loff, alpha, a,
                                 dm, red):
    """The oracle of gp._value_blocks: its kernel before session 8, which filled the
    cross-covariances query by query (the same arithmetic per entry)."""
    for t in range(len(starts)):
        s, e = starts[t], ends[t]
        b = bi[s]
        p0, p1 = ptr[b], ptr[b + 1]
        n4 = 4 * (p1 - p0)
        nq = e - s
        V = np.empty((n4, nq))
        for j in range(nq):
            q = qi[s + j]
            for i in range(p1 - p0):
                d0 = x[q, 0] - X[p0 + i, 0]
                d1 = x[q, 1] - X[p0 + i, 1]
                d2 = x[q, 2] - X[p0 + i, 2]
                r = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
                ex = math.exp(-a * r)
                sc = sig[q] * sp[p0 + i]
                a2e = sc * a * a * ex
                V[4 * i, j] = sc * (1.0 + a * r) * ex
                V[4 * i + 1, j] = a2e * d0
                V[4 * i + 2, j] = a2e * d1
                V[4 * i + 3, j] = a2e * d2
        for j in range(nq):
            mu = 0.0
            for k in range(n4):
                mu += V[k, j] * alpha[4 * p0 + k]
            dm[s + j] = mu
        base = Loff[b]
        acc = np.zeros(nq)
        for r_ in range(n4):
            row = base + r_ * (r_ + 1) // 2
            for c_ in range(r_):
                l = L[row + c_]
                for j in range(nq):
                    V[r_, j] -= l * V[c_, j]
            d = L[row + r_]
            for j in range(nq):
                V[r_, j] /= d
                acc[j] += V[r_, j] * V[r_, j]
        for j in range(nq):
            red[s + j] = acc[j]


def test_value_blocks_equal_the_query_by_query_kernel_bit_for_bit(sphere_scene):
    """The block-wise value kernel (cross-covariances filled point by point over the
    queries) gives the old query-by-query kernel's mean and variance reduction bit for
    bit, with blocks of 1 to many points and 1 to many queries."""
    from numba import njit

    from gmmgp_app.stages.gp import _runs, _value_blocks

    pts, nrm, prior = sphere_scene
    field = fit_local_gps(pts[:400], nrm[:400], prior, concrete(GPConfig(block_size=0.3)))
    rng = np.random.default_rng(8)
    a = math.sqrt(3.0) / field.hyper["length_scale"]
    f = field._flat()
    for n_q in (2500, 7):
        q = rng.uniform(-1.2, 1.2, size=(n_q, 3))
        m, v = prior.predict(q)[:2]
        qi, bi = field.grid.cover(q)
        sig = np.sqrt(np.maximum(v, 0.0)) * rng.uniform(0.5, 2.0, len(q))
        starts, ends = _runs(bi)
        n_pts = np.diff(f["ptr"])[bi[starts]]
        if n_q > 10:
            assert n_pts.min() <= 3 and n_pts.max() >= 10 and (ends - starts).max() >= 50
        else:
            assert len(starts) and (ends - starts).min() == 1
        args = (q, sig, qi, bi, starts, ends, f["ptr"], f["X"], f["sp"], f["L"], f["Loff"],
                f["alpha"], a)
        dm, red = np.empty(len(qi)), np.empty(len(qi))
        _value_blocks(*args, dm, red)
        dm0, red0 = np.empty(len(qi)), np.empty(len(qi))
        njit(_value_blocks_query_by_query)(*args, dm0, red0)
        np.testing.assert_array_equal(dm, dm0)
        np.testing.assert_array_equal(red, red0)


def test_gp_runs_blas_on_one_thread_and_restores_it():
    """Small block solves on a multithreaded BLAS spin on a loaded machine: the GP
    stage limits BLAS to one thread while it runs and restores the setting after."""
    threadpoolctl = pytest.importorskip("threadpoolctl")
    from gmmgp_app.stages._blas import one_blas_thread

    def blas_threads():
        return [i["num_threads"] for i in threadpoolctl.threadpool_info()
                if i["user_api"] == "blas"]

    before = blas_threads()
    with one_blas_thread():
        inside = blas_threads()
    assert inside and all(n == 1 for n in inside)
    assert blas_threads() == before


def test_compiled_block_fitter_matches_numpy_and_lapack():
    """fit_block (compiled kernel + Cholesky + solves) against the joint kernel of
    kernels.py, scaled by the prior and the noise, factorised by LAPACK."""
    from scipy.linalg import cho_solve

    rng = np.random.default_rng(11)
    for n in (1, 5, 30):
        X = rng.uniform(-0.1, 0.1, size=(n, 3))
        sp = rng.uniform(0.01, 0.05, size=n)
        t = rng.normal(scale=0.01, size=(n, 4))
        fit = fit_block(X, sp, t, 0.15, 4e-4, 5e-4, 1e-8)
        s = np.repeat(sp, 4)
        K = matern32_joint(X, X, 0.15) * s[:, None] * s[None, :]
        K[np.diag_indices_from(K)] += np.tile([4e-4, 5e-4, 5e-4, 5e-4], n)
        eps = 1e-8 * np.mean(np.diag(K))
        L = np.linalg.cholesky(K + eps * np.eye(4 * n))
        assert fit.jitter == pytest.approx(eps, rel=1e-12) and fit.jitter_raised == 0
        np.testing.assert_allclose(fit.L, L, rtol=1e-10, atol=1e-15)
        assert np.all(np.triu(fit.L, 1) == 0)
        np.testing.assert_allclose(fit.alpha, cho_solve((L, True), t.reshape(-1)),
                                   rtol=1e-8, atol=1e-12)


def test_blocks_are_made_on_demand_from_the_flat_arrays(sphere_scene):
    """A fitted (and a loaded) field keeps its blocks as the flat arrays (FlatBlocks):
    each BlockFit asked for is the views a list of BlockFits held (same arrays, jitter,
    times raised), and the executor path's list of BlockFits gives the same blocks."""
    from concurrent.futures import ThreadPoolExecutor

    from gmmgp_app.stages.gp import FlatBlocks

    pts, nrm, prior = sphere_scene
    cfg = concrete(GPConfig(block_size=0.4))
    field = fit_local_gps(pts[:300], nrm[:300], prior, cfg)
    assert isinstance(field.blocks, FlatBlocks) and len(field.blocks) > 3
    f = field._flat()
    for i in (0, len(field.blocks) - 1, -1):
        b = field.blocks[i]
        j = i % len(field.blocks)
        s, e = f["ptr"][j], f["ptr"][j + 1]
        assert np.shares_memory(b.L_packed, f["L"]) and np.shares_memory(b.X, f["X"])
        np.testing.assert_array_equal(b.X, f["X"][s:e])
        np.testing.assert_array_equal(b.alpha, f["alpha"][4 * s:4 * e])
    assert [b.jitter for b in field.blocks] == list(field.to_arrays()["gp_jitter"])
    assert len(field.blocks[1:3]) == 2
    with pytest.raises(IndexError):
        field.blocks[len(field.blocks)]
    with ThreadPoolExecutor(1) as ex:
        other = fit_local_gps(pts[:300], nrm[:300], prior, cfg, executor=ex)
    assert isinstance(other.blocks, list)
    for a, b in zip(field.blocks, other.blocks):
        for x, y in ((a.X, b.X), (a.L_packed, b.L_packed), (a.alpha, b.alpha)):
            np.testing.assert_array_equal(x, y)
        assert (a.jitter, a.jitter_raised) == (b.jitter, b.jitter_raised)
    loaded = LocalGPField.from_arrays(field.to_arrays(), prior, cfg)
    assert isinstance(loaded.blocks, FlatBlocks)
    for k, v in field.to_arrays().items():
        np.testing.assert_array_equal(v, loaded.to_arrays()[k])


def test_block_grid_from_points_hashed_equals_unique(monkeypatch):
    """BlockGrid.from_points through the hashed distinct cells gives the keys of the
    np.unique path (its fallback): negative coordinates, points on block borders."""
    from gmmgp_app.stages import _distinct

    rng = np.random.default_rng(9)
    pts = rng.uniform(-6, 6, size=(20000, 3)) * [3, 1, 0.2] + [-30.0, 12.0, 0.0]
    pts[:50] = np.round(pts[:50] / 0.7) * 0.7
    a = BlockGrid.from_points(pts, 0.7, 0.5)
    monkeypatch.setattr(_distinct, "cell_first", lambda p, s: None)
    b = BlockGrid.from_points(pts, 0.7, 0.5)
    np.testing.assert_array_equal(a.keys, b.keys)
    np.testing.assert_array_equal(a._packed, b._packed)
    assert a.n_blocks > 500


def test_capped_selection_is_the_block_by_block_draw():
    """The blocks' training points (capped blocks drawn in block order) are those of the
    loop over every block that fit_local_gps ran before (the oracle here), in order."""
    from gmmgp_app.stages.gp import _runs

    pts, nrm = sphere(400, r=0.2)
    cfg = concrete(GPConfig(max_block_points=25, block_size=0.15))
    field = fit_local_gps(pts, nrm, ConstantPrior(0.0, 0.01), cfg,
                          rng=np.random.default_rng(3))
    grid = BlockGrid.from_points(pts, cfg.block_size, cfg.block_overlap)
    pi, bi = grid.cover(pts)
    rng, sel = np.random.default_rng(3), []
    for s, e in zip(*_runs(bi)):
        idx = pi[s:e]
        if len(idx) > cfg.max_block_points:
            idx = np.sort(rng.choice(idx, cfg.max_block_points, replace=False))
        sel.append(idx)
    assert field.info["n_capped_blocks"] > 2
    np.testing.assert_array_equal(field._flat()["X"], pts[np.concatenate(sel)])
    np.testing.assert_array_equal(np.diff(field._flat()["ptr"]), [len(s) for s in sel])


def test_cholesky_crout_four_rows_at_a_time_is_row_by_row_bit_for_bit():
    """The block fitter's Cholesky (rows below the diagonal four at a time) gives the
    one-row-at-a-time Crout loop exactly, for sizes with every remainder, and reports a
    matrix that is not positive definite."""
    import math

    from gmmgp_app.stages.gp import _cholesky_crout

    def crout_rows(K, ep):
        m = len(K)
        L = np.zeros((m, m))
        for c in range(m):
            for r in range(c, m):
                t = float(K[r, c]) + (ep if r == c else 0.0)
                for k in range(c):
                    t -= float(L[r, k]) * float(L[c, k])
                if r == c:
                    if not t > 0.0:
                        return None
                    L[c, c] = math.sqrt(t)
                else:
                    L[r, c] = t / L[c, c]
        return L

    rng = np.random.default_rng(3)
    for m in (1, 2, 4, 5, 7, 8, 11, 16, 23):
        A = rng.normal(size=(m, m))
        K = A @ A.T + 1e-3 * np.eye(m)
        Lb = np.zeros((m, m))
        assert _cholesky_crout(K, 1e-9, Lb)
        np.testing.assert_array_equal(np.tril(Lb), crout_rows(K, 1e-9))
    assert not _cholesky_crout(-np.eye(6), 0.0, np.zeros((6, 6)))
