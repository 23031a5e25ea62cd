"""The map's mean: the GP field and the far field mixed by their calibrated error
variances and error correlation (stages/farfield.py, eqs. field_var, field_var_fit,
blend_correlated, error_correlation_fit): against draws from the model they assume,
the exact signed distance of a plane, and maps saved before the change."""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest

import gmmgp_app as gm
from gmmgp_app.stages import farfield as F
from gmmgp_app.types import Scan


def test_blend_correlated_is_the_best_convex_mix_of_correlated_draws():
    """Two estimates of y = 0 with errors of variances v1, v2 and correlation rho: the
    weight of eq. blend_correlated minimises the mixed error's variance over every
    convex weight (grid), its var is that variance (Monte Carlo), rho = 0 is eq. blend's
    inverse-variance weight, and at rho >= sqrt(v2 / v1) the better estimate alone."""
    rng = np.random.default_rng(0)
    n = 400_000
    for v1, v2, rho in ((4e-4, 1e-4, 0.3), (1e-4, 1e-4, 0.7), (2e-4, 3e-4, -0.2),
                        (1e-3, 1e-4, 0.5)):
        L = np.linalg.cholesky([[v1, rho * math.sqrt(v1 * v2)], [rho * math.sqrt(v1 * v2), v2]])
        e = rng.normal(size=(n, 2)) @ L.T
        m, var = F.blend_correlated(e[:, 0], np.full(n, v1), e[:, 1], np.full(n, v2), rho)
        grid = np.linspace(0, 1, 201)
        mse = [np.mean((w * e[:, 0] + (1 - w) * e[:, 1]) ** 2) for w in grid]
        w_best = grid[int(np.argmin(mse))]
        w = (m[0] - e[0, 1]) / (e[0, 0] - e[0, 1])
        assert abs(w - w_best) <= 0.02
        assert abs(np.mean(m ** 2) / var[0] - 1.0) < 0.01
        if rho >= math.sqrt(v2 / v1):
            np.testing.assert_array_equal(m, e[:, 1])
    # rho = 0: the inverse-variance weight of eq. blend (same mean)
    m1, m2 = rng.normal(size=50), rng.normal(size=50)
    v1, v2 = rng.uniform(0.1, 2, 50), rng.uniform(0.1, 2, 50)
    g1, g2 = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    a = F.blend_correlated(m1, v1, m2, v2, 0.0, g1, g2)
    b = F.blend_fields(m1, v1, m2, v2, g1, g2)
    np.testing.assert_allclose(a[0], b[0], rtol=1e-13)
    np.testing.assert_allclose(a[2], b[2], rtol=1e-13)
    np.testing.assert_allclose(a[1], v1 * v2 / (v1 + v2), rtol=1e-13)


def test_blend_correlated_infinite_variance_and_bad_rho():
    m, v = F.blend_correlated(np.array([1.0, 2.0, 3.0]), np.array([np.inf, 1.0, np.inf]),
                              np.array([5.0, 6.0, 7.0]), np.array([1.0, np.inf, np.inf]), 0.6,
                              np.ones((3, 3)), 2 * np.ones((3, 3)))[:2]
    np.testing.assert_array_equal(m, [5.0, 2.0, 7.0])
    np.testing.assert_array_equal(v, [1.0, 1.0, np.inf])
    with pytest.raises(F.FarFieldError, match="correlation"):
        F.blend_correlated(np.zeros(2), np.ones(2), np.zeros(2), np.ones(2), 1.0)


def test_field_variance_fit_recovers_a_known_model_and_rho():
    """Eq. field_var_fit on errors drawn from N(0, h^2 exp(X u)) recovers u; eq.
    error_correlation_fit recovers rho from their standardised values."""
    rng = np.random.default_rng(1)
    n, h = 200_000, 0.05
    r = rng.uniform(0, 1, n)
    s2 = rng.uniform(0, 1e-3, n)
    d2 = rng.uniform(0, 1e-2, n)
    v_own = rng.uniform(1e-5, 1e-2, n)
    X = F.variance_features(h, 0.005, r, s2, d2, v_own)
    u = np.array([0.3, -0.4, 0.5, 0.2, 0.6])
    v = F.field_variance(h, 0.005, r, s2, d2, v_own, u)
    np.testing.assert_allclose(v, h * h * np.exp(X @ u), rtol=1e-12)
    e = rng.normal(size=n) * np.sqrt(v)
    got = F.fit_field_variance(X, e * e / h ** 2)
    np.testing.assert_allclose(got, u, atol=0.03)
    z = rng.normal(size=(n, 2)) @ np.linalg.cholesky([[1, 0.66], [0.66, 1]]).T
    assert abs(F.fit_error_correlation(z[:, 0], z[:, 1]) - 0.66) < 0.005
    with pytest.raises(ValueError, match="squared errors"):
        F.fit_field_variance(X[:3], np.ones(3))


def test_field_variance_scales_with_the_scan():
    """Every feature is a ratio of lengths: a scan scaled by a scales eq. field_var by
    a^2 (so the weights of eq. blend_correlated do not change)."""
    rng = np.random.default_rng(2)
    r, s2, d2, v = (rng.uniform(0, 1, 20), rng.uniform(0, 1e-3, 20), rng.uniform(0, 1e-2, 20),
                    rng.uniform(1e-5, 1e-2, 20))
    for coef in F.FIELD_VAR_COEF.values():
        base = F.field_variance(0.05, 0.005, r, s2, d2, v, coef)
        for a in (10.0, 0.1):
            np.testing.assert_allclose(
                F.field_variance(0.05 * a, 0.005 * a, r * a, s2 * a * a, d2 * a * a, v * a * a,
                                 coef), base * a * a, rtol=1e-10)
    assert np.all(np.isinf(F.field_variance(0.05, 0.005, r[:2], s2[:2], d2[:2],
                                            np.array([np.inf, np.inf]), coef)))


def _plane_scan(n=3000, seed=4):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-1.5, 1.5, (n, 2))
    return Scan(np.c_[xy, rng.normal(0.0, 0.003, n)], origins=np.tile([0.0, 0.0, 3.0], (n, 1)))


def test_map_of_a_plane_and_maps_saved_before_load_with_the_growth_blend(tmp_path):
    """A map with far.blend = correlated of a noisy plane: its mean is within about
    the noise of the exact distance z near the data and convex (between the two
    fields); it round-trips through save / load; a map saved before far.blend existed
    or eq. point_projection (no such lines in its config) loads with the growth weights
    (eq. blend with (g r)^2), its stored far-field points and VARIANCE_COEF, and
    predicts as that formula; the defaults are still growth and raw points."""
    assert gm.MappingConfig().far.blend == "growth"
    assert gm.MappingConfig().far.project_points is False
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        # the far field of the maps before session 13 (plane vote of the raw points, no
        # split-half term, Gaussian components), which the maps this test loads had
        smap = gm.build_map(_plane_scan(), gm.MappingConfig().with_overrides(
            ["far.blend=correlated", "far.project_points=true", "far.vote=plane",
             "far.leave_self_out=0", "far.split_half=false", "far.predictive_dof=0"]))
    rng = np.random.default_rng(5)
    q = np.c_[rng.uniform(-1, 1, (500, 2)), rng.uniform(-0.3, 0.3, 500)]
    m, v = smap.predict(q)
    assert np.sqrt(np.mean((m - q[:, 2]) ** 2)) < 0.004
    m_gp = smap.predict(q, far=False)[0]
    m_far = smap.far.predict(q)[0]
    lo, hi = np.minimum(m_gp, m_far), np.maximum(m_gp, m_far)
    assert np.all((m >= lo - 1e-12) & (m <= hi + 1e-12))
    # the GP carries weight somewhere (the growth blend gives it < 1 % everywhere here)
    assert np.mean(np.abs(m - m_far) > 0.1 * np.abs(m_gp - m_far)) > 0.2
    smap.save(tmp_path / "new")
    nm, nv = gm.load_map(tmp_path / "new").predict(q)
    np.testing.assert_array_equal(nm, m)
    np.testing.assert_array_equal(nv, v)
    # a map saved before far.blend: the growth weights and VARIANCE_COEF
    smap.save(tmp_path / "old")
    meta_path = tmp_path / "old" / "map.json"
    meta = json.loads(meta_path.read_text())
    assert 'blend = "correlated"' in meta["config_toml"]
    assert "project_points = true" in meta["config_toml"]
    meta["config_toml"] = "\n".join(l for l in meta["config_toml"].splitlines()
                                    if not l.startswith(("blend =", "project_points =")))
    del meta["variance_coef"]  # saved before the coefficients were saved with the map
    meta_path.write_text(json.dumps(meta))
    old = gm.load_map(tmp_path / "old")
    assert old.config.far.blend == "growth" and old.config.far.project_points is False
    np.testing.assert_array_equal(old.far.points, smap.far.points)  # stored, not redone
    om, ov = old.predict(q)
    gp_m, gp_v = old.predict(q, far=False)
    c = old.far.components(q)
    g = old.config.far.gp_growth
    want_m = F.blend_fields(gp_m, gp_v + (g * c["r"]) ** 2, c["mean"], c["var"])[0]
    np.testing.assert_array_equal(om, want_m)
    d2 = (gp_m - c["mean"]) ** 2
    kappa = old.config.far.disagreement_weight * np.exp(
        -(c["r"] / F.BlendedField(old.gp, old.far).length_scale) ** 2)
    v_obs = F.calibrated_variance(old.far.rho0, old.far.noise, c["r"], c["spread2"], d2, gp_v,
                                  coef=F.VARIANCE_COEF, disagreement_weight=kappa)
    plain = ~old.distribution(q).mixed
    assert plain.mean() > 0.3
    np.testing.assert_allclose(ov[plain], v_obs[plain], rtol=1e-12)


def test_projection_removes_the_noise_along_the_normal_of_a_plane():
    """Eq. point_projection on a noisy plane (exact truth z = 0): the points' RMS
    distance to the plane drops from the noise (3 mm) to a fraction of it, and they
    move only along their normals (x, y unchanged)."""
    rng = np.random.default_rng(6)
    n = 20000
    p = np.c_[rng.uniform(-1, 1, (n, 2)), rng.normal(0, 0.003, n)]
    nrm = np.tile([0.0, 0.0, 1.0], (n, 1))
    q = F.project_to_local_planes(p, nrm, 0.02, k=16)
    np.testing.assert_array_equal(q[:, :2], p[:, :2])
    assert np.sqrt(np.mean(q[:, 2] ** 2)) < 0.4 * 0.003


def test_projection_keeps_an_exact_sphere_and_the_faces_of_a_thin_wall():
    """Noise-free points of a unit sphere stay on it within the curvature bound
    rho0^2 / R (the centroid of a cap of radius ~rho0 lies that far inside); the two
    faces of a 2 cm wall (opposite normals) are not pulled towards each other."""
    rng = np.random.default_rng(7)
    u = rng.normal(size=(30000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    rho0 = 0.02
    q = F.project_to_local_planes(u, u, rho0, k=16)
    assert np.max(np.abs(np.linalg.norm(q, axis=1) - 1.0)) < rho0 ** 2
    m = 5000
    yz = rng.uniform(-1, 1, (2 * m, 2))
    x = np.r_[np.zeros(m), np.full(m, 0.02)]
    nx = np.r_[-np.ones(m), np.ones(m)]
    p = np.c_[x, yz]
    nrm = np.c_[nx, np.zeros((2 * m, 2))]
    np.testing.assert_allclose(F.project_to_local_planes(p, nrm, 0.05, k=16)[:, 0], x,
                               atol=1e-12)


def test_projected_far_field_is_not_compressed_next_to_a_noisy_sphere():
    """The far field of noisy points on a unit sphere (noise 5 mm along the normal):
    its mean error at 1-5 cm in front is positive (the nearest neighbours are the
    points displaced towards the query, |m| too small) and eq. point_projection
    at least halves it (2.9 -> 1.2 mm); inside likewise with the opposite sign."""
    rng = np.random.default_rng(8)
    u = rng.normal(size=(60000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    pts = u * (1.0 + rng.normal(0, 0.005, (len(u), 1)))
    v = rng.normal(size=(3000, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    t = rng.uniform(0.01, 0.05, 3000)
    out, ins = v * (1 + t)[:, None], v * (1 - t)[:, None]
    bias = {}
    for proj in (False, True):
        p = F.project_to_local_planes(pts, u, 0.012) if proj else pts
        f = F.FarField(p, u, 0.012, 0.005, robust_scale=1.0)
        bias[proj] = (np.mean(t - f.predict(out)[0]), np.mean(-t - f.predict(ins)[0]))
    assert bias[False][0] > 1e-3 and bias[False][1] < -1e-3
    assert abs(bias[True][0]) < 0.5 * bias[False][0]
    assert abs(bias[True][1]) < 0.5 * abs(bias[False][1])


def test_a_map_predicts_a_query_alone_as_in_a_batch_bit_for_bit():
    """The map's mean and variance at a query do not depend on the batch it is in:
    eq. calibrated_var's linear predictor is summed feature by feature (numpy's
    matrix-vector product took another path for one row and changed the last bits)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        smap = gm.build_map(_plane_scan(1500, seed=7), gm.MappingConfig())
    rng = np.random.default_rng(8)
    q = np.c_[rng.uniform(-1.2, 1.2, (300, 2)), rng.uniform(-0.6, 0.6, 300)]
    m, v = smap.predict(q)
    alone = [smap.predict(q[j:j + 1]) for j in range(0, 300, 7)]
    np.testing.assert_array_equal(np.concatenate([a[0] for a in alone]), m[::7])
    np.testing.assert_array_equal(np.concatenate([a[1] for a in alone]), v[::7])
    # the linear predictor itself, against the matrix product within rounding
    X = rng.normal(size=(50, 5))
    u = rng.normal(size=5)
    np.testing.assert_allclose(F._features_dot(X, u), X @ u, rtol=1e-13, atol=1e-14)
    np.testing.assert_array_equal(F._features_dot(X[3:4], u), F._features_dot(X, u)[3:4])
    with pytest.raises(ValueError, match="5 features"):
        F._features_dot(X[:, :4], u)
