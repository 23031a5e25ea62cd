"""GP hyper-parameters by marginal likelihood (stages/gp_hyper.py, issue 15 item 2).

Oracles: a dense multivariate-normal log density with the joint kernel built by finite
differences of the Matern 3/2 value kernel; the compiled block factorisation of gp.py;
draws from the exact block model with known hyper-parameters.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from scipy.stats import multivariate_normal

import gmmgp_app as gm
from gmmgp_app.stages.gp import fit_block
from gmmgp_app.stages.gp_hyper import (GRID, BlockSample, block_log_marginal_likelihood,
                                       sample_blocks, select_hyperparameters)
from gmmgp_app.stages.kernels import matern32_joint, matern32_value
from gmmgp_app.synth import scan_scene
from gmmgp_app.types import Scan


def _k(x, y, ls):
    return matern32_value(x[None], y[None], ls)[0, 0]


def _joint_by_differences(X, ls, h=1e-5):
    """cov of (f, grad f) at X from central differences of the value kernel."""
    n = len(X)
    K = np.empty((4 * n, 4 * n))
    E = np.eye(3) * h
    for i in range(n):
        for j in range(n):
            xi, xj = X[i], X[j]
            K[4 * i, 4 * j] = _k(xi, xj, ls)
            for q in range(3):
                K[4 * i, 4 * j + 1 + q] = (_k(xi, xj + E[q], ls) - _k(xi, xj - E[q], ls)) / (2 * h)
                K[4 * i + 1 + q, 4 * j] = (_k(xi + E[q], xj, ls) - _k(xi - E[q], xj, ls)) / (2 * h)
                for p in range(3):
                    K[4 * i + 1 + p, 4 * j + 1 + q] = (
                        _k(xi + E[p], xj + E[q], ls) - _k(xi + E[p], xj - E[q], ls)
                        - _k(xi - E[p], xj + E[q], ls) + _k(xi - E[p], xj - E[q], ls)) / (4 * h * h)
    return K


def test_block_lml_equals_a_dense_gaussian_log_density():
    rng = np.random.default_rng(0)
    X = rng.uniform(0, 0.3, (6, 3))
    sp = rng.uniform(0.02, 0.05, 6)
    T = np.c_[rng.normal(0, 0.01, 6), rng.normal(0, 0.2, (6, 3))]
    ls, vn, gn, c = 0.12, 3e-5, 2e-3, 0.7
    lml, eps, raised = block_log_marginal_likelihood(X, sp, T, ls, vn, gn, jitter=1e-8,
                                                     prior_scale=c)
    S = np.repeat(c * sp, 4)
    # the diagonal of the gradient blocks is a^2 (the limit r -> 0): difference away from 0
    K = S[:, None] * _joint_by_differences(X, ls) * S[None]
    K[np.diag_indices_from(K)] = S ** 2 * np.diag(matern32_joint(X, X, ls))
    K += np.diag(np.tile([vn, gn, gn, gn], 6))
    assert raised == 0 and eps == pytest.approx(1e-8 * np.max(np.diag(K)))
    K += 1e-8 * np.diag(np.diag(K))
    dense = multivariate_normal(mean=np.zeros(24), cov=K).logpdf(T.reshape(-1))
    assert lml == pytest.approx(dense, rel=1e-6, abs=1e-6)
    # the factor gp.py keeps for the map (jitter 1e-8 x the mean diagonal) gives the
    # same number to the jitter's order
    fit = fit_block(X, c * sp, T, ls, vn, gn, 1e-8)
    y = T.reshape(-1)
    from_fit = (-0.5 * y @ fit.alpha - np.sum(np.log(np.diag(fit.L)))
                - 0.5 * len(y) * math.log(2 * math.pi))
    assert lml == pytest.approx(from_fit, rel=1e-6)
    # and without jitter exactly
    lml0 = block_log_marginal_likelihood(X, sp, T, ls, vn, gn, jitter=0.0, prior_scale=c)[0]
    fit0 = fit_block(X, c * sp, T, ls, vn, gn, 0.0)
    assert lml0 == pytest.approx(-0.5 * y @ fit0.alpha - np.sum(np.log(np.diag(fit0.L)))
                                 - 0.5 * len(y) * math.log(2 * math.pi), rel=1e-10)


def _draw_blocks(n_blocks, n_pts, ls, vn, gn, c, seed, spacing=0.02):
    """Independent blocks drawn from the exact block model (points on a wavy patch)."""
    rng = np.random.default_rng(seed)
    X, SP, T = [], [], []
    side = spacing * math.sqrt(n_pts)
    for b in range(n_blocks):
        xy = rng.uniform(0, side, (n_pts, 2))
        x = np.c_[xy, 0.1 * side * np.sin(3 * xy[:, 0] / side)] + 10 * side * b
        sp = np.full(n_pts, 0.03)
        S = np.repeat(c * sp, 4)
        K = S[:, None] * matern32_joint(x, x, ls) * S[None]
        K += np.diag(np.tile([vn, gn, gn, gn], n_pts))
        y = np.linalg.cholesky(K + 1e-12 * np.eye(len(K))) @ rng.normal(size=len(K))
        X.append(x)
        SP.append(sp)
        T.append(y.reshape(-1, 4))
    return BlockSample(X, SP, T, n_blocks)


def test_selection_recovers_the_true_values_within_the_grid():
    ls, vn, gn, c = 0.04, 4e-5, 2e-3, 1.0
    sample = _draw_blocks(20, 40, ls, vn, gn, c, seed=1)
    # start one grid step off in every field: the truth is a grid point
    start = {"length_scale": ls / 1.4, "value_noise": vn * 4, "gradient_noise": gn / 4,
             "prior_scale": c * 2}
    ch = select_hyperparameters(sample, start, GRID.keys())
    assert ch.multipliers == {"length_scale": 1.4, "value_noise": 0.25,
                              "gradient_noise": 4.0, "prior_scale": 0.5}
    assert ch.values["length_scale"] == pytest.approx(ls)
    assert ch.values["value_noise"] == pytest.approx(vn)
    assert ch.lml_best > ch.lml_start
    # the profile holds every candidate of each field; the choice is its maximum
    for k, prof in ch.profile.items():
        assert set(prof) == set(GRID[k])
        assert max(prof, key=prof.get) == ch.multipliers[k]
    assert ch.n_blocks == 20 and ch.n_points == 800 and ch.max_jitter > 0
    # the batched sum equals the sum of the blocks' own LMLs
    per_block = sum(block_log_marginal_likelihood(
        X, sp, t, ch.values["length_scale"], ch.values["value_noise"],
        ch.values["gradient_noise"], prior_scale=ch.values["prior_scale"])[0]
        for X, sp, t in zip(sample.X, sample.sigma_p, sample.targets))
    assert ch.lml_best == pytest.approx(per_block, rel=1e-9)
    assert ch.at_edge == ["value_noise", "gradient_noise", "prior_scale"]


def test_fields_set_by_hand_are_not_searched():
    ls, vn, gn, c = 0.04, 4e-5, 2e-3, 1.0
    sample = _draw_blocks(10, 40, ls, vn, gn, c, seed=2)
    start = {"length_scale": ls / 2, "value_noise": vn, "gradient_noise": gn,
             "prior_scale": c}
    ch = select_hyperparameters(sample, start, ["value_noise", "gradient_noise"])
    assert ch.multipliers["length_scale"] == 1.0 and "length_scale" not in ch.values


@pytest.mark.parametrize("a", [10.0, 0.1])
def test_selection_is_scale_equivariant(a):
    """A scan scaled by a: values and sigma_p by a, gradients unchanged, lengths by a,
    value noise by a^2: the same multipliers are chosen."""
    ls, vn, gn, c = 0.04, 4e-5, 2e-3, 1.0
    s1 = _draw_blocks(12, 40, ls, vn, gn, c, seed=3)
    s2 = BlockSample([x * a for x in s1.X], [s * a for s in s1.sigma_p],
                     [t * np.r_[a, 1, 1, 1] for t in s1.targets], s1.n_blocks_total)
    st = {"length_scale": ls * 0.8, "value_noise": vn * 2, "gradient_noise": gn,
          "prior_scale": 1.0}
    st2 = dict(st, length_scale=st["length_scale"] * a, value_noise=st["value_noise"] * a * a)
    c1 = select_hyperparameters(s1, st, GRID.keys())
    c2 = select_hyperparameters(s2, st2, GRID.keys())
    assert c1.multipliers == c2.multipliers
    # every candidate's summed LML shifts by the same constant, -log a per value row
    shift = -c1.n_points * math.log(a)
    for k in c1.profile:
        for m in c1.profile[k]:
            assert c2.profile[k][m] - c1.profile[k][m] == pytest.approx(shift, abs=1e-6)


def test_block_sample_is_seeded_and_bounded():
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(0, 4, (5000, 2)), np.zeros(5000)]
    b1, n1 = sample_blocks(pts, 0.2, 1.0, n_blocks=20, max_points=30, seed=7)
    b2, _ = sample_blocks(pts[::-1] * 1.0, 0.2, 1.0, n_blocks=20, max_points=30, seed=7)
    assert len(b1) == 20 and n1 == 400 and all(4 <= len(b) <= 30 for b in b1)
    # the same point sets whatever order the points come in
    flip = len(pts) - 1
    assert [sorted(pts[b].tolist()) for b in b1] == [sorted(pts[flip - b].tolist()) for b in b2]


# ------------------------------------------------------------------ through build_map
def _quiet(fn, *a, **k):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fn(*a, **k)


@pytest.fixture(scope="module")
def box_scan():
    scan, _ = scan_scene("box", density=0.02, seed=3)
    return scan


ML = ["gp.marginal_likelihood=true", "gp.prior_scale=auto"]


def test_build_map_records_the_choice_and_keeps_set_values(box_scan):
    cfg = gm.MappingConfig().with_overrides(ML)
    m = _quiet(gm.build_map, box_scan, cfg)
    rec = m.summary["auto"]["gp.hyper"]
    assert rec["reason"].startswith("max. marginal likelihood over ")
    assert rec["blocks"] > 0 and rec["jitter_relative"] == 1e-8 and rec["max_jitter"] > 0
    for k in ("length_scale", "value_noise", "gradient_noise", "prior_scale"):
        mult = rec["multipliers"][k]
        assert getattr(m.config.gp, k) == pytest.approx(rec["start"][k] * mult)
        assert m.summary["auto"][f"gp.{k}"]["value"] == pytest.approx(getattr(m.config.gp, k))
        assert max(rec["summed_lml"][k], key=rec["summed_lml"][k].get) == f"x{mult:g}"
    assert m.gp.hyper["prior_scale"] == m.config.gp.prior_scale
    # a value set by hand is kept
    m2 = _quiet(gm.build_map, box_scan, cfg.replace("gp.length_scale", 0.07))
    assert m2.config.gp.length_scale == 0.07
    assert m2.summary["auto"]["gp.hyper"]["multipliers"]["length_scale"] == 1.0
    # the prior scale is a number (1) by default: searched only when set to 'auto'
    m3 = _quiet(gm.build_map, box_scan, gm.MappingConfig().with_overrides(ML[:1]))
    assert m3.config.gp.prior_scale == 1.0
    assert set(m3.summary["auto"]["gp.hyper"]["summed_lml"]) == {
        "length_scale", "value_noise", "gradient_noise"}


def test_saved_map_with_a_prior_scale_predicts_identically(box_scan, tmp_path):
    cfg = gm.MappingConfig().with_overrides(ML + ["gp.prior_scale=0.5"])
    m = _quiet(gm.build_map, box_scan, cfg)
    q = np.random.default_rng(1).uniform(-1.2, 1.2, (300, 3))
    m.save(tmp_path / "m")
    m2 = gm.load_map(tmp_path / "m")
    a, b = m.predict(q), m2.predict(q)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert m2.gp.hyper["prior_scale"] == 0.5


@pytest.mark.parametrize("a", [10.0, 0.1])
def test_scale_equivariance_with_the_marginal_likelihood(box_scan, a):
    cfg = gm.MappingConfig().with_overrides(ML)
    m1 = _quiet(gm.build_map, box_scan, cfg)
    scaled = Scan(box_scan.points * a, origins=box_scan.origins * a)
    m2 = _quiet(gm.build_map, scaled, cfg)
    assert m2.summary["auto"]["gp.hyper"]["multipliers"] == \
        m1.summary["auto"]["gp.hyper"]["multipliers"]
    assert m2.config.gp.length_scale == pytest.approx(a * m1.config.gp.length_scale, rel=1e-6)
    q = np.random.default_rng(0).uniform(-1.4, 1.4, (400, 3))
    f1, v1 = m1.predict(q)
    f2, v2 = m2.predict(q * a)
    scale = np.maximum(np.abs(f1), m1.summary["auto"]["train_spacing"]["value"])
    assert np.max(np.abs(f2 / a - f1) / scale) < 0.01
    assert np.median(np.abs(v2 / a ** 2 - v1) / v1) < 0.01
