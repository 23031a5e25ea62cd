"""The predictive distribution where the scan cannot see (issue 15, eq. unseen_mixture).

The unseen-geometry design (stages/farfield.py, eqs. unseen_behind, unseen_extent)
says what the error ``e = y - m`` of the map's mean is where the scan holds no
evidence: behind the located surface it is 0 when the hidden matter is solid and
about uniform over ``[0, w_behind]`` when it is a thin wall (the truth lies in
``[m, |m| - t_min]``); beyond the end of the data it is 0 when the surface continues
and about uniform over ``sign(m) [0, w_extent]`` when it ends (the truth is farther
from the located surface, never nearer). Each happens with probability ``1 - p``.
eq. unseen_var summarised that by a Gaussian of the same second moment,
``lambda^2 w^2`` with ``lambda = sqrt((1 - p) / 3)``; a Gaussian cannot be tight for the
solids (97-99 % of the queries behind a seen face) and wide for the thin walls at once
(docs/field.md, "Variance by query category": median |z| 0.06 behind solids, 6.7
behind thin walls).

This module splits that variance into its two components instead of adding it to
every query: with ``v`` the calibrated variance of the observed surface (eq.
calibrated_var), ``w^2 = w_behind^2 + w_extent^2`` and ``q = min(3 lambda^2, 1/2)``
(= 1 - p, the same prior as eq. unseen_var: no new number) where ``w > 0``
(eq. unseen_mixture):

    p(e) = (1 - q) N(e; 0, v) + q N(e; 0, v + w^2 / 3),

the hidden matter solid (the surface continuing) with probability ``1 - q``, otherwise
an error with the second moment ``w^2 / 3`` of the design's uniform; its total
variance ``v + lambda^2 w^2`` is eq. unseen_var's. The second component is a Gaussian,
not the uniform itself: the intervals are bounds for the exact located face, and the
held-out scenes' thin walls and ends of the data exceed them by up to 1.5 w where the
mean is off (docs/field.md, "The predictive behind the located surface"); a
one-sided uniform put those at log densities of -50 to -2000, the Gaussian at about -5.
Its standard deviation is not what a user reads as "sigma" (it is set by the rare
thin walls): the map reports as its std the central 68.27 % half-width ``sigma`` of
the mixture, ``P(|e| <= sigma) = erf(1/sqrt 2)`` (eq. unseen_halfwidth), which is the
Gaussian's sigma exactly where ``w = 0``, and scores itself by the mixture's log
density. Both are computed by :class:`UnseenMixture`; the mean is unchanged.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import ndtr, ndtri

__all__ = ["UnseenMixture", "ONE_SIGMA", "unseen_prior"]

#: Central probability of a Gaussian's +-1 sigma interval, erf(1 / sqrt 2).
ONE_SIGMA = math.erf(1.0 / math.sqrt(2.0))
#: Below this width / s an interval's uniform is replaced by a point mass at its
#: middle (the convolution's error is O((w / s)^2), 1e-12).
_TINY = 1e-6


def unseen_prior(weight: float) -> float:
    """Probability ``q = 1 - p`` that the scan's unseen side differs from the located
    surface (a thin wall, an ending surface), from the weight ``lambda`` of eq.
    unseen_var: ``q = 3 lambda^2`` (``lambda = sqrt((1 - p) / 3)``), at most 1/2."""
    return float(min(3.0 * float(weight) ** 2, 0.5))


class UnseenMixture:
    """The predictive distribution of eq. unseen_mixture for K queries.

    Parameters
    ----------
    mean : (K,) the map's mean m (m)
    var_observed : (K,) v, the calibrated variance of the observed surface (m^2)
    w_behind, w_extent : (K,) widths of eqs. unseen_behind, unseen_extent (m)
    weight : float, lambda of eq. unseen_var (q = 3 lambda^2, at most 1/2); 0 (or zero
        widths): the Gaussian N(m, v)
    """

    def __init__(self, mean, var_observed, w_behind=None, w_extent=None, weight: float = 0.0):
        self.mean = np.asarray(mean, dtype=np.float64).reshape(-1)
        K = len(self.mean)
        self.var_observed = np.broadcast_to(
            np.maximum(np.asarray(var_observed, dtype=np.float64), 1e-300), (K,)).copy()
        w2 = np.zeros(K)
        for w in (w_behind, w_extent):
            if w is not None:
                w2 = w2 + np.broadcast_to(np.asarray(w, dtype=np.float64), (K,)) ** 2
        #: variance of the unseen component, v + w^2 / 3, and its weight q
        self.var_unseen = self.var_observed + w2 / 3.0
        self.q = np.where(w2 > 0, unseen_prior(weight), 0.0)
        self.mixed = self.q > 0
        self._std = None

    def __len__(self):
        return len(self.mean)

    # ---------------------------------------------------------------- density
    def logpdf(self, y) -> np.ndarray:
        """(K,) log density of the truth ``y`` under eq. unseen_mixture."""
        e2 = (np.asarray(y, dtype=np.float64).reshape(-1) - self.mean) ** 2
        out = -0.5 * e2 / self.var_observed - 0.5 * np.log(2.0 * math.pi * self.var_observed)
        on = self.mixed
        if on.any():
            vu = self.var_unseen[on]
            lu = -0.5 * e2[on] / vu - 0.5 * np.log(2.0 * math.pi * vu)
            out[on] = np.logaddexp(np.log1p(-self.q[on]) + out[on], np.log(self.q[on]) + lu)
        return out

    # ---------------------------------------------------------------- intervals
    def central_mass(self, half_width, rows=None) -> np.ndarray:
        """P(|y - m| <= half_width) per query (``rows``: a subset of the queries)."""
        sl = slice(None) if rows is None else rows
        t = np.asarray(half_width, dtype=np.float64)
        q = self.q[sl]
        return (1.0 - q) * (2.0 * ndtr(t / np.sqrt(self.var_observed[sl])) - 1.0) \
            + q * (2.0 * ndtr(t / np.sqrt(self.var_unseen[sl])) - 1.0)

    def half_width(self, level: float = ONE_SIGMA, iterations: int = 60) -> np.ndarray:
        """(K,) central half-width: P(|y - m| <= half_width) = ``level`` (eq.
        unseen_halfwidth). The Gaussian's ``s Phi^-1((1 + level) / 2)`` where the unseen
        component is off; elsewhere Newton's method on F(t) = P(|y - m| <= t) - level
        from the narrow component's half-width, where F < 0. F is increasing and concave
        for t > 0 (a sum of increasing concave terms), so each Newton step lands at or
        below the root: the iterates rise monotonically to it, quadratically near it,
        without a bracket (steps that round to below zero are taken as converged)."""
        if not 0.0 < level < 1.0:
            raise ValueError(f"Expected a central probability level in (0, 1), found {level!r}.")
        zl = ndtri(0.5 + 0.5 * level)
        out = np.sqrt(self.var_observed) * zl
        rows = np.flatnonzero(self.mixed)
        if len(rows):
            t = out[rows].copy()
            q = self.q[rows]
            s1 = np.sqrt(self.var_observed[rows])
            s2 = np.sqrt(self.var_unseen[rows])
            norm = math.sqrt(2.0 / math.pi)         # 2 phi(0)
            active = np.arange(len(rows))
            for _ in range(iterations):
                ta, qa, a1, a2 = t[active], q[active], s1[active], s2[active]
                f = self.central_mass(ta, rows[active]) - level
                # F'(t) = 2 [(1 - q) phi(t / s1) / s1 + q phi(t / s2) / s2]
                fp = norm * ((1.0 - qa) * np.exp(-0.5 * (ta / a1) ** 2) / a1
                             + qa * np.exp(-0.5 * (ta / a2) ** 2) / a2)
                step = np.maximum(-f / fp, 0.0)
                t[active] = ta + step
                active = active[step > 4.0 * np.finfo(float).eps * ta]
                if not len(active):
                    break
            out[rows] = t
        return out

    @property
    def std(self) -> np.ndarray:
        """(K,) the reported sigma: the central 68.27 % half-width (eq. unseen_halfwidth)."""
        if self._std is None:
            self._std = self.half_width(ONE_SIGMA)
        return self._std

    @property
    def var(self) -> np.ndarray:
        """(K,) sigma^2 of :attr:`std` (what :meth:`SurfaceMap.predict` reports)."""
        return self.std ** 2
