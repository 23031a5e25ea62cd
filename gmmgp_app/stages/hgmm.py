"""Top-down hierarchical Gaussian mixture in 4D (paper Sec. III-A).

The hierarchy starts with ``initial_components`` Gaussians fitted by EM on all
rows ``(x, y, z, d)``. Each node's complexity ``c`` (eq. complexity) says how far
it is from a flat (degenerate) Gaussian; nodes with ``c`` above the split
threshold that hold enough rows are split: their hard-assigned rows are fitted by
EM with ``n_children`` components, and the children get global weights
``parent weight x local weight``. Unsplit nodes of every level are the leaves:
the mixture the GMR stage uses.

>>> import numpy as np
>>> from gmmgp_app.config import HGMMConfig
>>> rows = np.random.default_rng(0).normal(size=(2000, 4))
>>> h = fit_hgmm(rows, HGMMConfig(split_threshold=0.2))
>>> float(h.leaves.weights.sum().round(12))
1.0

On a prepared scan pass the :class:`~gmmgp_app.types.TrainingSet` itself
(``fit_hgmm(prepare(scan, cfg), cfg.hgmm)``): its ``groups`` make the EM tied (a
hit point and its virtual points share one component, ``HGMMConfig.tie_virtual``);
plain rows without ``groups=`` get free EM.
"""

from __future__ import annotations

import time
from typing import Optional

import numpy as np

from gmmgp_app.config import HGMMConfig
from gmmgp_app.stages import em_kernels as ek
from gmmgp_app.types import GaussianMixture, HGMMLevel, HierarchicalGMM, TrainingSet

__all__ = [
    "HGMMError",
    "HGMMFitCache",
    "complexity",
    "fit_gmm",
    "fit_hgmm",
    "score_samples",
    "score",
    "score_groups",
    "predict_labels",
    "predict_group_labels",
    "group_boundaries",
    "hgmm_diagnostics",
    "format_level_history",
]

# A child of a split needs at least this many rows per dimension (24 rows, about
# 8 hit points with their virtual points in 4D); fewer rows => fewer children.
# With 8 rows (2 per dimension) the last level was full of 3-hit-point slabs whose
# orientation is noise: street2 log-likelihood at 0.2-0.3 m +1.23, with 24 rows
# +2.40 and RMSE at 0.05-0.1 m 18.2 -> 12.3 mm (scripts/bench_accuracy.py); 40 rows
# gave the same as 24.
_ROWS_PER_CHILD_PER_DIM = 6


class HGMMError(ValueError):
    """Training rows or mixture parameters unusable for EM."""


# --------------------------------------------------------------------- checks
def _check_rows(X, name: str = "rows", min_rows: int = 1) -> np.ndarray:
    X = np.asarray(X)
    if X.ndim != 2 or X.shape[1] < 1:
        raise HGMMError(
            f"Expected {name} as a 2-D array (N, D), found shape {X.shape}; "
            "reshape to one row per sample (e.g. rows[:, :4] for x, y, z, d)."
        )
    X = np.ascontiguousarray(X, dtype=np.float64)
    bad = ~np.isfinite(X).all(axis=1)
    if bad.any():
        raise HGMMError(
            f"Expected finite {name}, found {int(bad.sum())} of {len(X)} rows with NaN or "
            "inf; drop them first (rows[np.isfinite(rows).all(axis=1)])."
        )
    if len(X) < min_rows:
        raise HGMMError(
            f"Expected at least {min_rows} {name} (one per component), found {len(X)}; "
            "use fewer components or more rows."
        )
    return X


def _all_equal(X) -> bool:
    """Whether every row of the finite (N, D) ``X`` equals the first (``X.max(0) ==
    X.min(0)``, without numpy's strided column reductions: ~10x slower on (N, 4))."""
    return bool(np.all(X == X[0])) if len(X) else True


def _check_not_identical(X, name: str = "rows") -> None:
    if len(X) > 1 and _all_equal(X):
        raise HGMMError(
            f"All {len(X)} {name} are identical, so no mixture can be fitted; check the "
            "input (e.g. a scan of one repeated point)."
        )


def _terms(gm: GaussianMixture):
    K, D = gm.means.shape
    pchol = np.empty((K, D, D))
    logconst = np.empty(K)
    bad = ek.component_terms(gm.weights, gm.covariances, pchol, logconst)
    if bad >= 0:
        raise HGMMError(
            f"Component {bad} of the mixture has a covariance that is not positive definite "
            f"(or weight {gm.weights[bad]!r} <= 0); refit with a larger reg_covar."
        )
    return pchol, logconst


# ------------------------------------------------------------------ equations
def complexity(covariances: np.ndarray, *, normalize: bool = False) -> np.ndarray:
    """Node complexity, eq. complexity: ``c = lambda_n / sum_i lambda_i``.

    ``lambda_i`` are the eigenvalues of a node's covariance, ``lambda_n`` the
    smallest. ``c`` lies in [0, 1/D]: 0 for a degenerate (flat) Gaussian, 1/D
    for an isotropic one.

    Parameters
    ----------
    covariances : (K, D, D) or (D, D)
    normalize : bool
        Evaluate ``c`` on the correlation matrix ``S^-1/2 Sigma S^-1/2`` (S the
        diagonal) instead of the covariance. In 4D rows ``(x, y, z, d)`` the
        distance axis has a small fixed variance (about 2 s^2 / 3), which caps
        ``lambda_n`` and makes ``c`` of any node wider than a metre or two fall
        under the paper's threshold whatever its shape; the correlation form
        keeps "flat = 0, round = 1/D" while removing the per-axis scale.

    Returns
    -------
    c : (K,) float64 (a float for a single (D, D) input)
    """
    C = np.asarray(covariances, dtype=np.float64)
    single = C.ndim == 2
    if single:
        C = C[None]
    if C.ndim != 3 or C.shape[1] != C.shape[2]:
        raise HGMMError(f"Expected covariances of shape (K, D, D), found {C.shape}.")
    if normalize:
        s = np.sqrt(np.clip(np.einsum("kii->ki", C), 1e-300, None))
        C = C / (s[:, :, None] * s[:, None, :])
    lam = np.linalg.eigvalsh(C)
    total = lam.sum(axis=1)
    c = np.where(total > 0, np.clip(lam[:, 0], 0.0, None) / np.where(total > 0, total, 1.0), 0.0)
    return float(c[0]) if single else c


# ------------------------------------------------------------------- flat EM
def _init_from_labels(X, labels, K, reg_covar):
    resp = np.zeros((len(X), K))
    resp[np.arange(len(X)), labels] = 1.0
    return ek.mstep_from_resp(X, resp, reg_covar)


def fit_gmm(
    X: np.ndarray,
    n_components: int,
    *,
    max_iter: int = 100,
    tol: float = 1e-4,
    reg_covar: float = 1e-6,
    rng: Optional[np.random.Generator] = None,
    init="kmeans++",
    on_empty: str = "reseed",
    min_component_rows: float = 1.0,
    parallel: bool = False,
    group_ptr: Optional[np.ndarray] = None,
) -> tuple[GaussianMixture, dict]:
    """Flat EM for a full-covariance Gaussian mixture (E and M steps in numba).

    Parameters
    ----------
    X : (N, D) float64
        Finite rows, N >= n_components.
    n_components : int
    max_iter, tol : EM stops after ``max_iter`` iterations or when the mean
        row log-likelihood changes by less than ``tol`` (as scikit-learn).
    reg_covar : float
        Added to every covariance diagonal after each M-step.
    rng : numpy Generator, used for the k-means++ seeding.
    init : "kmeans++", (K, D) means, (N, K) responsibilities, or a GaussianMixture
        "kmeans++": seeded k-means++ centres, rows hard-assigned to the nearest
        one, one M-step. Means: rows assigned to the nearest mean. A mixture is
        used as is (e.g. to reproduce a scikit-learn run).
    on_empty : "reseed" or "drop"
        What to do with a component that loses its rows (responsibility sum
        below ``min_component_rows``) or whose covariance stops being positive
        definite: "reseed" puts it on the worst-explained row with the average
        covariance (at most ``n_components`` times per fit, then drop);
        "drop" removes it.
    min_component_rows : float
    parallel : bool
        Run the E/M pass with numba threads. Free EM: by chunks of rows, whose
        partial sums are added in chunk order (worth it on an idle machine with
        large N; off by default, see em_kernels.accumulate). Tied EM: the same fit
        bit for bit as the serial pass (em_kernels.accumulate_groups_parallel).
    group_ptr : (G + 1,) int64, optional
        Tied EM: rows ``group_ptr[g]:group_ptr[g + 1]`` share one latent component
        (a hit point and its virtual points, see ``em_kernels.em_loop_groups``).
        The returned weights are still row fractions (the density over rows);
        ``info["group_weights"]`` holds the group fractions.

    Returns
    -------
    mixture : GaussianMixture
    info : dict
        ``n_iter``, ``converged``, ``lower_bound`` (mean log-likelihood of the
        last E-step), ``reseeded`` / ``dropped`` (lists of ``(iteration,
        component)``), ``n_init_components`` (k-means++ may find fewer distinct
        centres than asked).
    """
    if on_empty not in ("reseed", "drop"):
        raise HGMMError(f"Expected on_empty 'reseed' or 'drop', found {on_empty!r}.")
    n_components = int(n_components)
    if n_components < 1:
        raise HGMMError(f"Expected n_components >= 1, found {n_components}.")
    X = _check_rows(X, min_rows=n_components)
    rng = np.random.default_rng(0) if rng is None else rng
    N, D = X.shape
    gptr = _check_group_ptr(group_ptr, N)
    info = dict(n_iter=0, converged=False, lower_bound=-np.inf, reseeded=[], dropped=[],
                n_init_components=n_components)

    if isinstance(init, GaussianMixture):
        if init.means.shape[1] != D:
            raise HGMMError(f"Expected an initial mixture in {D} dimensions, found {init.dim}.")
        w, m, c = (init.weights.copy(), init.means.copy(), init.covariances.copy())
    elif isinstance(init, str):
        if init != "kmeans++":
            raise HGMMError(f"Expected init 'kmeans++', means or a mixture, found {init!r}.")
        _check_not_identical(X)
        idx = ek.kmeanspp(X, n_components, rng.random(n_components))
        info["n_init_components"] = len(idx)
        labels = ek.nearest_center(X, X[idx])
        if gptr is not None:
            # a group starts on the centre nearest to its first row (the hit point)
            labels = np.repeat(labels[gptr[:-1]], np.diff(gptr))
        w, m, c = _init_from_labels(X, labels, len(idx), reg_covar)
    else:
        a = np.ascontiguousarray(np.asarray(init, dtype=np.float64))
        if a.shape == (n_components, D):
            labels = ek.nearest_center(X, a)
            w, m, c = _init_from_labels(X, labels, n_components, reg_covar)
            m = a.copy()
        elif a.shape == (N, n_components):
            w, m, c = ek.mstep_from_resp(X, a, reg_covar)
        else:
            raise HGMMError(
                f"Expected init means ({n_components}, {D}) or responsibilities "
                f"({N}, {n_components}), found {a.shape}."
            )

    if gptr is not None:
        w = _group_fractions(X, gptr, w, m, c)
    budget = n_components if on_empty == "reseed" else 0
    it_done = 0
    n_units = N if gptr is None else len(gptr) - 1
    while True:
        if gptr is None:
            n_iter, conv, status, bad_k, lb, worst_i = ek.em_loop(
                X, w, m, c, int(max_iter - it_done), float(tol), float(reg_covar),
                float(min_component_rows), bool(parallel))
        else:
            n_iter, conv, status, bad_k, lb, worst_i = ek.em_loop_groups(
                X, gptr, w, m, c, int(max_iter - it_done), float(tol), float(reg_covar),
                float(min_component_rows), bool(parallel))
        it_done += n_iter
        info["lower_bound"] = float(lb)
        if status == 0:
            info["converged"] = bool(conv)
            break
        if bad_k < 0:
            raise HGMMError(
                "EM produced a non-finite log-likelihood; the rows may span wildly "
                "different scales; rescale them or raise reg_covar."
            )
        if budget > 0 and len(w) > 1:
            budget -= 1
            info["reseeded"].append((it_done, int(bad_k)))
            others = np.arange(len(w)) != bad_k
            cov_avg = np.einsum("k,kij->ij", w[others] / w[others].sum(), c[others])
            m[bad_k] = X[worst_i] if worst_i >= 0 else X[rng.integers(N)]
            c[bad_k] = cov_avg
            w[bad_k] = 1.0 / n_units
            w /= w.sum()
        elif len(w) > 1:
            info["dropped"].append((it_done, int(bad_k)))
            keep = np.arange(len(w)) != bad_k
            w, m, c = w[keep].copy(), m[keep].copy(), c[keep].copy()
            w /= w.sum()
        else:
            raise HGMMError(
                "The only mixture component became degenerate (covariance not positive "
                f"definite) after {it_done} iterations; raise reg_covar (now {reg_covar})."
            )
        if it_done >= max_iter:
            break
    if gptr is not None:
        info["group_weights"] = w.copy()
        w = _row_fractions(X, gptr, w, m, c)
    # A stop on max_iter right after a re-seed leaves parameters that were never
    # checked; make sure what we hand out is usable.
    gm = GaussianMixture(w, m, c)
    _terms(gm)
    info["n_iter"] = int(it_done)
    return gm, info


def _check_group_ptr(group_ptr, N: int):
    if group_ptr is None:
        return None
    g = np.ascontiguousarray(np.asarray(group_ptr, dtype=np.int64))
    if g.ndim != 1 or len(g) < 2 or g[0] != 0 or g[-1] != N or np.any(np.diff(g) <= 0):
        raise HGMMError(f"Expected group_ptr to be increasing boundaries from 0 to {N} "
                        f"(one group per hit point), found shape {g.shape}; build it with "
                        "group_boundaries(groups).")
    return g


def _sort_by_groups(X: np.ndarray, groups) -> tuple:
    """Rows reordered so that each group's rows are contiguous: (X sorted, groups sorted).

    ``groups`` (N,) integers, the hit point of each row (``TrainingSet.groups``).
    """
    groups = np.asarray(groups)
    if groups.shape != (len(X),) or not np.issubdtype(groups.dtype, np.integer):
        raise HGMMError(f"Expected groups as ({len(X)},) integers (the hit point of each "
                        f"row), found {groups.dtype} {groups.shape}; pass TrainingSet.groups.")
    order = np.argsort(groups, kind="stable")
    return np.ascontiguousarray(X[order]), groups[order]


def group_boundaries(groups: np.ndarray) -> np.ndarray:
    """Boundaries ``(G + 1,)`` of the runs of equal values in a sorted group array."""
    groups = np.asarray(groups)
    starts = np.flatnonzero(np.diff(groups)) + 1
    return np.concatenate([[0], starts, [len(groups)]]).astype(np.int64)


def _group_fractions(X, gptr, w, m, c) -> np.ndarray:
    """Group fractions from hard labels of groups (used to start tied EM)."""
    gm = GaussianMixture(w, m, c)
    pchol, logconst = _terms(gm)
    lab = ek.assign_groups(X, gptr, m, pchol, logconst, np.log(w))
    frac = np.bincount(lab, minlength=len(w)).astype(np.float64) + 1.0
    return frac / frac.sum()


def _row_fractions(X, gptr, gw, m, c) -> np.ndarray:
    """Row fractions (weights of the density over rows) of a tied mixture: sum_g r_gk |g| / N."""
    pchol, logconst = _terms(GaussianMixture(gw, m, c))
    nk = ek.accumulate_groups(X, gptr, m, pchol, logconst, np.log(gw))[0]
    nk = nk + ek.EPS10
    return nk / nk.sum()


def predict_group_labels(gm: GaussianMixture, group_weights, X, group_ptr) -> np.ndarray:
    """Hard assignment of whole groups (tied EM), expanded to rows, (N,) int64."""
    X = _check_rows(X)
    gptr = _check_group_ptr(group_ptr, len(X))
    gw = np.asarray(group_weights, dtype=np.float64)
    pchol, logconst = _terms(GaussianMixture(gw, gm.means, gm.covariances))
    lab = ek.assign_groups(X, gptr, gm.means, pchol, logconst, np.log(gw))
    return np.repeat(lab, np.diff(gptr))


def score_samples(gm: GaussianMixture, X: np.ndarray) -> np.ndarray:
    """Per-row log-likelihood ``log p(x_n)`` under the mixture, (N,)."""
    X = _check_rows(X)
    if X.shape[1] != gm.dim:
        raise HGMMError(f"Expected rows with {gm.dim} columns, found {X.shape[1]}.")
    pchol, logconst = _terms(gm)
    return ek.log_likelihood(X, gm.means, pchol, logconst)


def score(gm: GaussianMixture, X: np.ndarray) -> float:
    """Mean per-row log-likelihood under the mixture."""
    return float(np.mean(score_samples(gm, X)))


def score_groups(gm: GaussianMixture, X: np.ndarray, groups: np.ndarray,
                 group_weights: Optional[np.ndarray] = None) -> float:
    """Log-likelihood of whole observations under a tied mixture, per row.

    An observation is a hit point with its virtual points (the rows sharing a value
    of ``groups``); tied EM models it as one draw of a component:
    ``log p(group) = log sum_k pi_k prod_n N(x_n | k)``. Returned is the sum over
    groups divided by the number of rows, so it compares with :func:`score` of a
    mixture that treats rows as independent (whose group likelihood is the product
    of its row likelihoods, i.e. the same per-row mean).

    Parameters
    ----------
    gm : GaussianMixture
    X : (N, D) rows
    groups : (N,) int
        Observation of each row (``TrainingSet.groups``); any order.
    group_weights : (K,), optional
        Component fractions of observations (tied EM's ``pi``); default the
        mixture's weights (fractions of rows: equal when all groups have the same
        size, as with both virtual points kept).
    """
    Xs, gsorted = _sort_by_groups(_check_rows(X), groups)
    gptr = group_boundaries(gsorted)
    gw = gm.weights if group_weights is None else np.asarray(group_weights, dtype=np.float64)
    pchol, logconst = _terms(GaussianMixture(gw, gm.means, gm.covariances))
    ll = ek.group_log_likelihood(Xs, gptr, gm.means, pchol, logconst, np.log(gw))
    return float(ll.sum() / len(X))


def predict_labels(gm: GaussianMixture, X: np.ndarray) -> np.ndarray:
    """Hard assignment of rows to the component with the largest ``pi_k N(x|.)``, (N,) int64."""
    X = _check_rows(X)
    pchol, logconst = _terms(gm)
    return ek.assign(X, gm.means, pchol, logconst)


# ----------------------------------------------------------------- hierarchy
def fit_hgmm(rows: np.ndarray, hcfg: HGMMConfig, *,
             rng: Optional[np.random.Generator] = None,
             groups: Optional[np.ndarray] = None,
             cache: Optional["HGMMFitCache"] = None) -> HierarchicalGMM:
    """Fit the top-down hierarchical GMM (paper Sec. III-A).

    Parameters
    ----------
    rows : (M, D) float64 or TrainingSet
        Training rows, in the mapper ``(x, y, z, d)``; a
        :class:`~gmmgp_app.types.TrainingSet` (``prepare``'s result) brings its
        ``groups`` along, so ``fit_hgmm(prepare(scan, cfg), cfg.hgmm)`` is tied.
    hcfg : HGMMConfig
        ``initial_components``, ``n_children``, ``split_threshold``,
        ``min_rows``, ``max_levels``, EM settings, ``seed`` and
        ``complexity_metric``.
    rng : numpy Generator, optional
        Seeds the first fit; defaults to ``np.random.default_rng(hcfg.seed)``. The
        split of a node draws its k-means++ uniforms from its own stream, seeded by
        ``hcfg.seed`` (or, with ``rng``, one integer drawn from it) and the node's
        path in the tree (:func:`_node_uniforms`): a node's fit depends on its rows
        and its place only, not on how many other nodes split before it, so nodes
        split under two thresholds get the same fit (what ``cache`` relies on).
    groups : (M,) int, optional
        ``TrainingSet.groups``: the hit point each row belongs to. When given (and
        ``hcfg.tie_virtual``), every EM of the hierarchy is tied: a hit point and its
        virtual points share one component, and nodes are split by whole groups.
    cache : HGMMFitCache, optional
        Fits of nodes kept from earlier calls (owned by the caller, e.g. the desktop
        app between threshold changes): a node fitted before with the same rows,
        place and fit settings is taken from it, the others are fitted and added.
        The result is bitwise the one without a cache. Not with ``rng``.

    Returns
    -------
    HierarchicalGMM
        ``levels[l]`` holds the nodes of level l with global weights, parents,
        ``c``, split flags and row counts; ``leaves`` every unsplit node
        (weights sum to 1); ``info`` fit statistics (timings, EM iterations,
        components re-seeded or dropped per level).
    """
    from gmmgp_app.config import concrete

    hcfg = concrete(hcfg)    # 'auto' fields: build_map resolves them from the scan first
    t0 = time.perf_counter()
    if isinstance(rows, TrainingSet):
        if groups is not None:
            raise HGMMError("Expected groups either inside the TrainingSet or as groups=, "
                            "found both; pass the TrainingSet alone.")
        rows, groups = rows.rows, rows.groups
    if cache is not None and rng is not None:
        raise HGMMError("Expected either rng= or cache=, found both; a cache holds fits "
                        "seeded by hcfg.seed, so drop rng (set hcfg.seed instead).")
    X = _check_rows(rows, min_rows=hcfg.initial_components)
    _check_not_identical(X)
    node_seed = hcfg.seed
    if rng is None:
        rng = np.random.default_rng(hcfg.seed)
    else:
        node_seed = int(rng.integers(2 ** 63))
    D = X.shape[1]
    gsorted = None
    if groups is not None and hcfg.tie_virtual:
        # Rows of a group made contiguous; node row lists stay sorted, so groups
        # stay contiguous inside every node.
        X, gsorted = _sort_by_groups(X, groups)
    if cache is not None:
        cache._use(X, gsorted, hcfg)

    def group_ptr(idx):
        """Group boundaries of the rows ``idx`` (all rows: None), or None untied."""
        if gsorted is None:
            return None
        return group_boundaries(gsorted if idx is None else gsorted[idx])

    threads = _numba_threads()

    def wide(gptr, level_groups: int) -> bool:
        return gptr is not None and _wide(len(gptr) - 1, level_groups, threads)

    def fit(Xrows, gptr, k, u=None, parallel=False):
        """EM with k components, then hard labels per row (per group when tied);
        ``u``: the k-means++ uniforms drawn beforehand (fits run in threads)."""
        g = fit_gmm(Xrows, k, rng=rng if u is None else _Drawn(u), on_empty="drop",
                    min_component_rows=float(D), group_ptr=gptr, parallel=parallel,
                    **em_kw)
        if gptr is None:
            return g + (predict_labels(g[0], Xrows),)
        return g + (predict_group_labels(g[0], g[1]["group_weights"], Xrows, gptr),)
    normalize = hcfg.complexity_metric == "correlation"
    em_kw = dict(max_iter=hcfg.max_iter, tol=hcfg.tol, reg_covar=hcfg.reg_covar)
    min_child_rows = _ROWS_PER_CHILD_PER_DIM * D

    got0 = None if cache is None else cache._get((), None)
    if got0 is None:
        gptr0 = group_ptr(None)
        got0 = fit(X, gptr0, hcfg.initial_components,
                   parallel=wide(gptr0, 0 if gptr0 is None else len(gptr0) - 1))
        if cache is not None:
            cache._put((), None, got0)
    gm0, info0, labels = got0
    # Current level: arrays of node parameters and the row indices of each node.
    weights, means, covs = gm0.weights, gm0.means, gm0.covariances
    # fractions of observations (hit point groups) per node, for the tied likelihood
    gweights = info0.get("group_weights", weights)
    parents = np.full(len(weights), -1, dtype=np.int64)
    node_rows = _group(labels, len(weights))
    paths = [(j,) for j in range(len(weights))]  # each node's place: child index per level

    levels = []
    leaves_w, leaves_m, leaves_c, leaf_level, leaves_gw = [], [], [], [], []
    level_info = [dict(n_fits=1, em_iter=info0["n_iter"], dropped=len(info0["dropped"]),
                       not_converged=int(not info0["converged"]), failed_splits=0)]
    for lev in range(hcfg.max_levels):
        c = complexity(covs, normalize=normalize)
        n_rows = np.array([len(r) for r in node_rows], dtype=np.int64)
        want = c > hcfg.split_threshold
        max_std = hcfg.split_max_std
        if max_std is not None:
            d3 = min(3, D)
            want |= np.linalg.eigvalsh(covs[:, :d3, :d3])[:, -1] > max_std ** 2
        want &= (n_rows >= hcfg.min_rows) & (lev < hcfg.max_levels - 1)
        split = np.zeros(len(weights), dtype=bool)
        nxt_w, nxt_m, nxt_c, nxt_p, nxt_rows, nxt_gw = [], [], [], [], [], []
        nxt_paths = []
        stats = dict(n_fits=0, em_iter=0, dropped=0, not_converged=0, failed_splits=0)
        # The splits of one level are independent: each gets the k-means++ uniforms of
        # its own place in the tree, then the fits run in threads (the EM kernels
        # release the GIL); results are taken in node order, so the hierarchy is the
        # one a sequential loop builds. Fits found in the cache are not run again.
        tasks = []
        for j in np.flatnonzero(want):
            idx = node_rows[j]
            k = min(hcfg.n_children, len(idx) // min_child_rows)
            if k < 2:
                stats["failed_splits"] += 1
                continue
            Xj = X[idx]
            if _all_equal(Xj):
                stats["failed_splits"] += 1
                continue
            gptr = group_ptr(idx)
            if gptr is not None and len(gptr) - 1 < k:
                k = len(gptr) - 1  # no more children than hit points
                if k < 2:
                    stats["failed_splits"] += 1
                    continue
            tasks.append((j, idx, Xj, gptr, k, _node_uniforms(node_seed, paths[j], k)))
        got = [None if cache is None else cache._get(paths[t[0]], t[1]) for t in tasks]
        todo = [t for t, g in zip(tasks, got) if g is None]
        # a wide fit first on all threads, then the others in the pool
        level_groups = sum(len(t[3]) - 1 for t in todo if t[3] is not None)
        done = {i: fit(*t[2:6], parallel=True) for i, t in enumerate(todo)
                if wide(t[3], level_groups)}
        narrow = [i for i in range(len(todo)) if i not in done]
        done.update(zip(narrow, _map_threads(lambda i: fit(*todo[i][2:6]), narrow)))
        fitted = iter(done[i] for i in range(len(todo)))
        results = []
        for t, g in zip(tasks, got):
            if g is None:
                g = next(fitted)
                if cache is not None:
                    cache._put(paths[t[0]], t[1], g)
            results.append(g)
        for (j, idx, Xj, gptr, k, u), (gmj, infoj, lab) in zip(tasks, results):
            stats["n_fits"] += 1
            stats["em_iter"] += infoj["n_iter"]
            stats["dropped"] += len(infoj["dropped"])
            stats["not_converged"] += int(not infoj["converged"])
            child_rows = _group(lab, gmj.n_components)
            alive = [g for g in range(gmj.n_components) if len(child_rows[g]) > 0]
            if len(alive) < 2:
                # EM put everything in one child: it would equal its parent.
                stats["failed_splits"] += 1
                continue
            split[j] = True
            child_gw = infoj.get("group_weights", gmj.weights)
            for g in range(gmj.n_components):
                nxt_w.append(weights[j] * gmj.weights[g])
                nxt_gw.append(gweights[j] * child_gw[g])
                nxt_m.append(gmj.means[g])
                nxt_c.append(gmj.covariances[g])
                nxt_p.append(j)
                nxt_rows.append(idx[child_rows[g]])
                nxt_paths.append(paths[j] + (g,))
        levels.append(HGMMLevel(
            mixture=GaussianMixture(weights, means, covs), parent=parents,
            complexity=np.asarray(c, dtype=np.float64), split=split, n_rows=n_rows))
        keep = ~split
        leaves_w.append(weights[keep])
        leaves_gw.append(np.asarray(gweights)[keep])
        leaves_m.append(means[keep])
        leaves_c.append(covs[keep])
        leaf_level.append(np.full(int(keep.sum()), lev, dtype=np.int64))
        if not nxt_w:
            break
        level_info.append(stats)  # the fits that made level lev + 1
        weights = np.asarray(nxt_w)
        gweights = np.asarray(nxt_gw)
        means = np.asarray(nxt_m)
        covs = np.asarray(nxt_c)
        parents = np.asarray(nxt_p, dtype=np.int64)
        node_rows = nxt_rows
        paths = nxt_paths
    lw = np.concatenate(leaves_w)
    leaves = GaussianMixture(lw / lw.sum(), np.concatenate(leaves_m), np.concatenate(leaves_c))
    lgw = np.concatenate(leaves_gw)
    info = dict(
        reg_covar=hcfg.reg_covar,
        # tied EM: the leaves' fractions of observations (see score_groups), else None
        leaf_group_weights=None if gsorted is None else lgw / lgw.sum(),
        complexity_metric="correlation" if normalize else "covariance",
        tied_groups=None if gsorted is None else int(len(group_boundaries(gsorted)) - 1),
        n_rows=int(len(X)),
        n_leaves=int(leaves.n_components),
        level_fits=level_info,
        fit_seconds=time.perf_counter() - t0,
    )
    return HierarchicalGMM(levels=tuple(levels), leaves=leaves,
                           leaf_level=np.concatenate(leaf_level), info=info)


def _node_uniforms(seed: int, path: tuple, k: int) -> np.ndarray:
    """The k-means++ uniforms of the split of the node at ``path`` (its child index at
    every level from the first): a stream of its own, seeded by (seed, path)."""
    return np.random.default_rng([int(seed), _NODE_STREAM, len(path), *path]).random(k)


_NODE_STREAM = 0x48474D4D  # tags the node streams apart from default_rng(seed)


class HGMMFitCache:
    """Fits of hierarchy nodes kept between :func:`fit_hgmm` calls on the same rows.

    With the same rows and seeds, a node has the same rows and the same fit under any
    split threshold, as long as its ancestors split (each split's k-means++ uniforms
    come from the node's own stream, :func:`_node_uniforms`); only the decision to
    split it depends on the threshold. So after a threshold change only the nodes that
    were never split before need EM. An entry is keyed by the node's path in the tree
    and a digest of its rows; the cache holds the fits of one set of rows and fit
    settings (everything of :class:`HGMMConfig` but the split decision fields
    ``split_threshold``, ``split_max_std``, ``min_rows``, ``max_levels`` and
    ``complexity_metric``) and empties itself when either changes.

    The caller owns it (e.g. the desktop app's model, through the pipeline's
    ``RunContext.hgmm_cache``); stages keep no state. Not thread safe: one fit at a
    time. ``hits`` / ``misses`` count the node fits reused and computed.
    """

    #: HGMMConfig fields that decide which nodes split, not how a node is fitted
    DECISION_FIELDS = ("split_threshold", "split_max_std", "min_rows", "max_levels",
                       "complexity_metric")

    def __init__(self):
        self._key = None
        self._fits: dict = {}
        self.hits = 0
        self.misses = 0

    def __len__(self) -> int:
        return len(self._fits)

    def clear(self) -> None:
        self._key, self._fits = None, {}

    def _use(self, X: np.ndarray, gsorted, hcfg: HGMMConfig) -> None:
        import dataclasses
        import hashlib

        h = hashlib.blake2b(digest_size=16)
        h.update(repr(X.shape).encode())
        h.update(X.tobytes())
        if gsorted is not None:
            h.update(np.ascontiguousarray(gsorted).tobytes())
        fit_settings = tuple((f.name, getattr(hcfg, f.name)) for f in dataclasses.fields(hcfg)
                             if f.name not in self.DECISION_FIELDS)
        key = (h.digest(), gsorted is None, fit_settings)
        if key != self._key:
            self._key, self._fits = key, {}

    @staticmethod
    def _rows_key(idx) -> bytes:
        import hashlib

        if idx is None:
            return b"all"
        return hashlib.blake2b(np.ascontiguousarray(idx).tobytes(), digest_size=16).digest()

    def _get(self, path: tuple, idx):
        import copy

        got = self._fits.get((path, self._rows_key(idx)))
        if got is None:
            return None
        self.hits += 1
        return copy.deepcopy(got)  # a result never shares arrays with the cache

    def _put(self, path: tuple, idx, fit) -> None:
        import copy

        self.misses += 1
        self._fits[(path, self._rows_key(idx))] = copy.deepcopy(fit)


class _Drawn:
    """Stands in for the Generator of one fit: hands out its pre-drawn k-means++
    uniforms (fit_gmm with on_empty="drop" draws nothing else)."""

    def __init__(self, u):
        self.u = u

    def random(self, n):
        if n != len(self.u):
            raise HGMMError(f"Expected {len(self.u)} uniforms to be drawn, found {n}.")
        return self.u


# A tied fit of at least this many groups that holds more than half of its level's
# groups runs its E-step on numba's threads (fit_hgmm's ``wide``); below it two
# parallel regions per EM iteration cost more than they share (street: the first
# level's 107k groups; its next level's fits hold 29k-38k groups each, a third each).
_WIDE_GROUPS = 8192


def _wide(n_groups: int, level_groups: int, threads: int) -> bool:
    """Whether a tied fit of ``n_groups`` runs its E-step on all numba threads rather
    than whole in one thread of the pool (its parallel E-step gives the serial fit bit
    for bit, em_kernels.accumulate_groups_parallel): when it has many groups and holds
    more than half of the ``level_groups`` fitted at its level, so that the pool could
    not keep the threads busy while it runs (the first level's single fit). Fits of
    similar sizes share the threads better in the pool (no extra work)."""
    return threads > 1 and n_groups >= _WIDE_GROUPS and 2 * n_groups > level_groups


def _numba_threads() -> int:
    import numba

    return int(numba.get_num_threads())


def _map_threads(fn, items):
    """``map(fn, items)`` on up to ``os.cpu_count()`` threads (in order); serial for one."""
    import os

    workers = min(len(items), os.cpu_count() or 1)
    if workers <= 1:
        return [fn(t) for t in items]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(workers) as pool:
        return list(pool.map(fn, items))


def _group(labels: np.ndarray, K: int) -> list:
    """Row indices per label, each sorted, (K lists)."""
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(K + 1))
    return [order[bounds[k]:bounds[k + 1]] for k in range(K)]


# --------------------------------------------------------------- diagnostics
def hgmm_diagnostics(hgmm: HierarchicalGMM, heldout_rows: Optional[np.ndarray] = None,
                     heldout_groups: Optional[np.ndarray] = None) -> dict:
    """Summary of a fitted hierarchy.

    Returns
    -------
    dict with ``n_levels``, ``n_leaves``, ``nodes_per_level``,
    ``leaves_per_level``, ``split_per_level``, ``leaf_complexity_quantiles``
    (c over leaves at q = 0, 0.05, 0.25, 0.5, 0.75, 0.95, 1) and, when held-out
    rows are given, ``heldout_mean_loglik`` (mean log p of those rows under the
    leaves) and ``n_heldout``; with their ``heldout_groups`` (the hit point of each
    row) also ``heldout_observation_loglik`` (:func:`score_groups` with the leaves'
    group weights of a tied fit).
    """
    leaf_c = np.concatenate([lv.complexity[~lv.split] for lv in hgmm.levels])
    qs = [0.0, 0.05, 0.25, 0.5, 0.75, 0.95, 1.0]
    out = dict(
        n_levels=len(hgmm.levels),
        n_leaves=int(hgmm.leaves.n_components),
        nodes_per_level=[int(lv.mixture.n_components) for lv in hgmm.levels],
        split_per_level=[int(lv.split.sum()) for lv in hgmm.levels],
        leaves_per_level=[int((~lv.split).sum()) for lv in hgmm.levels],
        leaf_complexity_quantiles={f"q{int(q * 100):02d}": float(np.quantile(leaf_c, q))
                                   for q in qs},
    )
    if heldout_rows is not None:
        out["heldout_mean_loglik"] = score(hgmm.leaves, heldout_rows)
        out["n_heldout"] = int(len(heldout_rows))
        if heldout_groups is not None:
            out["heldout_observation_loglik"] = score_groups(
                hgmm.leaves, heldout_rows, heldout_groups,
                hgmm.info.get("leaf_group_weights"))
    return out


def format_level_history(hgmm: HierarchicalGMM) -> str:
    """The level history as a text table (level, nodes, split, leaves, rows, c min/median/max)."""
    head = f"{'level':>5} {'nodes':>6} {'split':>6} {'leaves':>6} {'rows':>9} " \
           f"{'c min':>9} {'c median':>9} {'c max':>9}"
    lines = [head, "-" * len(head)]
    for i, lv in enumerate(hgmm.levels):
        c = lv.complexity
        lines.append(
            f"{i:>5} {lv.mixture.n_components:>6} {int(lv.split.sum()):>6} "
            f"{int((~lv.split).sum()):>6} {int(lv.n_rows.sum()):>9} "
            f"{c.min():>9.2e} {np.median(c):>9.2e} {c.max():>9.2e}")
    lines.append(f"leaves: {hgmm.leaves.n_components} "
                 f"(complexity on the {hgmm.info.get('complexity_metric', '?')}, "
                 f"fit {hgmm.info.get('fit_seconds', float('nan')):.2f} s)")
    return "\n".join(lines)
