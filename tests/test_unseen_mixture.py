"""The predictive where the scan cannot see (stages/unseen.py, eq. unseen_mixture):
against its closed form, quadrature and sampling from its own generative model, and
the coverage behind a wall of unknown thickness (exact slab SDF)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate
from scipy.stats import norm
from scipy.stats import t as t_dist

import json
import warnings

import gmmgp_app as gm
from gmmgp_app.stages.farfield import behind_width
from gmmgp_app.stages.unseen import ONE_SIGMA, UnseenMixture, component_scale, unseen_prior
from gmmgp_app.types import Scan


def draws(m, s, wb, we, lam, n, rng):
    """Errors drawn from eq. unseen_mixture's generative reading: the observed-surface
    Gaussian, plus with probability q an unseen error of variance w^2 / 3 (Gaussian)."""
    e = rng.normal(scale=s, size=n)
    w2 = wb * wb + we * we
    if w2 > 0:
        on = rng.uniform(size=n) < unseen_prior(lam)
        e[on] += rng.normal(scale=math.sqrt(w2 / 3.0), size=on.sum())
    return e


CASES = [  # mean, s, w_behind, w_extent
    (-0.30, 0.02, 0.48, 0.0),     # behind a seen face
    (0.25, 0.01, 0.0, 0.30),      # past the end of the data, in front
    (-0.20, 0.03, 0.30, 0.10),    # both
    (0.10, 0.05, 0.0, 1e-9),      # a width far below s: the Gaussian
]


@pytest.mark.parametrize("m,s,wb,we", CASES)
def test_log_density_is_the_two_gaussian_mixture_and_integrates_to_one(m, s, wb, we):
    lam = 0.15
    q = unseen_prior(lam)
    mix = UnseenMixture(np.full(7, m), s * s, wb, we, lam)
    y = m + np.array([-6 * s, -s, 0.0, 0.5 * s, 0.1, wb + we, 3 * (wb + we) + 8 * s])
    su = math.sqrt(s * s + (wb * wb + we * we) / 3.0)
    want = np.log((1 - q) * norm.pdf(y, m, s) + q * norm.pdf(y, m, su))
    np.testing.assert_allclose(mix.logpdf(y), want, rtol=1e-12)
    tot, _ = integrate.quad(lambda t: math.exp(mix.logpdf(np.full(7, t))[0]),
                            m - 12 * su, m + 12 * su, limit=400, points=[m])
    assert abs(tot - 1.0) < 1e-8


@pytest.mark.parametrize("m,s,wb,we", CASES)
def test_half_width_is_the_central_quantile_of_draws_from_the_model(m, s, wb, we):
    lam = 0.15
    rng = np.random.default_rng(3)
    n = 400_000
    e = draws(m, s, wb, we, lam, n, rng)
    mix = UnseenMixture(np.array([m]), s * s, wb, we, lam)
    for level in (0.3, ONE_SIGMA, 0.9, 0.954):
        h = mix.half_width(level)[0]
        # the model's own mass within h is the level (bisection)
        assert abs(mix.central_mass(np.array([h]))[0] - level) < 1e-9
        # and draws from the generative model agree within the Monte-Carlo error
        assert abs(np.mean(np.abs(e) <= h) - level) < 4 * math.sqrt(level * (1 - level) / n)
    # the unseen part widens sigma beyond s, never beyond the wide component's
    assert s * (1 - 1e-12) <= mix.std[0] <= math.sqrt(s * s + (wb * wb + we * we) / 3) + 1e-15


def test_without_unseen_width_it_is_the_gaussian():
    rng = np.random.default_rng(0)
    m, v, y = rng.normal(size=50), rng.uniform(1e-4, 1e-2, 50), rng.normal(size=50)
    mix = UnseenMixture(m, v, np.zeros(50), np.zeros(50), 0.15)
    np.testing.assert_allclose(mix.std, np.sqrt(v), rtol=1e-12)
    np.testing.assert_allclose(mix.logpdf(y), norm.logpdf(y, m, np.sqrt(v)), rtol=1e-12)
    np.testing.assert_allclose(mix.half_width(0.954), np.sqrt(v) * norm.ppf(0.977),
                               rtol=1e-12)
    # lambda 0: the Gaussian whatever the widths
    g = UnseenMixture(m, v, np.ones(50), np.ones(50), 0.0)
    np.testing.assert_allclose(g.logpdf(y), norm.logpdf(y, m, np.sqrt(v)), rtol=1e-12)
    with pytest.raises(ValueError, match="level"):
        mix.half_width(1.0)


def test_coverage_and_likelihood_behind_walls_of_unknown_thickness():
    """Queries at depth x behind a face seen from one side (x = 0, seen from x < 0): the
    wall is solid (5 m) with probability p = 1 - 3 lambda^2, otherwise of a thickness
    uniform in [t_min, 2 x] (then the error is uniform over the design's interval
    [0, 2 x - t_min]); exact slab SDF. The map's mean is -x with a Gaussian error of 1 cm.
    The mixture's central 68.27 % / 95.45 % intervals cover as much of the truths and its
    log-likelihood beats the moment-matched Gaussian of eq. unseen_var by far."""
    rng = np.random.default_rng(1)
    n, s, t_min, lam = 60_000, 0.01, 0.04, 0.15
    x = rng.uniform(0.05, 0.5, n)
    thin = rng.uniform(size=n) < unseen_prior(lam)
    t = np.where(thin, rng.uniform(t_min, 2 * x), 5.0)
    y = np.where(x > t, x - t, -np.minimum(x, t - x))       # exact slab SDF
    m = -x + rng.normal(scale=s, size=n)                     # the map's mean, noisy
    wb = behind_width(m, t_min)
    mix = UnseenMixture(m, s * s, wb, 0.0, lam)
    z = np.abs(y - m) / mix.std
    assert abs(np.mean(z <= 1) - ONE_SIGMA) < 0.02
    # the central 95.45 % interval (a Gaussian's 2 sigma) holds 95.45 %; twice the
    # 68 % half-width holds less (0.93 p): the error is not Gaussian
    two = math.erf(2.0 / math.sqrt(2.0))
    assert abs(np.mean(np.abs(y - m) <= mix.half_width(two)) - two) < 0.02
    assert 0.88 < np.mean(z <= 2) < two - 0.02
    v_gauss = s * s + (lam * wb) ** 2
    ll_gauss = norm.logpdf(y, m, np.sqrt(v_gauss))
    assert mix.logpdf(y).mean() > ll_gauss.mean() + 1.0
    # the thin walls are not overconfident: inside the design's interval the log density
    # is at least that of the unseen component at its edge (|z| = sqrt 3), about
    # log(q / w) - 0.6, where eq. unseen_var's Gaussian falls off as -z^2 / 2
    inside = thin & (y - m > 0) & (y - m < wb)
    vu = s * s + wb[inside] ** 2 / 3.0
    floor = np.log(unseen_prior(lam)) - 0.5 * np.log(2 * np.pi * vu) - 0.5 * wb[inside] ** 2 / vu
    assert np.all(mix.logpdf(y)[inside] > floor)
    assert mix.logpdf(y)[thin].mean() > ll_gauss[thin].mean()


def _wall_scan():
    # a 0.1 m wall (0 <= x <= 0.1, |y| <= 1, 0 <= z <= 2) seen from x = -3 only
    rng = np.random.default_rng(7)
    n = 4000
    yz = rng.uniform([-1.0, 0.0], [1.0, 2.0], (n, 2))
    return Scan(np.c_[rng.normal(0.0, 0.002, n), yz], origins=np.tile([-3.0, 0.0, 1.0], (n, 1)))


def test_map_behind_a_thin_wall_and_old_maps_load_with_the_gaussian(tmp_path):
    """The default map (eq. unseen_mixture) behind a 0.1 m wall seen from one side: the
    truth (exact slab SDF, free space behind the wall: every query is a 'thin wall' one)
    is far likelier than under eq. unseen_var; in front nothing changes; predict reports
    the mixture's 68.27 % half-width; a saved map round-trips, and a map saved before the
    mixture (no far.unseen_predictive in its config) loads with the Gaussian."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        smap = gm.build_map(_wall_scan())
    assert smap.config.far.unseen_predictive == "mixture"
    rng = np.random.default_rng(8)
    k = 400
    qb = np.c_[rng.uniform(0.1, 0.5, k), rng.uniform(-0.4, 0.4, k), rng.uniform(0.6, 1.4, k)]
    qf = np.c_[rng.uniform(-0.5, -0.01, k), rng.uniform(-0.4, 0.4, k), rng.uniform(0.6, 1.4, k)]
    yb = np.where(qb[:, 0] > 0.1, qb[:, 0] - 0.1, -np.minimum(qb[:, 0], 0.1 - qb[:, 0]))
    yf = -qf[:, 0]
    mix_b, mix_f = smap.distribution(qb), smap.distribution(qf)
    mb, vb = smap.predict(qb)
    np.testing.assert_array_equal(mb, mix_b.mean)
    np.testing.assert_allclose(vb, mix_b.std ** 2, rtol=1e-12)
    gauss = gm.pipeline.SurfaceMap(smap.method, smap.config.with_overrides(
        ["far.unseen_predictive=gaussian"]), smap.offset, smap.prior, hgmm=smap.hgmm,
        gp=smap.gp, gp_points=smap.gp_points, gp_normals=smap.gp_normals,
        seed_points=smap.seed_points, far=smap.far)
    gb, gvb = gauss.predict(qb)
    np.testing.assert_array_equal(gb, mb)                      # the mean is unchanged
    ll_gauss = norm.logpdf(yb, gb, np.sqrt(gvb))
    assert np.all(mix_b.mixed)
    assert mix_b.logpdf(yb).mean() > ll_gauss.mean() + 2.0
    # in observed free space the predictive is the same Gaussian for most queries
    gf, gvf = gauss.predict(qf)
    same = ~mix_f.mixed                     # both unseen widths zero: the Gaussian
    assert np.mean(same) > 0.5
    # (the others face a gap in the scan: a small extent width) and the std barely moves
    assert np.mean(np.isclose(mix_f.std, np.sqrt(gvf), rtol=0.05)) > 0.8
    np.testing.assert_allclose(mix_f.var[same], gvf[same], rtol=1e-12)
    # (the map's components: Student-t with nu = far.predictive_dof and the Gaussian's
    # 68.27 % half-width, eq. unseen_mixture_t; Gaussian at nu = 0)
    nu = smap.config.far.predictive_dof
    want = t_dist.logpdf(yf, nu, gf, np.sqrt(gvf) / component_scale(nu)) if nu > 0 \
        else norm.logpdf(yf, gf, np.sqrt(gvf))
    np.testing.assert_allclose(mix_f.logpdf(yf)[same], want[same], rtol=1e-9)
    # save / load: identical predictive; an old map's config loads as the Gaussian
    smap.save(tmp_path / "new")
    new = gm.load_map(tmp_path / "new")
    np.testing.assert_array_equal(new.distribution(qb).logpdf(yb), mix_b.logpdf(yb))
    smap.save(tmp_path / "old")
    meta_path = tmp_path / "old" / "map.json"
    meta = json.loads(meta_path.read_text())
    toml = meta["config_toml"]
    assert 'unseen_predictive = "mixture"' in toml
    meta["config_toml"] = "\n".join(l for l in toml.splitlines() if "unseen_predictive" not in l)
    meta_path.write_text(json.dumps(meta))
    old = gm.load_map(tmp_path / "old")
    assert old.config.far.unseen_predictive == "gaussian"
    ob, ovb = old.predict(qb)
    np.testing.assert_array_equal(ob, gb)
    np.testing.assert_allclose(ovb, gvb, rtol=1e-12)


def test_evaluation_scores_the_predictive_distribution():
    """binned_metrics / reliability with a predictive distribution: its log density, its
    std and its central 95.45 % interval; the Gaussian case equals the Gaussian path; on
    truths drawn from the mixture every reliability level is met."""
    from gmmgp_app.evaluation import TWO_SIGMA, binned_metrics, reliability

    rng = np.random.default_rng(5)
    n, lam = 60_000, 0.15
    m = rng.normal(size=n)
    s = rng.uniform(0.005, 0.02, n)
    wb = np.where(rng.uniform(size=n) < 0.5, rng.uniform(0.1, 0.5, n), 0.0)
    e = rng.normal(scale=s)
    on = (wb > 0) & (rng.uniform(size=n) < unseen_prior(lam))
    e[on] += rng.normal(scale=wb[on] / math.sqrt(3.0))
    y, dist = m + e, rng.uniform(0.0, 0.3, n)
    bins = (0.0, 0.1, 0.3)
    mix = UnseenMixture(m, s * s, wb, 0.0, lam)
    res = binned_metrics(mix.mean, mix.var, y, dist, bins, distribution=mix)
    sel = dist < 0.1
    ll = mix.logpdf(y)
    assert res["ll_sdf"][0] == pytest.approx(ll[sel].mean(), rel=1e-12)
    assert res["ll_edf"][0] == pytest.approx(np.logaddexp(
        mix.logpdf(np.abs(y)), mix.logpdf(-np.abs(y)))[sel].mean(), rel=1e-12)
    err = np.abs(y - m)
    assert res["cov1_sdf"][0] == pytest.approx(np.mean(err[sel] <= mix.std[sel]))
    assert res["cov2_sdf"][0] == pytest.approx(np.mean(err[sel] <= mix.half_width(TWO_SIGMA)[sel]))
    assert res["cov2sig_sdf"][0] == pytest.approx(np.mean(err[sel] <= 2 * mix.std[sel]))
    # calibrated by construction: within the Monte-Carlo error at every level
    rel = reliability(y, mix.mean, mix.var, distribution=mix)
    for p, o in zip(rel["expected"], rel["observed"]):
        assert abs(o - p) < 4 * math.sqrt(p * (1 - p) / n), (p, o)
    # without unseen widths the distribution is the Gaussian: the same numbers
    g = UnseenMixture(m, s * s)
    a = binned_metrics(m, s * s, y, dist, bins)
    b = binned_metrics(m, s * s, y, dist, bins, distribution=g)
    for key in ("ll_sdf", "ll_edf", "cov1_sdf", "cov2_sdf"):
        np.testing.assert_allclose(b[key], a[key], rtol=1e-9)
    np.testing.assert_allclose(reliability(y, m, s * s, distribution=g)["observed"],
                               reliability(y, m, s * s)["observed"], atol=1e-12)


def test_stitched_predictive_is_the_weighted_mixture_of_its_parts():
    """StitchedPredictive (a tiled map's predictive): queries in one part are that
    part's UnseenMixture exactly; queries in several are sum_t w_t p_t / W, whose log
    density matches scipy's normal densities and whose central half-widths hold the
    level (quadrature of the density) about the given mean, also for far-apart tile
    means (a plateau of the central mass, where Newton's steps leave the bracket)."""
    from gmmgp_app.stages.unseen import StitchedPredictive

    rng = np.random.default_rng(11)
    K = 60
    a = UnseenMixture(rng.normal(0, 0.3, K), rng.uniform(1e-4, 4e-2, K),
                      rng.uniform(0, 1, K) * (rng.uniform(size=K) < 0.6), None, 0.3)
    b = UnseenMixture(a.mean + rng.normal(0, 0.5, K), rng.uniform(1e-4, 1e-3, K),
                      None, rng.uniform(0, 2, K) * (rng.uniform(size=K) < 0.6), 0.2)
    wa = rng.uniform(0.05, 1.0, K)
    blend = np.arange(K) >= 20
    rows_b = np.flatnonzero(blend)
    W = wa.copy()
    W[rows_b] += 1 - wa[rows_b]
    mean = np.where(blend, (wa * a.mean + (1 - wa) * b.mean) / W, a.mean)
    w_b = np.sqrt(3 * (b.var_unseen - b.var_observed))  # b's widths again
    b_sub = UnseenMixture(b.mean[rows_b], b.var_observed[rows_b], None, w_b[rows_b], 0.2)
    parts = [(np.arange(K), wa, a), (rows_b, 1 - wa[rows_b], b_sub)]
    var = rng.uniform(0.01, 0.1, K)
    d = StitchedPredictive(mean, var, parts, W)
    y = mean + rng.normal(0, 0.3, K)
    one = ~blend
    np.testing.assert_array_equal(d.logpdf(y)[one], a.logpdf(y)[one])
    np.testing.assert_array_equal(d.half_width(0.8)[one], a.half_width(0.8)[one])
    assert np.array_equal(d.std, np.sqrt(var)) and np.array_equal(d.mean, mean)

    def pdf(i, x):
        out = 0.0
        for w, m in ((wa[i] / W[i], a), ((1 - wa[i]) / W[i], b)):
            out += w * ((1 - m.q[i]) * norm.pdf(x, m.mean[i], math.sqrt(m.var_observed[i]))
                        + m.q[i] * norm.pdf(x, m.mean[i], math.sqrt(m.var_unseen[i])))
        return out

    lp = d.logpdf(y)
    for level in (0.2, ONE_SIGMA, 0.99):
        hw = d.half_width(level)
        for i in rows_b:
            assert lp[i] == pytest.approx(math.log(pdf(i, y[i])), rel=1e-12, abs=1e-12)
            brk = [x for x in (a.mean[i], b.mean[i]) if abs(x - mean[i]) < hw[i]]
            mass = integrate.quad(lambda x: pdf(i, x), mean[i] - hw[i], mean[i] + hw[i],
                                  points=brk or None, epsabs=1e-13, epsrel=1e-12,
                                  limit=200)[0]
            assert mass == pytest.approx(level, abs=1e-9)
    with pytest.raises(ValueError, match="in at least one part"):
        StitchedPredictive(mean, var, [parts[1]], W)
