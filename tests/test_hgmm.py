"""Tests of the EM kernels, flat EM and the hierarchical GMM (stages/hgmm.py)."""

import dataclasses

import numpy as np
import pytest
from scipy.special import logsumexp
from scipy.stats import multivariate_normal

from gmmgp_app.config import HGMMConfig
from gmmgp_app.stages import em_kernels as ek
from gmmgp_app.stages.hgmm import (
    HGMMError,
    complexity,
    fit_gmm,
    fit_hgmm,
    format_level_history,
    hgmm_diagnostics,
    predict_labels,
    score,
    score_groups,
    score_samples,
)
from gmmgp_app.types import GaussianMixture


# ------------------------------------------------------------------ fixtures
def random_mixture(rng, K=3, D=4, scale=5.0):
    means = rng.normal(scale=scale, size=(K, D))
    A = rng.normal(size=(K, D, D))
    covs = np.einsum("kij,klj->kil", A, A) + 0.3 * np.eye(D)
    w = rng.uniform(0.5, 1.5, K)
    return GaussianMixture(w / w.sum(), means, covs)


def sample_mixture(gm, n, rng):
    counts = rng.multinomial(n, gm.weights)
    X = np.concatenate([rng.multivariate_normal(gm.means[k], gm.covariances[k], size=c)
                        for k, c in enumerate(counts)])
    return X[rng.permutation(len(X))]


def np_weighted_log_prob(X, gm):
    return np.stack([np.log(gm.weights[k]) + multivariate_normal(
        gm.means[k], gm.covariances[k]).logpdf(X) for k in range(gm.n_components)], axis=1)


def np_mstep(X, resp, reg):
    nk = resp.sum(0) + 10 * np.finfo(float).eps
    means = resp.T @ X / nk[:, None]
    covs = np.stack([(resp[:, k, None] * (X - means[k])).T @ (X - means[k]) / nk[k]
                     + reg * np.eye(X.shape[1]) for k in range(resp.shape[1])])
    return nk / nk.sum(), means, covs


def terms(gm):
    K, D = gm.means.shape
    P, lc = np.empty((K, D, D)), np.empty(K)
    assert ek.component_terms(gm.weights, gm.covariances, P, lc) == -1
    return P, lc


def plane_rows(rng, n=600, s=0.25, size=4.0, noise=0.002):
    """4D rows of a noisy planar patch z = 0 with virtual points at +-s."""
    p = np.c_[rng.uniform(0, size, (n, 2)), rng.normal(scale=noise, size=n)]
    nrm = np.tile([0.0, 0.0, 1.0], (n, 1))
    return np.concatenate([np.c_[p, np.zeros(n)], np.c_[p + s * nrm, np.full(n, s)],
                           np.c_[p - s * nrm, np.full(n, -s)]])


def corner_rows(rng, n=600, s=0.25, size=2.0):
    """4D rows of the three faces of a box corner (outside of the octant x,y,z <= 0)."""
    out = []
    for ax in range(3):
        p = -rng.uniform(0, size, (n, 3))
        p[:, ax] = 0.0
        nrm = np.zeros((n, 3))
        nrm[:, ax] = 1.0
        out += [np.c_[p, np.zeros(n)], np.c_[p + s * nrm, np.full(n, s)],
                np.c_[p - s * nrm, np.full(n, -s)]]
    return np.concatenate(out)


# ------------------------------------------------------------------- kernels
def test_weighted_log_prob_and_loglik_match_scipy():
    rng = np.random.default_rng(0)
    gm = random_mixture(rng)
    X = sample_mixture(gm, 5000, rng)
    P, lc = terms(gm)
    ref = np_weighted_log_prob(X, gm)
    np.testing.assert_allclose(ek.weighted_log_prob(X, gm.means, P, lc), ref, rtol=1e-10,
                               atol=1e-10)
    np.testing.assert_allclose(ek.log_likelihood(X, gm.means, P, lc), logsumexp(ref, axis=1),
                               rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(score_samples(gm, X), logsumexp(ref, axis=1), rtol=1e-10)
    assert score(gm, X) == pytest.approx(logsumexp(ref, axis=1).mean(), rel=1e-12)
    np.testing.assert_array_equal(ek.assign(X, gm.means, P, lc), ref.argmax(1))
    np.testing.assert_array_equal(predict_labels(gm, X), ref.argmax(1))


def test_cholesky_and_precision_factor_match_numpy():
    rng = np.random.default_rng(1)
    gm = random_mixture(rng, K=4)
    P, lc = terms(gm)
    for k in range(4):
        L = np.linalg.cholesky(gm.covariances[k])
        np.testing.assert_allclose(P[k], np.linalg.inv(L), rtol=1e-10, atol=1e-12)
        ref = np.log(gm.weights[k]) - 2 * np.log(2 * np.pi) - np.log(np.diag(L)).sum()
        assert lc[k] == pytest.approx(ref, rel=1e-12)
    bad = gm.covariances.copy()
    bad[2] = -np.eye(4)
    assert ek.component_terms(gm.weights, bad, P, lc) == 2


def test_mstep_from_resp_matches_numpy():
    rng = np.random.default_rng(2)
    X = rng.normal(size=(3000, 4)) * [10, 10, 3, 0.2] + [50, -20, 5, 0]
    resp = rng.dirichlet(np.ones(5), size=len(X))
    for a, b in zip(ek.mstep_from_resp(X, resp, 1e-6), np_mstep(X, resp, 1e-6)):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)


def test_fused_em_step_matches_numpy_e_then_m():
    """One iteration of the numba loop (shifted statistics, responsibility floor)
    equals a numpy E-step followed by the numpy M-step."""
    rng = np.random.default_rng(3)
    gm = random_mixture(rng, K=4)
    X = sample_mixture(gm, 4000, rng) + [100.0, 200.0, 0.0, 0.0]  # far from the origin
    gm = GaussianMixture(gm.weights, gm.means + [100.0, 200.0, 0.0, 0.0], gm.covariances)
    lr = np_weighted_log_prob(X, gm)
    resp = np.exp(lr - logsumexp(lr, axis=1, keepdims=True))
    w_ref, m_ref, c_ref = np_mstep(X, resp, 1e-6)
    w, m, c = gm.weights.copy(), gm.means.copy(), gm.covariances.copy()
    n_iter, conv, status, bad, lb, worst = ek.em_loop(X, w, m, c, 1, 0.0, 1e-6, 1.0)
    assert (n_iter, status) == (1, 0)
    assert lb == pytest.approx(logsumexp(lr, axis=1).mean(), rel=1e-12)
    assert worst == np.argmin(logsumexp(lr, axis=1))
    np.testing.assert_allclose(w, w_ref, rtol=1e-9)
    np.testing.assert_allclose(m, m_ref, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(c, c_ref, rtol=1e-8, atol=1e-10)


def test_parallel_accumulate_equals_serial():
    rng = np.random.default_rng(4)
    gm = random_mixture(rng, K=3)
    X = sample_mixture(gm, 3 * ek.CHUNK + 17, rng)
    P, lc = terms(gm)
    a = ek.accumulate(X, gm.means, P, lc, False)
    b = ek.accumulate(X, gm.means, P, lc, True)
    for x, y in zip(a, b):
        np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-12)


def np_kmeanspp(X, K, u):
    idx = [min(int(u[0] * len(X)), len(X) - 1)]
    d2 = ((X - X[idx[0]]) ** 2).sum(1)
    for c in range(1, K):
        cs = np.cumsum(d2)
        i = int(np.flatnonzero((cs > u[c] * cs[-1]) & (d2 > 0))[0])
        idx.append(i)
        d2 = np.minimum(d2, ((X - X[i]) ** 2).sum(1))
    return np.array(idx)


def test_kmeanspp_matches_numpy_and_stops_on_duplicates():
    rng = np.random.default_rng(5)
    X = rng.normal(size=(500, 4))
    u = rng.random(8)
    np.testing.assert_array_equal(ek.kmeanspp(X, 8, u), np_kmeanspp(X, 8, u))
    two = np.repeat(np.array([[0.0, 0, 0, 0], [1.0, 1, 1, 1]]), 50, axis=0)
    idx = ek.kmeanspp(two, 5, u[:5])
    assert len(idx) == 2 and len(np.unique(two[idx], axis=0)) == 2


# ------------------------------------------------------------------- flat EM
def test_em_recovers_known_mixture():
    rng = np.random.default_rng(6)
    truth = random_mixture(rng, K=3, scale=8.0)
    X = sample_mixture(truth, 30000, rng)
    gm, info = fit_gmm(X, 3, rng=np.random.default_rng(0), tol=1e-8, max_iter=500)
    assert info["converged"] and not info["reseeded"] and not info["dropped"]
    order = [int(np.argmin(((gm.means - m) ** 2).sum(1))) for m in truth.means]
    assert sorted(order) == [0, 1, 2]
    np.testing.assert_allclose(gm.weights[order], truth.weights, atol=0.01)
    np.testing.assert_allclose(gm.means[order], truth.means, atol=0.1)
    np.testing.assert_allclose(gm.covariances[order], truth.covariances, rtol=0.1, atol=0.15)


def test_em_matches_sklearn_from_same_initialisation():
    sk = pytest.importorskip("sklearn.mixture")
    rng = np.random.default_rng(7)
    truth = random_mixture(rng, K=4, scale=3.0)  # overlapping: many iterations
    X = sample_mixture(truth, 4000, rng)
    init, _ = fit_gmm(X, 4, rng=np.random.default_rng(1), max_iter=1)
    for max_iter, tol in ((30, 0.0), (200, 1e-5)):
        gm, info = fit_gmm(X, 4, init=init, max_iter=max_iter, tol=tol, reg_covar=1e-4)
        ref = sk.GaussianMixture(
            4, covariance_type="full", weights_init=init.weights, means_init=init.means,
            precisions_init=np.linalg.inv(init.covariances), reg_covar=1e-4,
            max_iter=max_iter, tol=tol).fit(X)
        assert info["n_iter"] == ref.n_iter_
        np.testing.assert_allclose(gm.weights, ref.weights_, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(gm.means, ref.means_, rtol=1e-8, atol=1e-8)
        np.testing.assert_allclose(gm.covariances, ref.covariances_, rtol=1e-7, atol=1e-9)
        assert score(gm, X) == pytest.approx(ref.score(X), rel=1e-10)


def test_empty_component_is_reseeded_or_dropped_and_reported():
    rng = np.random.default_rng(8)
    X = np.concatenate([rng.normal(size=(500, 4)), rng.normal(size=(500, 4)) + 10.0])
    # Third component far from every row: it gets no responsibility at all.
    init = GaussianMixture(np.full(3, 1 / 3), np.array([[0.0] * 4, [10.0] * 4, [1e3] * 4]),
                           np.tile(np.eye(4), (3, 1, 1)))
    gm, info = fit_gmm(X, 3, init=init, on_empty="reseed")
    assert info["reseeded"] and info["reseeded"][0][1] == 2
    assert gm.n_components == 3 and np.isfinite(gm.covariances).all()
    assert np.isfinite(score(gm, X))
    gm, info = fit_gmm(X, 3, init=init, on_empty="drop")
    assert info["dropped"] == [(0, 2)] and gm.n_components == 2
    assert gm.weights.sum() == pytest.approx(1.0)


def test_degenerate_covariance_never_gives_nan():
    # Rows on a 2-D subspace of 4-D with reg_covar 0: covariances are singular.
    rng = np.random.default_rng(9)
    X = np.c_[rng.normal(size=(400, 2)), np.zeros((400, 2))]
    with pytest.raises(HGMMError, match="not positive definite|degenerate"):
        fit_gmm(X, 2, reg_covar=0.0, rng=np.random.default_rng(0), on_empty="drop")
    gm, _ = fit_gmm(X, 2, reg_covar=1e-6, rng=np.random.default_rng(0))
    assert np.isfinite(score_samples(gm, X)).all()


@pytest.mark.parametrize("bad, match", [
    (np.zeros((3, 4)) + np.arange(3)[:, None], "at least 4 rows"),
    (np.ones((50, 4)), "identical"),
    (np.r_[np.random.default_rng(0).normal(size=(50, 4)), [[np.nan, 0, 0, 0]]], "NaN"),
    (np.arange(10.0), "2-D array"),
])
def test_bad_rows_raise(bad, match):
    with pytest.raises(HGMMError, match=match):
        fit_gmm(bad, 4)
    with pytest.raises(HGMMError, match=match):
        fit_hgmm(bad, HGMMConfig())


def test_bad_arguments_raise():
    X = np.random.default_rng(0).normal(size=(100, 4))
    with pytest.raises(HGMMError, match="on_empty"):
        fit_gmm(X, 2, on_empty="ignore")
    with pytest.raises(HGMMError, match="init means"):
        fit_gmm(X, 2, init=np.zeros((3, 4)))
    with pytest.raises(HGMMError, match="init 'kmeans"):
        fit_gmm(X, 2, init="random")
    with pytest.raises(HGMMError, match="n_components >= 1"):
        fit_gmm(X, 0)
    gm = GaussianMixture(np.ones(1), np.zeros((1, 4)), -np.eye(4)[None])
    with pytest.raises(HGMMError, match="not positive definite"):
        score_samples(gm, X)
    with pytest.raises(HGMMError, match="columns"):
        score_samples(GaussianMixture(np.ones(1), np.zeros((1, 3)), np.eye(3)[None]), X)
    with pytest.raises(HGMMError, match=r"shape \(K, D, D\)"):
        complexity(np.zeros((2, 3, 4)))


# ---------------------------------------------------------------- complexity
def test_complexity_known_values():
    assert complexity(np.eye(4)) == pytest.approx(0.25)
    assert complexity(np.diag([1.0, 1, 1, 0])) == pytest.approx(0.0)
    assert complexity(np.diag([4.0, 3, 2, 1])) == pytest.approx(0.1)
    R = np.linalg.qr(np.random.default_rng(0).normal(size=(4, 4)))[0]
    rotated = R @ np.diag([4.0, 3, 2, 1]) @ R.T
    np.testing.assert_allclose(complexity(np.stack([rotated, np.eye(4) * 7])), [0.1, 0.25])
    # Correlation form: per-axis scale does not matter, flatness does.
    S = np.diag([100.0, 10.0, 1.0, 0.1])
    assert complexity(S @ np.eye(4) @ S, normalize=True) == pytest.approx(0.25)
    assert complexity(S @ np.eye(4) @ S) < 1e-5
    flat = S @ np.diag([1.0, 1, 1, 0]) @ S
    assert complexity(flat, normalize=True) == pytest.approx(0.0, abs=1e-12)


# ----------------------------------------------------------------- hierarchy
def test_plane_does_not_split_but_corner_does():
    rng = np.random.default_rng(10)
    cfg = HGMMConfig(initial_components=1, split_threshold=0.01, min_rows=64)
    h = fit_hgmm(plane_rows(rng), cfg)
    assert len(h.levels) == 1 and h.leaves.n_components == 1
    assert h.levels[0].complexity[0] < 1e-3
    h = fit_hgmm(corner_rows(rng), cfg)
    assert h.levels[0].complexity[0] > 0.01 and h.levels[0].split[0]
    assert len(h.levels) >= 2 and h.leaves.n_components > 1


def test_hierarchy_bookkeeping():
    rng = np.random.default_rng(11)
    rows = corner_rows(rng, n=1500)
    h = fit_hgmm(rows, HGMMConfig(initial_components=2, split_threshold=0.005, max_levels=4))
    assert h.leaves.weights.sum() == pytest.approx(1.0, abs=1e-12)
    assert len(h.leaf_level) == h.leaves.n_components
    assert h.levels[0].n_rows.sum() == len(rows)
    for lev in range(1, len(h.levels)):
        prev, cur = h.levels[lev - 1], h.levels[lev]
        assert set(cur.parent) == set(np.flatnonzero(prev.split))
        for j in np.flatnonzero(prev.split):
            kids = cur.parent == j
            # Children's global weights are the parent's times the local ones.
            assert cur.mixture.weights[kids].sum() == pytest.approx(prev.mixture.weights[j])
            assert cur.n_rows[kids].sum() == prev.n_rows[j]
    # Leaves are exactly the unsplit nodes of all levels.
    n_unsplit = sum(int((~lv.split).sum()) for lv in h.levels)
    assert n_unsplit == h.leaves.n_components
    assert not h.levels[-1].split.any()
    assert len(h.levels) <= 4


def test_same_seed_same_result_bitwise():
    rows = corner_rows(np.random.default_rng(12), n=800)
    cfg = HGMMConfig(split_threshold=0.005)
    a, b = fit_hgmm(rows, cfg), fit_hgmm(rows, cfg)
    for x, y in zip((a.leaves.weights, a.leaves.means, a.leaves.covariances),
                    (b.leaves.weights, b.leaves.means, b.leaves.covariances)):
        assert np.array_equal(x, y)
    c = fit_hgmm(rows, HGMMConfig(split_threshold=0.005, seed=3))
    assert c.leaves.n_components != a.leaves.n_components or not np.array_equal(
        c.leaves.means, a.leaves.means)


def test_split_max_std_tiles_large_flat_nodes():
    rows = plane_rows(np.random.default_rng(13), n=3000, size=20.0)
    flat = fit_hgmm(rows, HGMMConfig(initial_components=1))
    assert flat.leaves.n_components == 1  # c alone: a plane is one Gaussian
    h = fit_hgmm(rows, HGMMConfig(initial_components=1, split_max_std=2.0))
    sd = np.sqrt(np.linalg.eigvalsh(h.leaves.covariances[:, :3, :3])[:, -1])
    n_rows = np.concatenate([lv.n_rows[~lv.split] for lv in h.levels])
    # Every leaf is small enough, or could not be split further.
    assert np.all((sd <= 2.0) | (n_rows < 64))
    assert h.leaves.n_components >= 20


def test_diagnostics_and_level_table():
    rng = np.random.default_rng(14)
    rows = corner_rows(rng, n=1000)
    h = fit_hgmm(rows, HGMMConfig(split_threshold=0.005))
    d = hgmm_diagnostics(h, rows[:500])
    assert d["n_leaves"] == h.leaves.n_components == sum(d["leaves_per_level"])
    assert d["nodes_per_level"][0] == 4
    assert d["heldout_mean_loglik"] == pytest.approx(score(h.leaves, rows[:500]))
    q = list(d["leaf_complexity_quantiles"].values())
    assert q == sorted(q)
    table = format_level_history(h)
    assert table.splitlines()[0].split()[:4] == ["level", "nodes", "split", "leaves"]
    assert len(table.splitlines()) == 2 + len(h.levels) + 1


# ------------------------------------------------------------------ tied EM
def np_tied_responsibilities(X, gptr, gm, group_weights):
    """Group responsibilities by brute force: log pi_k + sum of row log N (scipy)."""
    lp = np_weighted_log_prob(X, GaussianMixture(np.full(gm.n_components, 1.0 / gm.n_components),
                                                 gm.means, gm.covariances))
    lp -= np.log(1.0 / gm.n_components)  # plain log N(x | k)
    G = len(gptr) - 1
    lg = np.stack([lp[gptr[g]:gptr[g + 1]].sum(0) for g in range(G)]) + np.log(group_weights)
    return np.exp(lg - logsumexp(lg, axis=1, keepdims=True)), logsumexp(lg, axis=1)


def random_groups(rng, X, max_size=3):
    """Rows of X cut into consecutive groups of 1..max_size rows: (X, group_ptr)."""
    sizes = rng.integers(1, max_size + 1, size=len(X) // 2)
    gptr = np.concatenate([[0], np.cumsum(sizes)])
    gptr = gptr[gptr <= len(X)]
    return np.ascontiguousarray(X[:gptr[-1]]), gptr


def test_tied_e_step_matches_numpy_reference():
    rng = np.random.default_rng(7)
    gm = random_mixture(rng, K=4)
    X, gptr = random_groups(rng, sample_mixture(gm, 300, rng))
    gw = rng.dirichlet(np.ones(4))
    P, lc = terms(GaussianMixture(gw, gm.means, gm.covariances))
    nk, gk, sx, sxx, ll, worst, worst_i = ek.accumulate_groups(X, gptr, gm.means, P, lc,
                                                               np.log(gw))
    resp_g, ll_g = np_tied_responsibilities(X, gptr, gm, gw)
    resp_rows = np.repeat(resp_g, np.diff(gptr), axis=0)
    np.testing.assert_allclose(gk, resp_g.sum(0), rtol=1e-10)
    np.testing.assert_allclose(nk, resp_rows.sum(0), rtol=1e-10)
    np.testing.assert_allclose(ll, ll_g.sum(), rtol=1e-12)
    np.testing.assert_allclose(sx, np.einsum("nk,nkd->kd", resp_rows,
                                             X[:, None, :] - gm.means[None]), atol=1e-9)
    np.testing.assert_allclose(ek.group_log_likelihood(X, gptr, gm.means, P, lc, np.log(gw)),
                               ll_g, rtol=1e-12)
    assert worst_i == gptr[np.argmin(ll_g)]
    np.testing.assert_array_equal(ek.assign_groups(X, gptr, gm.means, P, lc, np.log(gw)),
                                  resp_g.argmax(1))


def test_tied_em_with_singleton_groups_is_plain_em():
    rng = np.random.default_rng(3)
    gm = random_mixture(rng, K=3)
    X = sample_mixture(gm, 900, rng)
    init = GaussianMixture(gm.weights, gm.means + 0.5, gm.covariances)
    a, ia = fit_gmm(X, 3, init=init, max_iter=30, tol=0.0)
    b, ib = fit_gmm(X, 3, init=init, max_iter=30, tol=0.0,
                    group_ptr=np.arange(len(X) + 1))
    np.testing.assert_allclose(b.means, a.means, atol=1e-10)
    np.testing.assert_allclose(b.covariances, a.covariances, atol=1e-10)
    np.testing.assert_allclose(b.weights, a.weights, atol=1e-10)
    np.testing.assert_allclose(ib["lower_bound"], ia["lower_bound"], rtol=1e-12)


def test_tied_em_lower_bound_never_decreases():
    rng = np.random.default_rng(5)
    gm = random_mixture(rng, K=3, scale=1.5)
    X = sample_mixture(gm, 600, rng)
    gptr = np.arange(0, 601, 3)
    bounds = [fit_gmm(X, 3, init=GaussianMixture(np.full(3, 1 / 3), gm.means[::-1].copy(),
                                                 gm.covariances), max_iter=it, tol=0.0,
                      group_ptr=gptr)[1]["lower_bound"] for it in range(1, 15)]
    assert np.all(np.diff(bounds) >= -1e-12), bounds


def sphere_triplets(rng, n=1500, radius=1.0, s=0.25, noise=0.002):
    """Rows of a unit sphere: hits (d = 0) and virtual points at +-s, one group per hit."""
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    p = radius * u + noise * rng.normal(size=(n, 1)) * u
    rows = np.concatenate([np.c_[p, np.zeros(n)], np.c_[p + s * u, np.full(n, s)],
                           np.c_[p - s * u, np.full(n, -s)]])
    return rows, np.tile(np.arange(n), 3)


def test_tied_hierarchy_keeps_every_leaf_across_the_surface():
    """Untied EM puts the three sheets of a 1 m sphere into separate leaves (d constant, so
    a zero SDF gradient); tied EM never does: every leaf spans d = -s .. +s."""
    rows, groups = sphere_triplets(np.random.default_rng(0))
    cfg = HGMMConfig(split_threshold=0.01)
    free = fit_hgmm(rows, cfg)
    tied = fit_hgmm(rows, cfg, groups=groups)
    sd_d = lambda h: np.sqrt(h.leaves.covariances[:, 3, 3])  # noqa: E731
    assert free.leaves.weights[sd_d(free) < 0.05].sum() > 0.3
    assert np.all(sd_d(tied) > 0.15)
    assert tied.info["tied_groups"] == 1500
    np.testing.assert_allclose(tied.leaves.weights.sum(), 1.0)
    # rows of one hit point never end up in different children of a split
    assert fit_hgmm(rows, cfg, groups=groups).leaves.means.tobytes() == \
        tied.leaves.means.tobytes()


def test_bad_groups_raise():
    rows, groups = sphere_triplets(np.random.default_rng(0), n=50)
    with pytest.raises(HGMMError, match="Expected groups as"):
        fit_hgmm(rows, HGMMConfig(), groups=groups[:-1])
    with pytest.raises(HGMMError, match="Expected group_ptr"):
        fit_gmm(rows, 2, group_ptr=np.array([0, 5, 3, len(rows)]))


def test_score_groups_matches_brute_force_and_reduces_to_score():
    """The tied (observation) likelihood: groups in any order, against scipy; with
    one row per group it is the plain mean row log-likelihood."""
    rng = np.random.default_rng(11)
    gm = random_mixture(rng, K=3)
    X, gptr = random_groups(rng, sample_mixture(gm, 240, rng))
    groups = np.repeat(np.arange(len(gptr) - 1), np.diff(gptr))
    gw = rng.dirichlet(np.ones(3))
    _, ll_g = np_tied_responsibilities(X, gptr, gm, gw)
    shuffle = rng.permutation(len(X))
    got = score_groups(gm, X[shuffle], groups[shuffle] * 7 + 3, group_weights=gw)
    np.testing.assert_allclose(got, ll_g.sum() / len(X), rtol=1e-12)
    np.testing.assert_allclose(score_groups(gm, X, np.arange(len(X))), score(gm, X),
                               rtol=1e-12)
    with pytest.raises(HGMMError, match="Expected groups as"):
        score_groups(gm, X, groups[:-1])


def test_tied_hierarchy_reports_leaf_group_weights():
    rows, groups = sphere_triplets(np.random.default_rng(2), n=400)
    h = fit_hgmm(rows, HGMMConfig(), groups=groups)
    gw = h.info["leaf_group_weights"]
    assert gw.shape == (h.leaves.n_components,) and np.all(gw > 0)
    np.testing.assert_allclose(gw.sum(), 1.0, rtol=1e-12)
    # every group here has three rows: fractions of groups ~ fractions of rows
    np.testing.assert_allclose(gw, h.leaves.weights, atol=0.02)
    assert fit_hgmm(rows, HGMMConfig()).info["leaf_group_weights"] is None


def test_fit_hgmm_takes_a_training_set_and_ties_its_groups():
    from gmmgp_app.config import MappingConfig
    from gmmgp_app.stages.prepare import prepare
    from gmmgp_app.synth import scan_scene

    scan, _ = scan_scene("box", density=0.03)
    cfg = MappingConfig()
    data = prepare(scan, cfg)
    h = fit_hgmm(data, cfg.hgmm)
    ref = fit_hgmm(data.rows, cfg.hgmm, groups=data.groups)
    assert h.info["tied_groups"] == len(data.points)
    np.testing.assert_array_equal(h.leaves.means, ref.leaves.means)
    assert fit_hgmm(data.rows, cfg.hgmm).info["tied_groups"] is None
    with pytest.raises(HGMMError, match="found both"):
        fit_hgmm(data, cfg.hgmm, groups=data.groups)
    d = hgmm_diagnostics(h, data.rows, data.groups)
    assert d["heldout_observation_loglik"] == pytest.approx(score_groups(
        h.leaves, data.rows, data.groups, h.info["leaf_group_weights"]))
    # a hit point and its virtual points share one component: counted once, the
    # observation likelihood per row is above the row marginal
    assert d["heldout_observation_loglik"] > d["heldout_mean_loglik"]


# ----------------------------------------------------------------- node-fit cache
def _assert_same_hierarchy(a, b):
    """Bitwise the same levels, leaves and fit statistics (timings aside)."""
    assert len(a.levels) == len(b.levels)
    for x, y in zip(a.levels, b.levels):
        for f in ("weights", "means", "covariances"):
            assert getattr(x.mixture, f).tobytes() == getattr(y.mixture, f).tobytes()
        for f in ("parent", "complexity", "split", "n_rows"):
            assert getattr(x, f).tobytes() == getattr(y, f).tobytes()
    for f in ("weights", "means", "covariances"):
        assert getattr(a.leaves, f).tobytes() == getattr(b.leaves, f).tobytes()
    assert a.leaf_level.tobytes() == b.leaf_level.tobytes()
    drop = ("fit_seconds",)
    assert repr({k: v for k, v in a.info.items() if k not in drop}) == \
        repr({k: v for k, v in b.info.items() if k not in drop})


@pytest.mark.parametrize("tied", [False, True])
def test_cached_refit_after_threshold_changes_equals_a_fresh_fit(tied):
    """A node's fit depends on its rows and place only, so a cache of node fits kept
    across threshold changes gives bitwise the hierarchy a fresh fit gives, and fits
    only the nodes never split before."""
    from gmmgp_app.stages.hgmm import HGMMFitCache

    rows, groups = sphere_triplets(np.random.default_rng(5), n=1200)
    kw = dict(groups=groups) if tied else {}
    cache = HGMMFitCache()
    base = HGMMConfig(split_threshold=0.02, min_rows=32)
    seen = {}
    for t in (0.02, 0.05, 0.005, 0.05, 0.02, 0.002):
        cfg = dataclasses.replace(base, split_threshold=t)
        before = cache.misses
        got = fit_hgmm(rows, cfg, cache=cache, **kw)
        fresh = fit_hgmm(rows, cfg, **kw)
        _assert_same_hierarchy(got, fresh)
        fitted = cache.misses - before
        n_fits = sum(s["n_fits"] for s in fresh.info["level_fits"])
        if t == 0.02 and not seen:
            assert fitted == n_fits   # an empty cache fits every node
        if t == 0.05 or t in seen:
            assert fitted == 0        # a higher or a known threshold splits known nodes
        seen[t] = fresh.leaves.n_components
    assert seen[0.002] > seen[0.005] > seen[0.02] > seen[0.05]  # the thresholds matter
    assert cache.hits > 0 and len(cache) == cache.misses


def test_fit_cache_empties_on_other_rows_or_fit_settings():
    from gmmgp_app.stages.hgmm import HGMMFitCache

    rows, _ = sphere_triplets(np.random.default_rng(6), n=600)
    cache = HGMMFitCache()
    cfg = HGMMConfig(split_threshold=0.01, min_rows=32)
    fit_hgmm(rows, cfg, cache=cache)
    n = len(cache)
    assert n > 1
    # the decision fields keep the fits; other rows, seeds or children counts do not
    fit_hgmm(rows, dataclasses.replace(cfg, split_threshold=0.03, max_levels=3), cache=cache)
    assert len(cache) == n
    for other_rows, other in ((rows[::-1].copy(), cfg), (rows, dataclasses.replace(cfg, seed=1)),
                              (rows, dataclasses.replace(cfg, n_children=4))):
        before = cache.misses
        _assert_same_hierarchy(fit_hgmm(other_rows, other, cache=cache),
                               fit_hgmm(other_rows, other))
        assert len(cache) == cache.misses - before > 0  # emptied, then filled again
    with pytest.raises(HGMMError, match="either rng= or cache="):
        fit_hgmm(rows, cfg, cache=cache, rng=np.random.default_rng(0))


# ------------------------------------------- session 8: skipped exps, parallel tied E-step
def _group_lp_loops(X, a, b, means, P, lc, logw) -> list:
    """Per component, the tied group log-density of rows ``a:b`` (``-(b - a - 1) log w_k``
    plus each row's ``log N``), plain Python loops in the kernel's order of operations."""
    K, D = means.shape
    lp = [-(b - a - 1) * logw[k] for k in range(K)]
    for n in range(a, b):
        for k in range(K):
            maha = 0.0
            for i in range(D):
                y = 0.0
                for j in range(i + 1):
                    y += P[k, i, j] * (X[n, j] - means[k, j])
                maha += y * y
            lp[k] += lc[k] - 0.5 * maha
    return lp


def _tied_e_step_loops(X, gptr, means, P, lc, logw):
    """The tied E-step as the serial kernel computed it before exps were skipped:
    every exp taken (also those that underflow), plain Python loops in the kernel's
    order of operations; the oracle of the kernels' bits."""
    import math

    G, (K, D) = len(gptr) - 1, means.shape
    nk, gk = np.zeros(K), np.zeros(K)
    sx, sxx = np.zeros((K, D)), np.zeros((K, D, D))
    ll, worst, worst_i = 0.0, np.inf, -1
    for g in range(G):
        a, b = int(gptr[g]), int(gptr[g + 1])
        lp = _group_lp_loops(X, a, b, means, P, lc, logw)
        m = max(lp)
        s = 0.0
        for k in range(K):
            s += math.exp(lp[k] - m)
        lse = m + math.log(s)
        ll += lse
        if lse < worst:
            worst, worst_i = lse, a
        for k in range(K):
            r = math.exp(lp[k] - lse)
            if r < ek.RESP_FLOOR:
                continue
            gk[k] += r
            nk[k] += r * (b - a)
            for n in range(a, b):
                diff = [X[n, i] - means[k, i] for i in range(D)]
                for i in range(D):
                    sx[k, i] += r * diff[i]
                for i in range(D):
                    ri = r * diff[i]
                    for j in range(i + 1):
                        sxx[k, i, j] += ri * diff[j]
    return nk, gk, sx, sxx, ll, worst, worst_i


def _separated_groups(rng, K, D, n=400):
    """Rows of K separated, thin components cut into groups of 1-3 rows: log-
    responsibilities below -746, between -746 and -28, and above."""
    gm = random_mixture(rng, K=K, D=D)
    spread = np.geomspace(0.2, 10.0, K)[:, None]        # near and far pairs of components
    gm = GaussianMixture(gm.weights, rng.normal(size=(K, D)) * spread, gm.covariances * 0.05)
    X, gptr = random_groups(rng, sample_mixture(gm, n, rng))
    gw = rng.dirichlet(np.ones(K))
    P, lc = terms(GaussianMixture(gw, gm.means, gm.covariances))
    return X, gptr, gm.means, P, lc, np.log(gw)


@pytest.mark.parametrize("D", [4, 3])
def test_tied_e_step_skipping_exps_is_bit_for_bit(D):
    """Skipping exp(t) for t < -28 (under RESP_FLOOR) and t < -746 (exactly 0) changes no
    bit of the E-step: serial and parallel kernels against the loops taking every exp."""
    rng = np.random.default_rng(20 + D)
    args = _separated_groups(rng, K=5, D=D)
    X, gptr, means, P, lc, logw = args
    lp = np.stack([lc[k] - 0.5 * (np.einsum("ij,nj->ni", P[k], X - means[k]) ** 2).sum(1)
                   for k in range(5)], 1)
    t = lp - lp.max(1, keepdims=True)          # rows' t, a proxy of the groups'
    assert (t < -746).sum() > 50 and ((t >= -746) & (t < -28)).sum() > 50 \
        and ((t >= -28) & (t < 0)).sum() > 20       # both skips happen, and exps
    ref = _tied_e_step_loops(*args)
    G, K = len(gptr) - 1, len(means)
    for got in (ek.accumulate_groups(*args),
                ek.accumulate_groups_parallel(*args, np.empty((K, G)), np.empty(G))):
        for x, y in zip(got[:4], ref[:4]):
            np.testing.assert_array_equal(np.tril(x) if x.ndim == 3 else x,
                                          np.tril(y) if y.ndim == 3 else y)
        assert got[4:] == ref[4:]


def _lse_loop(v):
    """Log-sum-exp taking every exp in order (the kernels' order of operations)."""
    import math

    m = max(v, key=lambda x: -math.inf if math.isnan(x) else x)
    if m == -math.inf:
        return m
    s = 0.0
    for x in v:
        t = x - m
        s += math.exp(t) if not math.isnan(t) else math.nan
    return m + math.log(s) if not math.isnan(s) else math.nan


def test_lse_skipping_absorbed_exps_is_the_loop_bit_for_bit():
    """_lse (exps under 2^-53 of a sum >= 1 not taken, nor those before the largest
    term when they all are tiny, exp(0) = 1) gives the loop taking every exp exactly:
    random vectors with terms in every range, ties, and the edge values."""
    import math

    rng = np.random.default_rng(5)
    cases = []
    for K in (1, 2, 3, 4, 8, 9, 64, 65, 80):
        for _ in range(400):
            v = rng.choice([0.0, -1e-3, -0.7, -3.0, -20.0, -30.0, -36.9, -37.1, -40.0,
                            -41.9, -42.1, -45.0, -200.0, -745.5, -746.5, -1e4], size=K)
            v = v + rng.normal(scale=rng.choice([0.0, 1e-9, 0.5, 5.0]), size=K)
            cases.append(v + rng.normal() * 100.0)
    near = [0.0] + [-(37.0 + 1e-12)] * 7 + [-(42.0 + 1e-12)] * 3
    cases += [np.array(near), np.array(near[::-1]), np.array([-42.1] * 63 + [0.0]),
              np.array([-41.9, 0.0, -41.9]), np.array([-50.0, 0.0, 0.0, -50.0]),
              np.array([-np.inf, -np.inf]), np.array([-np.inf, 1.0, -np.inf]),
              np.array([np.nan, 0.0, -50.0]), np.array([-50.0, 0.0, np.nan]),
              np.array([np.inf, 0.0]), np.array([-50.0, np.inf]), np.array([0.0, -0.0])]
    for v in cases:
        got, want = ek._lse(np.asarray(v, dtype=np.float64)), _lse_loop([float(x) for x in v])
        assert (math.isnan(got) and math.isnan(want)) or got == want, v


@pytest.mark.parametrize("D", [4, 3])
def test_group_log_likelihood_and_labels_are_the_loops_bit_for_bit(D):
    """group_log_likelihood and assign_groups (the D = 4 path reads each component once
    per group) give the oracle loops' per-group log-sum-exp and argmax exactly."""
    import math

    rng = np.random.default_rng(40 + D)
    X, gptr, means, P, lc, logw = _separated_groups(rng, K=5, D=D)
    want_ll, want_lab = [], []
    for g in range(len(gptr) - 1):
        lp = _group_lp_loops(X, int(gptr[g]), int(gptr[g + 1]), means, P, lc, logw)
        m = max(lp)
        want_ll.append(m + math.log(sum(math.exp(v - m) for v in lp)))
        want_lab.append(int(np.argmax(lp)))
    np.testing.assert_array_equal(ek.group_log_likelihood(X, gptr, means, P, lc, logw),
                                  want_ll)
    np.testing.assert_array_equal(ek.assign_groups(X, gptr, means, P, lc, logw), want_lab)


@pytest.mark.parametrize("D", [4, 2])
def test_parallel_tied_em_equals_serial_bit_for_bit(D):
    """em_loop_groups(parallel=True) (phase 1 on chunks of groups, phase 2 by statistic)
    gives the serial fit exactly, D = 4 (the registers' path) and another D."""
    rng = np.random.default_rng(30 + D)
    gm = random_mixture(rng, K=4, D=D, scale=2.0)
    X, gptr = random_groups(rng, sample_mixture(gm, 3 * ek.GROUP_CHUNK * 2 + 11, rng))
    init = GaussianMixture(np.full(4, 0.25), gm.means + 0.3, gm.covariances)
    out = []
    for parallel in (False, True):
        w, m, c = init.weights.copy(), init.means.copy(), init.covariances.copy()
        res = ek.em_loop_groups(X, gptr, w, m, c, 25, 0.0, 1e-6, 1.0, parallel)
        out.append((res, w, m, c))
    assert out[0][0] == out[1][0] and out[0][0][0] == 25
    for a, b in zip(out[0][1:], out[1][1:]):
        np.testing.assert_array_equal(a, b)


def test_hierarchy_with_wide_fits_equals_pooled_fits(monkeypatch):
    """Fits run wide (E-step on numba's threads, one at a time) or whole in the pool of
    threads: the same hierarchy bit for bit."""
    import gmmgp_app.stages.hgmm as hg

    rows, groups = sphere_triplets(np.random.default_rng(2), n=1200)
    cfg = HGMMConfig(split_threshold=0.01)
    monkeypatch.setattr(hg, "_numba_threads", lambda: 2)
    monkeypatch.setattr(hg, "_WIDE_GROUPS", 10 ** 9)
    pooled = fit_hgmm(rows, cfg, groups=groups)
    calls = []
    real = hg.fit_gmm
    monkeypatch.setattr(hg, "fit_gmm", lambda *a, **k: calls.append(k["parallel"])
                        or real(*a, **k))
    monkeypatch.setattr(hg, "_WIDE_GROUPS", 16)
    default_rule = fit_hgmm(rows, cfg, groups=groups)
    assert calls[0] and not any(calls[1:])   # the first level's fit; then similar sizes
    calls.clear()
    import itertools

    flip = itertools.cycle([True, False])
    monkeypatch.setattr(hg, "_wide", lambda n, level, threads: next(flip))
    wide = fit_hgmm(rows, cfg, groups=groups)
    assert 1 < sum(calls) < len(calls)          # wide and pooled fits mixed in levels
    for h in (default_rule, wide):
        for a, b in ((pooled.leaves.means, h.leaves.means),
                     (pooled.leaves.covariances, h.leaves.covariances),
                     (pooled.leaves.weights, h.leaves.weights),
                     (pooled.info["leaf_group_weights"], h.info["leaf_group_weights"])):
            np.testing.assert_array_equal(a, b)
