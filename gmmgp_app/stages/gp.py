"""Local GPs with derivative observations on a non-stationary prior (paper Sec. IV).

The prior (GMR, or a constant for the GPIS baseline) supplies the mean ``m(x)``, its
gradient and the standard deviation ``sigma_p(x)`` that scales the Matern 3/2
kernel (eq. kernel2). Hit points the prior models badly (eq. condition1) are the
training points; the GP learns the *residuals*: values ``0 - m(x)`` and gradients
``n - grad m(x)`` (eq. gpm2). Space is cut into grid-aligned blocks
(:mod:`gmmgp_app.stages.octree`); every block is an independent exact GP whose
fit is a pure function of its arrays (:func:`fit_block`), so blocks can run on any
executor. Predictions of overlapping blocks are blended by inverse variance;
outside every block the prior stands.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np
from scipy.linalg import cho_solve, solve_triangular

from gmmgp_app.stages.kernels import matern32_cross, matern32_joint
from gmmgp_app.stages.octree import BlockGrid

__all__ = [
    "GPError",
    "ConstantPrior",
    "BlockFit",
    "LocalGPField",
    "select_gp_points",
    "fit_block",
    "predict_block",
    "fit_local_gps",
]

#: Cholesky jitter is raised x10 from ``GPConfig.jitter`` up to this (relative) bound.
MAX_RELATIVE_JITTER = 1e-2

_HYPER = ("length_scale", "value_noise", "gradient_noise", "block_size", "block_overlap")


class GPError(ValueError):
    """Bad input to the local GPs, or a block that cannot be factorised."""


def _xyz(a, name: str) -> np.ndarray:
    x = np.asarray(a, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise GPError(f"Expected {name} with shape (P, 3), found {x.shape}; pass xyz rows.")
    if not np.all(np.isfinite(x)):
        bad = int(np.count_nonzero(~np.all(np.isfinite(x), axis=1)))
        raise GPError(f"Expected finite {name}, found {bad} rows with NaN or inf; "
                      "drop or fill them first.")
    return np.ascontiguousarray(x)


# ------------------------------------------------------------------- priors
class ConstantPrior:
    """A stationary prior: constant distance and variance, zero gradient.

    Parameters
    ----------
    distance : float
        Prior mean of the signed distance (m).
    variance : float
        Prior variance ``sigma_p^2`` (m^2), > 0.
    """

    def __init__(self, distance: float, variance: float):
        if not (variance > 0 and math.isfinite(variance) and math.isfinite(distance)):
            raise GPError(f"Expected a finite distance and a positive variance, found "
                          f"{distance} and {variance}.")
        self.distance = float(distance)
        self.variance = float(variance)

    def params(self) -> dict:
        """Constructor arguments, for saving a map without pickle."""
        return {"distance": self.distance, "variance": self.variance}

    def predict(self, xyz, return_grad: bool = False):
        """Constant mean (K,), variance (K,)[, zero gradient (K, 3)]."""
        x = _xyz(xyz, "query points")
        m = np.full(len(x), self.distance)
        v = np.full(len(x), self.variance)
        return (m, v, np.zeros((len(x), 3))) if return_grad else (m, v)


# --------------------------------------------------------------- selection
def select_gp_points(prior_mean_at_hits, d_m: float) -> np.ndarray:
    """Training point selection (paper eq. condition1): ``|m(x)| > d_m``.

    Parameters
    ----------
    prior_mean_at_hits : (P,) array_like
        Prior mean at the hit points (whose true distance is 0).
    d_m : float
        Allowed discrepancy (m), >= 0.

    Returns
    -------
    (P,) bool mask of the points the GP trains on.
    """
    m = np.asarray(prior_mean_at_hits, dtype=np.float64)
    if m.ndim != 1:
        raise GPError(f"Expected prior means with shape (P,), found {m.shape}.")
    if not np.all(np.isfinite(m)):
        raise GPError(f"Expected finite prior means, found "
                      f"{int(np.count_nonzero(~np.isfinite(m)))} NaN or inf values.")
    if not (d_m >= 0 and math.isfinite(d_m)):
        raise GPError(f"Expected d_m >= 0, found {d_m}; use e.g. 0.02 m.")
    return np.abs(m) > d_m


# -------------------------------------------------------------- one block
@dataclass(frozen=True)
class BlockFit:
    """A fitted block: everything prediction needs.

    Attributes
    ----------
    X : (n, 3) training points
    sigma_p : (n,) prior standard deviation at ``X``
    L : (4n, 4n) lower Cholesky factor of ``S K S + noise + jitter``
    alpha : (4n,) ``K^-1`` times the residual targets (interleaved per point)
    jitter : float
        Absolute jitter added to the diagonal (m^2).
    jitter_raised : int
        How many times the jitter was raised x10 because Cholesky failed.
    """

    X: np.ndarray
    sigma_p: np.ndarray
    L: np.ndarray
    alpha: np.ndarray
    jitter: float
    jitter_raised: int = 0


def fit_block(X, sigma_p, targets, length_scale: float, value_noise: float,
              gradient_noise: float, jitter: float) -> BlockFit:
    """Factorise one block's training covariance (paper eqs. kernel2, kernel_j).

    ``K = S K_j S + diag(value_noise, gradient_noise x3, ...) + eps I`` with ``K_j``
    the joint kernel (eq. kernel_j), ``S`` the per-point prior standard deviations
    (eq. kernel2) and ``eps = jitter * mean(diag K)``; when the Cholesky
    factorisation fails ``eps`` grows x10 up to ``MAX_RELATIVE_JITTER``.

    Parameters
    ----------
    X : (n, 3)
    sigma_p : (n,)
    targets : (n, 4)
        Residual targets: value ``y - m(x)``, then ``n - grad m(x)``.
    length_scale, value_noise, gradient_noise, jitter : float

    Returns
    -------
    BlockFit
    """
    X = np.ascontiguousarray(X, dtype=np.float64)
    s = np.repeat(np.asarray(sigma_p, dtype=np.float64), 4)
    K = matern32_joint(X, X, length_scale)
    K *= s[:, None]
    K *= s[None, :]
    noise = np.tile([value_noise, gradient_noise, gradient_noise, gradient_noise], len(X))
    K[np.diag_indices_from(K)] += noise
    scale = float(np.mean(np.diag(K)))
    rel = jitter
    raised = 0
    while True:
        eps = rel * scale
        try:
            L = np.linalg.cholesky(K + eps * np.eye(len(K)))
            break
        except np.linalg.LinAlgError:
            rel = max(rel * 10.0, 1e-12)
            raised += 1
            if rel > MAX_RELATIVE_JITTER:
                raise GPError(
                    f"Block covariance of {len(X)} points is not positive definite even "
                    f"with relative jitter {MAX_RELATIVE_JITTER:g}; check for duplicate "
                    "points or raise GPConfig.value_noise.") from None
    y = np.asarray(targets, dtype=np.float64).reshape(-1)
    alpha = cho_solve((L, True), y)
    return BlockFit(X=X, sigma_p=np.asarray(sigma_p, dtype=np.float64), L=L, alpha=alpha,
                    jitter=float(eps), jitter_raised=raised)


def predict_block(fit: BlockFit, xs, sigma_s, length_scale: float, with_grad: bool):
    """Posterior of one block at test points (paper eqs. gpm2, gpv2, residual part).

    Returns the correction to the prior mean ``k*^T alpha``, the variance reduction
    ``k*^T K^-1 k*`` of the value, and (``with_grad``) the gradient correction.

    Parameters
    ----------
    fit : BlockFit
    xs : (q, 3)
    sigma_s : (q,)
        Prior standard deviation at the test points.
    length_scale : float
    with_grad : bool

    Returns
    -------
    dmean (q,), reduction (q,), dgrad (q, 3) or None
    """
    cols = np.repeat(fit.sigma_p, 4)
    Kc = matern32_cross(xs, fit.X, length_scale, with_grad=with_grad)
    Kc *= cols[None, :]
    if with_grad:
        Kc *= np.repeat(sigma_s, 4)[:, None]
        kv = Kc[0::4]
    else:
        Kc *= sigma_s[:, None]
        kv = Kc
    v = solve_triangular(fit.L, kv.T, lower=True, check_finite=False)
    reduction = np.einsum("ij,ij->j", v, v)
    if with_grad:
        full = Kc @ fit.alpha
        return full[0::4], reduction, full.reshape(-1, 4)[:, 1:]
    return kv @ fit.alpha, reduction, None


def blend_blocks(qi, dm, vb, n: int):
    """Inverse-variance blend of per-block predictions at the same queries.

    Parameters
    ----------
    qi : (P,) query index of each (query, block) pair
    dm, vb : (P,) block mean and variance of each pair
    n : number of queries

    Returns
    -------
    mbar (n,) blended mean, spread (n,) mixture variance (law of total variance, so
    disagreeing blocks widen it), covered (n,) bool, w (P,) normalised pair weights.
    """
    w = 1.0 / vb
    wsum = np.bincount(qi, weights=w, minlength=n)
    w = w / wsum[qi]
    mbar = np.bincount(qi, weights=w * dm, minlength=n)
    spread = np.bincount(qi, weights=w * (vb + (dm - mbar[qi]) ** 2), minlength=n)
    return mbar, spread, wsum > 0, w


# --------------------------------------------------------------- the field
class LocalGPField:
    """Prior + blended local GP posteriors (paper eqs. gpm2, gpv2).

    Built by :func:`fit_local_gps` or :meth:`from_arrays`.

    Attributes
    ----------
    prior : object with ``predict(xyz, return_grad)``
    grid : BlockGrid
    blocks : list of BlockFit
    info : dict
        Counts and jitter per fit (``n_points``, ``n_blocks``, ``n_capped_blocks``,
        ``max_jitter``, ...).
    """

    def __init__(self, prior, grid: BlockGrid, blocks: list, hyper: dict, info: dict):
        self.prior = prior
        self.grid = grid
        self.blocks = blocks
        self.hyper = dict(hyper)
        self.info = dict(info)

    @property
    def gp_points(self) -> np.ndarray:
        """(P, 3) distinct training points of all blocks."""
        if not self.blocks:
            return np.zeros((0, 3))
        return np.unique(np.concatenate([b.X for b in self.blocks]), axis=0)

    def predict(self, xyz, return_grad: bool = False):
        """Posterior signed distance at query points.

        ``mean = m(x) + k*^T alpha`` (eq. gpm2), ``var = sigma_p^2(x) - k*^T K^-1 k*
        + sigma_eta^2`` (eq. gpv2) per block; where several blocks cover a query they
        are mixed with weights proportional to ``1 / var_b`` and the variance is the
        mixture's (law of total variance, so disagreeing blocks widen it), capped at
        ``sigma_p^2(x) + sigma_eta^2``; the gradient
        uses the same weights (treated as constant). Outside every block the prior's
        mean and variance are returned unchanged.

        Parameters
        ----------
        xyz : (K, 3)
        return_grad : bool

        Returns
        -------
        mean (K,), var (K,)[, grad (K, 3)]
        """
        x = _xyz(xyz, "query points")
        out = self.prior.predict(x, return_grad=return_grad)
        m, v = np.array(out[0], dtype=np.float64), np.array(out[1], dtype=np.float64)
        g = np.array(out[2], dtype=np.float64) if return_grad else None
        if len(x) == 0 or not self.blocks:
            return (m, v, g) if return_grad else (m, v)
        qi, bi = self.grid.cover(x)
        if len(qi) == 0:
            return (m, v, g) if return_grad else (m, v)
        sig = np.sqrt(np.maximum(v, 0.0))
        noise = self.hyper["value_noise"]
        a = math.sqrt(3.0) / self.hyper["length_scale"]
        if return_grad:
            flat = self._flat()
            dm, red, dg = _predict_pairs(x, sig, qi, bi, flat["ptr"], flat["X"], flat["sp"],
                                         flat["L"], flat["Loff"], flat["alpha"], a, True)
        else:
            dm, red = self._value_pairs(x, sig, qi, bi, a)
        # eq. gpv2; clipped at the noise floor against round-off in k^T K^-1 k
        vb = np.maximum(v[qi] - red, 0.0) + noise
        mbar, spread, covered, w = blend_blocks(qi, dm, vb, len(x))
        m = m + mbar
        # block disagreement widens the variance, but never beyond what the prior
        # alone plus the noise would claim (the bound of eq. gpv2 for one block)
        v = np.where(covered, np.minimum(spread, v + noise), v)
        if return_grad:
            for c in range(3):
                g[:, c] += np.bincount(qi, weights=w * dg[:, c], minlength=len(x))
            return m, v, g
        return m, v

    def _value_pairs(self, x, sig, qi, bi, a):
        """Value posterior for (query, block) pairs sorted by block, one BLAS solve per block.

        The same numbers as :func:`_predict_pairs` without gradients (a test checks
        it); all queries of a block share one triangular solve with many right-hand
        sides (``trsm``), about 10x faster than one forward substitution per pair once
        a block has tens of queries, which the surface lattice always gives.
        """
        dm = np.empty(len(qi))
        red = np.empty(len(qi))
        for s, e in zip(*_runs(bi)):
            blk = self.blocks[bi[s]]
            kv = _value_cross(x, sig, qi[s:e], blk.X, blk.sigma_p, a)   # (q, 4n)
            dm[s:e] = kv @ blk.alpha
            # L v = k*  <=>  (L^T)^T v = k*: L^T of a C-ordered L is Fortran-ordered,
            # and kv^T too, so LAPACK gets both without a copy.
            v = solve_triangular(np.ascontiguousarray(blk.L).T, kv.T, trans="T", lower=False,
                                 check_finite=False, overwrite_b=True)
            red[s:e] = np.einsum("ij,ij->j", v, v)
        return dm, red

    def _flat(self) -> dict:
        """All blocks as flat arrays for the compiled predictor (built once)."""
        if getattr(self, "_flat_cache", None) is None:
            n = np.array([len(b.X) for b in self.blocks], dtype=np.int64)
            ptr = np.zeros(len(n) + 1, dtype=np.int64)
            np.cumsum(n, out=ptr[1:])
            loff = np.zeros(len(n) + 1, dtype=np.int64)
            np.cumsum((4 * n) ** 2, out=loff[1:])
            self._flat_cache = dict(
                ptr=ptr, Loff=loff,
                X=np.ascontiguousarray(np.concatenate([b.X for b in self.blocks])),
                sp=np.concatenate([b.sigma_p for b in self.blocks]),
                L=np.concatenate([b.L.reshape(-1) for b in self.blocks]),
                alpha=np.concatenate([b.alpha for b in self.blocks]))
        return self._flat_cache

    # ------------------------------------------------------------ persistence
    def to_arrays(self) -> dict:
        """Plain arrays describing the fitted blocks (for ``np.savez``, no pickle)."""
        n = np.array([len(b.X) for b in self.blocks], dtype=np.int64)
        ptr = np.zeros(len(n) + 1, dtype=np.int64)
        np.cumsum(n, out=ptr[1:])
        cat = lambda f, shape: (np.concatenate([f(b) for b in self.blocks])  # noqa: E731
                                if self.blocks else np.zeros(shape))
        return dict(
            gp_block_keys=self.grid.keys.copy(),
            gp_point_ptr=ptr,
            gp_X=cat(lambda b: b.X, (0, 3)),
            gp_sigma_p=cat(lambda b: b.sigma_p, (0,)),
            gp_alpha=cat(lambda b: b.alpha, (0,)),
            gp_L=cat(lambda b: b.L.reshape(-1), (0,)),
            gp_jitter=np.array([b.jitter for b in self.blocks], dtype=np.float64),
            gp_hyper=np.array([self.hyper[k] for k in _HYPER], dtype=np.float64),
        )

    @classmethod
    def from_arrays(cls, arrays: dict, prior, cfg) -> "LocalGPField":
        """Rebuild a field saved with :meth:`to_arrays`; it predicts identically.

        ``cfg`` (GPConfig) must carry the hyper-parameters the field was fitted with.
        """
        from gmmgp_app.config import concrete

        cfg = concrete(cfg)
        need = ("gp_block_keys", "gp_point_ptr", "gp_X", "gp_sigma_p", "gp_alpha", "gp_L",
                "gp_jitter", "gp_hyper")
        missing = [k for k in need if k not in arrays]
        if missing:
            raise GPError(f"Expected saved GP arrays {list(need)}, missing {missing}; "
                          "the map directory may be incomplete.")
        hyper = dict(zip(_HYPER, (float(h) for h in arrays["gp_hyper"])))
        for k in _HYPER:
            if not math.isclose(hyper[k], float(getattr(cfg, k)), rel_tol=1e-12):
                raise GPError(f"Saved GP was fitted with {k}={hyper[k]!r}, the config has "
                              f"{getattr(cfg, k)!r}; load with the configuration the map "
                              "was built with.")
        keys = np.asarray(arrays["gp_block_keys"], dtype=np.int64).reshape(-1, 3)
        grid = BlockGrid(keys, hyper["block_size"], hyper["block_overlap"])
        if not np.array_equal(grid.keys, keys):
            raise GPError("Saved GP block keys are not sorted; the arrays were not written "
                          "by LocalGPField.to_arrays.")
        ptr = np.asarray(arrays["gp_point_ptr"], dtype=np.int64)
        X = np.asarray(arrays["gp_X"], dtype=np.float64).reshape(-1, 3)
        sp = np.asarray(arrays["gp_sigma_p"], dtype=np.float64)
        al = np.asarray(arrays["gp_alpha"], dtype=np.float64)
        Lf = np.asarray(arrays["gp_L"], dtype=np.float64)
        jit = np.asarray(arrays["gp_jitter"], dtype=np.float64)
        if len(ptr) != len(keys) + 1 or ptr[-1] != len(X) or len(sp) != len(X) \
                or len(al) != 4 * len(X) or len(Lf) != int(np.sum((4 * np.diff(ptr)) ** 2)):
            raise GPError(f"Saved GP arrays are inconsistent ({len(keys)} blocks, "
                          f"{len(X)} points); the map directory may be corrupted.")
        blocks, lo = [], 0
        for b in range(len(keys)):
            s, e = ptr[b], ptr[b + 1]
            n4 = 4 * (e - s)
            blocks.append(BlockFit(X=X[s:e], sigma_p=sp[s:e], L=Lf[lo:lo + n4 * n4].reshape(
                n4, n4), alpha=al[4 * s:4 * e], jitter=float(jit[b])))
            lo += n4 * n4
        info = dict(n_blocks=len(blocks), loaded=True)
        return cls(prior, grid, blocks, hyper, info)


# ---------------------------------------------------------------- fitting
def fit_local_gps(points, normals, prior, cfg, *, rng=None, executor=None,
                  progress=None, min_task_seconds: float = 0.01) -> LocalGPField:
    """Fit the local GPs on residuals of ``prior`` (paper Sec. IV).

    Parameters
    ----------
    points : (P, 3)
        GP training points (hit points, true distance 0), usually those selected by
        :func:`select_gp_points`.
    normals : (P, 3)
        Unit normals at ``points`` (observed gradients of the distance).
    prior : object
        ``predict(xyz, return_grad=True) -> (mean, var, grad)``: a GMRField or a
        :class:`ConstantPrior`.
    cfg : GPConfig
        ``length_scale``, ``value_noise``, ``gradient_noise``, ``block_size``,
        ``block_overlap``, ``max_block_points``, ``jitter``.
    rng : numpy.random.Generator, optional
        Subsampling of blocks with more than ``max_block_points`` points
        (default ``np.random.default_rng(0)``).
    executor : concurrent.futures.Executor, optional
        Fit the blocks as tasks on this executor (local processes, Dask, ...; see
        :mod:`gmmgp_app.distributed`), consecutive blocks batched into tasks of at
        least ``min_task_seconds`` of estimated work. ``None`` (default): a plain
        loop in this process. Block subsampling always happens here, so every
        executor fits the same blocks on the same points.
    progress : callable(done, total), optional
        Called with the number of blocks fitted so far (one bar across tasks).
    min_task_seconds : float
        Smallest estimated work per task (s); Dask tasks cost about 1 ms each.

    Returns
    -------
    LocalGPField
    """
    from gmmgp_app.config import concrete

    cfg = concrete(cfg)
    pts = _xyz(points, "GP points")
    nrm = _xyz(normals, "GP normals")
    if len(pts) == 0:
        raise GPError("Expected at least one GP training point, found 0; lower "
                      "GPConfig.d_m or use the prior alone.")
    if nrm.shape != pts.shape:
        raise GPError(f"Expected one normal per GP point ({pts.shape}), found {nrm.shape}.")
    rng = np.random.default_rng(0) if rng is None else rng
    m, v, g = prior.predict(pts, return_grad=True)
    targets = np.column_stack([-np.asarray(m), nrm - np.asarray(g)])
    sigma_p = np.sqrt(np.maximum(np.asarray(v, dtype=np.float64), 0.0))
    if np.any(sigma_p <= 0):
        raise GPError("Expected a positive prior variance at every GP point, found zeros; "
                      "the prior cannot scale the kernel (eq. kernel2).")
    grid = BlockGrid.from_points(pts, cfg.block_size, cfg.block_overlap)
    pi, bi = grid.cover(pts)
    # Training points per block, capped by a draw in block order (the executor path
    # gets exactly the same selection as the serial one).
    sel, n_cand = [], []
    for s, e in zip(*_runs(bi)):
        idx = pi[s:e]
        n_cand.append(len(idx))
        if len(idx) > cfg.max_block_points:
            idx = np.sort(rng.choice(idx, cfg.max_block_points, replace=False))
        sel.append(idx)
    n_cand = np.array(n_cand)
    n_used = np.array([len(idx) for idx in sel])
    if executor is None:
        blocks = []
        for idx in sel:
            blocks.append(fit_block(pts[idx], sigma_p[idx], targets[idx], cfg.length_scale,
                                    cfg.value_noise, cfg.gradient_noise, cfg.jitter))
            if progress is not None:
                progress(len(blocks), len(sel))
    else:
        blocks = _fit_blocks_on(executor, pts, sigma_p, targets, sel, n_used, cfg, progress,
                                min_task_seconds)
    jit = np.array([b.jitter for b in blocks])
    info = dict(
        n_points=len(pts), n_blocks=len(blocks),
        points_per_block_max=int(n_used.max()), points_per_block_mean=float(n_used.mean()),
        n_capped_blocks=int(np.count_nonzero(n_cand > cfg.max_block_points)),
        n_points_dropped_by_cap=int(np.sum(n_cand - n_used)),
        max_block_points=int(cfg.max_block_points),
        jitter_relative=float(cfg.jitter), max_jitter=float(jit.max()),
        n_jitter_raised=int(sum(b.jitter_raised > 0 for b in blocks)),
        cholesky_bytes=int(np.sum((4 * n_used) ** 2) * 8),
    )
    hyper = {k: float(getattr(cfg, k)) for k in _HYPER}
    return LocalGPField(prior, grid, blocks, hyper, info)


def _runs(keys):
    """(starts, ends) of the runs of equal values in a sorted key array."""
    starts = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]]) if len(keys) else \
        np.zeros(0, dtype=np.int64)
    return starts, np.r_[starts[1:], len(keys)].astype(np.int64)


def _fit_blocks_on(executor, pts, sigma_p, targets, sel, n_used, cfg, progress,
                   min_task_seconds):
    """The block loop of :func:`fit_local_gps` as batched executor tasks."""
    from gmmgp_app.distributed import batch_by_cost, gp_block_seconds, map_batched

    hyper = (float(cfg.length_scale), float(cfg.value_noise), float(cfg.gradient_noise),
             float(cfg.jitter))
    batches = batch_by_cost(gp_block_seconds(n_used), min_task_seconds)
    tasks = [([(pts[sel[b]], sigma_p[sel[b]], targets[sel[b]]) for b in bt], hyper)
             for bt in batches]
    out = map_batched(executor, _fit_block_batch, tasks, sizes=[len(b) for b in batches],
                      progress=progress)
    return [fit for part in out for fit in part]


def _fit_block_batch(task) -> list:
    """One executor task: :func:`fit_block` on each ``(X, sigma_p, targets)``."""
    items, (ls, vn, gn, jit) = task
    return [fit_block(X, sp, t, ls, vn, gn, jit) for X, sp, t in items]


@nb.njit(cache=True)
def _value_cross(x, sig, q, X, sp, a):
    """Scaled cross-covariance rows ``k*`` of query values with a block's value+gradient
    observations (eqs. kernel2, kernel_j), (len(q), 4n); as in :func:`_predict_pairs`."""
    n = X.shape[0]
    out = np.empty((len(q), 4 * n))
    for p in range(len(q)):
        i0 = q[p]
        for i in range(n):
            d0 = x[i0, 0] - X[i, 0]
            d1 = x[i0, 1] - X[i, 1]
            d2 = x[i0, 2] - X[i, 2]
            r = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            ex = math.exp(-a * r)
            sc = sig[i0] * sp[i]
            a2e = sc * a * a * ex
            out[p, 4 * i] = sc * (1.0 + a * r) * ex
            out[p, 4 * i + 1] = a2e * d0
            out[p, 4 * i + 2] = a2e * d1
            out[p, 4 * i + 3] = a2e * d2
    return out


@nb.njit(parallel=True, cache=True, fastmath=False)
def _predict_pairs(x, sig, qi, bi, ptr, X, sp, L, Loff, alpha, a, with_grad):
    """Residual posterior of block ``bi[p]`` at query ``qi[p]`` for every pair p.

    The compiled twin of :func:`predict_block` (eqs. gpm2, gpv2 per block): the
    scaled cross-covariance row k* of the query's value (and gradient) with the
    block's value+gradient observations, ``k*^T alpha`` and ``|L^-1 k*|^2`` by
    forward substitution on the cached Cholesky factor.

    Returns
    -------
    dmean (P,), reduction (P,), dgrad (P, 3) (zeros unless ``with_grad``)
    """
    npair = len(qi)
    dm = np.empty(npair)
    red = np.empty(npair)
    dg = np.zeros((npair, 3))
    for p in nb.prange(npair):
        q, b = qi[p], bi[p]
        s, e = ptr[b], ptr[b + 1]
        n4 = 4 * (e - s)
        kv = np.empty(n4)
        kg = np.empty((3, n4)) if with_grad else np.empty((3, 0))
        for i in range(e - s):
            d0 = x[q, 0] - X[s + i, 0]
            d1 = x[q, 1] - X[s + i, 1]
            d2 = x[q, 2] - X[s + i, 2]
            r = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            ex = math.exp(-a * r)
            a2e = a * a * ex
            sc = sig[q] * sp[s + i]
            kv[4 * i] = sc * (1.0 + a * r) * ex
            kv[4 * i + 1] = sc * a2e * d0
            kv[4 * i + 2] = sc * a2e * d1
            kv[4 * i + 3] = sc * a2e * d2
            if with_grad:
                dd = (d0, d1, d2)
                ar = a / r if r > 0 else 0.0
                for c in range(3):
                    kg[c, 4 * i] = -sc * a2e * dd[c]
                    for j in range(3):
                        kg[c, 4 * i + 1 + j] = sc * a2e * ((1.0 if c == j else 0.0)
                                                           - ar * dd[c] * dd[j])
        mu = 0.0
        for k in range(n4):
            mu += kv[k] * alpha[4 * s + k]
        dm[p] = mu
        # forward substitution L v = kv, L row-major (n4, n4) at Loff[b]
        v = np.empty(n4)
        base = Loff[b]
        acc = 0.0
        for r_ in range(n4):
            t = kv[r_]
            row = base + r_ * n4
            for c_ in range(r_):
                t -= L[row + c_] * v[c_]
            v[r_] = t / L[row + r_]
            acc += v[r_] * v[r_]
        red[p] = acc
        if with_grad:
            for c in range(3):
                g = 0.0
                for k in range(n4):
                    g += kg[c, k] * alpha[4 * s + k]
                dg[p, c] = g
    return dm, red, dg
