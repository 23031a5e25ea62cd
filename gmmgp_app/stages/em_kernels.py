"""numba kernels of expectation-maximisation for full-covariance Gaussian mixtures.

These are the inner loops of :mod:`gmmgp_app.stages.hgmm`; they work on raw
arrays and never allocate per point. Conventions shared by every kernel:

* ``X`` is ``(N, D)`` float64, C-contiguous.
* A component is described to the kernels by its *precision Cholesky factor*
  ``P = L^{-1}`` (lower triangular, ``Sigma = L L^T``) and a log constant
  ``log pi_k - D/2 log(2 pi) - sum(log diag L)``, so that
  ``log pi_k N(x | mu_k, Sigma_k) = logconst_k - 0.5 * |P (x - mu_k)|^2``.
* Reductions over points are done in fixed-size chunks whose partial sums are
  added in chunk order: results do not depend on the number of threads, so a
  seed gives bitwise identical fits on any machine with the same numba build.

Each kernel has a plain numpy reference in ``tests/test_hgmm.py``.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

__all__ = [
    "CHUNK",
    "cholesky_into",
    "component_terms",
    "weighted_log_prob",
    "log_likelihood",
    "accumulate",
    "mstep_from_resp",
    "em_loop",
    "assign",
    "kmeanspp",
    "group_log_likelihood",
    "assign_groups",
    "accumulate_groups",
    "accumulate_groups_parallel",
    "em_loop_groups",
]

LOG_2PI = float(np.log(2.0 * np.pi))
CHUNK = 2048
# Responsibilities below this are not accumulated: their share of any statistic
# is below 1e-12 of one row's, far under float64 noise for the sums involved,
# and skipping them halves the M-step work once components have separated.
RESP_FLOOR = 1e-12
# A responsibility exp(t) with t below this is under RESP_FLOOR (exp(-28) = 6.9e-13),
# so it is skipped without calling exp: the same rows are accumulated, and no exp of
# a very negative argument is taken (glibc's exp takes a slow error path, errno and
# all, whenever its result underflows; on the street's tied EM half the (group,
# component) pairs sit beyond -745 once the fit has separated them).
LOG_RESP_SKIP = -28.0
# exp(t) of t below this is exactly 0.0 in double precision (the smallest subnormal
# is exp(-744.4); below -745.13 the result rounds to zero): log-sum-exp skips such
# terms, which adds the same +0.0 they would have added.
LOG_EXP_ZERO = -746.0
# Log-sum-exp adds exp(t - m) of every term to a running sum s; once s >= 1 (the
# largest term adds exp(0) = 1), a term exp(t) < 2^-53 (half an ulp of 1) leaves s
# unchanged whatever s is: with t < LOG_ABSORBED (exp(-37) = 8.5e-17 < 2^-53 = 1.1e-16)
# the exp is not taken, and s keeps the same bits.
LOG_ABSORBED = -37.0
# Terms before the largest one are added while s < 1; when every one of them (at most
# LSE_PRE_MAX_K - 1) is below this, their sum p < (K - 1) exp(-42) < 2^-53 and
# fl(p + 1) = 1: s is exactly 1 after the largest term, as if they were not there.
LOG_ABSORBED_PRE = -42.0
LSE_PRE_MAX_K = 64
EPS10 = 10.0 * np.finfo(np.float64).eps


@njit(cache=True, nogil=True)
def cholesky_into(A, L):
    """Lower Cholesky factor of ``A`` (D, D) into ``L``; False if not positive definite."""
    D = A.shape[0]
    for j in range(D):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not (s > 0.0) or not np.isfinite(s):
            return False
        ljj = np.sqrt(s)
        L[j, j] = ljj
        for i in range(j + 1, D):
            t = A[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / ljj
        for i in range(j):
            L[i, j] = 0.0
    return True


@njit(cache=True, nogil=True)
def component_terms(weights, covs, pchol, logconst):
    """Fill ``pchol`` (K, D, D) with ``L_k^{-1}`` and ``logconst`` (K,).

    Returns the index of the first component whose covariance is not positive
    definite (or whose weight is not positive), else -1.
    """
    K, D = covs.shape[0], covs.shape[1]
    L = np.empty((D, D))
    for k in range(K):
        if not (weights[k] > 0.0):
            return k
        if not cholesky_into(covs[k], L):
            return k
        logdet_half = 0.0
        for i in range(D):
            logdet_half += np.log(L[i, i])
        # P = L^{-1} by forward substitution, column by column.
        for c in range(D):
            for i in range(D):
                if i < c:
                    pchol[k, i, c] = 0.0
                    continue
                t = 1.0 if i == c else 0.0
                for j in range(c, i):
                    t -= L[i, j] * pchol[k, j, c]
                pchol[k, i, c] = t / L[i, i]
        logconst[k] = np.log(weights[k]) - 0.5 * D * LOG_2PI - logdet_half
    return -1


@njit(cache=True, inline="always")
def _row_logprob(X, n, means, pchol, logconst, out):
    K, D = means.shape
    for k in range(K):
        maha = 0.0
        for i in range(D):
            y = 0.0
            for j in range(i + 1):
                y += pchol[k, i, j] * (X[n, j] - means[k, j])
            maha += y * y
        out[k] = logconst[k] - 0.5 * maha


@njit(cache=True, inline="always")
def _lse(v):
    """``m + log(sum_k exp(v[k] - m))``, ``m = max v``, summed in k order; the exps that
    cannot change the sum's bits are not taken (``LOG_EXP_ZERO``, ``LOG_ABSORBED``,
    ``LOG_ABSORBED_PRE``) and exp(0) is 1: the bits of every exp taken in order."""
    K = v.shape[0]
    m = -np.inf
    km = -1
    for k in range(K):
        if v[k] > m:
            m = v[k]
            km = k
    if m == -np.inf:
        return m
    s = 0.0
    start = 0
    if K <= LSE_PRE_MAX_K and m < np.inf:   # (m = inf: the largest term's t is NaN)
        tiny = True
        for k in range(km):
            if not (v[k] - m < LOG_ABSORBED_PRE):     # a NaN is not tiny
                tiny = False
                break
        if tiny:            # the terms before the largest add nothing to its 1.0
            s = 1.0
            start = km + 1
    for k in range(start, K):
        t = v[k] - m
        if t < LOG_EXP_ZERO:
            continue        # exp(t) == 0.0 exactly (a NaN t still goes to exp)
        if t < LOG_ABSORBED and s >= 1.0:
            continue        # exp(t) < 2^-53: s + exp(t) == s
        s += 1.0 if t == 0.0 else np.exp(t)
    return m + np.log(s)


@njit(cache=True, parallel=True)
def weighted_log_prob(X, means, pchol, logconst):
    """``log pi_k N(x_n | mu_k, Sigma_k)`` for all rows and components, (N, K)."""
    N = X.shape[0]
    K = means.shape[0]
    out = np.empty((N, K))
    for n in prange(N):
        _row_logprob(X, n, means, pchol, logconst, out[n])
    return out


@njit(cache=True, parallel=True)
def log_likelihood(X, means, pchol, logconst):
    """Per-row mixture log-likelihood ``log sum_k pi_k N(x_n | .)``, (N,).

    Works chunk-wise so that memory stays O(K) per thread for any K.
    """
    N = X.shape[0]
    K = means.shape[0]
    out = np.empty(N)
    nch = (N + CHUNK - 1) // CHUNK
    for c in prange(nch):
        lp = np.empty(K)
        for n in range(c * CHUNK, min(N, (c + 1) * CHUNK)):
            _row_logprob(X, n, means, pchol, logconst, lp)
            out[n] = _lse(lp)
    return out


@njit(cache=True, nogil=True)
def assign(X, means, pchol, logconst):
    """Hard assignment: index of the component with the largest ``pi_k N(x|.)``, (N,) int64."""
    N = X.shape[0]
    K = means.shape[0]
    out = np.empty(N, dtype=np.int64)
    nch = (N + CHUNK - 1) // CHUNK
    lp = np.empty(K)
    for c in range(nch):
        for n in range(c * CHUNK, min(N, (c + 1) * CHUNK)):
            _row_logprob(X, n, means, pchol, logconst, lp)
            best = 0
            for k in range(1, K):
                if lp[k] > lp[best]:
                    best = k
            out[n] = best
    return out


@njit(cache=True, inline="always")
def _add_row_stats(X, n, means, k, r, sx, sxx, diff):
    """Add row n with responsibility r to component k's shifted sums (lower triangle)."""
    D = X.shape[1]
    for i in range(D):
        diff[i] = X[n, i] - means[k, i]
        sx[k, i] += r * diff[i]
    for i in range(D):
        ri = r * diff[i]
        for j in range(i + 1):
            sxx[k, i, j] += ri * diff[j]


@njit(cache=True, nogil=True)
def _accumulate_range(X, start, end, means, pchol, logconst, nk, sx, sxx, lp):
    """E-step for rows [start, end) fused with the M-step sufficient statistics.

    Statistics are taken about the *current* means (``x - mu_k``): the new
    covariance is then ``S / n_k - delta delta^T`` with a small ``delta``, which
    avoids the cancellation of raw second moments when coordinates are tens of
    metres and covariances are millimetres squared.
    Returns (sum of row log-likelihoods, worst row log-likelihood, its index).
    """
    K, D = means.shape
    ll = 0.0
    worst = np.inf
    worst_i = -1
    diff = np.empty(D)
    for n in range(start, end):
        _row_logprob(X, n, means, pchol, logconst, lp)
        lse = _lse(lp)
        ll += lse
        if lse < worst:
            worst = lse
            worst_i = n
        for k in range(K):
            t = lp[k] - lse
            if t < LOG_RESP_SKIP:
                continue    # exp(t) < RESP_FLOOR (a NaN t still goes to exp)
            r = np.exp(t)
            if r < RESP_FLOOR:
                continue
            nk[k] += r
            _add_row_stats(X, n, means, k, r, sx, sxx, diff)
    return ll, worst, worst_i


@njit(cache=True, parallel=True)
def _accumulate_parallel(X, means, pchol, logconst):
    N = X.shape[0]
    K, D = means.shape
    nch = (N + CHUNK - 1) // CHUNK
    NK = np.zeros((nch, K))
    SX = np.zeros((nch, K, D))
    SXX = np.zeros((nch, K, D, D))
    LL = np.zeros(nch)
    WORST = np.zeros(nch)
    WI = np.zeros(nch, dtype=np.int64)
    for c in prange(nch):
        lp = np.empty(K)
        ll, w, wi = _accumulate_range(X, c * CHUNK, min(N, (c + 1) * CHUNK), means, pchol,
                                      logconst, NK[c], SX[c], SXX[c], lp)
        LL[c] = ll
        WORST[c] = w
        WI[c] = wi
    # Fixed-order reduction: identical sums whatever the thread count.
    nk = np.zeros(K)
    sx = np.zeros((K, D))
    sxx = np.zeros((K, D, D))
    ll = 0.0
    worst = np.inf
    worst_i = -1
    for c in range(nch):
        nk += NK[c]
        sx += SX[c]
        sxx += SXX[c]
        ll += LL[c]
        if WORST[c] < worst:
            worst = WORST[c]
            worst_i = WI[c]
    return nk, sx, sxx, ll, worst, worst_i


@njit(cache=True, nogil=True)
def accumulate(X, means, pchol, logconst, parallel=False):
    """Fused E-step and M-step statistics over all rows.

    Returns
    -------
    nk : (K,) sum of responsibilities
    sx : (K, D) sum of r * (x - mu_k)
    sxx : (K, D, D) sum of r * (x - mu_k)(x - mu_k)^T (lower triangle filled)
    ll : float, sum of row log-likelihoods
    worst, worst_i : lowest row log-likelihood and its row index
    """
    N = X.shape[0]
    K, D = means.shape
    if N <= CHUNK or not parallel:
        # Serial by default: on a shared, oversubscribed machine a parallel
        # region waits for its slowest thread and measured 2-10x *slower* than
        # one thread; and one chunk never pays for the region's start-up.
        nk = np.zeros(K)
        sx = np.zeros((K, D))
        sxx = np.zeros((K, D, D))
        lp = np.empty(K)
        ll, worst, worst_i = _accumulate_range(X, 0, N, means, pchol, logconst, nk, sx, sxx, lp)
        return nk, sx, sxx, ll, worst, worst_i
    return _accumulate_parallel(X, means, pchol, logconst)


@njit(cache=True, nogil=True)
def _mstep_from_stats(N, nk, sx, sxx, means_old, reg_covar, weights, means, covs):
    """M-step from shifted statistics (as scikit-learn: n_k + 10 eps, reg_covar on the diagonal)."""
    K, D = means_old.shape
    total = 0.0
    for k in range(K):
        total += nk[k] + EPS10
    for k in range(K):
        n = nk[k] + EPS10
        weights[k] = n / total
        delta = np.empty(D)
        for i in range(D):
            delta[i] = sx[k, i] / n
            means[k, i] = means_old[k, i] + delta[i]
        for i in range(D):
            for j in range(i + 1):
                v = sxx[k, i, j] / n - delta[i] * delta[j]
                covs[k, i, j] = v
                covs[k, j, i] = v
            covs[k, i, i] += reg_covar


@njit(cache=True, nogil=True)
def mstep_from_resp(X, resp, reg_covar):
    """M-step from given responsibilities (N, K): (weights (K,), means (K, D), covs (K, D, D))."""
    N, D = X.shape
    K = resp.shape[1]
    nk = np.zeros(K)
    sx = np.zeros((K, D))
    sxx = np.zeros((K, D, D))
    zero = np.zeros((K, D))
    for n in range(N):
        for k in range(K):
            r = resp[n, k]
            if r == 0.0:
                continue
            nk[k] += r
            for i in range(D):
                sx[k, i] += r * X[n, i]
    # Second pass about the new means: the exact two-pass formula.
    mu = np.zeros((K, D))
    for k in range(K):
        for i in range(D):
            mu[k, i] = sx[k, i] / (nk[k] + EPS10)
    for n in range(N):
        for k in range(K):
            r = resp[n, k]
            if r == 0.0:
                continue
            for i in range(D):
                di = X[n, i] - mu[k, i]
                for j in range(i + 1):
                    sxx[k, i, j] += r * di * (X[n, j] - mu[k, j])
    weights = np.empty(K)
    means = np.empty((K, D))
    covs = np.empty((K, D, D))
    _mstep_from_stats(N, nk, zero, sxx, mu, reg_covar, weights, means, covs)
    return weights, means, covs


@njit(cache=True, nogil=True)
def em_loop(X, weights, means, covs, max_iter, tol, reg_covar, min_nk, parallel=False):
    """Run EM in place until convergence, ``max_iter`` or a bad component.

    The sequence is scikit-learn's: E-step with the current parameters (its mean
    log-likelihood is the "lower bound"), M-step, stop when the lower bound
    changed by less than ``tol``.

    Returns
    -------
    n_iter : int, EM iterations done (E+M pairs)
    converged : bool
    status : 0 ok; 1 component ``bad_k`` not positive definite; 2 component
        ``bad_k`` empty (fewer than ``min_nk`` rows of responsibility). On status
        1 or 2 the parameters are those of the last good M-step (for status 2 the
        E-step that found the empty component is not applied).
    bad_k : int
    lower_bound : float, mean row log-likelihood of the last E-step
    worst_i : int, row with the lowest log-likelihood in the last E-step
    """
    N, D = X.shape
    K = means.shape[0]
    pchol = np.empty((K, D, D))
    logconst = np.empty(K)
    prev = -np.inf
    lb = -np.inf
    worst_i = -1
    for it in range(max_iter):
        bad = component_terms(weights, covs, pchol, logconst)
        if bad >= 0:
            return it, False, 1, bad, lb, worst_i
        nk, sx, sxx, ll, worst, worst_i = accumulate(X, means, pchol, logconst, parallel)
        lb = ll / N
        if not np.isfinite(lb):
            return it, False, 1, -1, lb, worst_i
        for k in range(K):
            if nk[k] < min_nk:
                return it, False, 2, k, lb, worst_i
        old = means.copy()
        _mstep_from_stats(N, nk, sx, sxx, old, reg_covar, weights, means, covs)
        if abs(lb - prev) < tol:
            return it + 1, True, 0, -1, lb, worst_i
        prev = lb
    return max_iter, False, 0, -1, lb, worst_i


@njit(cache=True, nogil=True)
def kmeanspp(X, K, u):
    """k-means++ seeding: indices of up to K rows, (k,) int64 with k <= K.

    ``u`` (K,) are uniform draws in [0, 1) supplied by the caller's Generator, so
    the seeding is reproducible. Fewer than K indices come back when the rows
    have fewer than K distinct values (every remaining row sits on a centre).
    """
    N, D = X.shape
    idx = np.empty(K, dtype=np.int64)
    idx[0] = min(int(u[0] * N), N - 1)
    d2 = np.empty(N)
    for n in range(N):
        s = 0.0
        for i in range(D):
            t = X[n, i] - X[idx[0], i]
            s += t * t
        d2[n] = s
    for c in range(1, K):
        total = 0.0
        for n in range(N):
            total += d2[n]
        if not (total > 0.0):
            return idx[:c]
        target = u[c] * total
        acc = 0.0
        pick = -1
        last_pos = -1
        for n in range(N):
            if d2[n] > 0.0:
                last_pos = n
            acc += d2[n]
            if acc > target and d2[n] > 0.0:
                pick = n
                break
        if pick < 0:
            pick = last_pos  # rounding at the very end of the cumulative sum
        idx[c] = pick
        for n in range(N):
            s = 0.0
            for i in range(D):
                t = X[n, i] - X[pick, i]
                s += t * t
            if s < d2[n]:
                d2[n] = s
    return idx


@njit(cache=True, nogil=True)
def nearest_center(X, centers):
    """Index of the Euclidean-nearest centre for every row, (N,) int64."""
    N, D = X.shape
    K = centers.shape[0]
    out = np.empty(N, dtype=np.int64)
    for n in range(N):
        best = 0
        bd = np.inf
        for k in range(K):
            s = 0.0
            for i in range(D):
                t = X[n, i] - centers[k, i]
                s += t * t
            if s < bd:
                bd = s
                best = k
        out[n] = best
    return out


# ------------------------------------------------------------- tied (grouped) EM
# The training rows of one hit point -- the hit (d = 0) and its virtual points at
# +-s -- are one observation of the surface: they are drawn from the *same*
# component. Rows are sorted so that every group is contiguous, ``gptr`` (G + 1,)
# holds the group boundaries. The latent label is per group:
#
#     log r_gk = log pi_k + sum_{n in g} log N(x_n | mu_k, Sigma_k) - log Z_g
#
# with pi_k the fraction of *groups* of component k. Free EM on the rows instead
# separates the three sheets (d = -s, 0, +s) into different components wherever
# the surface bends within s (a 1 m sphere, poles, corners): such a component has
# d constant, so its regression has zero gradient and the zero level set between
# sheets is ill-defined. Tied labels keep each component a slab across the surface.
# Contract of the kernels below: ``logconst`` comes from :func:`component_terms`
# called with the *group* weights, and ``logw`` is their log.


@njit(cache=True, inline="always")
def _group_logprob(X, a, b, means, pchol, logconst, logw, lp, tmp):
    """lp[k] = log pi_k + sum_{n in [a, b)} log N(x_n | k).

    ``logconst`` holds log pi_k once per row, hence the ``-(b - a - 1) log pi_k``.
    """
    K = means.shape[0]
    for k in range(K):
        lp[k] = -(b - a - 1) * logw[k]
    for n in range(a, b):
        _row_logprob(X, n, means, pchol, logconst, tmp)
        for k in range(K):
            lp[k] += tmp[k]


@njit(cache=True, inline="always")
def _soa4(means, pchol, logconst, logw):
    """The D = 4 components' terms by row, each row contiguous over the components
    (for :func:`_group_logprob4`): ``Q[0:4]`` the means, ``Q[4:14]`` the precision
    factor's lower triangle row by row (p00, p10, p11, p20, ..., p33), ``Q[14]``
    ``logconst``, ``Q[15]`` ``logw``. (16, K)."""
    K = means.shape[0]
    Q = np.empty((16, K))
    for k in range(K):
        for d in range(4):
            Q[d, k] = means[k, d]
        t = 4
        for i in range(4):
            for j in range(i + 1):
                Q[t, k] = pchol[k, i, j]
                t += 1
        Q[14, k] = logconst[k]
        Q[15, k] = logw[k]
    return Q


@njit(cache=True, inline="always")
def _group_logprob4(X, a, b, Q, lp):
    """:func:`_group_logprob` for D = 4 (the mapper's rows), from :func:`_soa4`'s terms:
    the same operations in the same order for each component (its sum over the
    group's rows taken row after row), with the components side by side in the inner
    loop (the compiler computes several at once: independent lanes, the same bits)."""
    K = Q.shape[1]
    for k in range(K):
        lp[k] = -(b - a - 1) * Q[15, k]
    for n in range(a, b):
        x0 = X[n, 0]
        x1 = X[n, 1]
        x2 = X[n, 2]
        x3 = X[n, 3]
        for k in range(K):
            d0 = x0 - Q[0, k]
            d1 = x1 - Q[1, k]
            d2 = x2 - Q[2, k]
            d3 = x3 - Q[3, k]
            y0 = 0.0 + Q[4, k] * d0
            y1 = (0.0 + Q[5, k] * d0) + Q[6, k] * d1
            y2 = ((0.0 + Q[7, k] * d0) + Q[8, k] * d1) + Q[9, k] * d2
            y3 = (((0.0 + Q[10, k] * d0) + Q[11, k] * d1) + Q[12, k] * d2) + Q[13, k] * d3
            maha = (((0.0 + y0 * y0) + y1 * y1) + y2 * y2) + y3 * y3
            lp[k] += Q[14, k] - 0.5 * maha


@njit(cache=True, inline="always")
def _group_lp(X, a, b, means, pchol, logconst, logw, lp, tmp, Q):
    """:func:`_group_logprob`, through :func:`_group_logprob4` when D = 4 (``Q``:
    :func:`_soa4`'s terms)."""
    if X.shape[1] == 4:
        _group_logprob4(X, a, b, Q, lp)
    else:
        _group_logprob(X, a, b, means, pchol, logconst, logw, lp, tmp)


@njit(cache=True, nogil=True)
def group_log_likelihood(X, gptr, means, pchol, logconst, logw):
    """Per-group log-likelihood ``log sum_k pi_k prod_n N(x_n | k)``, (G,)."""
    G = gptr.shape[0] - 1
    K = means.shape[0]
    out = np.empty(G)
    lp = np.empty(K)
    tmp = np.empty(K)
    Q = _soa4(means, pchol, logconst, logw) if X.shape[1] == 4 else np.empty((16, 0))
    for g in range(G):
        _group_lp(X, gptr[g], gptr[g + 1], means, pchol, logconst, logw, lp, tmp, Q)
        out[g] = _lse(lp)
    return out


@njit(cache=True, nogil=True)
def assign_groups(X, gptr, means, pchol, logconst, logw):
    """Hard assignment of every group to its most likely component, (G,) int64."""
    G = gptr.shape[0] - 1
    K = means.shape[0]
    out = np.empty(G, dtype=np.int64)
    lp = np.empty(K)
    tmp = np.empty(K)
    Q = _soa4(means, pchol, logconst, logw) if X.shape[1] == 4 else np.empty((16, 0))
    for g in range(G):
        _group_lp(X, gptr[g], gptr[g + 1], means, pchol, logconst, logw, lp, tmp, Q)
        best = 0
        for k in range(1, K):
            if lp[k] > lp[best]:
                best = k
        out[g] = best
    return out


@njit(cache=True, nogil=True)
def accumulate_groups(X, gptr, means, pchol, logconst, logw):
    """Tied E-step fused with the M-step statistics (about the current means).

    Returns
    -------
    nk : (K,) sum over rows of their group's responsibility
    gk : (K,) sum over groups of the responsibility
    sx, sxx : as :func:`accumulate`
    ll : float, sum of group log-likelihoods
    worst, worst_i : lowest group log-likelihood and the first row of that group
    """
    G = gptr.shape[0] - 1
    K = means.shape[0]
    return _accumulate_groups_into(X, gptr, means, pchol, logconst, logw, np.empty((K, G)))


@njit(cache=True, inline="always")
def _group_resp(lp, RT, g):
    """Group ``g``'s log-likelihood (log-sum-exp of its ``lp``) and responsibilities
    ``RT[k, g]`` (0.0 where ``t < LOG_RESP_SKIP``: exp(t) < RESP_FLOOR; a NaN t still
    goes to exp; exp(0) is 1)."""
    lse = _lse(lp)
    for k in range(lp.shape[0]):
        t = lp[k] - lse
        RT[k, g] = 0.0 if t < LOG_RESP_SKIP else (1.0 if t == 0.0 else np.exp(t))
    return lse


@njit(cache=True, nogil=True)
def _accumulate_groups_into(X, gptr, means, pchol, logconst, logw, RT):
    """:func:`accumulate_groups` with the scratch ``RT`` (K, G) (kept by
    :func:`em_loop_groups` across iterations): first every group's log-likelihood and
    responsibilities (``RT[k, g]``, 0.0 where ``t < LOG_RESP_SKIP``), then each
    component's statistics over the groups in order (:func:`_group_stats_task4`: the
    sums in registers, not read and written back per row); D = 4 in one pass
    (:func:`_accumulate_groups4`). Every sum is the one row by row would take, in the
    same order: the same bits."""
    G = gptr.shape[0] - 1
    K, D = means.shape
    lp = np.empty(K)
    tmp = np.empty(K)
    ll = 0.0
    worst = np.inf
    worst_i = -1
    # the branch outside the loop: inside, the generic path's code slows the D = 4 one
    if D == 4:
        return _accumulate_groups4(X, gptr, means, pchol, logconst, logw, RT)
    else:
        for g in range(G):
            _group_logprob(X, gptr[g], gptr[g + 1], means, pchol, logconst, logw, lp, tmp)
            lse = _group_resp(lp, RT, g)
            ll += lse
            if lse < worst:
                worst = lse
                worst_i = gptr[g]
    nk = np.zeros(K)
    gk = np.zeros(K)
    sx = np.zeros((K, D))
    sxx = np.zeros((K, D, D))
    isplit = _stats_split(D)
    for task in range(2 * K):
        _group_stats_one(X, gptr, means, RT, task, isplit, nk, gk, sx, sxx)
    return nk, gk, sx, sxx, ll, worst, worst_i


@njit(cache=True, nogil=True)
def _accumulate_groups4(X, gptr, means, pchol, logconst, logw, RT):
    """:func:`_accumulate_groups_into` for D = 4 in one pass over the groups: each
    group's responsibilities, then its rows added at once (still in the cache) to the
    statistics of the components it has a share of. Every statistic is the sum
    :func:`_group_stats_task4` takes (the same products, over the groups and rows in
    order; here in an array, there in registers): the same bits."""
    G = gptr.shape[0] - 1
    K = means.shape[0]
    lp = np.empty(K)
    Q = _soa4(means, pchol, logconst, logw)
    # S[k]: n_k, g_k, sx (4), sxx rows 0-1 (q00 q10 q11), rows 2-3 (q20 .. q33)
    S = np.zeros((K, 16))
    ll = 0.0
    worst = np.inf
    worst_i = -1
    for g in range(G):
        a, b = gptr[g], gptr[g + 1]
        _group_logprob4(X, a, b, Q, lp)
        lse = _group_resp(lp, RT, g)
        ll += lse
        if lse < worst:
            worst = lse
            worst_i = a
        for k in range(K):
            r = RT[k, g]
            if r < RESP_FLOOR:
                continue
            m0, m1, m2, m3 = Q[0, k], Q[1, k], Q[2, k], Q[3, k]
            n_k, g_k = S[k, 0], S[k, 1]
            s0, s1, s2, s3 = S[k, 2], S[k, 3], S[k, 4], S[k, 5]
            q00, q10, q11 = S[k, 6], S[k, 7], S[k, 8]
            q20, q21, q22 = S[k, 9], S[k, 10], S[k, 11]
            q30, q31, q32, q33 = S[k, 12], S[k, 13], S[k, 14], S[k, 15]
            g_k += r
            n_k += r * (b - a)
            for n in range(a, b):
                d0 = X[n, 0] - m0
                d1 = X[n, 1] - m1
                d2 = X[n, 2] - m2
                d3 = X[n, 3] - m3
                s0 += r * d0
                s1 += r * d1
                s2 += r * d2
                s3 += r * d3
                r0 = r * d0
                q00 += r0 * d0
                r1 = r * d1
                q10 += r1 * d0
                q11 += r1 * d1
                r2 = r * d2
                q20 += r2 * d0
                q21 += r2 * d1
                q22 += r2 * d2
                r3 = r * d3
                q30 += r3 * d0
                q31 += r3 * d1
                q32 += r3 * d2
                q33 += r3 * d3
            S[k, 0], S[k, 1] = n_k, g_k
            S[k, 2], S[k, 3], S[k, 4], S[k, 5] = s0, s1, s2, s3
            S[k, 6], S[k, 7], S[k, 8] = q00, q10, q11
            S[k, 9], S[k, 10], S[k, 11] = q20, q21, q22
            S[k, 12], S[k, 13], S[k, 14], S[k, 15] = q30, q31, q32, q33
    nk = np.zeros(K)
    gk = np.zeros(K)
    sx = np.zeros((K, 4))
    sxx = np.zeros((K, 4, 4))
    for k in range(K):
        nk[k] = S[k, 0]
        gk[k] = S[k, 1]
        for i in range(4):
            sx[k, i] = S[k, 2 + i]
        sxx[k, 0, 0] = S[k, 6]
        sxx[k, 1, 0] = S[k, 7]
        sxx[k, 1, 1] = S[k, 8]
        sxx[k, 2, 0] = S[k, 9]
        sxx[k, 2, 1] = S[k, 10]
        sxx[k, 2, 2] = S[k, 11]
        sxx[k, 3, 0] = S[k, 12]
        sxx[k, 3, 1] = S[k, 13]
        sxx[k, 3, 2] = S[k, 14]
        sxx[k, 3, 3] = S[k, 15]
    return nk, gk, sx, sxx, ll, worst, worst_i


# Tied E-step on threads, bit for bit the serial one. The serial pass adds each
# statistic (nk[k], gk[k], sx[k, i], sxx[k, i, j]) and the log-likelihood over the
# groups in order; floating-point sums depend on that order, so the work is split
# where no sum is: (1) the groups' log-densities, log-sum-exp and responsibilities,
# independent per group, computed on threads by chunks of groups into RT (K, G) and
# LSE (G,); (2) the sums, each still taken over the groups in order, by tasks that
# own whole statistics: task (part, k) adds component k's nk, gk, sx and the first
# rows of sxx (part 0) or the other rows of sxx (part 1), so the two halves of the
# work are about equal whatever the components' sizes; (3) the log-likelihood and
# the worst group, a serial pass over LSE.
GROUP_CHUNK = 512


@njit(cache=True, parallel=True)
def _group_resp_parallel(X, gptr, means, pchol, logconst, logw, RT, LSE):
    """Phase 1: ``LSE[g]`` (the group log-likelihood) and ``RT[k, g]`` (responsibility,
    0.0 where skipped as below ``RESP_FLOOR``) of every group, on threads."""
    G = gptr.shape[0] - 1
    K = means.shape[0]
    nch = (G + GROUP_CHUNK - 1) // GROUP_CHUNK
    D = X.shape[1]
    Q = _soa4(means, pchol, logconst, logw) if D == 4 else np.empty((16, 0))
    for c in prange(nch):
        lp = np.empty(K)
        tmp = np.empty(K)
        if D == 4:
            for g in range(c * GROUP_CHUNK, min(G, (c + 1) * GROUP_CHUNK)):
                _group_logprob4(X, gptr[g], gptr[g + 1], Q, lp)
                LSE[g] = _group_resp(lp, RT, g)
        else:
            for g in range(c * GROUP_CHUNK, min(G, (c + 1) * GROUP_CHUNK)):
                _group_logprob(X, gptr[g], gptr[g + 1], means, pchol, logconst, logw, lp,
                               tmp)
                LSE[g] = _group_resp(lp, RT, g)


@njit(cache=True, nogil=True)
def _group_stats_task(X, gptr, means, Rk, k, part, isplit, nk, gk, sx, sxx):
    """One task of phase 2 (any D): component k's statistics of ``part``."""
    G = gptr.shape[0] - 1
    D = X.shape[1]
    lo = 0 if part == 0 else isplit
    hi = isplit if part == 0 else D
    n_k = 0.0
    g_k = 0.0
    s1 = np.zeros(D)
    s2 = np.zeros((D, D))
    diff = np.empty(D)
    for g in range(G):
        r = Rk[g]
        if r < RESP_FLOOR:
            continue
        a, b = gptr[g], gptr[g + 1]
        if part == 0:
            g_k += r
            n_k += r * (b - a)
        for n in range(a, b):
            for i in range(D):
                diff[i] = X[n, i] - means[k, i]
            if part == 0:
                for i in range(D):
                    s1[i] += r * diff[i]
            for i in range(lo, hi):
                ri = r * diff[i]
                for j in range(i + 1):
                    s2[i, j] += ri * diff[j]
    if part == 0:
        nk[k] = n_k
        gk[k] = g_k
        for i in range(D):
            sx[k, i] = s1[i]
    for i in range(lo, hi):
        for j in range(i + 1):
            sxx[k, i, j] = s2[i, j]


@njit(cache=True, nogil=True)
def _group_stats_task4(X, gptr, means, Rk, k, part, nk, gk, sx, sxx):
    """:func:`_group_stats_task` for D = 4 (the mapper's rows), the sums in registers:
    part 0 nk, gk, sx and sxx rows 0-1, part 1 sxx rows 2-3. Same operations."""
    G = gptr.shape[0] - 1
    m0, m1, m2, m3 = means[k, 0], means[k, 1], means[k, 2], means[k, 3]
    if part == 0:
        n_k = 0.0
        g_k = 0.0
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        s3 = 0.0
        q00 = 0.0
        q10 = 0.0
        q11 = 0.0
        for g in range(G):
            r = Rk[g]
            if r < RESP_FLOOR:
                continue
            a, b = gptr[g], gptr[g + 1]
            g_k += r
            n_k += r * (b - a)
            for n in range(a, b):
                d0 = X[n, 0] - m0
                d1 = X[n, 1] - m1
                s0 += r * d0
                s1 += r * d1
                s2 += r * (X[n, 2] - m2)
                s3 += r * (X[n, 3] - m3)
                r0 = r * d0
                q00 += r0 * d0
                r1 = r * d1
                q10 += r1 * d0
                q11 += r1 * d1
        nk[k] = n_k
        gk[k] = g_k
        sx[k, 0] = s0
        sx[k, 1] = s1
        sx[k, 2] = s2
        sx[k, 3] = s3
        sxx[k, 0, 0] = q00
        sxx[k, 1, 0] = q10
        sxx[k, 1, 1] = q11
    else:
        q20 = 0.0
        q21 = 0.0
        q22 = 0.0
        q30 = 0.0
        q31 = 0.0
        q32 = 0.0
        q33 = 0.0
        for g in range(G):
            r = Rk[g]
            if r < RESP_FLOOR:
                continue
            for n in range(gptr[g], gptr[g + 1]):
                d0 = X[n, 0] - m0
                d1 = X[n, 1] - m1
                d2 = X[n, 2] - m2
                d3 = X[n, 3] - m3
                r2 = r * d2
                q20 += r2 * d0
                q21 += r2 * d1
                q22 += r2 * d2
                r3 = r * d3
                q30 += r3 * d0
                q31 += r3 * d1
                q32 += r3 * d2
                q33 += r3 * d3
        sxx[k, 2, 0] = q20
        sxx[k, 2, 1] = q21
        sxx[k, 2, 2] = q22
        sxx[k, 3, 0] = q30
        sxx[k, 3, 1] = q31
        sxx[k, 3, 2] = q32
        sxx[k, 3, 3] = q33


@njit(cache=True, inline="always")
def _stats_split(D):
    """Rows [0, isplit) of sxx go with sx to part 0 of a component's statistics, the
    rest to part 1: about half of the D + D (D + 1) / 2 sums each (D = 4: 7 and 7)."""
    isplit = 0
    while isplit < D and 2 * (D + (isplit + 1) * (isplit + 2) // 2) <= D + D * (D + 1) // 2:
        isplit += 1
    return isplit


@njit(cache=True, inline="always")
def _group_stats_one(X, gptr, means, RT, task, isplit, nk, gk, sx, sxx):
    """Task ``task`` of phase 2: tasks 0..K-1 are part 0 of component ``task``,
    K..2K-1 part 1 of component ``task - K``."""
    K, D = means.shape
    part = task // K
    k = task % K
    if D == 4:
        _group_stats_task4(X, gptr, means, RT[k], k, part, nk, gk, sx, sxx)
    else:
        _group_stats_task(X, gptr, means, RT[k], k, part, isplit, nk, gk, sx, sxx)


@njit(cache=True, parallel=True)
def _group_stats_parallel(X, gptr, means, RT, nk, gk, sx, sxx):
    """Phase 2: the statistics of :func:`accumulate_groups` from ``RT`` (K, G), each
    summed over the groups in order by the one task that owns it (see above)."""
    K, D = means.shape
    isplit = _stats_split(D)
    # tasks 0..K-1 are part 0, K..2K-1 part 1: with two threads each takes one part
    for task in prange(2 * K):
        _group_stats_one(X, gptr, means, RT, task, isplit, nk, gk, sx, sxx)


@njit(cache=True)
def accumulate_groups_parallel(X, gptr, means, pchol, logconst, logw, RT, LSE):
    """:func:`accumulate_groups` on numba's threads, the same result bit for bit.

    ``RT`` (K, G) and ``LSE`` (G,) are scratch arrays (kept by the caller across EM
    iterations). The sums are those of the serial kernel, in its order (see the
    comment above :data:`GROUP_CHUNK`), so the fit does not depend on the number of
    threads; worth it from a few thousand groups (two parallel regions per call).
    """
    G = gptr.shape[0] - 1
    K, D = means.shape
    _group_resp_parallel(X, gptr, means, pchol, logconst, logw, RT, LSE)
    nk = np.zeros(K)
    gk = np.zeros(K)
    sx = np.zeros((K, D))
    sxx = np.zeros((K, D, D))
    _group_stats_parallel(X, gptr, means, RT, nk, gk, sx, sxx)
    ll = 0.0
    worst = np.inf
    worst_i = -1
    for g in range(G):
        lse = LSE[g]
        ll += lse
        if lse < worst:
            worst = lse
            worst_i = gptr[g]
    return nk, gk, sx, sxx, ll, worst, worst_i


@njit(cache=True, nogil=True)
def em_loop_groups(X, gptr, weights, means, covs, max_iter, tol, reg_covar, min_nk,
                   parallel=False):
    """Tied EM in place; same contract as :func:`em_loop`.

    ``parallel``: the E-step on numba's threads (:func:`accumulate_groups_parallel`,
    the same fit bit for bit).

    ``weights`` are group fractions on entry and on return (the caller converts
    them to row fractions for the density over rows). ``lower_bound`` is the sum
    of group log-likelihoods divided by the number of rows.
    """
    N, D = X.shape
    K = means.shape[0]
    pchol = np.empty((K, D, D))
    logconst = np.empty(K)
    logw = np.empty(K)
    prev = -np.inf
    lb = -np.inf
    worst_i = -1
    row_w = np.empty(K)
    G = gptr.shape[0] - 1
    RT = np.empty((K, G))
    LSE = np.empty(G if parallel else 0)
    for it in range(max_iter):
        bad = component_terms(weights, covs, pchol, logconst)
        if bad >= 0:
            return it, False, 1, bad, lb, worst_i
        for k in range(K):
            logw[k] = np.log(weights[k])
        if parallel:
            nk, gk, sx, sxx, ll, worst, worst_i = accumulate_groups_parallel(
                X, gptr, means, pchol, logconst, logw, RT, LSE)
        else:
            nk, gk, sx, sxx, ll, worst, worst_i = _accumulate_groups_into(
                X, gptr, means, pchol, logconst, logw, RT)
        lb = ll / N
        if not np.isfinite(lb):
            return it, False, 1, -1, lb, worst_i
        for k in range(K):
            if nk[k] < min_nk:
                return it, False, 2, k, lb, worst_i
        old = means.copy()
        _mstep_from_stats(N, nk, sx, sxx, old, reg_covar, row_w, means, covs)
        total = 0.0
        for k in range(K):
            total += gk[k] + EPS10
        for k in range(K):
            weights[k] = (gk[k] + EPS10) / total
        if abs(lb - prev) < tol:
            return it + 1, True, 0, -1, lb, worst_i
        prev = lb
    return max_iter, False, 0, -1, lb, worst_i
