#!/usr/bin/env python
"""Session 12 (field-15s): variance candidates for the sphere vote with the resampling
features of resample_features.py, fitted (eq. variance_quantile_fit) on FIT scenes and
scored on the bench six, the held-out four and (``--train``) the training sixteen, as
session 10's sphere_sweep.py (whose loading, fit and scoring this reuses) and
scripts/bench_bins.py count.

    PYTHONPATH=$PWD python docs/field_bench/session12/scripts/sweep.py FIT CANDIDATES \
        [--train] [--cache /tmp/field-15s/calib]

CANDIDATES: comma-separated ``FEATURES`` (``base5`` or extras joined by ``+``): session
10's extras (curv, delta, shrink, ssph, lnoise, ...) and
  jk   log((jack_s + sigma^2 / 16) / h^2)   the sphere vote's jackknife variance
  jk0  log((jack_s + 1e-6 h^2) / h^2)
  hs   log((half_s + sigma^2 / 16) / h^2)   split-half disagreement (three partitions)
  hp   log((half_p + sigma^2 / 16) / h^2)   the same for the plane vote
  jkp  log((jack_p + sigma^2 / 16) / h^2)   the plane vote's jackknife variance
  jkr  log((jack_s + sigma^2 / 16) / (jack_p + sigma^2 / 16))
  nnb  log((sigma^2 tanh(r sigma / h^2)^2 + sigma^2 / 16) / h^2), the scale of the
       nearest-neighbour selection bias (selection strength r sigma / h^2)
  xsp  (no column) drop the spread feature (base5's third)
``@k`` after a candidate: the kappa-aware fit (:func:`fit`); ``@h``: the same with the
split-half variance hs added to the model at weight 1 (:func:`variance`).
A leading ``plane:`` scores the plane-vote caches instead, ``proj:`` the sphere vote of
projected points (eq. point_projection), ``pplane:`` the plane vote of projected points.
"""
import sys
from pathlib import Path

import numpy as np

from gmmgp_app.stages import farfield as F
from gmmgp_app.stages.unseen import UnseenMixture

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "session10" / "scripts"))
import sphere_sweep as SS  # noqa: E402

FV, B = SS.FV, SS.B
NEW = ("jk", "jk0", "hs", "hp", "jkp", "jkr", "xsp", "nnb")
_old_extra = SS.extra
_old_design = SS.design
_res = {}


def resample(d):
    key = str(d["_res_path"])  # not id(d): ids are reused once a scene's dict is freed
    if key not in _res:
        _res[key] = dict(np.load(d["_res_path"]))
    return _res[key]


def extra(d, which):
    h2, s2 = d["h"] ** 2, d["noise"] ** 2
    cols = [_old_extra(d, [w for w in which if w not in NEW])]
    if any(w in NEW and w != "nnb" for w in which):
        r = resample(d)
    for w in which:
        if w == "nnb":  # the nearest-neighbour selection bias's scale: sigma tanh(r sigma / h^2)
            b = d["noise"] * np.tanh(d["r"] * d["noise"] / h2)
            cols.append(np.log((b * b + s2 / 16) / h2)[:, None])
        elif w == "jk":
            cols.append(np.log((r["jack_s"] + s2 / 16) / h2)[:, None])
        elif w == "jk0":
            cols.append(np.log((r["jack_s"] + 1e-6 * h2) / h2)[:, None])
        elif w == "hs":
            cols.append(np.log((r["half_s"] + s2 / 16) / h2)[:, None])
        elif w == "hp":
            cols.append(np.log((r["half_p"] + s2 / 16) / h2)[:, None])
        elif w == "jkp":
            cols.append(np.log((r["jack_p"] + s2 / 16) / h2)[:, None])
        elif w == "jkr":
            cols.append(np.log((r["jack_s"] + s2 / 16) / (r["jack_p"] + s2 / 16))[:, None])
    return np.hstack(cols)


def design(d, which):
    X = _old_design(d, which)
    if "xsp" in which:
        X = np.delete(X, 2, axis=1)
    return X


SS.extra = extra
SS.design = design
_old_fit = SS.fit
KAPPA_AWARE = [False]


def fit(cases, which, tau=0.68, per_scene=4000):
    """sphere_sweep.fit, or with ``@k`` after a candidate the kappa-aware target
    log(max(e^2 - kappa exp(-r^2/l^2) d^2, 1e-30 h^2) / h^2): the quantile of the whole
    variance h^2 exp(X t) + kappa d^2 (a query whose error the kappa term covers is
    covered whatever X t)."""
    if not KAPPA_AWARE[0]:
        coef = _old_fit(cases, which, tau, per_scene)
        if T_CORE[0]:
            T_CORE[1] = fit_nu(cases, coef, which)
            print(f"(t core: nu = {T_CORE[1]:.2f})")
        return coef
    X, Y = [], []
    rng = np.random.default_rng(0)
    for d in cases:
        t = FV.terms(d)
        keep = (t["w_b"] == 0) & (t["w_e"] == 0)
        if len(cases) > 2 and keep.sum() > per_scene:
            idx = rng.choice(np.flatnonzero(keep), per_scene, replace=False)
            keep = np.zeros_like(keep)
            keep[idx] = True
        h2 = d["h"] ** 2
        extra_v = t["kap"] + (resample(d)["half_s"] if ADD_HS[0] else 0.0)
        e2 = np.maximum((d["y"] - d["mean"]) ** 2 - extra_v, 1e-30 * h2)[keep]
        X.append(design(d, which)[keep])
        Y.append(np.log(e2 / h2))
    coef = SS.F.fit_variance_quantile(np.concatenate(X), np.concatenate(Y), tau)
    if T_CORE[0]:
        T_CORE[1] = fit_nu(cases, coef, which)
        print(f"(t core: nu = {T_CORE[1]:.2f})")
    return coef


SS.fit = fit
ADD_HS = [False]
_old_variance = SS.variance


def variance(d, coef, which):
    """sphere_sweep.variance, plus with ``@h`` the split-half estimate of the vote's own
    variance added at its theoretical weight 1 (v = h^2 exp(X t) + kappa d^2 + hs)."""
    v = _old_variance(d, coef, which)
    return v + resample(d)["half_s"] if ADD_HS[0] else v


SS.variance = variance
#: ``@t`` after a candidate: a Student-t core for the observed queries (both unseen widths
#: 0) with its central 68.27 % half-width at the reported sigma (the 1-sigma coverage is
#: unchanged; the 95.45 % interval and the log density follow the t), nu by maximum
#: likelihood on the FIT scenes' observed queries; ``@T``: t components in eq.
#: unseen_mixture everywhere (:class:`TMixture`), nu fitted the same way
T_CORE = [False, None]
_old_score = SS.score
Q1 = 0.5 + 0.6826894921370859 / 2


def fit_nu(cases, coef, which):
    """nu of the t core by maximum likelihood of the standardised errors z = e / sigma of
    the observed queries, the t scaled so that P(|T| <= 1) = 0.6827."""
    from scipy import stats
    from scipy.optimize import minimize_scalar
    z = []
    for d in cases:
        t = FV.terms(d)
        keep = (t["w_b"] == 0) & (t["w_e"] == 0)
        z.append((np.abs(d["y"] - d["mean"]) / np.sqrt(variance(d, coef, which)))[keep])
    z = np.concatenate(z)

    def nll(lognu):
        nu = np.exp(lognu)
        s = 1.0 / stats.t.ppf(Q1, nu)
        return -np.mean(stats.t.logpdf(z / s, nu) - np.log(s))

    return float(np.exp(minimize_scalar(nll, bounds=(np.log(1.0), np.log(200.0)),
                                        method="bounded").x))


class TMixture:
    """eq. unseen_mixture with Student-t components of ``nu`` dof in place of the two
    Gaussians, each scaled so that its central 68.27 % half-width is the Gaussian's sigma
    (sqrt v, sqrt(v + w^2 / 3)); intervals by bisection (prototype)."""

    def __init__(self, mean, v, w_b, w_e, lam, nu):
        from scipy import stats
        self.t = stats.t
        self.nu = nu
        q1 = stats.t.ppf(Q1, nu)
        w2 = w_b ** 2 + w_e ** 2
        self.mean = mean
        self.s1 = np.sqrt(v) / q1
        self.s2 = np.sqrt(v + w2 / 3.0) / q1
        self.q = np.where(w2 > 0, min(3.0 * lam ** 2, 0.5), 0.0)

    def mass(self, t):
        c = lambda s: 2.0 * self.t.cdf(t / s, self.nu) - 1.0
        return (1 - self.q) * c(self.s1) + self.q * c(self.s2)

    def half_width(self, level):
        lo = np.zeros_like(self.s1)
        hi = 1e3 * self.s2
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            below = self.mass(mid) < level
            lo = np.where(below, mid, lo)
            hi = np.where(below, hi, mid)
        return 0.5 * (lo + hi)

    def logpdf(self, y):
        e = y - self.mean
        l1 = self.t.logpdf(e / self.s1, self.nu) - np.log(self.s1)
        l2 = self.t.logpdf(e / self.s2, self.nu) - np.log(self.s2)
        q = np.clip(self.q, 1e-300, 1.0)
        return np.where(self.q > 0, np.logaddexp(np.log1p(-self.q) + l1, np.log(q) + l2), l1)


def score(d, coef, which, base=None):
    if T_CORE[0] == "all":
        v0 = variance(d, coef, which)
        w_b = F.behind_width(d["mean"], d["t_min"])
        w_e = F.extent_width(d["mean"], d["r"], d["gap"])
        mix = TMixture(d["mean"], v0, w_b, w_e, d["lam"], T_CORE[1])
        e = np.abs(d["y"] - d["mean"])
        z = e / mix.half_width(FV.ONE_SIGMA if hasattr(FV, "ONE_SIGMA") else 0.6826894921370859)
        in2 = e <= mix.half_width(FV.TWO_SIGMA)
        ll = mix.logpdf(d["y"])
        return _tally(d, z, in2, ll, base)
    if not T_CORE[0]:
        return _old_score(d, coef, which, base)
    from scipy import stats
    nu = T_CORE[1]
    v0 = variance(d, coef, which)
    w_b = F.behind_width(d["mean"], d["t_min"])
    w_e = F.extent_width(d["mean"], d["r"], d["gap"])
    mix = UnseenMixture(d["mean"], v0, w_b, w_e, d["lam"])
    obs = (w_b == 0) & (w_e == 0)
    e = np.abs(d["y"] - d["mean"])
    sig = np.sqrt(mix.var)
    z = e / sig
    in2 = e <= mix.half_width(FV.TWO_SIGMA)
    ll = mix.logpdf(d["y"])
    q1 = stats.t.ppf(Q1, nu)
    r2 = stats.t.ppf(0.5 + FV.TWO_SIGMA / 2, nu) / q1
    in2 = np.where(obs, e <= r2 * sig, in2)
    sc = sig / q1
    ll = np.where(obs, stats.t.logpdf(e / sc, nu) - np.log(sc), ll)
    return _tally(d, z, in2, ll, base)


def _tally(d, z, in2, ll, base):
    c1, c2, n1, n2, nl, nr, rm = [], [], 0, 0, 0, 0, []
    for i in range(len(B.BINS) - 1):
        s_ = d["bin"] == i
        a, b = float(np.mean(z[s_] <= 1)), float(np.mean(in2[s_]))
        c1.append(a)
        c2.append(b)
        n1 += abs(round(a, 2) - 0.68) <= 0.05 + 1e-9
        n2 += abs(round(b, 2) - 0.95) <= 0.03 + 1e-9
        r = float(np.sqrt(np.mean((d["y"][s_] - d["mean"][s_]) ** 2)))
        rm.append(r)
        if base is not None:
            nl += float(ll[s_].mean()) > FV.best_baseline_ll(base, i)
            nr += r < base["plane"]["rmse_sdf"][i]
    return dict(c1=c1, c2=c2, n=(n1, n2, nl, nr), rm=rm, rmse=rm)


SS.score = score


#: cache tags of a candidate's ``VOTE:`` prefix -> the map's overrides
TAGS = {"plane": [], "sphere": ["far.vote=sphere"],
        "proj": ["far.vote=sphere", "far.project_points=true"],
        "pplane": ["far.project_points=true"]}


def main():
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    if "--cache" in sys.argv:
        SS.CACHE = Path(sys.argv[sys.argv.index("--cache") + 1])
        args = [a for a in args if a != str(SS.CACHE)]
    else:
        SS.CACHE = Path("/tmp/field-15s/calib")
    def load(name, tag):
        if tag.startswith("foot") or tag.startswith("reproj") or tag.startswith("loo"):
            path = SS.CACHE / f"{name}_seed0_far.vote-sphere_{tag}.npz"
            if not path.exists():
                import foot_vote
                np.savez(path, **(foot_vote.foot_case(SS.CACHE, name, int(tag[4:]))
                                  if tag.startswith("foot") else
                                  foot_vote.loo_case(SS.CACHE, name, cap=float(tag[3:]) if tag[3:]
                                                     else None) if tag.startswith("loo") else
                                  foot_vote.reproject_case(SS.CACHE, name, int(tag[6:]))))
            d = {k: (v.item() if v.ndim == 0 else v) for k, v in np.load(path).items()}
            d["_res_path"] = SS.CACHE / f"{name}_seed0_far.vote-sphere_{tag}_resample.npz"
            return d
        ov = TAGS[tag]
        d = FV.scene_case(name, 0, SS.CACHE, ov)
        t = "".join(f"_{o.replace('=', '-')}" for o in ov)
        d["_res_path"] = SS.CACHE / f"{name}_seed0{t}_resample.npz"
        return d

    SS.load = load
    fit_on = args[0]
    cands = [c if ":" in c else "sphere:" + c for c in args[1].split(",")]
    for c in cands:
        T_CORE[0] = "all" if c.endswith("@T") else c.endswith("@t")
        c = c.removesuffix("@t").removesuffix("@T")
        KAPPA_AWARE[0] = c.endswith("@k") or c.endswith("@h")
        ADD_HS[0] = c.endswith("@h")
        if KAPPA_AWARE[0]:
            print("(kappa-aware fit" + (", + hs additive)" if ADD_HS[0] else ")"))
        sys.argv = [sys.argv[0], fit_on, c.removesuffix("@k").removesuffix("@h")] + \
            (["--train"] if "--train" in sys.argv else [])
        SS.main()


if __name__ == "__main__":
    main()
