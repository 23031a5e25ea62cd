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
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numba as nb
import numpy as np
from scipy.linalg import solve_triangular

from gmmgp_app.stages._blas import single_threaded_blas
from gmmgp_app.stages.kernels import _check_l, matern32_cross
from gmmgp_app.stages.octree import BlockGrid

__all__ = [
    "GPError",
    "ConstantPrior",
    "BlockFit",
    "LocalGPField",
    "select_gp_points",
    "neighbourhood_residual",
    "fit_block",
    "predict_block",
    "fit_local_gps",
    "fit_gp_blocks_at",
    "touched_blocks",
    "points_near_blocks",
    "refit_touched_blocks",
]

#: Cholesky jitter is raised x10 from ``GPConfig.jitter`` up to this (relative) bound.
MAX_RELATIVE_JITTER = 1e-2

_HYPER = ("length_scale", "value_noise", "gradient_noise", "block_size", "block_overlap",
          "prior_scale")


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


def neighbourhood_residual(points, prior_mean_at_hits, k: int) -> np.ndarray:
    """Mean of the prior's residual over each hit point's ``k`` nearest hit points
    (itself included): what the opt-in selection ``GPConfig.select_neighbours``
    compares with d_m in place of each point's own residual (paper eq. condition1).
    Not in the paper.

    Why: condition1 on a noisy point's own residual keeps, where the prior misses a
    surface by about d_m, only the points whose noise adds to the miss: a truncated,
    biased sample of the surface (the bench street's far facade: GP points 0.6-1.3 mm
    on the street side, docs/check.md Session 6), and a sparse one, between whose
    points the GP field is the prior. Averaged over ``k`` neighbours the noise drops by
    about sqrt(k) and the decision is the prior's error at that place: every point of
    a misfitted patch is kept, none of a fitted one.

    Parameters
    ----------
    points : (P, 3) array_like
        Hit points (the prepared training hits).
    prior_mean_at_hits : (P,) array_like
        Prior mean at ``points`` (their true distance is 0).
    k : int
        Neighbours averaged, >= 1 (1: the residuals themselves; at most P are used).

    Returns
    -------
    (P,) float64 array.
    """
    from scipy.spatial import cKDTree

    pts = _xyz(points, "hit points")
    m = np.asarray(prior_mean_at_hits, dtype=np.float64)
    if m.shape != (len(pts),):
        raise GPError(f"Expected one prior mean per hit point ({len(pts)}), found shape "
                      f"{m.shape}.")
    if int(k) != k or k < 1:
        raise GPError(f"Expected a neighbour count k >= 1, found {k}; use e.g. 16 "
                      "(or 1 for each point's own residual).")
    k = min(int(k), len(pts))
    if k <= 1:
        return m.copy()
    _, idx = cKDTree(pts).query(pts, k=k)
    return m[idx].mean(axis=1)


# -------------------------------------------------------------- one block
@dataclass(frozen=True)
class BlockFit:
    """A fitted block: everything prediction needs.

    Attributes
    ----------
    X : (n, 3) training points
    sigma_p : (n,) prior standard deviation at ``X``
    L_packed : (4n (4n + 1) / 2,) lower Cholesky factor of ``S K S + noise + jitter``,
        its lower triangle packed row by row (row ``r`` holds ``L[r, :r + 1]`` from
        ``r (r + 1) / 2``): half the memory of the square factor; :attr:`L` unpacks it
    alpha : (4n,) ``K^-1`` times the residual targets (interleaved per point)
    jitter : float
        Absolute jitter added to the diagonal (m^2).
    jitter_raised : int
        How many times the jitter was raised x10 because Cholesky failed.
    """

    X: np.ndarray
    sigma_p: np.ndarray
    L_packed: np.ndarray
    alpha: np.ndarray
    jitter: float
    jitter_raised: int = 0

    @property
    def L(self) -> np.ndarray:
        """The (4n, 4n) lower Cholesky factor (a new array, zeros above the diagonal)."""
        return unpack_lower(self.L_packed, 4 * len(self.X))


class FlatBlocks(Sequence):
    """The fitted blocks of a field, held as the flat arrays the compiled predictor
    reads (``ptr``, ``Loff``, ``X``, ``sp``, ``L``, ``alpha``) with each block's jitter;
    a :class:`BlockFit` (views into those arrays) is made when a block is asked for.
    The street's 57,786 blocks as BlockFit objects were ~28 MB of Python objects and
    ~0.7 s to make, which prediction and saving never use."""

    def __init__(self, flat: dict, jitter: np.ndarray, raised=None):
        self.flat = flat
        self.jitter = np.asarray(jitter, dtype=np.float64)
        self.raised = (np.zeros(len(self.jitter), np.int64) if raised is None
                       else np.asarray(raised, dtype=np.int64))

    def __len__(self) -> int:
        return len(self.flat["ptr"]) - 1

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        n = len(self)
        i = int(i)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"block {i} of {n}")
        f = self.flat
        s, e = f["ptr"][i], f["ptr"][i + 1]
        return BlockFit(X=f["X"][s:e], sigma_p=f["sp"][s:e],
                        L_packed=f["L"][f["Loff"][i]:f["Loff"][i + 1]],
                        alpha=f["alpha"][4 * s:4 * e], jitter=float(self.jitter[i]),
                        jitter_raised=int(self.raised[i]))


def _jitters(blocks) -> tuple:
    """(jitter (B,) float64, times raised (B,) int64) of a field's blocks."""
    if isinstance(blocks, FlatBlocks):
        return blocks.jitter, blocks.raised
    return (np.array([b.jitter for b in blocks], dtype=np.float64),
            np.array([b.jitter_raised for b in blocks], dtype=np.int64))


def packed_size(m) -> np.ndarray:
    """Entries of the packed lower triangle of an (m, m) matrix: ``m (m + 1) / 2``."""
    m = np.asarray(m, dtype=np.int64)
    return m * (m + 1) // 2


def pack_lower(L: np.ndarray) -> np.ndarray:
    """The lower triangle of a square matrix, row by row (the layout of
    :attr:`BlockFit.L_packed`)."""
    return np.ascontiguousarray(L[np.tril_indices(len(L))])


def unpack_lower(Lp: np.ndarray, m: int) -> np.ndarray:
    """(m, m) lower-triangular matrix from its packed rows (inverse of
    :func:`pack_lower`)."""
    L = np.zeros((m, m))
    L[np.tril_indices(m)] = Lp
    return L


def fit_block(X, sigma_p, targets, length_scale: float, value_noise: float,
              gradient_noise: float, jitter: float) -> BlockFit:
    """Factorise one block's training covariance (paper eqs. kernel2, kernel_j).

    ``K = S K_j S + diag(value_noise, gradient_noise x3, ...) + eps I`` with ``K_j``
    the joint kernel (eq. kernel_j), ``S`` the per-point prior standard deviations
    (eq. kernel2) and ``eps = jitter * mean(diag K)``; when the Cholesky
    factorisation fails ``eps`` grows x10 up to ``MAX_RELATIVE_JITTER``.

    The work is done by the compiled batch fitter :func:`_fit_blocks` (one block
    here; :func:`fit_local_gps` hands it all blocks at once).

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
    X = np.ascontiguousarray(X, dtype=np.float64).reshape(-1, 3)
    blocks, _ = _fit_many(X, sigma_p, targets, np.array([len(X)]), length_scale,
                          value_noise, gradient_noise, jitter)
    return blocks[0]


def _fit_many(X, sigma_p, targets, counts, length_scale, value_noise, gradient_noise,
              jitter, progress=None):
    """Fit consecutive blocks of ``counts`` points each from concatenated arrays.

    Returns the blocks (:class:`FlatBlocks`: BlockFits made on demand as views into
    shared flat arrays) and those flat arrays
    (``ptr``, ``Loff``, ``X``, ``sp``, ``L``, ``alpha``: the layout the compiled
    predictor reads, so prediction needs no copy of the factors; ``L`` holds the packed
    lower triangles, block ``b`` at ``Loff[b]``).
    """
    X = np.ascontiguousarray(X, dtype=np.float64).reshape(-1, 3)
    sp = np.ascontiguousarray(sigma_p, dtype=np.float64).reshape(-1)
    T = np.ascontiguousarray(targets, dtype=np.float64).reshape(-1, 4)
    counts = np.asarray(counts, dtype=np.int64)
    a = math.sqrt(3.0) / _check_l(length_scale)
    nb_ = len(counts)
    ptr = np.zeros(nb_ + 1, dtype=np.int64)
    np.cumsum(counts, out=ptr[1:])
    loff = np.zeros(nb_ + 1, dtype=np.int64)
    np.cumsum(packed_size(4 * counts), out=loff[1:])
    L = np.empty(int(loff[-1]))
    alpha = np.empty(4 * int(ptr[-1]))
    eps = np.zeros(nb_)
    raised = np.zeros(nb_, dtype=np.int64)
    failed = np.zeros(nb_, dtype=np.bool_)
    # chunks of about equal work, so a progress bar moves
    cost = np.cumsum((4.0 * counts) ** 3 + 1e3)
    n_chunks = 1 if progress is None else min(nb_, 50)
    cuts = np.searchsorted(cost, cost[-1] * np.arange(1, n_chunks) / n_chunks) if nb_ else []
    bounds = np.r_[0, np.asarray(cuts, dtype=np.int64), nb_]
    for b0, b1 in zip(bounds[:-1], bounds[1:]):
        if b1 > b0:
            _fit_blocks(X, sp, T, ptr, loff, a, float(value_noise), float(gradient_noise),
                        float(jitter), MAX_RELATIVE_JITTER, int(b0), int(b1), L, alpha, eps,
                        raised, failed)
        if progress is not None:
            progress(int(b1), nb_)
    if failed.any():
        n = int(counts[np.flatnonzero(failed)[0]])
        raise GPError(
            f"Block covariance of {n} points is not positive definite even "
            f"with relative jitter {MAX_RELATIVE_JITTER:g}; check for duplicate "
            "points or raise GPConfig.value_noise.")
    flat = dict(ptr=ptr, Loff=loff, X=X, sp=sp, L=L, alpha=alpha)
    return FlatBlocks(flat, eps, raised), flat


@nb.njit(parallel=True, cache=True)
def _fit_blocks(X, sp, T, ptr, loff, a, value_noise, gradient_noise, jitter, max_rel,
                b0, b1, L, alpha, eps_out, raised_out, failed):
    """Blocks ``b0 .. b1-1``: joint kernel (eq. kernel_j) scaled by the prior (eq.
    kernel2) plus noise, its Cholesky factor (jitter raised x10 on failure, as
    :func:`fit_block` documents) into ``L`` (lower triangle packed row by row at
    ``loff[b]``) and ``alpha = K^-1 targets`` into ``alpha``; ``failed[b]`` when even
    ``max_rel`` jitter does not make the block positive definite."""
    for b in nb.prange(b0, b1):
        s0 = ptr[b]
        n = ptr[b + 1] - s0
        m = 4 * n
        K = np.empty((m, m))                        # lower triangle used
        for i in range(n):
            for j in range(i + 1):
                d0 = X[s0 + i, 0] - X[s0 + j, 0]
                d1 = X[s0 + i, 1] - X[s0 + j, 1]
                d2 = X[s0 + i, 2] - X[s0 + j, 2]
                r = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
                e = math.exp(-a * r)
                a2e = a * a * e
                ar = a * (1.0 / r) if r > 0 else 0.0
                si, sj = sp[s0 + i], sp[s0 + j]
                dd = (d0, d1, d2)
                for p in range(4):
                    for q in range(4):
                        if i == j and q > p:
                            continue
                        if p == 0 and q == 0:
                            k = (1.0 + a * r) * e
                        elif p == 0:
                            k = a2e * dd[q - 1]
                        elif q == 0:
                            k = -(a2e * dd[p - 1])
                        else:
                            k = a2e * ((1.0 if p == q else 0.0) - ar * (dd[p - 1] * dd[q - 1]))
                        K[4 * i + p, 4 * j + q] = (k * si) * sj
        diag = 0.0
        for d in range(m):
            K[d, d] += value_noise if d % 4 == 0 else gradient_noise
            diag += K[d, d]
        scale = diag / m
        Lb = np.empty((m, m))                       # this block's factor, lower part
        rel = jitter
        raised = 0
        while True:
            ep = rel * scale
            ok = _cholesky_crout(K, ep, Lb)
            if ok:
                break
            rel = max(rel * 10.0, 1e-12)
            raised += 1
            if rel > max_rel:
                failed[b] = True
                break
        eps_out[b] = ep
        raised_out[b] = raised
        if failed[b]:
            continue
        base = loff[b]
        for r_ in range(m):
            row = base + r_ * (r_ + 1) // 2
            for c in range(r_ + 1):
                L[row + c] = Lb[r_, c]
        # alpha = L^-T L^-1 y, y interleaved per point (value, gradient)
        z = np.empty(m)
        for r_ in range(m):
            t = T[s0 + r_ // 4, r_ % 4]
            for c in range(r_):
                t -= Lb[r_, c] * z[c]
            z[r_] = t / Lb[r_, r_]
        for r_ in range(m - 1, -1, -1):
            t = z[r_]
            for c in range(r_ + 1, m):
                t -= Lb[c, r_] * alpha[4 * s0 + c]
            alpha[4 * s0 + r_] = t / Lb[r_, r_]


@nb.njit(cache=True, inline="always")
def _cholesky_crout(K, ep, Lb):
    """Lower Cholesky factor of ``K + ep I`` (lower triangle of ``K`` read) into ``Lb``,
    column by column (Crout), each entry ``K[r, c] - sum_k Lb[r, k] Lb[c, k]`` taken
    with k ascending; False (``Lb`` partly written) when a pivot is not positive.

    The rows below the diagonal are done four at a time: their sums are independent
    chains of the same operations, which the processor overlaps instead of waiting on
    one subtraction after another (the same bits as one row at a time).
    """
    m = K.shape[0]
    for c in range(m):
        t = K[c, c] + ep
        for k2 in range(c):
            t -= Lb[c, k2] * Lb[c, k2]
        if not t > 0.0:
            return False
        d = math.sqrt(t)
        Lb[c, c] = d
        r_ = c + 1
        while r_ + 4 <= m:
            t0 = K[r_, c] + 0.0
            t1 = K[r_ + 1, c] + 0.0
            t2 = K[r_ + 2, c] + 0.0
            t3 = K[r_ + 3, c] + 0.0
            for k2 in range(c):
                lc = Lb[c, k2]
                t0 -= Lb[r_, k2] * lc
                t1 -= Lb[r_ + 1, k2] * lc
                t2 -= Lb[r_ + 2, k2] * lc
                t3 -= Lb[r_ + 3, k2] * lc
            Lb[r_, c] = t0 / d
            Lb[r_ + 1, c] = t1 / d
            Lb[r_ + 2, c] = t2 / d
            Lb[r_ + 3, c] = t3 / d
            r_ += 4
        while r_ < m:
            t = K[r_, c] + 0.0
            for k2 in range(c):
                t -= Lb[r_, k2] * Lb[c, k2]
            Lb[r_, c] = t / d
            r_ += 1
    return True


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
    blocks : sequence of BlockFit (a :class:`FlatBlocks` when fitted or loaded)
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

    @single_threaded_blas
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
        # the GP's prior standard deviation is c sigma_p (GPConfig.prior_scale)
        v *= self.hyper.get("prior_scale", 1.0) ** 2
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
        """Value posterior for (query, block) pairs sorted by block, one compiled
        triangular solve per block for all its queries (:func:`_value_blocks`; BLAS
        ``trsm`` per block did the same with a call overhead per block)."""
        flat = self._flat()
        starts, ends = _runs(bi)
        dm = np.empty(len(qi))
        red = np.empty(len(qi))
        _value_blocks(x, sig, qi, bi, starts, ends, flat["ptr"], flat["X"], flat["sp"],
                      flat["L"], flat["Loff"], flat["alpha"], a, dm, red)
        return dm, red

    def _flat(self) -> dict:
        """All blocks as flat arrays for the compiled predictor (built once)."""
        if getattr(self, "_flat_cache", None) is None:
            n = np.array([len(b.X) for b in self.blocks], dtype=np.int64)
            ptr = np.zeros(len(n) + 1, dtype=np.int64)
            np.cumsum(n, out=ptr[1:])
            loff = np.zeros(len(n) + 1, dtype=np.int64)
            np.cumsum(packed_size(4 * n), out=loff[1:])
            self._flat_cache = dict(
                ptr=ptr, Loff=loff,
                X=np.ascontiguousarray(np.concatenate([b.X for b in self.blocks])),
                sp=np.concatenate([b.sigma_p for b in self.blocks]),
                L=np.concatenate([b.L_packed for b in self.blocks]),
                alpha=np.concatenate([b.alpha for b in self.blocks]))
        return self._flat_cache

    # ------------------------------------------------------------ persistence
    def to_arrays(self) -> dict:
        """Plain arrays describing the fitted blocks (for ``np.savez``, no pickle)."""
        if self.blocks:  # the flat arrays the blocks are views of: no copy of the factors
            f = self._flat()
            return dict(gp_block_keys=self.grid.keys.copy(), gp_point_ptr=f["ptr"],
                        gp_X=f["X"], gp_sigma_p=f["sp"], gp_alpha=f["alpha"], gp_L=f["L"],
                        gp_jitter=_jitters(self.blocks)[0].copy(),
                        gp_hyper=np.array([self.hyper[k] for k in _HYPER], dtype=np.float64))
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
            gp_L=cat(lambda b: b.L_packed, (0,)),
            gp_jitter=np.array([b.jitter for b in self.blocks], dtype=np.float64),
            gp_hyper=np.array([self.hyper[k] for k in _HYPER], dtype=np.float64),
        )

    @classmethod
    def from_arrays(cls, arrays: dict, prior, cfg) -> "LocalGPField":
        """Rebuild a field saved with :meth:`to_arrays`; it predicts identically.

        ``cfg`` (GPConfig) must carry the hyper-parameters the field was fitted with.
        ``gp_L`` holds the packed lower triangles of the factors; maps saved before
        they were packed (square factors, told apart by the array's length) are packed
        on loading.
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
        hyper.setdefault("prior_scale", 1.0)     # maps saved before the field existed
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
        m = 4 * np.diff(ptr) if len(ptr) == len(keys) + 1 else np.zeros(0, np.int64)
        n_packed, n_square = int(np.sum(packed_size(m))), int(np.sum(m ** 2))
        if len(ptr) != len(keys) + 1 or ptr[-1] != len(X) or len(sp) != len(X) \
                or len(al) != 4 * len(X) or len(Lf) not in (n_packed, n_square):
            raise GPError(f"Saved GP arrays are inconsistent ({len(keys)} blocks, "
                          f"{len(X)} points); the map directory may be corrupted.")
        loff = np.zeros(len(keys) + 1, dtype=np.int64)
        np.cumsum(packed_size(m), out=loff[1:])
        if len(Lf) != n_packed:          # square factors of an older map: pack them
            Lf = _pack_square_factors(Lf, m, loff)
        flat = dict(ptr=ptr, Loff=loff, X=np.ascontiguousarray(X), sp=sp, L=Lf, alpha=al)
        blocks = FlatBlocks(flat, jit)
        info = dict(n_blocks=len(blocks), loaded=True)
        field_ = cls(prior, grid, blocks, hyper, info)
        field_._flat_cache = flat
        return field_


# ---------------------------------------------------------------- fitting
@single_threaded_blas
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
    sigma_p = cfg.prior_scale * np.sqrt(np.maximum(np.asarray(v, dtype=np.float64), 0.0))
    if np.any(sigma_p <= 0):
        raise GPError("Expected a positive prior variance at every GP point, found zeros; "
                      "the prior cannot scale the kernel (eq. kernel2).")
    grid = BlockGrid.from_points(pts, cfg.block_size, cfg.block_overlap)
    pi, bi = grid.cover(pts)
    # Training points per block, capped by a draw in block order (the executor path
    # gets exactly the same selection as the serial one). Only the capped blocks draw
    # (a loop over them, in block order: the draws of a loop over every block).
    starts, ends = _runs(bi)
    n_cand = ends - starts
    cap = int(cfg.max_block_points)
    n_used = np.minimum(n_cand, cap)
    capped = np.flatnonzero(n_cand > cap)
    cat, prev = [], 0
    for b in capped:
        cat.append(pi[prev:starts[b]])
        cat.append(np.sort(rng.choice(pi[starts[b]:ends[b]], cap, replace=False)))
        prev = ends[b]
    cat = np.concatenate(cat + [pi[prev:]]) if len(capped) else pi
    from gmmgp_app.distributed import SerialExecutor

    if executor is None or type(executor) is SerialExecutor:  # in this process: no copies
        blocks, flat = _fit_many(pts[cat], sigma_p[cat], targets[cat], n_used,
                                 cfg.length_scale, cfg.value_noise, cfg.gradient_noise,
                                 cfg.jitter, progress=progress)
    else:
        sel = np.split(cat, np.cumsum(n_used)[:-1])
        blocks = _fit_blocks_on(executor, pts, sigma_p, targets, sel, n_used, cfg, progress,
                                min_task_seconds)
        blocks, flat = _pack_blocks(blocks)
    jit, raised = _jitters(blocks)
    info = dict(
        n_points=len(pts), n_blocks=len(blocks),
        points_per_block_max=int(n_used.max()), points_per_block_mean=float(n_used.mean()),
        n_capped_blocks=int(np.count_nonzero(n_cand > cfg.max_block_points)),
        n_points_dropped_by_cap=int(np.sum(n_cand - n_used)),
        max_block_points=int(cfg.max_block_points),
        jitter_relative=float(cfg.jitter), max_jitter=float(jit.max()),
        n_jitter_raised=int(np.count_nonzero(raised > 0)),
        cholesky_bytes=int(np.sum(packed_size(4 * n_used)) * 8),
    )
    hyper = {k: float(getattr(cfg, k)) for k in _HYPER}
    field_ = LocalGPField(prior, grid, blocks, hyper, info)
    field_._flat_cache = flat
    return field_


def _pack_blocks(blocks):
    """Blocks fitted elsewhere, re-pointed into one set of flat arrays (the compiled
    predictor's layout; the per-block copies are freed)."""
    n = np.array([len(b.X) for b in blocks], dtype=np.int64)
    ptr = np.zeros(len(n) + 1, dtype=np.int64)
    np.cumsum(n, out=ptr[1:])
    loff = np.zeros(len(n) + 1, dtype=np.int64)
    np.cumsum(packed_size(4 * n), out=loff[1:])
    flat = dict(ptr=ptr, Loff=loff,
                X=np.ascontiguousarray(np.concatenate([b.X for b in blocks]).reshape(-1, 3)),
                sp=np.concatenate([b.sigma_p for b in blocks]),
                L=np.concatenate([b.L_packed for b in blocks]),
                alpha=np.concatenate([b.alpha for b in blocks]))
    out = []
    for i, b in enumerate(blocks):
        s, e = ptr[i], ptr[i + 1]
        out.append(replace(b, X=flat["X"][s:e], sigma_p=flat["sp"][s:e],
                           L_packed=flat["L"][loff[i]:loff[i + 1]],
                           alpha=flat["alpha"][4 * s:4 * e]))
    return out, flat


@nb.njit(cache=True)
def _pack_square_factors(Lsq, m, loff):
    """Square row-major factors (an older map's ``gp_L``) -> packed lower triangles."""
    out = np.empty(loff[-1])
    sq = 0
    for b in range(len(m)):
        mb = m[b]
        for r in range(mb):
            row = loff[b] + r * (r + 1) // 2
            for c in range(r + 1):
                out[row + c] = Lsq[sq + r * mb + c]
        sq += mb * mb
    return out


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


def fit_gp_blocks_at(keys, points, normals, prior, cfg, executor=None) -> LocalGPField:
    """Local GPs of the blocks ``keys`` only, each on the GP points of its region.

    The blocks of :func:`fit_local_gps` restricted to given cells (the incremental
    update of a map refits only the blocks new points touch); points per block are
    capped as there, with the same seed.
    """
    from gmmgp_app.config import concrete

    cfg = concrete(cfg)
    grid = BlockGrid(keys, cfg.block_size, cfg.block_overlap)
    m, v, g = prior.predict(points, return_grad=True)
    targets = np.column_stack([-np.asarray(m), normals - np.asarray(g)])
    sigma_p = cfg.prior_scale * np.sqrt(np.maximum(np.asarray(v, dtype=np.float64), 0.0))
    pi, bi = grid.cover(points)
    rng = np.random.default_rng(0)
    items = []
    for b in range(grid.n_blocks):
        idx = pi[bi == b]
        if len(idx) > cfg.max_block_points:
            idx = np.sort(rng.choice(idx, cfg.max_block_points, replace=False))
        items.append((points[idx], sigma_p[idx], targets[idx]))
    from gmmgp_app.distributed import batch_by_cost, gp_block_seconds, map_batched

    hyper = (float(cfg.length_scale), float(cfg.value_noise), float(cfg.gradient_noise),
             float(cfg.jitter))
    batches = batch_by_cost(gp_block_seconds([len(it[0]) for it in items]))
    out = map_batched(executor, _fit_block_batch,
                      [([items[i] for i in bt], hyper) for bt in batches])
    blocks = [f for part in out for f in part]
    return LocalGPField(prior, grid, blocks, {k: float(getattr(cfg, k)) for k in _HYPER}, {})


def touched_blocks(gp: LocalGPField, new_points) -> BlockGrid:
    """Cells of ``gp``'s block lattice whose training region holds a new point."""
    bs, ov = gp.hyper["block_size"], gp.hyper["block_overlap"]
    half = 0.5 * (1.0 + ov) * bs
    # cells whose training region [c*bs + bs/2 - half, ...] contains a new point
    reach = int(math.ceil(half / bs - 0.5))
    base = np.unique(np.floor(new_points / bs).astype(np.int64), axis=0)
    rng_ = np.arange(-reach, reach + 1)
    offs = np.stack(np.meshgrid(rng_, rng_, rng_, indexing="ij"), -1).reshape(-1, 3)
    touched = np.unique((base[:, None, :] + offs[None]).reshape(-1, 3), axis=0)
    return BlockGrid(touched, bs, ov)


def points_near_blocks(grid: BlockGrid, points, margin: float) -> np.ndarray:
    """Index of ``points`` within about ``margin`` (m) of the training regions of
    ``grid``'s blocks (a superset, through a coarse grid of cell >= margin: cells
    around the blocks' centres; BlockGrid.cover with a huge overlap loops over
    span^3 offsets)."""
    coarse = margin + grid.block_size
    ck = np.unique(np.floor(grid.centres / coarse).astype(np.int64), axis=0)
    o1 = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), -1).reshape(-1, 3)
    ck = np.unique((ck[:, None, :] + o1[None]).reshape(-1, 3), axis=0)
    return np.flatnonzero(BlockGrid(ck, coarse, 0.0).lookup(
        np.floor(points / coarse).astype(np.int64)) >= 0)


def refit_touched_blocks(gp: LocalGPField, touched: BlockGrid, points, normals, cfg,
                         executor=None):
    """Replace the blocks of ``gp`` in ``touched`` by blocks fitted on GP points.

    Only the touched cells that hold a GP point are fitted (as :func:`fit_local_gps`
    would create them), each on the GP points of its whole training region; every
    other block keeps its factorisation.

    Returns
    -------
    (LocalGPField, (P', 3) GP points used, int blocks refitted)
    """
    bs, ov = gp.hyper["block_size"], gp.hyper["block_overlap"]
    keep_pts = np.zeros(len(points), dtype=bool)
    if len(points):
        keep_pts[touched.cover(points)[0]] = True
    pts, nrm = points[keep_pts], normals[keep_pts]
    # old blocks outside the touched set stay as they are
    old_touched = touched.lookup(gp.grid.keys) >= 0
    keys = [gp.grid.keys[~old_touched]]
    blocks = [b for b, t in zip(gp.blocks, old_touched) if not t]
    n_refit = 0
    if len(pts):
        own = np.unique(np.floor(pts / bs).astype(np.int64), axis=0)
        own = own[touched.lookup(own) >= 0]
        new = fit_gp_blocks_at(own, pts, nrm, gp.prior, cfg, executor)
        keys.append(new.grid.keys)
        blocks += list(new.blocks)
        n_refit = len(new.blocks)
    all_keys = np.concatenate(keys)
    grid = BlockGrid(all_keys, bs, ov)
    # BlockGrid sorts its keys: put the blocks in the same order
    order = grid.lookup(all_keys)
    sorted_blocks = [None] * len(blocks)
    for b, pos in zip(blocks, order):
        sorted_blocks[pos] = b
    field = LocalGPField(gp.prior, grid, sorted_blocks, gp.hyper,
                         dict(gp.info, n_blocks=len(sorted_blocks), updated=True))
    return field, pts, n_refit


def _fit_block_batch(task) -> list:
    """One executor task: :func:`fit_block` on each ``(X, sigma_p, targets)``."""
    items, (ls, vn, gn, jit) = task
    if not items:
        return []
    counts = np.array([len(X) for X, _, _ in items], dtype=np.int64)
    blocks, _ = _fit_many(np.concatenate([np.reshape(X, (-1, 3)) for X, _, _ in items]),
                          np.concatenate([np.reshape(sp, -1) for _, sp, _ in items]),
                          np.concatenate([np.reshape(t, (-1, 4)) for _, _, t in items]),
                          counts, ls, vn, gn, jit)
    return list(blocks)


@nb.njit(cache=True, nogil=True)
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


@nb.njit(parallel=True, cache=True, nogil=True)
def _value_blocks(x, sig, qi, bi, starts, ends, ptr, X, sp, L, Loff, alpha, a, dm, red):
    """Value posterior of every (query, block) pair, pairs sorted by block; run
    ``[starts[t], ends[t])`` holds the queries of one block (eqs. gpm2, gpv2).

    Per block: the scaled cross-covariances ``k*`` of all its queries as the columns
    of a (4n, q) matrix, ``k*^T alpha``, then ``L V = K*`` by forward substitution
    row by row, each row update running over all q queries at once (what BLAS
    ``trsm`` does), and ``|v|^2`` per query. Blocks run in parallel.

    The cross-covariances are filled training point by training point, each pass over
    the block's queries (gathered once) in three loops: the distances (vectorised
    square roots), the exponentials, the four entries; the same arithmetic per entry
    as query by query (tests/test_gp.py keeps that kernel as the oracle), a sixth
    less time. (Holding eight queries' substitution in registers, or sixteen in a
    scratch row, was slower than the row updates.)
    """
    for blk in nb.prange(len(starts)):
        s, e = starts[blk], ends[blk]
        b = bi[s]
        p0, p1 = ptr[b], ptr[b + 1]
        n4 = 4 * (p1 - p0)
        nq = e - s
        q0 = np.empty(nq)
        q1 = np.empty(nq)
        q2 = np.empty(nq)
        sq = np.empty(nq)
        for j in range(nq):
            q = qi[s + j]
            q0[j] = x[q, 0]
            q1[j] = x[q, 1]
            q2[j] = x[q, 2]
            sq[j] = sig[q]
        V = np.empty((n4, nq))
        rr = np.empty(nq)
        ex = np.empty(nq)
        for i in range(p1 - p0):
            X0 = X[p0 + i, 0]
            X1 = X[p0 + i, 1]
            X2 = X[p0 + i, 2]
            spi = sp[p0 + i]
            for j in range(nq):
                d0 = q0[j] - X0
                d1 = q1[j] - X1
                d2 = q2[j] - X2
                rr[j] = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            for j in range(nq):
                ex[j] = math.exp(-a * rr[j])
            for j in range(nq):
                d0 = q0[j] - X0
                d1 = q1[j] - X1
                d2 = q2[j] - X2
                sc = sq[j] * spi
                a2e = sc * a * a * ex[j]
                V[4 * i, j] = sc * (1.0 + a * rr[j]) * ex[j]
                V[4 * i + 1, j] = a2e * d0
                V[4 * i + 2, j] = a2e * d1
                V[4 * i + 3, j] = a2e * d2
        for j in range(nq):
            dm[s + j] = 0.0
        for k in range(n4):                 # per query summed over k in order, as before
            al = alpha[4 * p0 + k]
            for j in range(nq):
                dm[s + j] += V[k, j] * al
        base = Loff[b]
        acc = np.zeros(nq)
        for r_ in range(n4):
            row = base + r_ * (r_ + 1) // 2         # packed lower triangle, row r_
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


@nb.njit(parallel=True, cache=True, fastmath=False, nogil=True)
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
        # forward substitution L v = kv, L's lower triangle packed by rows at Loff[b]
        v = np.empty(n4)
        base = Loff[b]
        acc = 0.0
        for r_ in range(n4):
            t = kv[r_]
            row = base + r_ * (r_ + 1) // 2
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
