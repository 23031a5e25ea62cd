"""The calibrated variance's fit (stages/farfield.py, eqs. calibrated_var and
variance_quantile_fit; issue 15): exact truth from simulated heteroscedastic errors."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from scipy.stats import chi2

from gmmgp_app.stages.farfield import (VARIANCE_COEF, calibrated_variance,
                                       fit_variance_quantile, variance_features)


def _features(rng, n, h=0.05, noise=0.004):
    r = h * rng.uniform(0, 20, n)
    spread2 = (h * rng.uniform(0, 1, n)) ** 2
    d2 = (h * rng.uniform(0, 2, n)) ** 2
    v_gp = h * h * np.exp(rng.uniform(-6, 0, n))
    return h, noise, r, spread2, d2, v_gp


def test_quantile_fit_recovers_a_known_log_linear_variance_and_its_coverage():
    rng = np.random.default_rng(0)
    t_true = np.array([-0.5, -0.3, 1.0, 0.2, 0.15])
    h, noise, r, s2, d2, vg = _features(rng, 6000)
    X = variance_features(h, noise, r, s2, d2, vg)
    v = h * h * np.exp(X @ t_true)
    e = rng.normal(0, np.sqrt(v))
    t = fit_variance_quantile(X, np.log(e ** 2 / h ** 2), 0.68)
    # Gaussian errors: P(e^2 <= c v) = 0.68 with c the chi^2_1 quantile, so only the
    # intercept moves, by log c
    expect = t_true + np.r_[np.log(chi2.ppf(0.68, 1)), 0, 0, 0, 0]
    np.testing.assert_allclose(t, expect, atol=0.12)
    # fresh draws: 68 % within 1 sigma, 95 % within 2 sigma (the errors are Gaussian)
    h, noise, r, s2, d2, vg = _features(rng, 20000)
    X = variance_features(h, noise, r, s2, d2, vg)
    e = rng.normal(0, np.sqrt(h * h * np.exp(X @ t_true)))
    z = np.abs(e) / np.sqrt(h * h * np.exp(X @ t))
    assert abs(np.mean(z <= 1) - 0.68) < 0.015
    assert abs(np.mean(z <= 2) - 0.954) < 0.015


def _contaminated(rng, scale):
    # 90 % N(0, s^2), 10 % N(0, (10 s)^2): a few queries far out, as near unseen geometry
    wide = rng.random(len(scale)) < 0.1
    return scale * rng.normal(size=len(scale)) * np.where(wide, 10.0, 1.0)


def test_quantile_fit_keeps_the_coverage_under_contamination_where_log_least_squares_does_not():
    # least squares on log e^2 + 1.27 (the former fit) matches the mean of log z^2: 10 %
    # of errors 10x wider raise it by 0.1 log 100 = 0.46, i.e. every sigma by 26 % and
    # the coverage to 0.72; the 0.68 quantile keeps 0.68
    rng = np.random.default_rng(1)
    t_true = np.array([0.2, -0.2, 0.8, 0.1, 0.1])
    h, noise, r, s2, d2, vg = _features(rng, 8000)
    X = variance_features(h, noise, r, s2, d2, vg)
    scale = np.sqrt(h * h * np.exp(X @ t_true))
    e = _contaminated(rng, scale)
    y = np.log(e ** 2 / h ** 2)
    t_q = fit_variance_quantile(X, y, 0.68)
    t_ls = np.linalg.lstsq(X, y + 1.27, rcond=None)[0]
    e2 = _contaminated(rng, scale)
    cov = lambda t: np.mean(np.abs(e2) <= np.sqrt(h * h * np.exp(X @ t)))  # noqa: E731
    assert abs(cov(t_q) - 0.68) < 0.02
    assert cov(t_ls) > 0.70


def test_quantile_fit_equals_scikit_learn_quantile_regression():
    sklearn = pytest.importorskip("sklearn.linear_model")
    rng = np.random.default_rng(2)
    X = np.c_[np.ones(400), rng.normal(size=(400, 2))]
    y = X @ [0.3, -1.0, 2.0] + rng.laplace(0, 0.5, 400)
    ours = fit_variance_quantile(X, y, 0.68)
    ref = sklearn.QuantileRegressor(quantile=0.68, alpha=0.0, fit_intercept=False,
                                    solver="highs").fit(X, y).coef_
    # the pinball loss at both (the LP optimum may not be unique; the loss is)
    loss = lambda t: np.sum(np.maximum(0.68 * (y - X @ t), -0.32 * (y - X @ t)))  # noqa: E731
    assert loss(ours) <= loss(ref) + 1e-9
    np.testing.assert_allclose(ours, ref, atol=1e-6)


def test_calibrated_variance_is_the_log_linear_model_plus_kappa_d2_and_scales_with_the_scan():
    rng = np.random.default_rng(3)
    h, noise, r, s2, d2, vg = _features(rng, 50)
    X = variance_features(h, noise, r, s2, d2, vg)
    v = calibrated_variance(h, noise, r, s2, d2, vg, disagreement_weight=0.7)
    np.testing.assert_allclose(v, h * h * np.exp(X @ np.asarray(VARIANCE_COEF)) + 0.7 * d2,
                               rtol=1e-12)
    a = 10.0   # every length x a: the variance x a^2
    va = calibrated_variance(a * h, a * noise, a * r, a * a * s2, a * a * d2, a * a * vg,
                             disagreement_weight=0.7)
    np.testing.assert_allclose(va, a * a * v, rtol=1e-10)


def test_quantile_fit_rejects_bad_input():
    with pytest.raises(ValueError, match="finite features"):
        fit_variance_quantile(np.ones((3, 5)), np.ones(3))
    with pytest.raises(ValueError, match="quantile tau"):
        fit_variance_quantile(np.ones((10, 2)), np.ones(10), 1.5)
    with pytest.raises(ValueError, match="finite features"):
        fit_variance_quantile(np.ones((10, 2)), np.r_[np.ones(9), np.nan])


# ------------------------------------------------------------------ robust far field
def _sphere_hits(rng, n=6000, flip=0.01):
    # the upper half of the unit sphere, exact points; a fraction of normals flipped
    v = rng.normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2])
    p = v / np.linalg.norm(v, axis=1, keepdims=True)
    nrm = p.copy()
    bad = rng.random(n) < flip
    nrm[bad] *= -1
    return p, nrm, bad


def test_robust_imls_drops_flipped_normals_of_a_plane_at_any_distance():
    from gmmgp_app.stages.farfield import FarField

    rng = np.random.default_rng(4)
    p = np.c_[rng.uniform(-2, 2, (8000, 2)), np.zeros(8000)]
    nrm = np.tile([0.0, 0.0, 1.0], (8000, 1))
    nrm[rng.random(8000) < 0.02] *= -1
    q = np.c_[rng.uniform(-0.5, 0.5, (300, 2)), rng.uniform(0.5, 2.0, 300)]
    plain = FarField(p, nrm, 0.03, 0.001).predict(q)[0]
    robust = FarField(p, nrm, 0.03, 0.001, robust_scale=1.0).predict(q)[0]
    # a flipped neighbour moves the plain IMLS by 2 |f| / k; the robust one keeps it at
    # weight exp(-(2 f / rho)^2) ~ exp(-4) (rho ~ r ~ f): within 1 % of the distance
    assert np.sqrt(np.mean((plain - q[:, 2]) ** 2)) > 0.05
    assert np.all(np.abs(robust - q[:, 2]) <= 0.01 * q[:, 2])
    # without flipped normals both are the exact plane distance
    nrm[:] = [0.0, 0.0, 1.0]
    np.testing.assert_allclose(FarField(p, nrm, 0.03, 0.001, robust_scale=1.0).predict(q)[0],
                               q[:, 2], atol=1e-12)


def test_robust_imls_far_from_a_sphere_with_flipped_normals():
    from gmmgp_app.stages.farfield import FarField

    rng = np.random.default_rng(5)
    p, nrm, _ = _sphere_hits(rng)
    d = rng.normal(size=(400, 3))
    d[:, 2] = np.abs(d[:, 2]) + 0.5
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    q = d * rng.uniform(1.5, 3.0, (400, 1))          # 0.5-2 m from the sphere
    truth = np.linalg.norm(q, axis=1) - 1.0
    h = np.sqrt(4 * np.pi / 2 / len(p))               # spacing of the hits
    err = lambda c: FarField(p, nrm, h, 0.001, robust_scale=c).predict(q)[0] - truth  # noqa: E731
    e0, e1 = err(0.0), err(1.0)
    # the plain IMLS is pulled in by the 1 % flipped normals; the robust one is within
    # the curvature error of averaging the tangent planes of a kernel of width ~ r
    assert np.sqrt(np.mean(e0 ** 2)) > 0.02
    assert np.sqrt(np.mean(e1 ** 2)) < 0.01


def test_robust_imls_changes_nothing_within_the_noise_near_the_data():
    from gmmgp_app.stages.farfield import FarField

    rng = np.random.default_rng(6)
    p = np.c_[rng.uniform(-1, 1, (5000, 2)), rng.normal(0, 0.002, 5000)]
    nrm = np.tile([0.0, 0.0, 1.0], (5000, 1))
    q = np.c_[rng.uniform(-0.5, 0.5, (300, 2)), rng.uniform(-0.02, 0.02, 300)]
    a = FarField(p, nrm, 0.03, 0.002).predict(q)[0]
    b = FarField(p, nrm, 0.03, 0.002, robust_scale=1.0).predict(q)[0]
    # residuals ~ noise (2 mm) against a scale of rho = 30 mm: weights change by < 1 %
    assert np.max(np.abs(a - b)) < 2e-4


def test_saved_maps_keep_their_variance_coefficients(tmp_path, monkeypatch):
    """A map saves eq. calibrated_var's coefficients (map.json) and predicts with them
    after a refit of the library's (here: VARIANCE_COEF's intercept raised by 1, i.e.
    the observed-surface variance x e); a map built in memory follows the refit; a map
    saved before the coefficients were saved loads with the session-6 fit, whatever
    the library's present one."""
    import json
    import warnings

    import gmmgp_app as gm
    from gmmgp_app.stages import farfield as F
    from gmmgp_app.types import Scan

    rng = np.random.default_rng(3)
    xy = rng.uniform(-1.5, 1.5, (3000, 2))
    scan = Scan(np.c_[xy, rng.normal(0.0, 0.003, 3000)],
                origins=np.tile([0.0, 0.0, 3.0], (3000, 1)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        # the plane vote of raw points, whose coefficients are VARIANCE_COEF (the
        # default before session 13)
        smap = gm.build_map(scan, gm.MappingConfig().with_overrides(
            ["far.vote=plane", "far.leave_self_out=0", "far.split_half=false"]))
    q = np.c_[rng.uniform(-1, 1, (400, 2)), rng.uniform(0.01, 0.3, 400)]
    m, v = smap.predict(q)
    plain = ~smap.distribution(q).mixed  # no unseen width: v is eq. calibrated_var
    assert plain.mean() > 0.5
    smap.save(tmp_path / "a")
    meta = json.loads((tmp_path / "a" / "map.json").read_text())
    assert meta["variance_coef"] == list(VARIANCE_COEF)
    del meta["variance_coef"]
    shutil.copytree(tmp_path / "a", tmp_path / "old")
    (tmp_path / "old" / "map.json").write_text(json.dumps(meta))

    refit = (VARIANCE_COEF[0] + 1.0,) + tuple(VARIANCE_COEF[1:])
    monkeypatch.setattr(F, "VARIANCE_COEF", refit)
    nm, nv = smap.predict(q)  # built in memory: the library's (refitted) coefficients
    np.testing.assert_array_equal(nm, m)
    # v = h^2 exp(X t) + kappa d^2 -> nv = e h^2 exp(X t) + kappa d^2: v < nv <= e v
    assert np.all(nv[plain] > v[plain]) and np.all(nv[plain] <= np.e * v[plain] * (1 + 1e-12))
    for name in ("a", "old"):
        loaded = gm.load_map(tmp_path / name)
        lm, lv = loaded.predict(q)
        np.testing.assert_array_equal(lm, m)
        np.testing.assert_array_equal(lv, v)
    assert gm.load_map(tmp_path / "old").variance_coef == F.variance_coef_unsaved("growth")
