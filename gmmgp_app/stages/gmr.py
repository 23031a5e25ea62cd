"""Gaussian mixture regression of the signed distance (paper Sec. III-B).

A 4D mixture over rows ``(x, y, z, d)`` is conditioned on the coordinates: each
component gives a linear regression ``mu_j(x)`` with variance ``sigma_j^2``, and the
``J`` *active* components are mixed with the responsibilities ``w_j(x)``
(eqs. gmm_mean and gmm_sigma).

Active components
-----------------
A component is a *candidate* for query ``x`` when its Mahalanobis distance in xyz,
``D_j(x) = sqrt((x - mu_jX)^T Sigma_jXX^-1 (x - mu_jX))``, is at most the cut; the
active set is the top ``J`` candidates by ``pi_j p_j(x)``.

The search is exact, not heuristic:

1. Queries are grouped into cubic cells of edge ``h`` (half diagonal ``rho``).
2. Component means sit in scipy cKDTrees, one per *radius bucket*. Because
   ``D_j(x) <= c`` implies ``|x - mu_jX| <= c sqrt(lambda_max(Sigma_jXX)) =: r_j``,
   a Euclidean ball of radius ``r_j`` contains the whole Mahalanobis ellipsoid; with
   flat (anisotropic) covariances ``r_j`` must use the *largest* eigenvalue or
   components elongated towards the query are missed. Components are bucketed by
   ``r_j`` (powers of two) so one very large component does not inflate the radius
   of all others; each cell queries each bucket with radius ``max r_j + rho``.
3. Per cell (numba) the candidates are pruned with bounds valid for every point of
   the cell: ``|D_j(x) - D_j(c)| <= rho sqrt(lambda_max(Sigma_jXX^-1))`` (triangle
   inequality in the Mahalanobis norm) bounds ``D_j`` and hence ``log pi_j p_j``.
   A component is dropped when it can never be inside the cut, or when ``J``
   components that are surely inside the cut have a lower bound above its upper
   bound (it can never be in the top ``J``). The result equals the per-query
   definition exactly.
4. Per query (numba, ``prange``) the exact cut and top ``J`` are applied.

Far from the data
-----------------
When no component lies within the cut, the top ``J`` of *all* components by
``pi_j p_j(x)`` are used (a linear scan; such queries are rare), so the field is
defined everywhere.

The plain GMR variance stays at the size of the ``+-s`` virtual-point band even
metres away from the data, which makes the predictive likelihood collapse there.
We therefore let each component's conditional variance grow with the Euclidean
distance of the query *beyond the component's support*::

    sigma_j^2(x) = Lambda_jYY^-1 + (gamma * e_j(x))^2,
    e_j(x) = max(0, |x - mu_jX| * (1 - D0 / D_j(x)))

``e_j`` is the distance from ``x`` to the ellipsoid ``D_j = D0`` measured along the
ray from the component mean (metres): zero inside the support, growing linearly
outside. ``gamma`` (dimensionless, ``GMRConfig.far_variance_growth``) is the
standard deviation gained per metre beyond the support and ``D0``
(``GMRConfig.far_growth_start``) where the support ends. These terms enter the law of
total variance like the component variances, so components responsible for the
query decide how fast the uncertainty grows. ``gamma = 0`` gives the paper's GMR.
The mean and its gradient are unaffected.
"""

from __future__ import annotations

import itertools
import math

import numba as nb
import numpy as np
from scipy.spatial import cKDTree

from gmmgp_app.types import GaussianMixture

__all__ = [
    "GMRError",
    "GMRField",
    "condition_on_xyz",
    "gmr_bruteforce",
    "DEFAULT_FAR_GROWTH",
    "DEFAULT_FAR_START",
]

#: Defaults of ``GMRConfig.far_variance_growth`` and ``far_growth_start``
#: (kept here too so the oracle and the field agree when called without a config).
DEFAULT_FAR_GROWTH = 0.5
DEFAULT_FAR_START = 1.0

_LOG_2PI = math.log(2.0 * math.pi)


class GMRError(ValueError):
    """Bad input to the Gaussian mixture regression."""


# ----------------------------------------------------------------------- checks
def _check_mixture(mixture) -> None:
    if not isinstance(mixture, GaussianMixture):
        raise GMRError(
            f"Expected a GaussianMixture, found {type(mixture).__name__}; "
            "build one with gmmgp_app.types.GaussianMixture(weights, means, covariances)."
        )
    if mixture.dim != 4:
        raise GMRError(
            f"Expected a 4D mixture over (x, y, z, d), found dimension {mixture.dim}; "
            "fit the HGMM on 4D training rows."
        )
    if mixture.n_components < 1:
        raise GMRError("Expected at least one mixture component, found 0.")
    if not (np.all(np.isfinite(mixture.weights)) and np.all(np.isfinite(mixture.means))
            and np.all(np.isfinite(mixture.covariances))):
        raise GMRError("Expected finite mixture parameters, found NaN or inf; "
                       "check the HGMM fit.")
    if np.any(mixture.weights < 0) or mixture.weights.sum() <= 0:
        raise GMRError(
            f"Expected non-negative weights with a positive sum, found min "
            f"{mixture.weights.min():.3g} and sum {mixture.weights.sum():.3g}."
        )


def _check_queries(xyz) -> np.ndarray:
    x = np.asarray(xyz, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise GMRError(f"Expected query points with shape (K, 3), found {x.shape}; "
                       "pass an array of xyz rows.")
    if not np.all(np.isfinite(x)):
        bad = int(np.count_nonzero(~np.all(np.isfinite(x), axis=1)))
        raise GMRError(f"Expected finite query coordinates, found {bad} rows with NaN "
                       "or inf; drop or fill them before predicting.")
    return np.ascontiguousarray(x)


# ------------------------------------------------------------------ conditioning
def condition_on_xyz(mixture: GaussianMixture) -> dict:
    """Condition every 4D component on its xyz part (paper Sec. III-B).

    Implements the per-component conditionals of the paper:
    ``mu_{Y|X}(x) = mu_Y - Lambda_YY^-1 Lambda_YX (x - mu_X)`` and
    ``Sigma_{Y|X} = Lambda_YY^-1`` with ``Lambda = Sigma^-1``, plus the marginal
    densities ``p_j(x) = N(x | mu_jX, Sigma_jXX)`` used for the responsibilities.

    Parameters
    ----------
    mixture : GaussianMixture
        4D mixture, last dimension the signed distance.

    Returns
    -------
    dict with
        ``mux`` (K, 3) component means in xyz; ``prec`` (K, 3, 3) ``Sigma_XX^-1``;
        ``logc`` (K,) ``log pi_j - 0.5 log det(2 pi Sigma_XX)``; ``a`` (K,) ``mu_Y``;
        ``b`` (K, 3) slope ``-Lambda_YY^-1 Lambda_YX``; ``s2`` (K,) ``Lambda_YY^-1``;
        ``r_max`` (K,) ``sqrt(lambda_max(Sigma_XX))``; ``lip`` (K,)
        ``sqrt(lambda_max(Sigma_XX^-1))``.
    """
    _check_mixture(mixture)
    cov = mixture.covariances
    sxx = cov[:, :3, :3]
    try:
        np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        raise GMRError(
            "Expected positive definite 4x4 component covariances, found a singular one; "
            "fit the mixture with a positive reg_covar."
        ) from None
    lam = np.linalg.inv(cov)
    lyy = lam[:, 3, 3]
    b = -lam[:, 3, :3] / lyy[:, None]
    eig = np.linalg.eigvalsh(sxx)
    prec = np.linalg.inv(sxx)
    prec = 0.5 * (prec + np.transpose(prec, (0, 2, 1)))
    w = mixture.weights / mixture.weights.sum()
    with np.errstate(divide="ignore"):
        logw = np.log(w)
    _, logdet = np.linalg.slogdet(sxx)
    return dict(
        mux=np.ascontiguousarray(mixture.means[:, :3]),
        prec=np.ascontiguousarray(prec),
        logc=np.ascontiguousarray(logw - 0.5 * (3 * _LOG_2PI + logdet)),
        a=np.ascontiguousarray(mixture.means[:, 3]),
        b=np.ascontiguousarray(b),
        s2=np.ascontiguousarray(1.0 / lyy),
        r_max=np.sqrt(eig[:, -1]),
        lip=1.0 / np.sqrt(eig[:, 0]),
    )


# ---------------------------------------------------------------- numba kernels
@nb.njit(cache=True, inline="always")
def _maha2(x0, x1, x2, mux, prec, j):
    d0 = x0 - mux[j, 0]
    d1 = x1 - mux[j, 1]
    d2 = x2 - mux[j, 2]
    p = prec[j]
    return (p[0, 0] * d0 * d0 + p[1, 1] * d1 * d1 + p[2, 2] * d2 * d2
            + 2.0 * (p[0, 1] * d0 * d1 + p[0, 2] * d0 * d2 + p[1, 2] * d1 * d2))


@nb.njit(cache=True, parallel=True)
def _prune_cells(centres, rho, ptr, idx, mux, prec, logc, lip, n_active, cut):
    """Mask of cell candidates that may be active somewhere in their cell."""
    n_cells = centres.shape[0]
    keep = np.zeros(idx.shape[0], dtype=np.bool_)
    for c in nb.prange(n_cells):
        lo, hi = ptr[c], ptr[c + 1]
        n = hi - lo
        if n == 0:
            continue
        upper = np.empty(n)
        lower_in = np.empty(n)
        n_in = 0
        for t in range(n):
            j = idx[lo + t]
            dc = math.sqrt(max(_maha2(centres[c, 0], centres[c, 1], centres[c, 2],
                                      mux, prec, j), 0.0))
            slack = rho * lip[j]
            dlo = max(dc - slack, 0.0)
            upper[t] = logc[j] - 0.5 * dlo * dlo if dlo <= cut else -np.inf
            if dc + slack <= cut:
                lower_in[n_in] = logc[j] - 0.5 * (dc + slack) ** 2
                n_in += 1
        thr = -np.inf
        if n_in >= n_active:
            srt = np.sort(lower_in[:n_in])
            thr = srt[n_in - n_active]
        for t in range(n):
            if upper[t] > -np.inf and upper[t] >= thr:
                keep[lo + t] = True
    return keep


@nb.njit(cache=True, inline="always")
def _push_top(l, j, best_l, best_j, n, imin):
    """Keep the n_active largest log-weights seen so far (unsorted, tracks the min)."""
    cap = best_l.shape[0]
    if n < cap:
        best_l[n] = l
        best_j[n] = j
        n += 1
        if n == cap:
            imin = 0
            for t in range(1, cap):
                if best_l[t] < best_l[imin]:
                    imin = t
        return n, imin
    if l > best_l[imin]:
        best_l[imin] = l
        best_j[imin] = j
        imin = 0
        for t in range(1, cap):
            if best_l[t] < best_l[imin]:
                imin = t
    return n, imin


@nb.njit(cache=True, parallel=True)
def _gmr_kernel(xyz, qcell, ptr, idx, mux, prec, logc, a, b, s2, n_active, cut,
                growth, start, want_grad):
    """GMR mean (eq. gmm_mean), variance (eq. gmm_sigma + far growth), gradient."""
    nq = xyz.shape[0]
    n_comp = mux.shape[0]
    mean = np.empty(nq)
    var = np.empty(nq)
    grad = np.zeros((nq, 3) if want_grad else (0, 3))
    cut2 = cut * cut
    n_fallback = 0
    for q in nb.prange(nq):
        x0, x1, x2 = xyz[q, 0], xyz[q, 1], xyz[q, 2]
        best_l = np.empty(n_active)
        best_j = np.empty(n_active, dtype=np.int64)
        n = 0
        imin = 0
        c = qcell[q]
        for t in range(ptr[c], ptr[c + 1]):
            j = idx[t]
            d2 = _maha2(x0, x1, x2, mux, prec, j)
            if d2 <= cut2:
                n, imin = _push_top(logc[j] - 0.5 * d2, j, best_l, best_j, n, imin)
        if n == 0:
            # no component within the cut: the nearest ones in the responsibility
            # sense, so the field (and its growing variance) is defined everywhere
            n_fallback += 1
            for j in range(n_comp):
                d2 = _maha2(x0, x1, x2, mux, prec, j)
                n, imin = _push_top(logc[j] - 0.5 * d2, j, best_l, best_j, n, imin)
        lmax = -np.inf
        for t in range(n):
            if best_l[t] > lmax:
                lmax = best_l[t]
        wsum = 0.0
        w = np.empty(n)
        mu = np.empty(n)
        for t in range(n):
            w[t] = math.exp(best_l[t] - lmax)
            wsum += w[t]
        m = 0.0
        for t in range(n):
            w[t] /= wsum
            j = best_j[t]
            mu[t] = (a[j] + b[j, 0] * (x0 - mux[j, 0]) + b[j, 1] * (x1 - mux[j, 1])
                     + b[j, 2] * (x2 - mux[j, 2]))
            m += w[t] * mu[t]
        v = 0.0
        g0 = 0.0
        g1 = 0.0
        g2 = 0.0
        for t in range(n):
            j = best_j[t]
            dmu = mu[t] - m
            extra = 0.0
            if growth > 0.0:
                d0 = x0 - mux[j, 0]
                d1 = x1 - mux[j, 1]
                d2_ = x2 - mux[j, 2]
                dd = math.sqrt(max(_maha2(x0, x1, x2, mux, prec, j), 0.0))
                if dd > start:
                    e = math.sqrt(d0 * d0 + d1 * d1 + d2_ * d2_) * (1.0 - start / dd)
                    extra = (growth * e) ** 2
            v += w[t] * (s2[j] + extra + dmu * dmu)
            if want_grad:
                d0 = x0 - mux[j, 0]
                d1 = x1 - mux[j, 1]
                d2_ = x2 - mux[j, 2]
                p = prec[j]
                # d log p_j / dx = -P_j (x - mu_jX); dw_j = w_j (g_j - sum_k w_k g_k),
                # so sum_j mu_j dw_j = sum_j w_j (mu_j - m) g_j
                h0 = -(p[0, 0] * d0 + p[0, 1] * d1 + p[0, 2] * d2_)
                h1 = -(p[1, 0] * d0 + p[1, 1] * d1 + p[1, 2] * d2_)
                h2 = -(p[2, 0] * d0 + p[2, 1] * d1 + p[2, 2] * d2_)
                g0 += w[t] * (b[j, 0] + dmu * h0)
                g1 += w[t] * (b[j, 1] + dmu * h1)
                g2 += w[t] * (b[j, 2] + dmu * h2)
        mean[q] = m
        var[q] = v
        if want_grad:
            grad[q, 0] = g0
            grad[q, 1] = g1
            grad[q, 2] = g2
    return mean, var, grad, n_fallback


# --------------------------------------------------------------------- the field
class GMRField:
    """The GMR signed distance field of a 4D mixture (eqs. gmm_mean, gmm_sigma).

    Parameters
    ----------
    mixture : GaussianMixture
        4D mixture over ``(x, y, z, d)``.
    n_active : int
        ``J``, the number of active components mixed per query.
    mahalanobis_cut : float
        Components farther than this Mahalanobis distance (xyz) are not candidates.
    far_variance_growth : float
        ``gamma``: standard deviation gained per metre beyond a component's support
        (see the module docstring); 0 gives the paper's variance.
    far_growth_start : float
        ``D0``: Mahalanobis radius where a component's support ends.
    cell_size : float or None
        Edge of the query cells used for candidate pruning (m); default four times
        the median smallest standard deviation of the components (per-cell
        Mahalanobis slack about 3.5 for a typical component). Smaller cells prune
        tighter but cost more cKDTree queries; measured with scripts/bench_gmr.py.

    Attributes
    ----------
    info : dict
        Counts of the last ``predict`` (``n_fallback``: queries with no component
        within the cut; ``mean_candidates`` per query after pruning).
    """

    def __init__(self, mixture: GaussianMixture, n_active: int = 16,
                 mahalanobis_cut: float = 6.0, *,
                 far_variance_growth: float = DEFAULT_FAR_GROWTH,
                 far_growth_start: float = DEFAULT_FAR_START,
                 cell_size: float | None = None):
        if int(n_active) < 1:
            raise GMRError(f"Expected n_active >= 1, found {n_active}; use e.g. 16.")
        if not (mahalanobis_cut > 0 and math.isfinite(mahalanobis_cut)):
            raise GMRError(f"Expected a positive finite mahalanobis_cut, found "
                           f"{mahalanobis_cut}; use e.g. 6.0.")
        if not (far_variance_growth >= 0 and far_growth_start >= 0):
            raise GMRError(
                f"Expected far_variance_growth >= 0 and far_growth_start >= 0, found "
                f"{far_variance_growth} and {far_growth_start}.")
        self.mixture = mixture
        self.n_active = int(n_active)
        self.mahalanobis_cut = float(mahalanobis_cut)
        self.far_variance_growth = float(far_variance_growth)
        self.far_growth_start = float(far_growth_start)
        self._c = condition_on_xyz(mixture)
        k = mixture.n_components
        r = self.mahalanobis_cut * self._c["r_max"]
        if cell_size is None:
            cell_size = 4.0 * float(np.median(1.0 / self._c["lip"]))
        if not (cell_size > 0 and math.isfinite(cell_size)):
            raise GMRError(f"Expected a positive cell_size, found {cell_size}.")
        self.cell_size = float(cell_size)
        # radius buckets (powers of two) so one large component does not widen the
        # search ball of every small one
        level = np.floor(np.log2(r / r.min())).astype(np.int64)
        self._buckets = []
        for lv in np.unique(level):
            members = np.flatnonzero(level == lv)
            self._buckets.append((cKDTree(self._c["mux"][members]), members,
                                  float(r[members].max())))
        self.n_components = k
        self.info: dict = {}

    @classmethod
    def from_config(cls, mixture: GaussianMixture, cfg) -> "GMRField":
        """Build from a :class:`gmmgp_app.config.GMRConfig`."""
        return cls(mixture, n_active=cfg.n_active, mahalanobis_cut=cfg.mahalanobis_cut,
                   far_variance_growth=getattr(cfg, "far_variance_growth",
                                               DEFAULT_FAR_GROWTH),
                   far_growth_start=getattr(cfg, "far_growth_start", DEFAULT_FAR_START))

    def _cell_candidates(self, xyz):
        h = self.cell_size
        cells = np.floor(xyz / h).astype(np.int64)
        lo = cells.min(axis=0)
        span = cells.max(axis=0) - lo + 1
        if float(np.prod(span.astype(np.float64))) < 2.0 ** 62:
            # one int64 key per cell: a 1D unique is far cheaper than unique(axis=0)
            rel = cells - lo
            key = (rel[:, 0] * span[1] + rel[:, 1]) * span[2] + rel[:, 2]
            ukey, first, qcell = np.unique(key, return_index=True, return_inverse=True)
            ucells = cells[first]
        else:
            ucells, qcell = np.unique(cells, axis=0, return_inverse=True)
        qcell = np.ascontiguousarray(qcell.reshape(-1).astype(np.int64))
        centres = (ucells + 0.5) * h
        rho = 0.5 * math.sqrt(3.0) * h
        n_cells = len(ucells)
        parts_cell, parts_idx = [], []
        for tree, members, rad in self._buckets:
            lists = tree.query_ball_point(centres, rad + rho, return_sorted=False)
            lens = np.fromiter(map(len, lists), dtype=np.int64, count=n_cells)
            flat = np.fromiter(itertools.chain.from_iterable(lists), dtype=np.int64,
                               count=int(lens.sum()))
            parts_cell.append(np.repeat(np.arange(n_cells), lens))
            parts_idx.append(members[flat])
        cell_of = np.concatenate(parts_cell)
        idx = np.concatenate(parts_idx)
        order = np.argsort(cell_of, kind="stable")
        idx = np.ascontiguousarray(idx[order])
        ptr = np.zeros(n_cells + 1, dtype=np.int64)
        np.cumsum(np.bincount(cell_of, minlength=n_cells), out=ptr[1:])
        c = self._c
        keep = _prune_cells(centres, rho, ptr, idx, c["mux"], c["prec"], c["logc"],
                            c["lip"], self.n_active, self.mahalanobis_cut)
        csum = np.concatenate([[0], np.cumsum(keep, dtype=np.int64)])
        counts = csum[ptr[1:]] - csum[ptr[:-1]]
        ptr2 = np.zeros(n_cells + 1, dtype=np.int64)
        np.cumsum(counts, out=ptr2[1:])
        return qcell, ptr2, np.ascontiguousarray(idx[keep]), counts

    def predict(self, xyz, return_grad: bool = False):
        """GMR at query points.

        Parameters
        ----------
        xyz : (K, 3) array_like
            Query coordinates (finite).
        return_grad : bool
            Also return the analytic gradient of the mean.

        Returns
        -------
        mean : (K,) float64
            ``m(x)`` (eq. gmm_mean), free space positive.
        var : (K,) float64
            ``sigma^2(x)`` (eq. gmm_sigma, plus the far-field growth term).
        grad : (K, 3) float64, only if ``return_grad``
            ``grad m(x)`` including the derivative of the responsibilities.
        """
        x = _check_queries(xyz)
        if len(x) == 0:
            out = (np.zeros(0), np.zeros(0))
            return out + (np.zeros((0, 3)),) if return_grad else out
        qcell, ptr, idx, counts = self._cell_candidates(x)
        c = self._c
        mean, var, grad, n_fb = _gmr_kernel(
            x, qcell, ptr, idx, c["mux"], c["prec"], c["logc"], c["a"], c["b"], c["s2"],
            self.n_active, self.mahalanobis_cut, self.far_variance_growth,
            self.far_growth_start, bool(return_grad))
        self.info = dict(n_queries=len(x), n_cells=len(ptr) - 1, n_fallback=int(n_fb),
                         mean_candidates=float(counts[qcell].mean()))
        return (mean, var, grad) if return_grad else (mean, var)


# ----------------------------------------------------------------- the oracle
def gmr_bruteforce(mixture: GaussianMixture, xyz, return_grad: bool = False, *,
                   n_active: int | None = None, mahalanobis_cut: float | None = None,
                   far_variance_growth: float = DEFAULT_FAR_GROWTH,
                   far_growth_start: float = DEFAULT_FAR_START, chunk: int = 1024):
    """Reference GMR in plain numpy over all components (the tests' oracle).

    Conditions with the covariance form (``b = Sigma_XX^-1 Sigma_XY``,
    ``sigma_j^2 = Sigma_YY - Sigma_YX Sigma_XX^-1 Sigma_XY``), independent of the
    precision form used by :func:`condition_on_xyz`. With ``n_active`` and
    ``mahalanobis_cut`` left at None every component is mixed; set both to reproduce
    :class:`GMRField`'s selection (top ``J`` within the cut, all components when none
    is within it). The gradient is computed by the same analytic formula.

    Parameters
    ----------
    mixture : GaussianMixture
    xyz : (Q, 3) array_like
    return_grad : bool
    n_active, mahalanobis_cut : int, float or None
    far_variance_growth, far_growth_start : float
        As in :class:`GMRField`.
    chunk : int
        Queries per vectorised block (memory: ``chunk * K * 3`` floats).

    Returns
    -------
    mean (Q,), var (Q,)[, grad (Q, 3)]
    """
    _check_mixture(mixture)
    x = _check_queries(xyz)
    cov = mixture.covariances
    sxx, sxy, syy = cov[:, :3, :3], cov[:, :3, 3], cov[:, 3, 3]
    b = np.linalg.solve(sxx, sxy[:, :, None])[:, :, 0]
    s2 = syy - np.einsum("ki,ki->k", sxy, b)
    prec = np.linalg.inv(sxx)
    _, logdet = np.linalg.slogdet(sxx)
    w0 = mixture.weights / mixture.weights.sum()
    with np.errstate(divide="ignore"):
        logc = np.log(w0) - 0.5 * (3 * _LOG_2PI + logdet)
    mux, a = mixture.means[:, :3], mixture.means[:, 3]
    k = len(a)
    out_m, out_v, out_g = [], [], []
    for s in range(0, len(x), chunk):
        xc = x[s:s + chunk]
        dx = xc[:, None, :] - mux[None]                          # (q, K, 3)
        pdx = np.einsum("kij,qkj->qki", prec, dx)
        d2 = np.einsum("qki,qki->qk", dx, pdx)
        logw = logc[None] - 0.5 * d2
        if mahalanobis_cut is not None:
            inside = d2 <= mahalanobis_cut ** 2
            none = ~inside.any(axis=1)
            inside[none] = True                                  # far: all components
            logw = np.where(inside, logw, -np.inf)
        if n_active is not None and n_active < k:
            kth = np.partition(logw, k - n_active, axis=1)[:, k - n_active][:, None]
            logw = np.where(logw >= kth, logw, -np.inf)
        logw = logw - logw.max(axis=1, keepdims=True)
        w = np.exp(logw)
        w /= w.sum(axis=1, keepdims=True)
        mu = a[None] + np.einsum("kj,qkj->qk", b, dx)
        m = np.sum(w * mu, axis=1)
        dmu = mu - m[:, None]
        extra = np.zeros_like(mu)
        if far_variance_growth > 0:
            dd = np.sqrt(np.maximum(d2, 0.0))
            with np.errstate(divide="ignore", invalid="ignore"):
                e = np.linalg.norm(dx, axis=2) * (1.0 - far_growth_start / dd)
            extra = np.where(dd > far_growth_start, (far_variance_growth * e) ** 2, 0.0)
        v = np.sum(w * (s2[None] + extra + dmu ** 2), axis=1)
        out_m.append(m)
        out_v.append(v)
        if return_grad:
            g = np.einsum("qk,kj->qj", w, b) - np.einsum("qk,qki->qi", w * dmu, pdx)
            out_g.append(g)
    mean = np.concatenate(out_m) if out_m else np.zeros(0)
    var = np.concatenate(out_v) if out_v else np.zeros(0)
    if return_grad:
        return mean, var, (np.concatenate(out_g) if out_g else np.zeros((0, 3)))
    return mean, var
