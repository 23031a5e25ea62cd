"""Matern 3/2 kernel with derivative observations (paper eqs. kernel, kernel_j, kernel2).

With ``a = sqrt(3) / l``, ``D = x - x'`` and ``r = |D|`` the kernel and its
derivatives have closed forms that stay finite at ``r = 0``::

    k(x, x')              = (1 + a r) exp(-a r)
    dk/dx_i               = -a^2 exp(-a r) D_i
    dk/dx'_j              = +a^2 exp(-a r) D_j
    d2k/dx_i dx'_j        =  a^2 exp(-a r) (delta_ij - a D_i D_j / r)   (-> a^2 delta_ij at r = 0)

Ordering of the joint matrices
------------------------------
Rows and columns are *interleaved per point*: index ``4 i`` is the value at point
``i`` and ``4 i + 1 .. 4 i + 3`` its gradient (d/dx, d/dy, d/dz). A joint target
vector is therefore ``targets.reshape(-1)`` for ``targets`` of shape (n, 4) with
columns (value, gx, gy, gz).

Scaling by the prior (eq. kernel2)
----------------------------------
``k0(x, x') = sigma_p(x) sigma_p(x') k(x, x')``. For the gradient blocks
``sigma_p`` is treated as locally constant per point: the joint matrix is
``S K S`` with ``S`` diagonal holding ``sigma_p(x_i)`` on all four rows of point
``i``. The exact derivative of ``sigma_p(x) sigma_p(x') k`` would add terms in
``grad sigma_p``; dropping them keeps the matrix positive semi-definite by
construction (a congruence of a PSD matrix) and avoids differentiating the GMR
variance, at the price of ignoring how fast the prior's confidence changes.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "KernelError",
    "matern32_value",
    "matern32_joint",
    "matern32_cross",
    "scale_joint",
]


class KernelError(ValueError):
    """Bad input to a kernel function."""


def _pts(X, name: str) -> np.ndarray:
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3:
        raise KernelError(f"Expected {name} with shape (n, 3), found {X.shape}; "
                          "pass xyz rows.")
    return X


def _check_l(length_scale: float) -> float:
    if not (length_scale > 0 and math.isfinite(length_scale)):
        raise KernelError(f"Expected a positive finite length_scale, found {length_scale}; "
                          "use e.g. 0.08 m.")
    return float(length_scale)


def _geometry(X1, X2, length_scale):
    a = math.sqrt(3.0) / length_scale
    D = X1[:, None, :] - X2[None, :, :]                       # (n1, n2, 3)
    r = np.sqrt(np.einsum("ijk,ijk->ij", D, D))
    e = np.exp(-a * r)
    return a, D, r, e


def matern32_value(X1, X2, length_scale: float) -> np.ndarray:
    """Matern 3/2 kernel between values (paper eq. kernel with ``sigma_p = 1``).

    Parameters
    ----------
    X1 : (n1, 3), X2 : (n2, 3)
    length_scale : float
        ``l`` in metres.

    Returns
    -------
    (n1, n2) float64: ``(1 + a r) exp(-a r)``, ``a = sqrt(3) / l``.
    """
    X1, X2 = _pts(X1, "X1"), _pts(X2, "X2")
    a, _, r, e = _geometry(X1, X2, _check_l(length_scale))
    return (1.0 + a * r) * e


def matern32_joint(X1, X2, length_scale: float) -> np.ndarray:
    """Joint value+gradient Matern 3/2 kernel (paper eq. kernel_j).

    ``[[k, k grad_x'^T], [grad_x k, grad_x k grad_x'^T]]`` for every pair of points,
    interleaved per point (see the module docstring).

    Parameters
    ----------
    X1 : (n1, 3), X2 : (n2, 3)
    length_scale : float

    Returns
    -------
    (4 n1, 4 n2) float64
    """
    X1, X2 = _pts(X1, "X1"), _pts(X2, "X2")
    a, D, r, e = _geometry(X1, X2, _check_l(length_scale))
    n1, n2 = len(X1), len(X2)
    out = np.empty((n1, 4, n2, 4))
    a2e = a * a * e
    out[:, 0, :, 0] = (1.0 + a * r) * e
    out[:, 0, :, 1:] = (a2e[..., None] * D)                   # cov(f(x), df(x')/dx'_j)
    out[:, 1:, :, 0] = -np.moveaxis(a2e[..., None] * D, 2, 1)  # cov(df(x)/dx_i, f(x'))
    with np.errstate(invalid="ignore", divide="ignore"):
        inv_r = np.where(r > 0, 1.0 / r, 0.0)
    outer = D[..., :, None] * D[..., None, :]                 # (n1, n2, 3, 3)
    gg = a2e[..., None, None] * (np.eye(3) - (a * inv_r)[..., None, None] * outer)
    out[:, 1:, :, 1:] = np.transpose(gg, (0, 2, 1, 3))
    return out.reshape(4 * n1, 4 * n2)


def matern32_cross(Xs, X, length_scale: float, with_grad: bool = False) -> np.ndarray:
    """Covariances of test values (and gradients) with joint observations.

    The rows of :func:`matern32_joint` needed for prediction: value rows only
    (``with_grad=False``, shape ``(ns, 4 n)``) or all rows (shape ``(4 ns, 4 n)``,
    interleaved per test point).

    Parameters
    ----------
    Xs : (ns, 3)
        Test points.
    X : (n, 3)
        Training points (value + gradient observations).
    length_scale : float
    with_grad : bool

    Returns
    -------
    (ns, 4 n) or (4 ns, 4 n) float64
    """
    if with_grad:
        return matern32_joint(Xs, X, length_scale)
    Xs, X = _pts(Xs, "Xs"), _pts(X, "X")
    a, D, r, e = _geometry(Xs, X, _check_l(length_scale))
    out = np.empty((len(Xs), len(X), 4))
    out[..., 0] = (1.0 + a * r) * e
    out[..., 1:] = (a * a * e)[..., None] * D
    return out.reshape(len(Xs), 4 * len(X))


def scale_joint(K: np.ndarray, sigma_rows: np.ndarray, sigma_cols: np.ndarray,
                rows_joint: bool = True, cols_joint: bool = True) -> np.ndarray:
    """Prior scaling of a kernel matrix (paper eq. kernel2), ``S_r K S_c``.

    Parameters
    ----------
    K : (R, C) float64
        Unscaled kernel matrix (joint blocks interleaved per point).
    sigma_rows : (n_r,), sigma_cols : (n_c,)
        ``sigma_p`` of the row / column points.
    rows_joint, cols_joint : bool
        Whether the rows / columns hold 4 entries per point (value + gradient) or 1.

    Returns
    -------
    (R, C) float64
    """
    sr = np.repeat(sigma_rows, 4) if rows_joint else np.asarray(sigma_rows)
    sc = np.repeat(sigma_cols, 4) if cols_joint else np.asarray(sigma_cols)
    if K.shape != (len(sr), len(sc)):
        raise KernelError(f"Expected a kernel of shape {(len(sr), len(sc))} for the given "
                          f"sigma_p, found {K.shape}.")
    return sr[:, None] * K * sc[None, :]
