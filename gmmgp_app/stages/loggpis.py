"""Log-GPIS baseline: a GP on ``v(x) = exp(-lambda d(x))`` (Wu et al., 2021).

The unsigned distance ``d`` is not smooth at the surface, but ``v`` behaves like
the solution of a screened heat (Helmholtz) equation: it is 1 on the surface and
decays as ``exp(-lambda d)`` away from it. Log-GPIS regresses ``v`` with a
zero-mean stationary GP from value observations ``v = 1`` at the hit points only
(no normals, no virtual points), and reads the distance back with the logarithm.

Choices made here (the paper only names the method):

- **Kernel and lambda are tied**: Matern 3/2 decays like ``exp(-sqrt(3) r / l)``,
  so the GP mean away from the surface follows ``exp(-lambda d)`` with
  ``lambda = sqrt(3) / l``. The default ``l`` is the GP length scale of the
  config (0.08 m), i.e. ``lambda = 21.7 / m``, inside the 10-50 / m of the
  Log-GPIS papers at room scale; ``scripts/bench_compare.py`` sweeps it.
- **Same blocks as GPIS**: grid-aligned blocks of ``GPConfig.block_size`` with the
  same overlap, at most ``GPConfig.max_block_points`` points each (the same points
  GPIS uses), blended by inverse variance in ``v`` like :mod:`.gp`.
- **Prediction margin**: a block answers queries up to ``margin`` metres beyond
  its training region (default ``4 / lambda``, where ``v`` is still
  ``exp(-4) = 0.02``), so the field reaches the evaluation distances.
- **Noise**: ``value_noise`` is the variance of ``v`` at a hit point (default
  ``0.01``: ``lambda sigma_r`` for a few millimetres of range noise).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_solve, solve_triangular

from gmmgp_app.stages.gp import blend_blocks
from gmmgp_app.stages.kernels import matern32_value
from gmmgp_app.stages.octree import BlockGrid

__all__ = ["LogGPISError", "LogGPISParams", "LogGPISField", "fit_loggpis",
           "loggpis_distance"]

#: Smallest ``v`` read back as a distance; below it ``d = -log(V_MIN) / lambda``.
V_MIN = 1e-12


class LogGPISError(ValueError):
    """Bad input or settings for the Log-GPIS baseline."""


@dataclass(frozen=True)
class LogGPISParams:
    """Settings of the Log-GPIS baseline.

    Attributes
    ----------
    lam : float
        lambda (1/m) of ``v = exp(-lambda d)``; the Matern 3/2 length scale is
        ``sqrt(3) / lam``.
    value_noise : float
        Noise variance of the ``v = 1`` observations.
    prior_variance : float
        Kernel variance of ``v`` (the prior mean is 0).
    block_size, block_overlap : float
        As ``GPConfig`` (m, fraction).
    max_block_points : int
    margin : float
        Extra reach of a block's predictions beyond its training region (m).
    jitter : float
        Relative Cholesky jitter.
    """

    lam: float = math.sqrt(3.0) / 0.08
    value_noise: float = 0.01
    prior_variance: float = 1.0
    block_size: float = 0.5
    block_overlap: float = 0.5
    max_block_points: int = 300
    margin: float | None = None
    jitter: float = 1e-8

    def __post_init__(self):
        for name in ("lam", "value_noise", "prior_variance", "block_size"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise LogGPISError(f"Expected LogGPISParams.{name} > 0, found {v!r}; "
                                   f"e.g. lam=20 (1/m), value_noise=0.01.")
        if self.margin is None:
            object.__setattr__(self, "margin", 4.0 / self.lam)

    @property
    def length_scale(self) -> float:
        """Matern 3/2 length scale ``sqrt(3) / lambda`` (m)."""
        return math.sqrt(3.0) / self.lam

    @classmethod
    def from_config(cls, cfg, lam: float | None = None, **overrides) -> "LogGPISParams":
        """Blocks and point cap from ``cfg.gp``; lambda from the GP length scale
        (``sqrt(3) / l``) unless given."""
        from gmmgp_app.config import concrete

        gp = concrete(cfg.gp)
        lam = math.sqrt(3.0) / gp.length_scale if lam is None else float(lam)
        kw = dict(lam=lam, block_size=gp.block_size, block_overlap=gp.block_overlap,
                  max_block_points=gp.max_block_points, jitter=gp.jitter)
        kw.update(overrides)
        return cls(**kw)


def loggpis_distance(v_mean, v_var, lam: float):
    """Distance and its variance from the GP on ``v`` (Log-GPIS read-back).

    ``d = -log(v) / lambda`` (clipped at 0 where ``v > 1``) and, by the delta
    method, ``var_d = var_v / (lambda v)^2``; ``v`` is floored at :data:`V_MIN`.

    Parameters
    ----------
    v_mean, v_var : (K,) array_like
    lam : float

    Returns
    -------
    d (K,), var_d (K,) float64
    """
    v = np.clip(np.asarray(v_mean, dtype=np.float64), V_MIN, None)
    d = np.maximum(-np.log(v) / lam, 0.0)
    var = np.asarray(v_var, dtype=np.float64) / (lam * v) ** 2
    return d, var


class LogGPISField:
    """Fitted Log-GPIS blocks; :meth:`predict` gives the unsigned distance.

    Attributes
    ----------
    params : LogGPISParams
    grid : BlockGrid
        Training blocks.
    blocks : list of (X (n,3), L (n,n), alpha (n,))
    signed : bool
        Always False: the field is an EDF.
    """

    signed = False

    def __init__(self, params: LogGPISParams, grid: BlockGrid, blocks: list, info: dict):
        self.params = params
        self.grid = grid
        self.blocks = blocks
        self.info = dict(info)
        reach = params.block_overlap + 2.0 * params.margin / params.block_size
        # the same blocks, answering a wider region than they train on
        self._reach = BlockGrid(grid.keys, params.block_size, reach)

    def predict_v(self, xyz):
        """GP posterior of ``v`` at (K, 3) queries: mean (K,), variance (K,).

        Per block ``mu = k*^T K^-1 1`` and ``var = s2 - k*^T K^-1 k* + noise`` with
        ``s2`` the prior variance; blocks covering a query are mixed with weights
        ``1 / var`` (law of total variance for the spread, capped at ``s2 + noise``);
        outside every block the prior (0, ``s2 + noise``) stands.
        """
        x = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        p = self.params
        s2, noise = p.prior_variance, p.value_noise
        mu = np.zeros(len(x))
        var = np.full(len(x), s2 + noise)
        if len(x) == 0 or not self.blocks:
            return mu, var
        # blocks whose training region holds the query answer it; the wider reach
        # only where none does (with blocks small against 4 / lambda, dozens of
        # distant blocks, each near the prior 0, would otherwise outvote the block
        # that sees the surface and pull v at the surface to ~0.5)
        qi, bi = self.grid.cover(x)
        out = np.ones(len(x), dtype=bool)
        out[qi] = False
        if out.any():
            qo, bo = self._reach.cover(x[out])
            qi = np.concatenate([qi, np.flatnonzero(out)[qo]])
            bi = np.concatenate([bi, bo])
            order = np.lexsort((qi, bi))
            qi, bi = qi[order], bi[order]
        if len(qi) == 0:
            return mu, var
        dm = np.empty(len(qi))
        vb = np.empty(len(qi))
        starts = np.flatnonzero(np.r_[True, bi[1:] != bi[:-1]])
        ends = np.r_[starts[1:], len(bi)]
        for s, e in zip(starts, ends):
            X, L, alpha = self.blocks[bi[s]]
            kv = s2 * matern32_value(x[qi[s:e]], X, p.length_scale)
            dm[s:e] = kv @ alpha
            w = solve_triangular(L, kv.T, lower=True, check_finite=False)
            vb[s:e] = np.maximum(s2 - np.einsum("ij,ij->j", w, w), 0.0) + noise
        mbar, spread, covered, _ = blend_blocks(qi, dm, vb, len(x))
        mu = np.where(covered, mbar, 0.0)
        var = np.where(covered, np.minimum(spread, s2 + noise), var)
        return mu, var

    _PARAMS = ("lam", "value_noise", "prior_variance", "block_size", "block_overlap",
               "max_block_points", "margin", "jitter")

    def to_arrays(self) -> dict:
        """Flat arrays (no pickle) that :meth:`from_arrays` reads back bit for bit."""
        n = np.array([len(X) for X, _, _ in self.blocks], dtype=np.int64)
        return {"params": np.array([float(getattr(self.params, k)) for k in self._PARAMS]),
                "block_keys": self.grid.keys, "point_ptr": np.r_[0, np.cumsum(n)],
                "X": np.concatenate([X for X, _, _ in self.blocks]) if self.blocks
                else np.zeros((0, 3)),
                "L": np.concatenate([L.ravel() for _, L, _ in self.blocks]) if self.blocks
                else np.zeros(0),
                "alpha": np.concatenate([a for _, _, a in self.blocks]) if self.blocks
                else np.zeros(0)}

    @classmethod
    def from_arrays(cls, arrays: dict) -> "LogGPISField":
        """The field saved by :meth:`to_arrays`."""
        vals = dict(zip(cls._PARAMS, (float(v) for v in arrays["params"])))
        vals["max_block_points"] = int(vals["max_block_points"])
        params = LogGPISParams(**vals)
        ptr = arrays["point_ptr"]
        lptr = np.r_[0, np.cumsum(np.diff(ptr) ** 2)]
        blocks = [(arrays["X"][a:b], arrays["L"][la:lb].reshape(b - a, b - a),
                   arrays["alpha"][a:b])
                  for a, b, la, lb in zip(ptr[:-1], ptr[1:], lptr[:-1], lptr[1:])]
        grid = BlockGrid(arrays["block_keys"], params.block_size, params.block_overlap)
        return cls(params, grid, blocks, dict(n_blocks=len(blocks), loaded=True))

    def predict(self, xyz, return_grad: bool = False):
        """Unsigned distance mean (K,) and variance (K,) (see :func:`loggpis_distance`)."""
        if return_grad:
            raise LogGPISError("Log-GPIS predicts an unsigned distance without gradients "
                               "here; call predict(xyz) without return_grad.")
        mu, var = self.predict_v(xyz)
        return loggpis_distance(mu, var, self.params.lam)


def fit_loggpis(points, params: LogGPISParams, *, rng=None) -> LogGPISField:
    """Fit Log-GPIS blocks on hit points (targets ``v = 1``, zero prior mean).

    Parameters
    ----------
    points : (P, 3)
        Hit points.
    params : LogGPISParams
    rng : numpy.random.Generator, optional
        Subsampling of blocks holding more than ``max_block_points`` points.

    Returns
    -------
    LogGPISField
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise LogGPISError(f"Expected hit points with shape (P, 3), P >= 1, found "
                           f"{pts.shape}; Log-GPIS needs surface points.")
    if not np.all(np.isfinite(pts)):
        raise LogGPISError("Expected finite hit points, found NaN or inf; drop them first.")
    rng = np.random.default_rng(0) if rng is None else rng
    grid = BlockGrid.from_points(pts, params.block_size, params.block_overlap)
    pi, bi = grid.cover(pts)
    starts = np.flatnonzero(np.r_[True, bi[1:] != bi[:-1]])
    ends = np.r_[starts[1:], len(bi)]
    blocks, used = [], []
    for s, e in zip(starts, ends):
        idx = pi[s:e]
        if len(idx) > params.max_block_points:
            idx = np.sort(rng.choice(idx, params.max_block_points, replace=False))
        X = pts[idx]
        K = params.prior_variance * matern32_value(X, X, params.length_scale)
        K[np.diag_indices_from(K)] += params.value_noise + params.jitter * params.prior_variance
        L = np.linalg.cholesky(K)
        alpha = cho_solve((L, True), np.ones(len(X)))
        blocks.append((X, L, alpha))
        used.append(len(X))
    info = dict(n_points=int(len(pts)), n_blocks=len(blocks),
                points_per_block_max=int(max(used)), lam=params.lam,
                length_scale=params.length_scale)
    return LogGPISField(params, grid, blocks, info)
