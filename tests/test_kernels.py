"""The Matern 3/2 value+gradient kernel against finite differences and by hand."""

import math

import numpy as np
import pytest

from gmmgp_app.stages.kernels import (KernelError, matern32_cross, matern32_joint,
                                      matern32_value, scale_joint)

L = 0.3


def k_fn(x, y, ell=L):
    r = np.linalg.norm(x - y)
    a = math.sqrt(3.0) / ell
    return (1 + a * r) * math.exp(-a * r)


def fd_blocks(x, y, eps=1e-5):
    """The 4x4 joint block of (x, y) by central finite differences of k."""
    out = np.zeros((4, 4))
    E = np.eye(3) * eps
    out[0, 0] = k_fn(x, y)
    for j in range(3):
        out[0, 1 + j] = (k_fn(x, y + E[j]) - k_fn(x, y - E[j])) / (2 * eps)
        out[1 + j, 0] = (k_fn(x + E[j], y) - k_fn(x - E[j], y)) / (2 * eps)
    for i in range(3):
        for j in range(3):
            out[1 + i, 1 + j] = (k_fn(x + E[i], y + E[j]) - k_fn(x + E[i], y - E[j])
                                 - k_fn(x - E[i], y + E[j]) + k_fn(x - E[i], y - E[j])
                                 ) / (4 * eps * eps)
    return out


def test_every_block_matches_finite_differences():
    rng = np.random.default_rng(0)
    X1 = rng.normal(scale=0.2, size=(4, 3))
    X2 = rng.normal(scale=0.2, size=(5, 3))
    K = matern32_joint(X1, X2, L)
    assert K.shape == (16, 20)
    for i in range(4):
        for j in range(5):
            blk = K[4 * i:4 * i + 4, 4 * j:4 * j + 4]
            fd = fd_blocks(X1[i], X2[j])
            np.testing.assert_allclose(blk[0, 0], fd[0, 0], rtol=1e-12)
            np.testing.assert_allclose(blk[0, 1:], fd[0, 1:], atol=1e-7)    # value-grad
            np.testing.assert_allclose(blk[1:, 0], fd[1:, 0], atol=1e-7)    # grad-value
            np.testing.assert_allclose(blk[1:, 1:], fd[1:, 1:], atol=1e-4)  # grad-grad


def test_hand_checked_two_points():
    # x1 = 0, x2 = (0.1, 0, 0), l = 0.3: a = sqrt(3)/0.3, r = 0.1
    X = np.array([[0.0, 0, 0], [0.1, 0, 0]])
    a = math.sqrt(3.0) / 0.3
    r = 0.1
    e = math.exp(-a * r)
    k = (1 + a * r) * e
    g = a * a * e * r        # |dk/dx| along the separation
    gg_par = a * a * e * (1 - a * r)   # d2k/dx dx' along the separation
    gg_perp = a * a * e                 # d2k/dx dx' across it
    # D = x1 - x2 = (-0.1, 0, 0): cov(f(x1), df/dx'(x2)) = a^2 e D = -g along x
    expected = np.array([
        [1, 0, 0, 0, k, -g, 0, 0],
        [0, a * a, 0, 0, g, gg_par, 0, 0],
        [0, 0, a * a, 0, 0, 0, gg_perp, 0],
        [0, 0, 0, a * a, 0, 0, 0, gg_perp],
        [k, g, 0, 0, 1, 0, 0, 0],
        [-g, gg_par, 0, 0, 0, a * a, 0, 0],
        [0, 0, gg_perp, 0, 0, 0, a * a, 0],
        [0, 0, 0, gg_perp, 0, 0, 0, a * a],
    ])
    np.testing.assert_allclose(matern32_joint(X, X, 0.3), expected, rtol=1e-12, atol=1e-14)


def test_positive_semidefinite_and_symmetric():
    rng = np.random.default_rng(1)
    X = rng.uniform(0, 0.5, size=(60, 3))
    X[1] = X[0] + 1e-9            # nearly duplicate points are the hard case
    K = matern32_joint(X, X, 0.08)
    np.testing.assert_allclose(K, K.T, atol=1e-12)
    ev = np.linalg.eigvalsh(K)
    assert ev.min() >= -1e-10 * ev.max()
    s = rng.uniform(0.01, 0.2, size=60)
    Ks = scale_joint(K, s, s)
    ev = np.linalg.eigvalsh(Ks)
    assert ev.min() >= -1e-10 * ev.max()


def test_value_and_cross_are_slices_of_joint():
    rng = np.random.default_rng(2)
    Xs, X = rng.normal(size=(7, 3)), rng.normal(size=(5, 3))
    J = matern32_joint(Xs, X, 0.5)
    np.testing.assert_allclose(matern32_cross(Xs, X, 0.5), J[0::4], rtol=1e-14)
    np.testing.assert_array_equal(matern32_cross(Xs, X, 0.5, with_grad=True), J)
    np.testing.assert_allclose(matern32_value(Xs, X, 0.5), J[0::4, 0::4], rtol=1e-14)


def test_scaling_is_diagonal_congruence():
    rng = np.random.default_rng(3)
    X = rng.normal(size=(3, 3))
    s = np.array([0.1, 0.2, 0.3])
    K = matern32_joint(X, X, 1.0)
    S = np.diag(np.repeat(s, 4))
    np.testing.assert_allclose(scale_joint(K, s, s), S @ K @ S, rtol=1e-14)
    Kv = matern32_cross(X, X, 1.0)
    np.testing.assert_allclose(scale_joint(Kv, s, s, rows_joint=False),
                               np.diag(s) @ Kv @ S, rtol=1e-14)


def test_bad_inputs():
    with pytest.raises(KernelError, match=r"X1 with shape \(n, 3\), found \(4,\)"):
        matern32_joint(np.zeros(4), np.zeros((2, 3)), 0.1)
    with pytest.raises(KernelError, match="positive finite length_scale, found 0.0"):
        matern32_value(np.zeros((2, 3)), np.zeros((2, 3)), 0.0)
    with pytest.raises(KernelError, match=r"kernel of shape \(8, 8\)"):
        scale_joint(np.zeros((4, 4)), np.ones(2), np.ones(2))
