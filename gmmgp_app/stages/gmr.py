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

The search is exact, not heuristic, and its set-up is paid once per cell:

1. Space is cut into a fixed grid of cubic cells of edge ``h`` (half diagonal
   ``rho``) over the box where any component can be a candidate (the union of the
   balls below). A query outside that box has no candidate at all.
2. Component means are grouped by *radius bucket* (each bucket's ball search is a
   compiled grid scan, stages/knn.py ``ball_lists``). Because
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
   bound (it can never be in the top ``J``).
4. The pruned list of a cell is built the first time a query falls in it and kept
   (a sorted table of cell keys + one CSR list per cell, bounded by
   ``cache_entries``; when full it is emptied and rebuilt on demand). A later query
   costs a binary search for its cell plus the exact cut and top ``J`` over that
   cell's list (numba, parallel over chunks of queries). The result equals the
   per-query definition exactly, whichever cells were built before.

Far from the data
-----------------
When no component lies within the cut, the top ``J`` of *all* components by
``pi_j p_j(x)`` are used (a linear scan; such queries are rare), so the field is
defined everywhere.

The plain GMR variance stays at the size of the ``+-s`` virtual-point band even
metres away from the data, which makes the predictive likelihood collapse there.
The variance therefore grows with the Euclidean distance of the query *outside
the region the responsible components describe* (eq. gmr_far_growth)::

    sigma^2(x) = sigma_GMR^2(x) + (gamma * e(x))^2,
    e(x) = max(0, -tau log sum_j (w_j(x) / w_max(x)) exp(-e_j(x) / tau)),
    e_j(x) = || max(|R_j^T (x - mu_jX)| - max(D0 sqrt(lambda_j), f), 0) ||

with ``Sigma_jXX = R_j diag(lambda_j) R_j^T``: ``e_j`` is the exact Euclidean
distance (m) from ``x`` to the box of half-sides ``D0`` standard deviations (at
least ``f`` metres, ``GMRConfig.far_growth_floor``) along the component's
principal axes, and ``e`` a soft minimum over the mixed components of
``e_j + tau log(w_max / w_j)``: about the distance to the nearest support box of a
component that is responsible for ``x`` (``tau = f / 3`` m per nat, 0.1 m at f = 0.3 m; zero when the
most responsible component's box holds ``x``). Every axis is
measured with its own extent, so a query beside a long flat patch does not count as
far merely because it is several thin-axis sigmas off the patch, and a query beyond
the end of the patch grows with its distance past that end; a query inside one
responsible component's box is not far because a neighbour's box ends short of it.
``e`` is zero inside, continuous (so are the responsibilities) and grows about one
metre per metre outside (each ``e_j`` is 1-Lipschitz), so the variance rises smoothly as one leaves the data instead of jumping when the
responsible components change. ``gamma`` (``GMRConfig.far_variance_growth``) is the
standard deviation gained per metre outside the support, ``D0``
(``GMRConfig.far_growth_start``) the half-extent in standard deviations (a uniform
patch ends at sqrt(3) = 1.73 sigma). ``gamma = 0`` gives the paper's GMR; the mean
and its gradient are unaffected.

What the mixture cannot tell: a hole in the data *inside* a component's extent
(a window in a facade, a gap in the ground) is covered by the box, so no growth
happens there; nor does a component whose data are skewed (denser on one side)
end exactly at ``D0`` sigma. Only the training points know these; the GP stage
corrects the mean near them.
"""

from __future__ import annotations

import math
import threading

import numba as nb
import numpy as np

from gmmgp_app.types import GaussianMixture

from .knn import ball_lists

__all__ = [
    "GMRError",
    "GMRField",
    "condition_on_xyz",
    "far_growth_distance",
    "gmr_bruteforce",
    "DEFAULT_FAR_GROWTH",
    "DEFAULT_FAR_START",
]

#: Defaults of ``GMRConfig.far_variance_growth``, ``far_growth_start`` and
#: ``far_growth_floor`` (kept here too so the oracle and the field agree when called without a config).
DEFAULT_FAR_GROWTH = 1.0
DEFAULT_FAR_START = 2.0
DEFAULT_FAR_FLOOR = 0.3

_LOG_2PI = math.log(2.0 * math.pi)
#: tau of eq. gmr_far_growth (m per nat): a component with responsibility w counts
#: as tau log(w_max / w) farther, so a query inside the box of a responsible component is
#: not "far" because a neighbour's box ends short of it
_SOFTMIN_TAU = 0.1
#: tau as a fraction of ``far_growth_floor`` (0.1 m at the urban 0.3 m), so that the
#: field scales with the scan (issue 15: a scan scaled by a gets a field scaled by a)
_SOFTMIN_TAU_PER_FLOOR = _SOFTMIN_TAU / DEFAULT_FAR_FLOOR
# queries per parallel work item: amortises the per-item scratch allocation
_CHUNK = 512
# cell lookups: not built yet / outside the candidate box (no candidate anywhere)
_MISSING = -1
_EMPTY_SLOT = 0


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
        ``sqrt(lambda_max(Sigma_XX^-1))``; ``axes`` (K, 3, 3) principal axes of
        ``Sigma_XX`` as rows (``R^T``); ``sd`` (K, 3) standard deviations along them.
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
    eig, vec = np.linalg.eigh(sxx)
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
        axes=np.ascontiguousarray(np.transpose(vec, (0, 2, 1))),
        sd=np.ascontiguousarray(np.sqrt(eig)),
    )


def far_growth_distance(dx, axes, half) -> np.ndarray:
    """Distance of queries outside each component's support box (eq. gmr_far_growth).

    ``e_j(x) = || max(|R_j^T (x - mu_jX)| - half_j, 0) ||``: the exact Euclidean
    distance from ``x`` to the box with half-sides ``half_j`` along the principal
    axes of ``Sigma_jXX`` (zero inside, 1-Lipschitz). This numpy form is the
    reference; the numba kernel inlines the same expression.

    Parameters
    ----------
    dx : (..., K, 3) array
        ``x - mu_jX`` per query and component.
    axes : (K, 3, 3) array
        Principal axes as rows (``R_j^T``), from :func:`condition_on_xyz`.
    half : (K, 3) array
        Half-sides of the support boxes (m), ``D0`` times the standard deviations.

    Returns
    -------
    (..., K) float64, metres.
    """
    u = np.einsum("kij,...kj->...ki", axes, dx)
    out = np.maximum(np.abs(u) - half, 0.0)
    return np.sqrt(np.einsum("...i,...i->...", out, out))


# ---------------------------------------------------------------- numba kernels
@nb.njit(cache=True, inline="always")
def _maha2(x0, x1, x2, mux, prec, j):
    d0 = x0 - mux[j, 0]
    d1 = x1 - mux[j, 1]
    d2 = x2 - mux[j, 2]
    p = prec[j]
    return (p[0, 0] * d0 * d0 + p[1, 1] * d1 * d1 + p[2, 2] * d2 * d2
            + 2.0 * (p[0, 1] * d0 * d1 + p[0, 2] * d0 * d2 + p[1, 2] * d1 * d2))


@nb.njit(cache=True, parallel=True, nogil=True)
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


@nb.njit(cache=True, parallel=True, nogil=True)
def _lookup_cells(xyz, inv_h, base, span, keys, slots):
    """Cell key and cached slot per query.

    ``key`` is -1 outside the candidate box (the slot is then the empty list);
    ``slot`` is ``_MISSING`` (-1) for a cell inside the box not built yet.
    """
    nq = xyz.shape[0]
    qkey = np.empty(nq, dtype=np.int64)
    qslot = np.empty(nq, dtype=np.int64)
    nk = keys.shape[0]
    for q in nb.prange(nq):
        c0 = math.floor(xyz[q, 0] * inv_h) - base[0]
        c1 = math.floor(xyz[q, 1] * inv_h) - base[1]
        c2 = math.floor(xyz[q, 2] * inv_h) - base[2]
        if (c0 < 0 or c1 < 0 or c2 < 0 or c0 >= span[0] or c1 >= span[1]
                or c2 >= span[2]):
            qkey[q] = -1
            qslot[q] = 0
            continue
        key = (np.int64(c0) * span[1] + np.int64(c1)) * span[2] + np.int64(c2)
        qkey[q] = key
        lo = 0
        hi = nk
        while lo < hi:
            mid = (lo + hi) >> 1
            if keys[mid] < key:
                lo = mid + 1
            else:
                hi = mid
        qslot[q] = slots[lo] if lo < nk and keys[lo] == key else -1
    return qkey, qslot


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


@nb.njit(cache=True, parallel=True, nogil=True)
def _gmr_kernel(xyz, qslot, ptr, idx, mux, prec, logc, a, b, s2, axes, half,
                n_active, cut, growth, tau, want_grad):
    """GMR mean (eq. gmm_mean), variance (eq. gmm_sigma + eq. gmr_far_growth), gradient.

    ``qslot[q]`` is the row of ``ptr`` holding query ``q``'s candidate list.
    """
    nq = xyz.shape[0]
    n_comp = mux.shape[0]
    mean = np.empty(nq)
    var = np.empty(nq)
    grad = np.zeros((nq, 3) if want_grad else (0, 3))
    cut2 = cut * cut
    g2 = growth * growth
    n_chunks = (nq + _CHUNK - 1) // _CHUNK
    fallback = np.zeros(n_chunks, dtype=np.int64)
    for ci in nb.prange(n_chunks):
        best_l = np.empty(n_active)
        best_j = np.empty(n_active, dtype=np.int64)
        w = np.empty(n_active)
        mu = np.empty(n_active)
        n_fb = 0
        for q in range(ci * _CHUNK, min(nq, (ci + 1) * _CHUNK)):
            x0, x1, x2 = xyz[q, 0], xyz[q, 1], xyz[q, 2]
            n = 0
            imin = 0
            c = qslot[q]
            for t in range(ptr[c], ptr[c + 1]):
                j = idx[t]
                d2 = _maha2(x0, x1, x2, mux, prec, j)
                if d2 <= cut2:
                    n, imin = _push_top(logc[j] - 0.5 * d2, j, best_l, best_j, n, imin)
            if n == 0:
                # no component within the cut: the nearest ones in the responsibility
                # sense, so the field (and its growing variance) is defined everywhere
                n_fb += 1
                for j in range(n_comp):
                    d2 = _maha2(x0, x1, x2, mux, prec, j)
                    n, imin = _push_top(logc[j] - 0.5 * d2, j, best_l, best_j, n, imin)
            lmax = -np.inf
            for t in range(n):
                if best_l[t] > lmax:
                    lmax = best_l[t]
            wsum = 0.0
            m = 0.0
            for t in range(n):
                j = best_j[t]
                w[t] = math.exp(best_l[t] - lmax)
                wsum += w[t]
                mu[t] = (a[j] + b[j, 0] * (x0 - mux[j, 0]) + b[j, 1] * (x1 - mux[j, 1])
                         + b[j, 2] * (x2 - mux[j, 2]))
                m += w[t] * mu[t]
            m /= wsum
            v = 0.0
            g0 = 0.0
            g1 = 0.0
            g2_ = 0.0
            emin = np.inf
            for t in range(n):
                j = best_j[t]
                wt = w[t] / wsum
                dmu = mu[t] - m
                d0 = x0 - mux[j, 0]
                d1 = x1 - mux[j, 1]
                d2 = x2 - mux[j, 2]
                if g2 > 0.0:
                    r = axes[j]
                    e2 = 0.0
                    for i in range(3):
                        u = abs(r[i, 0] * d0 + r[i, 1] * d1 + r[i, 2] * d2) - half[j, i]
                        if u > 0.0:
                            e2 += u * u
                    mu[t] = math.sqrt(e2)          # reuse: e_j from here on
                    if mu[t] < emin:
                        emin = mu[t]
                v += wt * (s2[j] + dmu * dmu)
                if want_grad:
                    p = prec[j]
                    # d log p_j / dx = -P_j (x - mu_jX); dw_j = w_j (g_j - sum_k w_k g_k),
                    # so sum_j mu_j dw_j = sum_j w_j (mu_j - m) g_j
                    h0 = -(p[0, 0] * d0 + p[0, 1] * d1 + p[0, 2] * d2)
                    h1 = -(p[1, 0] * d0 + p[1, 1] * d1 + p[1, 2] * d2)
                    h2 = -(p[2, 0] * d0 + p[2, 1] * d1 + p[2, 2] * d2)
                    g0 += wt * (b[j, 0] + dmu * h0)
                    g1 += wt * (b[j, 1] + dmu * h1)
                    g2_ += wt * (b[j, 2] + dmu * h2)
            if g2 > 0.0:
                # soft minimum of e_j + tau log(w_max / w_j) (eq. gmr_far_growth);
                # w holds w_j / w_max here
                acc = 0.0
                for t in range(n):
                    acc += w[t] * math.exp(-(mu[t] - emin) / tau)
                e = emin - tau * math.log(acc)
                if e > 0.0:
                    v += g2 * e * e
            mean[q] = m
            var[q] = v
            if want_grad:
                grad[q, 0] = g0
                grad[q, 1] = g1
                grad[q, 2] = g2_
        fallback[ci] = n_fb
    return mean, var, grad, fallback.sum()


def _merge_lists(n_cells, ptrs, idxs, members):
    """Concatenate per-cell candidate lists of the radius buckets (bucket order within
    a cell, member indices mapped to component indices) into one CSR."""
    lens = sum(np.diff(p) for p in ptrs)
    ptr = np.zeros(n_cells + 1, dtype=np.int64)
    np.cumsum(lens, out=ptr[1:])
    idx = np.empty(ptr[-1], dtype=np.int64)
    at = ptr[:-1].copy()
    for p, i, m in zip(ptrs, idxs, members):
        _scatter_lists(p, m[i], at, idx)
    return ptr, idx


@nb.njit(cache=True, nogil=True)
def _compact_lists(ptr, idx, keep):
    """The CSR (ptr, idx) with only the entries ``keep`` marks, idx as int32: the
    ``(concatenate([0], cumsum(keep))[ptr], idx[keep].astype(int32))`` of numpy in one
    pass, without the cumulative sum and mask copies over every candidate."""
    n_cells = ptr.shape[0] - 1
    ptr2 = np.zeros(n_cells + 1, dtype=np.int64)
    out = np.empty(idx.shape[0], dtype=np.int32)
    j = 0
    for c in range(n_cells):
        for t in range(ptr[c], ptr[c + 1]):
            if keep[t]:
                out[j] = idx[t]
                j += 1
        ptr2[c + 1] = j
    return ptr2, out[:j].copy()


@nb.njit(cache=True, nogil=True)
def _scatter_lists(p, vals, at, out):
    """Append list c of CSR (p, vals) at ``out[at[c]:]`` and advance ``at[c]``."""
    for c in range(len(p) - 1):
        n = p[c + 1] - p[c]
        for t in range(n):
            out[at[c] + t] = vals[p[c] + t]
        at[c] += n


# --------------------------------------------------------------------- the field
def _tau(far_growth_floor: float) -> float:
    """tau of eq. gmr_far_growth for a floor ``f``: ``f / 3`` (0.1 m at f = 0.3 m);
    a floor of 0 keeps the fixed 0.1 m."""
    return _SOFTMIN_TAU_PER_FLOOR * far_growth_floor if far_growth_floor > 0 else _SOFTMIN_TAU


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
        ``gamma``: standard deviation gained per metre outside a component's support
        (eq. gmr_far_growth in the module docstring); 0 gives the paper's variance.
    far_growth_start : float
        ``D0``: half-extent of a component's support box, in standard deviations
        along each principal axis of ``Sigma_XX``.
    far_growth_floor : float
        Least half-extent of a support box (m), so a component made of one layer of
        virtual points does not count the ``+-s`` band as outside.
    cell_size : float or None
        Edge of the grid cells whose pruned candidate lists are cached (m); default
        twice the median smallest standard deviation of the components (per-cell
        Mahalanobis slack about 1.7 for a typical component: a few candidates more
        than the exact set). Smaller cells prune tighter but cost more set-up and
        memory; measured with scripts/bench_gmr.py.
    cache_entries : int
        Bound on the cached candidate entries (4 bytes each); when a batch would
        exceed it the cache is emptied first and refilled on demand.

    Attributes
    ----------
    info : dict
        Counts of the last ``predict`` (``n_fallback``: queries with no component
        within the cut; ``mean_candidates`` per query after pruning;
        ``cells_built`` by this call; ``cells_cached`` in total).
    """

    def __init__(self, mixture: GaussianMixture, n_active: int = 16,
                 mahalanobis_cut: float = 6.0, *,
                 far_variance_growth: float = DEFAULT_FAR_GROWTH,
                 far_growth_start: float = DEFAULT_FAR_START,
                 far_growth_floor: float = DEFAULT_FAR_FLOOR,
                 cell_size: float | None = None, cache_entries: int = 1 << 25):
        if int(n_active) < 1:
            raise GMRError(f"Expected n_active >= 1, found {n_active}; use e.g. 16.")
        if not (mahalanobis_cut > 0 and math.isfinite(mahalanobis_cut)):
            raise GMRError(f"Expected a positive finite mahalanobis_cut, found "
                           f"{mahalanobis_cut}; use e.g. 6.0.")
        if not (far_variance_growth >= 0 and far_growth_start >= 0
                and math.isfinite(far_variance_growth) and math.isfinite(far_growth_start)):
            raise GMRError(
                f"Expected finite far_variance_growth >= 0 and far_growth_start >= 0, "
                f"found {far_variance_growth} and {far_growth_start}.")
        if not (far_growth_floor >= 0 and math.isfinite(far_growth_floor)):
            raise GMRError(f"Expected a finite far_growth_floor >= 0, found "
                           f"{far_growth_floor}; use e.g. 0.3 (m).")
        if int(cache_entries) < 1:
            raise GMRError(f"Expected cache_entries >= 1, found {cache_entries}; "
                           "use e.g. 2**25.")
        self.mixture = mixture
        self.n_active = int(n_active)
        self.mahalanobis_cut = float(mahalanobis_cut)
        self.far_variance_growth = float(far_variance_growth)
        self.far_growth_start = float(far_growth_start)
        self.cache_entries = int(cache_entries)
        self._c = condition_on_xyz(mixture)
        self.far_growth_floor = float(far_growth_floor)
        self._tau = _tau(self.far_growth_floor)
        self._half = np.ascontiguousarray(
            np.maximum(self.far_growth_start * self._c["sd"], self.far_growth_floor))
        k = mixture.n_components
        r = self.mahalanobis_cut * self._c["r_max"]
        if cell_size is None:
            cell_size = 2.0 * float(np.median(1.0 / self._c["lip"]))
        if not (cell_size > 0 and math.isfinite(cell_size)):
            raise GMRError(f"Expected a positive cell_size, found {cell_size}.")
        mux = self._c["mux"]
        lo = (mux - r[:, None]).min(axis=0)
        hi = (mux + r[:, None]).max(axis=0)
        # keys are int64: keep the grid below 2**60 cells whatever the extent
        cells = float(np.prod((hi - lo) / cell_size + 2.0))
        if cells > 2.0 ** 60:
            cell_size *= (cells / 2.0 ** 60) ** (1.0 / 3.0)
        self.cell_size = float(cell_size)
        self._base = np.floor(lo / self.cell_size).astype(np.int64)
        self._span = (np.floor(hi / self.cell_size).astype(np.int64) - self._base + 1)
        # radius buckets (powers of two) so one large component does not widen the
        # search ball of every small one
        level = np.floor(np.log2(r / r.min())).astype(np.int64)
        self._buckets = []
        for lv in np.unique(level):
            members = np.flatnonzero(level == lv)
            self._buckets.append((members, np.ascontiguousarray(mux[members]),
                                  float(r[members].max())))
        self.n_components = k
        self._lock = threading.Lock()
        self.clear_cache()
        self.info: dict = {}

    @classmethod
    def from_config(cls, mixture: GaussianMixture, cfg) -> "GMRField":
        """Build from a :class:`gmmgp_app.config.GMRConfig` (``"auto"`` fields take their
        fixed urban value here; ``build_map`` resolves them from the scan first)."""
        from gmmgp_app.config import concrete

        cfg = concrete(cfg)
        return cls(mixture, n_active=cfg.n_active, mahalanobis_cut=cfg.mahalanobis_cut,
                   far_variance_growth=getattr(cfg, "far_variance_growth",
                                               DEFAULT_FAR_GROWTH),
                   far_growth_start=getattr(cfg, "far_growth_start", DEFAULT_FAR_START),
                   far_growth_floor=getattr(cfg, "far_growth_floor", DEFAULT_FAR_FLOOR))

    # ------------------------------------------------------------------ cache
    def clear_cache(self) -> None:
        """Forget every cached cell (slot 0, the empty list, stays)."""
        self._keys = np.zeros(0, dtype=np.int64)      # sorted cell keys
        self._slots = np.zeros(0, dtype=np.int64)     # slot of each key
        self._ptr = np.zeros(2, dtype=np.int64)       # CSR over slots
        self._idx = np.zeros(0, dtype=np.int32)

    @property
    def cells_cached(self) -> int:
        """Number of grid cells whose candidate lists are built."""
        return len(self._keys)

    def _build_cells(self, keys: np.ndarray):
        """Pruned candidate lists of the cells ``keys`` (unique) as CSR (ptr, idx)."""
        h = self.cell_size
        span = self._span
        c2 = keys % span[2]
        c1 = (keys // span[2]) % span[1]
        c0 = keys // (span[2] * span[1])
        centres = (np.c_[c0, c1, c2] + self._base + 0.5) * h
        rho = 0.5 * math.sqrt(3.0) * h
        n_cells = len(keys)
        parts = []
        for members, mux_b, rad in self._buckets:
            # the bucket's means within rad + rho of each cell centre (compiled)
            parts.append(ball_lists(mux_b, centres, rad + rho))
        ptr, idx = _merge_lists(n_cells, [p for p, _ in parts], [i for _, i in parts],
                                [m for m, _, _ in self._buckets])
        c = self._c
        keep = _prune_cells(centres, rho, ptr, idx, c["mux"], c["prec"], c["logc"],
                            c["lip"], self.n_active, self.mahalanobis_cut)
        return _compact_lists(ptr, idx, keep)

    def _append(self, keys, ptr_new, idx_new) -> None:
        """Add built cells (unique keys, not cached) to the cache."""
        first = len(self._ptr) - 1
        slots_new = np.arange(first, first + len(keys), dtype=np.int64)
        self._ptr = np.concatenate([self._ptr, self._ptr[-1] + ptr_new[1:]])
        self._idx = np.concatenate([self._idx, idx_new])
        allk = np.concatenate([self._keys, keys])
        alls = np.concatenate([self._slots, slots_new])
        order = np.argsort(allk, kind="stable")
        self._keys = np.ascontiguousarray(allk[order])
        self._slots = np.ascontiguousarray(alls[order])

    def _query_slots(self, x: np.ndarray):
        """Slot of every query's cell, building the missing cells once."""
        inv_h = 1.0 / self.cell_size
        with self._lock:
            qkey, qslot = _lookup_cells(x, inv_h, self._base, self._span, self._keys,
                                        self._slots)
            miss = qslot == _MISSING
            n_built = 0
            if miss.any():
                new = np.unique(qkey[miss])
                ptr_new, idx_new = self._build_cells(new)
                if len(self._idx) + len(idx_new) > self.cache_entries:
                    # full: start again with the cells this batch needs (a batch
                    # larger than the bound is still served, then dropped later)
                    self.clear_cache()
                    new = np.unique(qkey[qkey >= 0])
                    ptr_new, idx_new = self._build_cells(new)
                n_built = len(new)
                self._append(new, ptr_new, idx_new)
                qkey, qslot = _lookup_cells(x, inv_h, self._base, self._span,
                                            self._keys, self._slots)
            return qslot, self._ptr, self._idx, n_built

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
            ``sigma^2(x)`` (eq. gmm_sigma, plus the far-field growth of
            eq. gmr_far_growth).
        grad : (K, 3) float64, only if ``return_grad``
            ``grad m(x)`` including the derivative of the responsibilities.
        """
        x = _check_queries(xyz)
        if len(x) == 0:
            out = (np.zeros(0), np.zeros(0))
            return out + (np.zeros((0, 3)),) if return_grad else out
        qslot, ptr, idx, n_built = self._query_slots(x)
        c = self._c
        mean, var, grad, n_fb = _gmr_kernel(
            x, qslot, ptr, idx, c["mux"], c["prec"], c["logc"], c["a"], c["b"], c["s2"],
            c["axes"], self._half, self.n_active, self.mahalanobis_cut,
            self.far_variance_growth, self._tau, bool(return_grad))
        counts = np.diff(ptr)
        self.info = dict(n_queries=len(x), n_fallback=int(n_fb), cells_built=n_built,
                         cells_cached=self.cells_cached,
                         mean_candidates=float(counts[qslot].mean()))
        return (mean, var, grad) if return_grad else (mean, var)


# ----------------------------------------------------------------- the oracle
def gmr_bruteforce(mixture: GaussianMixture, xyz, return_grad: bool = False, *,
                   n_active: int | None = None, mahalanobis_cut: float | None = None,
                   far_variance_growth: float = DEFAULT_FAR_GROWTH,
                   far_growth_start: float = DEFAULT_FAR_START,
                   far_growth_floor: float = DEFAULT_FAR_FLOOR, chunk: int = 1024):
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
    far_variance_growth, far_growth_start, far_growth_floor : float
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
    eig, vec = np.linalg.eigh(sxx)
    axes = np.transpose(vec, (0, 2, 1))
    half = np.maximum(far_growth_start * np.sqrt(eig), far_growth_floor)
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
        v = np.sum(w * (s2[None] + dmu ** 2), axis=1)
        if far_variance_growth > 0:
            e = far_growth_distance(dx, axes, half)
            # soft minimum of e_j + tau log(w_max / w_j) over the mixed components,
            # shifted by the smallest e_j so that exp does not underflow far away
            rel = w / w.max(axis=1, keepdims=True)
            emin = np.min(np.where(w > 0, e, np.inf), axis=1, keepdims=True)
            tau = _tau(far_growth_floor)
            acc = np.sum(rel * np.exp(-(e - emin) / tau), axis=1)
            soft = emin[:, 0] - tau * np.log(acc)
            v = v + (far_variance_growth * np.maximum(soft, 0.0)) ** 2
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
