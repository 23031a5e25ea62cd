"""GP hyper-parameters from the data: maximum marginal likelihood over sampled blocks.

The local GPs (:mod:`.gp`) model the residuals of the prior at the GP points with
the covariance ``K = c^2 S K_j S + diag(sigma_eta^2, sigma_g^2 x3, ...) + eps I``
(paper eqs. kernel_j, kernel2; ``c`` a multiplier on the prior's standard deviation
``sigma_p``). The automatic values of the length scale ``l``, the value and gradient
noise variances and ``c = 1`` are rules of thumb from the measured spacing and noise
(:mod:`.autoscale`). This stage checks them against the data: for a seeded sample of
GP blocks it evaluates the exact log marginal likelihood of each block's residual
targets (eq. lml, Rasmussen & Williams 2006, eq. 2.30)::

    log p(y | X, theta) = -1/2 y^T K^-1 y - 1/2 log |K| - (4 n / 2) log 2 pi      (eq. lml)

sums it over the blocks and picks the multipliers of the automatic values that
maximise the sum over a small grid (:data:`GRID`; every combination, at most 135). The blocks are the
:class:`~.octree.BlockGrid` leaves of the GP points, drawn uniformly among the
occupied leaves with a fixed seed; each contributes the (at most ``max_points``)
training points of its region nearest to its centre, a compact patch whose spacing
is the scan's. Every candidate is a multiplier, and a scan scaled by ``a`` scales
every block's covariance by ``diag(a, 1, 1, 1)`` on both sides, so the summed LML of
every candidate shifts by the same constant and the choice is the same at every
scale.

Only fields still chosen automatically are searched (a ``--set`` value is kept at
multiplier 1). The jitter is ``GPConfig.jitter`` (1e-8) times each row's own variance,
raised x10 when the factorisation fails (:func:`.gp.fit_block` uses the mean diagonal;
per row keeps the choice independent of the units).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import LinAlgError, cho_solve, cholesky, solve_triangular

from gmmgp_app.stages._blas import single_threaded_blas
from gmmgp_app.stages.gp import MAX_RELATIVE_JITTER, GPError
from gmmgp_app.stages.kernels import matern32_joint
from gmmgp_app.stages.octree import BlockGrid

__all__ = ["GRID", "HyperChoice", "block_log_marginal_likelihood", "sample_blocks",
           "BlockSample", "select_hyperparameters"]

#: Multipliers tried for each automatic value (the length scale, the two noise
#: variances and the prior's standard deviation).
GRID = {
    "length_scale": (0.5, 0.7, 1.0, 1.4, 2.0),
    "value_noise": (0.25, 1.0, 4.0),
    "gradient_noise": (0.25, 1.0, 4.0),
    "prior_scale": (0.5, 1.0, 2.0),
}
_ORDER = ("length_scale", "value_noise", "gradient_noise", "prior_scale")
_LOG2PI = math.log(2.0 * math.pi)


def _cholesky_with_jitter(K: np.ndarray, jitter: float):
    """Lower Cholesky factor of ``K + eps diag(K)`` with ``eps = jitter`` raised x10 on
    failure up to :data:`.gp.MAX_RELATIVE_JITTER` (the rule of :func:`.gp.fit_block`,
    but relative to each row's own variance rather than the mean diagonal: value rows
    (m^2) and gradient rows (1) scale differently with the scan, and a jitter of the
    mean diagonal would make the choice depend on the units). Returns ``(L, largest
    absolute jitter, times raised)``."""
    dK = np.diag(K).copy()
    rel, raised = float(jitter), 0
    idx = np.diag_indices_from(K)
    while True:
        A = K.copy()
        A[idx] += rel * dK
        try:
            return cholesky(A, lower=True, check_finite=False), rel * float(dK.max()), raised
        except LinAlgError:
            rel = max(rel * 10.0, 1e-12)
            raised += 1
            if rel > MAX_RELATIVE_JITTER:
                raise GPError(
                    f"Block covariance of {len(K) // 4} points is not positive definite "
                    f"even with relative jitter {MAX_RELATIVE_JITTER:g}; check for "
                    "duplicate points or raise GPConfig.value_noise.") from None


def _lml_from(Kj, sigma_p, y, value_noise, gradient_noise, prior_scale, jitter):
    s = np.repeat(prior_scale * sigma_p, 4)
    K = s[:, None] * Kj * s[None, :]
    d = np.diag_indices_from(K)
    K[d] += np.tile([value_noise, gradient_noise, gradient_noise, gradient_noise],
                    len(sigma_p))
    L, eps, raised = _cholesky_with_jitter(K, jitter)
    alpha = cho_solve((L, True), y, check_finite=False)
    lml = -0.5 * float(y @ alpha) - float(np.sum(np.log(np.diag(L)))) - 0.5 * len(y) * _LOG2PI
    return lml, eps, raised


@single_threaded_blas
def block_log_marginal_likelihood(X, sigma_p, targets, length_scale: float,
                                  value_noise: float, gradient_noise: float,
                                  jitter: float = 1e-8, prior_scale: float = 1.0):
    """Exact log marginal likelihood of one block's residual targets (eq. lml).

    The covariance is the one :func:`.gp.fit_block` factorises (eqs. kernel_j,
    kernel2) with the prior's standard deviation times ``prior_scale``.

    Parameters
    ----------
    X : (n, 3)
    sigma_p : (n,)
        Prior standard deviation at ``X`` (m).
    targets : (n, 4)
        Residual targets: value ``0 - m(x)`` then ``n - grad m(x)``.
    length_scale, value_noise, gradient_noise, jitter, prior_scale : float

    Returns
    -------
    (lml, eps, raised): the log marginal likelihood (nats), the largest absolute jitter
    added to the diagonal and how many times it was raised x10.
    """
    X = np.asarray(X, dtype=np.float64).reshape(-1, 3)
    sp = np.asarray(sigma_p, dtype=np.float64).reshape(-1)
    y = np.asarray(targets, dtype=np.float64).reshape(-1)
    if len(sp) != len(X) or len(y) != 4 * len(X):
        raise GPError(f"Expected sigma_p (n,) and targets (n, 4) for {len(X)} points, found "
                      f"{sp.shape} and {np.shape(targets)}.")
    Kj = matern32_joint(X, X, length_scale)
    return _lml_from(Kj, sp, y, value_noise, gradient_noise, prior_scale, jitter)


def sample_blocks(points, block_size: float, block_overlap: float, n_blocks: int = 48,
                  max_points: int = 64, min_points: int = 4, seed: int = 0):
    """A seeded sample of the GP blocks: for each, the indices of the points of its
    training region nearest to its centre (at most ``max_points``; blocks with fewer
    than ``min_points`` are skipped).

    Leaves are drawn uniformly among the occupied ones (so about evenly over the
    surface the GP points cover) from the key-sorted list, whose order does not
    change when the scan is scaled or its points reordered.

    Returns
    -------
    (list of (n_b,) int arrays, int number of occupied blocks)
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    grid = BlockGrid.from_points(pts, block_size, block_overlap)
    rng = np.random.default_rng(seed)
    # draw a few more than asked: some leaves are too sparse
    cand = rng.permutation(grid.n_blocks)[:min(grid.n_blocks, 4 * n_blocks)]
    sub = BlockGrid(grid.keys[np.sort(cand)], block_size, block_overlap)
    pi, bi = sub.cover(pts)
    starts = np.flatnonzero(np.r_[True, bi[1:] != bi[:-1]]) if len(bi) else \
        np.zeros(0, dtype=np.int64)
    ends = np.r_[starts[1:], len(bi)].astype(np.int64)
    runs = {int(bi[s]): pi[s:e] for s, e in zip(starts, ends)}
    out = []
    # sub-grid block index of each drawn leaf, in the order drawn
    for b in np.searchsorted(np.sort(cand), cand):
        idx = runs.get(int(b))
        if idx is None or len(idx) < min_points:
            continue
        if len(idx) > max_points:
            d = np.linalg.norm(pts[idx] - sub.centres[b], axis=1)
            idx = np.sort(idx[np.argsort(d, kind="stable")[:max_points]])
        out.append(idx)
        if len(out) == n_blocks:
            break
    return out, grid.n_blocks


@dataclass(frozen=True)
class BlockSample:
    """The blocks the marginal likelihood is summed over.

    Attributes
    ----------
    X, sigma_p, targets : lists of per-block arrays ((n, 3), (n,), (n, 4))
    n_blocks_total : int
        Occupied blocks of all the GP points.
    """

    X: list
    sigma_p: list
    targets: list
    n_blocks_total: int = 0

    @property
    def n_blocks(self) -> int:
        return len(self.X)

    @property
    def n_points(self) -> int:
        return int(sum(len(x) for x in self.X))

    @classmethod
    def from_prior(cls, points, normals, prior, blocks, n_blocks_total: int = 0):
        """Residual targets of the prior at the sampled blocks' points (as
        :func:`.gp.fit_local_gps` forms them): value ``-m(x)``, ``n - grad m(x)``;
        ``sigma_p`` the prior's standard deviation."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        nrm = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        if not blocks:
            return cls([], [], [], n_blocks_total)
        cat = np.concatenate(blocks)
        m, v, g = prior.predict(pts[cat], return_grad=True)
        t = np.column_stack([-np.asarray(m), nrm[cat] - np.asarray(g)])
        sp = np.sqrt(np.maximum(np.asarray(v, dtype=np.float64), 0.0))
        cuts = np.cumsum([len(b) for b in blocks])[:-1]
        return cls([pts[b] for b in blocks], np.split(sp, cuts), np.split(t, cuts),
                   n_blocks_total)


@dataclass
class HyperChoice:
    """The outcome of :func:`select_hyperparameters`.

    Attributes
    ----------
    values : dict
        Chosen value per searched field (``length_scale``, ``value_noise``,
        ``gradient_noise``, ``prior_scale``).
    multipliers : dict
        Chosen multiplier of the starting value per field (1 for fields not searched).
    profile : dict
        Per field: ``{multiplier: summed LML}`` with the other fields at their chosen
        multipliers (the candidates' summed LML).
    lml_start, lml_best : float
        Summed LML at the starting values and at the choice.
    evaluations : int
        Candidates evaluated (each over every sampled block).
    n_blocks, n_points, n_blocks_total : int
    max_jitter : float
        Largest absolute jitter added to a block diagonal (m^2).
    n_jitter_raised : int
    """

    values: dict
    multipliers: dict
    profile: dict
    lml_start: float
    lml_best: float
    evaluations: int
    n_blocks: int
    n_points: int
    n_blocks_total: int
    max_jitter: float
    n_jitter_raised: int
    start: dict = field(default_factory=dict)

    @property
    def at_edge(self) -> list:
        """Fields whose choice is the grid's smallest or largest multiplier (the
        maximum may lie beyond the grid)."""
        return [k for k, p in self.profile.items()
                if len(p) > 1 and self.multipliers[k] in (min(p), max(p))]

    @property
    def reason(self) -> str:
        return (f"max. marginal likelihood over {self.n_blocks} blocks "
                f"({self.n_points} points)")


def _dist(m: dict) -> float:
    return sum(abs(math.log(v)) for v in m.values())


@single_threaded_blas
def select_hyperparameters(sample: BlockSample, start: dict, free, *, jitter: float = 1e-8,
                           grid: dict = GRID) -> HyperChoice:
    """Maximise the summed block LML (eq. lml) over multipliers of ``start``.

    Parameters
    ----------
    sample : BlockSample
    start : dict
        Starting values of ``length_scale``, ``value_noise``, ``gradient_noise`` and
        ``prior_scale``.
    free : iterable of str
        Fields to search (the others stay at multiplier 1).
    jitter : float
        Relative Cholesky jitter (``GPConfig.jitter``).
    grid : dict
        Multipliers per field (:data:`GRID`).

    Returns
    -------
    HyperChoice
    """
    free = [k for k in _ORDER if k in set(free)]
    if sample.n_blocks == 0:
        raise GPError("Expected at least one GP block with points to fit the GP "
                      "hyper-parameters, found none; set them by hand or turn "
                      "gp.marginal_likelihood off.")
    ys = [np.asarray(t, dtype=np.float64).reshape(-1) for t in sample.targets]
    # all blocks at once: padded to the largest, padding rows are independent unit
    # variables with target 0 (they add nothing to y^T K^-1 y nor to log |K|)
    B, M = sample.n_blocks, 4 * max(len(x) for x in sample.X)
    rows = np.array([len(y) for y in ys])
    real = np.arange(M)[None, :] < rows[:, None]                    # (B, M)
    Y = np.zeros((B, M))
    SP = np.zeros((B, M))
    for b, (sp, y) in enumerate(zip(sample.sigma_p, ys)):
        Y[b, :len(y)] = y
        SP[b, :len(y)] = np.repeat(sp, 4)
    is_val = (np.arange(M) % 4 == 0)[None, :] & real
    is_grad = (np.arange(M) % 4 != 0)[None, :] & real
    kj_cache: dict = {}
    cache: dict = {}
    jit = {"max": 0.0, "raised": 0}
    const = -0.5 * float(rows.sum()) * _LOG2PI
    ar = np.arange(M)

    def kj(ml):
        if ml not in kj_cache:
            ls = start["length_scale"] * ml
            K = np.zeros((B, M, M))
            for b, X in enumerate(sample.X):
                n4 = 4 * len(X)
                K[b, :n4, :n4] = matern32_joint(X, X, ls)
            kj_cache[ml] = K * SP[:, :, None] * SP[:, None, :]
        return kj_cache[ml]

    def total_each(m):
        """Per-block loop with the jitter raised where needed (the batch failed)."""
        tot, ls = 0.0, start["length_scale"] * m["length_scale"]
        c = start["prior_scale"] * m["prior_scale"]
        for X, sp, y in zip(sample.X, sample.sigma_p, ys):
            lml, eps, raised = _lml_from(
                matern32_joint(X, X, ls), sp, y, start["value_noise"] * m["value_noise"],
                start["gradient_noise"] * m["gradient_noise"], c, jitter)
            tot += lml
            jit["max"] = max(jit["max"], eps)
            jit["raised"] += raised > 0
        return tot

    def total(m):
        key = tuple(m[k] for k in _ORDER)
        if key not in cache:
            c2 = (start["prior_scale"] * m["prior_scale"]) ** 2
            K = c2 * kj(m["length_scale"])
            d = (is_val * (start["value_noise"] * m["value_noise"])
                 + is_grad * (start["gradient_noise"] * m["gradient_noise"]))
            diag = K[:, ar, ar] + d
            diag = np.where(real, diag * (1.0 + jitter), 1.0)
            K[:, ar, ar] = diag
            try:
                L = np.linalg.cholesky(K)
            except np.linalg.LinAlgError:
                cache[key] = total_each(m)
                return cache[key]
            quad = sum(float(np.dot(z, z)) for z in (
                solve_triangular(L[b], Y[b], lower=True, check_finite=False)
                for b in range(B)))
            logdet = np.sum(np.log(L[:, ar, ar]))
            cache[key] = float(-0.5 * quad - logdet + const)
            jit["max"] = max(jit["max"], float(jitter * np.max(np.where(real, diag, 0.0))))
        return cache[key]

    cur = {k: 1.0 for k in _ORDER}
    lml0 = total(cur)
    # every combination of the free fields' multipliers (at most 5 x 3 x 3 x 3 = 135):
    # the length scale, the prior scale and the gradient noise trade off against each
    # other (the gradient's prior variance is c^2 sigma_p^2 3 / l^2), and coordinate
    # ascent stopped on that ridge on draws from the exact model
    axes = [grid[k] if k in free else (1.0,) for k in _ORDER]
    for combo in itertools.product(*axes):
        m = dict(zip(_ORDER, combo))
        # ties (round-off) go to the candidate nearest the rule
        if (total(m), -_dist(m)) > (total(cur), -_dist(cur)):
            cur = m
    # the candidates' summed LML around the choice, one field at a time
    profile = {k: {float(v): total(dict(cur, **{k: v})) for v in grid[k]} for k in free}
    vals = {k: start[k] * cur[k] for k in free}
    return HyperChoice(values=vals, multipliers=dict(cur), profile=profile,
                       lml_start=lml0, lml_best=total(cur), evaluations=len(cache),
                       n_blocks=sample.n_blocks, n_points=sample.n_points,
                       n_blocks_total=sample.n_blocks_total, max_jitter=jit["max"],
                       n_jitter_raised=jit["raised"], start=dict(start))
