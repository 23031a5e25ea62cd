"""Session 8 (field-15i): candidate variance features for eq. calibrated_var, fitted by
the 0.68-quantile regression (eq. variance_quantile_fit) on training scenes only and
scored, with the map's predictive (eq. unseen_mixture), on the bench six, the held-out
four and the training scenes, from the cached per-query ingredients (out/calib, built
by build_caches.py). Usage:

    PYTHONPATH=$PWD python docs/field_bench/session8/scripts/feature_sweep.py [MODEL ...]
"""
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, "scripts")
import fit_variance as FV  # noqa: E402

from gmmgp_app.stages import farfield as F  # noqa: E402
from gmmgp_app.stages.unseen import UnseenMixture  # noqa: E402

B = FV.B
CACHE = Path("out/calib")
BENCH = [n for n in B.SCENES if n != "bunny" or B.BUNNY.is_dir()]
HELD = [n for n in BENCH if not B.SCENES[n]["tuned"]]
TRAIN8 = list(FV.TRAIN_SCENES)
TRAIN_NOISE = list(FV.TRAIN_SCENES_NOISE)
BASE = {r["scene"]: r["methods"] for r in json.loads(
    Path("docs/field_bench/bench_accuracy.json").read_text())["results"]}
_cases = {}


def case(n):
    if n not in _cases:
        d = FV.scene_case(n, 0, CACHE)
        d["w_b"] = F.behind_width(d["mean"], d["t_min"])
        d["w_e"] = F.extent_width(d["mean"], d["r"], d["gap"])
        d["d2"] = (d["m_gp"] - d["m_far"]) ** 2
        _cases[n] = d
    return _cases[n]


def columns(d, feats, c_floor=0.0):
    """Design matrix: the five features of eq. calibrated_var (noise floor (c h)^2 in
    the two noise features) and the extra ones named in ``feats``."""
    h, s = d["h"], d["noise"]
    h2 = h * h
    s2 = s * s + (c_floor * h) ** 2
    r = d["r"]
    X = [np.ones_like(r), np.log((r ** 2 + h2) / h2), np.log((d["spread2"] + s2) / h2),
         np.log((d["d2"] + s2) / h2), np.log(np.maximum(d["v_gp"], 1e-300) / h2)]
    lat2 = np.maximum(r ** 2 - d["mean"] ** 2, 0.0)
    for f in feats:
        if f == "curv":  # bias of a curved surface ~ r^2 x dispersion of the normals
            X.append(np.log((r ** 2 * np.maximum(d["disp"], 0) + h2) / h2))
        elif f == "curvs":  # the same, floored at the noise
            X.append(np.log((r ** 2 * np.maximum(d["disp"], 0) + s2) / h2))
        elif f == "disp":
            X.append(np.log(np.maximum(d["disp"], 0) + 1e-4))
        elif f == "disp_p":
            X.append(np.log(np.maximum(d["disp_p"], 0) + 1e-4))
        elif f == "lnoise":  # local spread of plane distances at the nearest hit point
            X.append(np.log((d["spread2_p"] + s2) / h2))
        elif f == "lnoise_rel":  # local over global noise
            X.append(np.log((d["spread2_p"] + s2) / (s2 + 1e-300)))
        elif f == "spacing":
            X.append(np.log(d["spacing_p"] / h))
        elif f == "ext":
            X.append(np.log((d["w_e"] ** 2 + h2) / h2))
        elif f == "lat":
            X.append(np.log((lat2 + h2) / h2))
        elif f == "vfar":
            X.append(np.log(np.maximum(d["v_far"], 1e-300) / h2))
        elif f == "sig":
            X.append(np.full_like(r, np.log(s * s / h2)))
        elif f == "neff":
            X.append(np.log(d["n_eff"]))
        elif f == "behind":
            X.append((d["mean"] < 0).astype(float))
        elif f == "rfar":  # far-from-data switch: log((r^2 + l^2)/l^2), l the GP length scale
            ls2 = d["length_scale"] ** 2
            X.append(np.log((r ** 2 + ls2) / ls2))
        else:
            raise KeyError(f)
    return np.stack(X, axis=1)


def additive(d, feats):
    """Additive variance terms (each with coefficient exp(t)): ``acurv`` r^2 disp (the
    bias of a curved surface read through a kernel of width r)."""
    return [d["r"] ** 2 * np.maximum(d["disp"], 0) for f in feats if f == "acurv"]


def observed_var(d, feats, coef, c_floor=0.0):
    lin = [f for f in feats if f != "acurv"]
    add = additive(d, feats)
    coef = np.asarray(coef)
    X = columns(d, lin, c_floor)
    kap = d["kappa"] * np.exp(-(d["r"] / d["length_scale"]) ** 2) * d["d2"]
    v = d["h"] ** 2 * np.exp(X @ coef[:X.shape[1]]) + kap
    for j, a in enumerate(add):
        v = v + np.exp(coef[X.shape[1] + j]) * a
    return v


def score(n, v_obs):
    d = case(n)
    mix = UnseenMixture(d["mean"], v_obs, d["w_b"], d["w_e"], d["lam"])
    e = np.abs(d["y"] - d["mean"])
    z = e / np.sqrt(mix.var)
    in2 = e <= mix.half_width(FV.TWO_SIGMA)
    ll = mix.logpdf(d["y"])
    c1, c2, ok = [], [], []
    for i in range(len(B.BINS) - 1):
        s = d["bin"] == i
        c1.append(float(np.mean(z[s] <= 1)))
        c2.append(float(np.mean(in2[s])))
        if n in BASE:
            ok.append(ll[s].mean() > FV.best_baseline_ll(BASE[n], i))
    n1 = sum(abs(round(c, 2) - 0.68) <= 0.05 + 1e-9 for c in c1)
    n2 = sum(abs(round(c, 2) - 0.95) <= 0.03 + 1e-9 for c in c2)
    return dict(c1=c1, c2=c2, n1=n1, n2=n2, nll=sum(ok) if n in BASE else None)


def fit(names, feats, c_floor=0.0, mask="obs", per_bin=400, tau=0.68, seed=0,
        exact=False):
    """Eq. variance_quantile_fit over up to ``per_bin`` queries per bin and scene."""
    rng = np.random.default_rng(seed)
    Xs, Ys = [], []
    for n in names:
        d = case(n)
        keep = (d["w_b"] == 0) & (d["w_e"] == 0) if mask == "obs" else \
            (d["w_b"] == 0) if mask == "front" else np.ones(len(d["y"]), bool)
        X = columns(d, feats, c_floor)
        y = np.log(np.maximum((d["y"] - d["mean"]) ** 2, 1e-30) / d["h"] ** 2)
        for i in range(len(B.BINS) - 1):
            idx = np.flatnonzero(keep & (d["bin"] == i))
            if len(idx) > per_bin:
                idx = rng.choice(idx, per_bin, replace=False)
            Xs.append(X[idx])
            Ys.append(y[idx])
    X, y = np.concatenate(Xs), np.concatenate(Ys)
    if exact:
        return F.fit_variance_quantile(X, y, tau)
    return quantile_smooth(X, y, tau)


def quantile_smooth(X, y, tau=0.68, eps=0.02):
    """The pinball loss of eq. variance_quantile_fit smoothed on the scale ``eps`` (log
    units): ``tau u + eps softplus(-u / eps)``, by L-BFGS from the least-squares fit
    (for the sweep: seconds instead of minutes; the exact LP checks the chosen one)."""
    from scipy.optimize import minimize

    t0 = np.linalg.lstsq(X, y, rcond=None)[0]

    def f(t):
        u = y - X @ t
        a = -u / eps
        sp = np.logaddexp(0.0, a)
        sg = np.exp(a - sp)  # sigmoid(-u / eps)
        return np.mean(tau * u + eps * sp), -((tau - sg) @ X) / len(y)

    return minimize(f, t0, jac=True, method="L-BFGS-B",
                    options=dict(maxiter=5000, gtol=1e-12, ftol=1e-15)).x


def summary(feats, coef, c_floor=0.0, groups=None, detail=False):
    groups = groups or dict(bench=BENCH, held=HELD, train8=TRAIN8, noise8=TRAIN_NOISE)
    out, lines = {}, []
    for g, names in groups.items():
        tot = np.zeros(3, int)
        for n in names:
            r = score(n, observed_var(case(n), feats, coef, c_floor))
            tot += [r["n1"], r["n2"], r["nll"] or 0]
            if detail:
                lines.append(f"  {n}: 1s " + " ".join(f"{c:.2f}" for c in r["c1"])
                             + " [" + str(r["n1"]) + "]; 2s " + " ".join(f"{c:.2f}" for c in r["c2"])
                             + f" [{r['n2']}]" + ("" if r["nll"] is None else f"; LL {r['nll']}"))
        out[g] = tot
    s = " | ".join(f"{g} {t[0]}/{t[1]}" + (f"/{t[2]}" if g in ("bench", "held") else "")
                   for g, t in out.items())
    return s, "\n".join(lines)


if __name__ == "__main__":
    print("today:", summary([], F.VARIANCE_COEF, detail=True)[0])


def _packs(names, feats, c_floor):
    packs = []
    for n in names:
        d = case(n)
        X = columns(d, [f for f in feats if f != "acurv"], c_floor)
        kap = d["kappa"] * np.exp(-(d["r"] / d["length_scale"]) ** 2) * d["d2"]
        add = additive(d, feats)
        mix = UnseenMixture(d["mean"], np.ones(len(d["y"])), d["w_b"], d["w_e"], d["lam"])
        w2 = np.zeros(len(d["y"])) + d["w_b"] ** 2 + d["w_e"] ** 2
        e = np.abs(d["y"] - d["mean"])
        bins = [np.flatnonzero(d["bin"] == i) for i in range(len(B.BINS) - 1)]
        packs.append((X, kap, d["h"] ** 2, w2, mix.q, e, bins, add))
    return packs


def bin_objective(coef, packs, soft=0.02):
    """Sum over training bins of log(1 + ((c1 - 0.68) / 0.05)^2) + log(1 + ((c2 - 0.95)
    / 0.03)^2), coverages smoothed: per query u = P(|y - m| <= |e|) under eq.
    unseen_mixture (closed form), covered at level L when u <= L."""
    from scipy.special import ndtr, expit

    tot = 0.0
    for X, kap, h2, w2, q, e, bins, add in packs:
        v = h2 * np.exp(X @ coef[:X.shape[1]]) + kap
        for j, a in enumerate(add):
            v = v + np.exp(coef[X.shape[1] + j]) * a
        u = (1 - q) * (2 * ndtr(e / np.sqrt(v)) - 1) + q * (2 * ndtr(e / np.sqrt(v + w2 / 3)) - 1)
        a1 = expit((0.6827 - u) / soft)
        a2 = expit((0.9545 - u) / (soft / 3))
        for b in bins:
            if len(b):
                tot += np.log1p(((a1[b].mean() - 0.68) / 0.05) ** 2) \
                    + np.log1p(((a2[b].mean() - 0.95) / 0.03) ** 2)
    return tot


def fit_bins(names, feats, c_floor=0.0, start=None, maxiter=3000):
    """Coefficients minimising :func:`bin_objective` on ``names`` (Powell from
    ``start``, default the smoothed quantile fit)."""
    from scipy.optimize import minimize

    packs = _packs(names, feats, c_floor)
    lin = [f for f in feats if f != "acurv"]
    t0 = np.r_[fit(names, lin, c_floor), [-3.0] * (len(feats) - len(lin))] if start is None \
        else np.asarray(start, float)
    res = minimize(bin_objective, t0, args=(packs,), method="Powell",
                   options=dict(maxiter=maxiter, xtol=1e-3, ftol=1e-4))
    return res.x
