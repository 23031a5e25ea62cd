#!/usr/bin/env python
"""Fit and diagnose the blended field's variance (stages/farfield.py, eqs.
calibrated_var, variance_quantile_fit, unseen_var; docs/field.md "Variance by query
category").

For each scene the map is built exactly as ``scripts/bench_accuracy.py`` builds it
(same simulated scan, same random 10 % handed, same queries, defaults), and every
ingredient of the variance is kept per query (cached in ``--cache``; delete it after
changing the field's mean). Then:

* ``--fit`` (tuned scenes only): the 0.68-quantile regression of ``log (y - mu)^2 / h^2``
  on the five features of eq. calibrated_var over the queries where the
  unseen-geometry widths are zero (the observed surface), printed as VARIANCE_COEF;
* ``--sweep``: candidate fits (least squares on log e^2, Gaussian and Student-t
  likelihood, the 0.68 quantile; street or both tuned scenes; all or observed queries)
  scored on every scene;
* ``--mixture BASELINES_JSON``: the predictive where the scan cannot see, eq.
  unseen_var (its moment-matched Gaussian) against eq. unseen_mixture (stages/unseen.py:
  the design's own mixture, scored by its log density, sigma its central 68.27 %
  half-width) for several lambda, per scene and bin; ``--categories`` with
  ``--predictive mixture`` splits the mixture's figures by category;
* ``--score BASELINES_JSON``: bins in target per scene for VARIANCE_COEF, ``--coef``
  and a ``--fit`` (with ``--train``: the training scenes scored too);
* ``--categories``: per bin and per query category the count, coverage within 1 and
  2 sigma, mean log-likelihood, median and 99th percentile of |z| and which variance
  term dominates. Categories (exclusive): ``near`` |m| <= h (at the located surface),
  ``front`` m > h in observed free space, ``front_ext`` m > h with the extent term
  active (w_extent > h: the foot point is beyond the end of the data), ``beh_solid``
  m < -h with a negative truth (inside matter, as the mean says), ``beh_thin`` m < -h
  with a positive truth (free space behind a thin wall or a small object).

Examples::

    python scripts/fit_variance.py --fit
    python scripts/fit_variance.py --categories --scenes street,courtyard,pipes
    python scripts/fit_variance.py --sweep docs/field_bench/bench_accuracy.json
    python scripts/fit_variance.py --fit --train --score docs/field_bench/bench_accuracy.json

``--train`` uses random scenes apart from the benchmark's (:data:`TRAIN_SCENES`: four
mobile-mapping ``yard`` layouts and four terrestrial ``objects`` scenes of
gmmgp_app.synth.training_scenes, and with ``--train-set 16``, the default, the eight
of :data:`TRAIN_SCENES_NOISE` at chosen noise levels and spacings), so a fit on them
leaves all six bench scenes held out;
``--score`` counts each scene's bins in target for candidate coefficients from the
cached ingredients (the map's mean unchanged), as scripts/bench_bins.py counts them.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_accuracy as B  # noqa: E402

import gmmgp_app as gm  # noqa: E402
from gmmgp_app.config import concrete  # noqa: E402
from gmmgp_app.stages import farfield as F  # noqa: E402
from gmmgp_app.stages.unseen import UnseenMixture  # noqa: E402

CATEGORIES = ("near", "front", "front_ext", "beh_solid", "beh_thin")


#: Training scenes (gmmgp_app.synth.training_scenes, random layouts apart from the
#: benchmark's): ``train_<kind>_<seed>``; a fit on them leaves all six bench scenes held
#: out (docs/field.md, "Session 7").
TRAIN_SCENES = tuple(f"train_{k}_{s}" for k in ("yard", "objects") for s in (101, 102, 103, 104))

#: Training scenes at chosen noise levels and spacings (session 8): new layouts
#: (seeds 105-108), range noise ``_n<mm>`` from 1 to 20 mm and scan density ``_d<x>``
#: from 0.15 to 2 x the default, so that a fit sees noise / spacing variation the bench
#: (8 mm on every street-like scene) does not have (docs/field.md, "Session 8").
TRAIN_SCENES_NOISE = ("train_yard_105_n3", "train_yard_106_n15_d0.15",
                      "train_yard_107_n4_d0.6", "train_yard_108_n20",
                      "train_objects_105_n1", "train_objects_106_n12_d0.5",
                      "train_objects_107_n3_d2", "train_objects_108_n6")


def train_set(which="16"):
    """The training scenes of ``--train``: ``"8"`` TRAIN_SCENES (session 7), ``"16"``
    those and TRAIN_SCENES_NOISE."""
    return list(TRAIN_SCENES) + (list(TRAIN_SCENES_NOISE) if which == "16" else [])


def parse_training_name(name):
    """``train_<kind>_<seed>[_n<noise mm>][_d<density factor>]`` -> (kind, seed,
    range noise in m or None, density factor)."""
    parts = name.split("_")
    kind, seed, noise, dens = parts[1], int(parts[2]), None, 1.0
    for x in parts[3:]:
        if x[0] == "n":
            noise = float(x[1:]) / 1000.0
        elif x[0] == "d":
            dens = float(x[1:])
        else:
            raise ValueError(f"bad training scene name {name!r}")
    return kind, seed, noise, dens


def training_scan(name):
    """(scan, scene, spec) of a training scene ``train_<kind>_<seed>[_n<mm>][_d<x>]``:
    yards at the bench streets' density 0.3 (times x) and bins in metres; object scenes
    at density 1 (times x) with bins x 0.3 x their random scale (the pipes' 0.2 at a
    0.67 scale); ``_n<mm>``: the range noise in mm before the scene's scaling."""
    from gmmgp_app.synth.training_scenes import scan_training_scene

    kind, s, noise, dens = parse_training_name(name)
    density = (0.3 if kind == "yard" else 1.0) * dens
    scan, scene, k = scan_training_scene(kind, s, density=density, range_noise=noise)
    spec = dict(density=density, scale=1.0 if kind == "yard" else 0.3 * k, noise=None,
                tuned=False)
    return scan, scene, spec


def scene_spec(name):
    """The bench spec of a bench scene, or of a training scene (its scan made)."""
    return B.SCENES[name] if name in B.SCENES else training_scan(name)[2]


def scene_case(name, seed, cache: Path, overrides=()):
    """The per-query ingredients of one bench or training scene's variance (cached npz;
    the map built with the defaults and ``overrides``, e.g. ``["far.blend=correlated"]``).
    A training scene ``train_<kind>_<seed>`` uses its own seed for the 10 % handed and
    the queries (``seed`` is ignored)."""
    tag = "".join(f"_{o.replace('=', '-')}" for o in overrides)
    path = cache / f"{name}_seed{seed}{tag}.npz"
    if path.exists() and "half" in np.load(path).files and (
            "far.vote=sphere" not in overrides or "spread2_sphere" in np.load(path).files):
        d = dict(np.load(path))
        for k in ("delta", "shrink", "v_curv"):  # cached before eq. sphere_vote: plane vote
            d.setdefault(k, np.zeros(len(d["y"])))
        d.setdefault("spread2_sphere", d["spread2"])
        return {k: (v.item() if v.ndim == 0 else v) for k, v in d.items()}
    if name in B.SCENES:
        spec = B.SCENES[name]
        _, _, handed, q, y, dist = B.scene_queries(name, spec, seed, 20000, 6000)
    else:
        scan, scene, spec = training_scan(name)
        _, _, handed, q, y, dist = B.scene_queries(name, spec, parse_training_name(name)[1],
                                                   20000, 6000, made=(scan, scene))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        smap = gm.build_map(handed, gm.MappingConfig().with_overrides(list(overrides)))
    mean, var = smap.predict(q)[:2]
    base = smap.gp if smap.gp is not None else smap.prior
    m_gp, v_gp = base.predict(q)[:2]
    c = smap.far.components(q, True, split_half=True)   # eq. split_half_var, always kept
    f = smap.config.far
    d = dict(y=y, bin=np.digitize(dist, [b * spec["scale"] for b in B.BINS]) - 1,
             scale=spec["scale"],
             mean=mean, var=var, m_gp=m_gp, v_gp=v_gp, m_far=c["mean"], v_far=c["var"],
             r=c["r"], gp_growth=f.gp_growth,
             delta=c["delta"], shrink=c["shrink"], v_curv=c["v_curv"],  # eq. sphere_vote
             spread2_sphere=c["spread2_sphere"],
             spread2=c["spread2"], h=smap.far.rho0, noise=smap.far.noise,
             half=c["half"], split_half=f.split_half, dof=f.predictive_dof,
             disp=1.0 - np.linalg.norm(c["grad"], axis=1),  # the normals' dispersion
             length_scale=concrete(smap.config.gp).length_scale,
             kappa=f.disagreement_weight, lam=f.unseen_weight,
             t_min=f.min_thickness * smap.far.rho0, gap=f.edge_gap * smap.far.rho0,
             **local_ingredients(smap.far, q, c))
    cache.mkdir(parents=True, exist_ok=True)
    np.savez(path, **d)
    return d


def local_ingredients(far, q, c):
    """Per-query ingredients of the session-8 variance features (docs/field.md,
    "Session 8"): the query (``q``), the far field's effective neighbour count
    (``n_eff``) and, at the query's nearest hit point p (eq. imls at r = 0, kernel
    rho_0): the spread of its neighbours' plane distances (``spread2_p``: the local
    noise along the normals plus curvature at the data's scale), their normals'
    dispersion (``disp_p`` = 1 - |weighted normal|) and the mean distance to its six
    nearest hit points (``spacing_p``: the local spacing)."""
    _, i = far.tree.query(q, workers=-1)
    p = far.points[i]
    cp = far.components(p, True)
    dk = far.tree.query(p, k=7, workers=-1)[0][:, 1:]
    return dict(q=q, n_eff=c["n_eff"], spread2_p=cp["spread2"],
                disp_p=1.0 - np.linalg.norm(cp["grad"], axis=1), spacing_p=dk.mean(axis=1))


def terms(d, coef=F.VARIANCE_COEF):
    """The additive terms of the variance: log-linear, kappa d^2 (plus the split-half
    variance of eq. split_half_var when the map adds it, ``far.split_half``), behind,
    extent."""
    d2 = (d["m_gp"] - d["m_far"]) ** 2
    v_ll = F.calibrated_variance(d["h"], d["noise"], d["r"], d["spread2"], d2, d["v_gp"],
                                 coef=coef, disagreement_weight=0.0)
    v_k = d["kappa"] * np.exp(-(d["r"] / d["length_scale"]) ** 2) * d2
    if d.get("split_half", False):
        v_k = v_k + d["half"]
    w_b = F.behind_width(d["mean"], d["t_min"])
    w_e = F.extent_width(d["mean"], d["r"], d["gap"])
    return dict(ll=v_ll, kap=v_k, beh=(d["lam"] * w_b) ** 2, ext=(d["lam"] * w_e) ** 2,
                w_b=w_b, w_e=w_e)


def categories(d, t):
    m, y, h = d["mean"], d["y"], d["h"]
    c = np.full(len(m), "front", dtype=object)
    c[np.abs(m) <= h] = "near"
    c[(m > h) & (t["w_e"] > h)] = "front_ext"
    c[(m < -h) & (y < 0)] = "beh_solid"
    c[(m < -h) & (y >= 0)] = "beh_thin"
    return c


TWO_SIGMA = 0.9544997361036416  # erf(2 / sqrt 2): a Gaussian's +-2 sigma


def scored(d, coef=F.VARIANCE_COEF, predictive="gaussian", lam=None, two_sigma=False):
    """Per query: reported variance v (sigma^2), |z| = |y - m| / sigma and the log
    density of the truth, for eq. unseen_var (``gaussian``) or eq. unseen_mixture."""
    t = terms(d, coef)
    lam = d["lam"] if lam is None else lam
    if predictive == "gaussian":
        v = t["ll"] + t["kap"] + lam ** 2 * (t["w_b"] ** 2 + t["w_e"] ** 2)
        z = np.abs(d["y"] - d["mean"]) / np.sqrt(v)
        ll = -0.5 * np.log(2 * np.pi * v) - 0.5 * z * z
    else:
        mix = UnseenMixture(d["mean"], t["ll"] + t["kap"], t["w_b"], t["w_e"], lam,
                            dof=d.get("dof", 0.0))
        v = mix.var
        z = np.abs(d["y"] - d["mean"]) / np.sqrt(v)
        ll = mix.logpdf(d["y"])
        if two_sigma:
            return t, v, z, ll, np.abs(d["y"] - d["mean"]) <= mix.half_width(TWO_SIGMA)
    if two_sigma:
        return t, v, z, ll, z <= 2
    return t, v, z, ll


def category_table(name, d, coef=F.VARIANCE_COEF, predictive="gaussian") -> str:
    t, v, z, ll = scored(d, coef, predictive)
    e = d["y"] - d["mean"]
    cat = categories(d, t)
    dom = np.array(["ll", "kap", "beh", "ext"])[np.argmax(
        np.stack([t["ll"], t["kap"], t["beh"], t["ext"]]), axis=0)]
    sc = B.SCENES[name]["scale"]
    lines = [f"\n**{name}** ({'tuned' if B.SCENES[name]['tuned'] else 'held out'})\n",
             "| bin (m) | category | n (share) | cov 1s / 2s | mean LL | median / p99 |z| "
             "| RMSE / median std (mm) | dominant term (share) |",
             "|---|---|---|---|---|---|---|---|"]
    for i in range(len(B.BINS) - 1):
        s = d["bin"] == i
        lab = f"{B.BINS[i] * sc:g}-{B.BINS[i + 1] * sc:g}"
        lines.append(f"| {lab} | all | {s.sum()} | {np.mean(z[s] <= 1):.2f} / "
                     f"{np.mean(z[s] <= 2):.2f} | {ll[s].mean():+.2f} | | | |")
        for c in CATEGORIES:
            k = s & (cat == c)
            if k.sum() < 5:
                continue
            doms = ", ".join(f"{x} {np.mean(dom[k] == x):.2f}" for x in ("ll", "kap", "beh", "ext")
                             if np.mean(dom[k] == x) >= 0.05)
            lines.append(
                f"| | {c} | {k.sum()} ({k.sum() / s.sum():.2f}) | {np.mean(z[k] <= 1):.2f} / "
                f"{np.mean(z[k] <= 2):.2f} | {ll[k].mean():+.2f} | {np.median(z[k]):.2f} / "
                f"{np.quantile(z[k], 0.99):.1f} | {1000 * np.sqrt(np.mean(e[k] ** 2)):.1f} / "
                f"{1000 * np.sqrt(np.median(v[k])):.1f} | {doms} |")
    return "\n".join(lines)


def coverage_bins(d, coef=F.VARIANCE_COEF, base_methods=None):
    """Per bin of one cached scene, with the map's predictive (eq. unseen_mixture) and
    eq. calibrated_var's coefficients ``coef``: 1-sigma coverage, the central 95.45 %
    interval's coverage, mean LL and (with ``base_methods``, a bench_accuracy.py
    scene's "methods") whether it is above hgmm, gpis and loggpis; then the bins in
    target counted as scripts/bench_bins.py counts them."""
    _, _, z, ll, in2 = scored(d, coef, "mixture", two_sigma=True)
    c1, c2, lls, ok = [], [], [], []
    for i in range(len(B.BINS) - 1):
        s = d["bin"] == i
        c1.append(float(np.mean(z[s] <= 1)) if s.any() else float("nan"))
        c2.append(float(np.mean(in2[s])) if s.any() else float("nan"))
        lls.append(float(ll[s].mean()) if s.any() else float("nan"))
        if base_methods is not None:
            ok.append(lls[-1] > best_baseline_ll(base_methods, i))
    n1 = sum(abs(round(c, 2) - 0.68) <= 0.05 + 1e-9 for c in c1)
    n2 = sum(abs(round(c, 2) - 0.95) <= 0.03 + 1e-9 for c in c2)
    return dict(c1=c1, c2=c2, ll=lls, n1=n1, n2=n2, nll=sum(ok) if ok else None)


def score_coefs(names, coefs: dict, cache, seed=0, baselines=None, overrides=()) -> str:
    """Bins in target per scene for each candidate ``coefs`` (label -> t0..t4), the
    map's mean unchanged (cached ingredients of maps built with ``overrides``): a
    markdown table, then the coverages."""
    import json

    base = {} if baselines is None else {
        r["scene"]: r["methods"] for r in json.loads(Path(baselines).read_text())["results"]}
    names = [n for n in names if n != "bunny" or B.BUNNY.is_dir()]
    cases = {n: scene_case(n, seed, cache, overrides) for n in names}
    tag = lambda n: ("tuned" if B.SCENES[n]["tuned"] else "held out") if n in B.SCENES \
        else "training"  # noqa: E731
    lines = ["Bins in target per scene (1 sigma / 2 sigma / LL above hgmm, gpis and loggpis); "
             "then the coverages per bin (1 sigma; 2 sigma).\n",
             "| coefficients | " + " | ".join(f"{n} ({tag(n)})" for n in names)
             + " | all | held-out four |", "|---|" + "---|" * (len(names) + 2)]
    detail = []
    for label, coef in coefs.items():
        cells, tot, held = [], np.zeros(3, int), np.zeros(3, int)
        for n in names:
            r = coverage_bins(cases[n], coef, base.get(n))
            v = np.array([r["n1"], r["n2"], r["nll"] if r["nll"] is not None else 0])
            tot += v
            if n in B.SCENES and not B.SCENES[n]["tuned"]:
                held += v
            cells.append(f"{r['n1']} / {r['n2']} / {'-' if r['nll'] is None else r['nll']}")
            detail.append(f"{label} | {n}: 1s " + " ".join(f"{c:.2f}" for c in r["c1"])
                          + "; 2s " + " ".join(f"{c:.2f}" for c in r["c2"])
                          + "; LL " + " ".join(f"{c:+.2f}" for c in r["ll"]))
        lines.append(f"| {label} ({', '.join(f'{x:.4f}' for x in coef)}) | " + " | ".join(cells)
                     + f" | {tot[0]} / {tot[1]} / {tot[2]} | {held[0]} / {held[1]} / {held[2]} |")
    return "\n".join(lines) + "\n\n" + "\n".join(detail)


def fit(cases, tau=0.68, target="kappa"):
    """Eq. variance_quantile_fit over the observed queries (both unseen widths 0).

    ``target="kappa"`` (eq. variance_quantile_target): the log-linear part is fitted to
    what the additive terms leave of the squared error, ``log(max(e^2 - kappa
    e^{-r^2/l^2} d^2 [- v_half], 1e-30 h^2) / h^2)``, so that the variance the map
    reports (log-linear part plus those terms) covers ``tau`` of the queries (a query
    the additive terms cover is covered whatever X t); ``"plain"``: ``log(e^2 / h^2)``,
    the log-linear part alone (the fit of VARIANCE_COEF, VARIANCE_COEF_PROJECTED,
    VARIANCE_COEF_CORRELATED and VARIANCE_COEF_SPHERE, which ignored the kappa term)."""
    if target not in ("kappa", "plain"):
        raise ValueError(f"Expected a fit target 'kappa' or 'plain', found {target!r}.")
    X, Y = [], []
    for d in cases:
        t = terms(d)
        keep = (t["w_b"] == 0) & (t["w_e"] == 0)
        if target == "kappa":
            e2 = np.maximum((d["y"] - d["mean"]) ** 2 - t["kap"], 1e-30 * d["h"] ** 2)[keep]
        else:
            e2 = np.maximum((d["y"] - d["mean"]) ** 2, 1e-30)[keep]
        X.append(F.variance_features(d["h"], d["noise"], d["r"][keep], d["spread2"][keep],
                                     ((d["m_gp"] - d["m_far"]) ** 2)[keep], d["v_gp"][keep]))
        Y.append(np.log(e2 / d["h"] ** 2))
    return F.fit_variance_quantile(np.concatenate(X), np.concatenate(Y), tau)


def fit_dof(cases, coef):
    """nu of eq. unseen_mixture_t by maximum likelihood of the observed queries' (both
    unseen widths 0) standardised errors ``z = (y - m) / sigma``, sigma the reported
    std (log-linear part with ``coef`` plus the additive terms), under the Student-t
    of nu dof scaled so that P(|z| <= 1) = erf(1/sqrt 2):

        nu = argmax_nu  mean_i [ log t_nu(c_nu z_i) + log c_nu ],
        c_nu = t_nu^-1((1 + erf(1/sqrt 2)) / 2)

    (bounded scalar search of log nu on [log 1, log 200])."""
    from scipy.optimize import minimize_scalar
    from gmmgp_app.stages.unseen import _logpdf, component_scale

    z = []
    for d in cases:
        t = terms(d, coef)
        keep = (t["w_b"] == 0) & (t["w_e"] == 0)
        z.append((np.abs(d["y"] - d["mean"]) / np.sqrt(t["ll"] + t["kap"]))[keep])
    z = np.concatenate(z)

    def nll(lognu):
        nu = float(np.exp(lognu))
        c = component_scale(nu)
        return -float(np.mean(_logpdf(c * z, nu) + np.log(c)))

    return float(np.exp(minimize_scalar(nll, bounds=(0.0, np.log(200.0)), method="bounded",
                                        options=dict(xatol=1e-6)).x))


def _design(d, mask_obs):
    t = terms(d)
    keep = (t["w_b"] == 0) & (t["w_e"] == 0) if mask_obs else np.ones(len(d["y"]), bool)
    X = F.variance_features(d["h"], d["noise"], d["r"], d["spread2"],
                            (d["m_gp"] - d["m_far"]) ** 2, d["v_gp"])
    e2 = np.maximum((d["y"] - d["mean"]) ** 2, 1e-30)
    return X, e2, t, keep


def _lik_fit(cases, nu=None):
    """Coefficients maximising the Gaussian (nu None) or Student-t likelihood of the
    whole variance (the other terms held fixed), from VARIANCE_COEF."""
    from scipy.optimize import minimize

    packs = []
    for d in cases:
        X, e2, t, _ = _design(d, False)
        packs.append((X, e2, t["kap"] + t["beh"] + t["ext"], d["h"] ** 2))

    def f(c):
        tot, g = 0.0, 0.0
        for X, e2, ex, h2 in packs:
            b = h2 * np.exp(X @ c)
            v = b + ex
            if nu is None:
                nll, gv = 0.5 * np.log(v) + 0.5 * e2 / v, 0.5 / v - 0.5 * e2 / v ** 2
            else:
                nll = 0.5 * np.log(v) + 0.5 * (nu + 1) * np.log1p(e2 / (nu * v))
                gv = 0.5 / v - 0.5 * (nu + 1) * e2 / (nu * v * v + e2 * v)
            tot += nll.mean()
            g = g + (gv * b) @ X / len(e2)
        return tot, g

    return minimize(f, np.asarray(F.VARIANCE_COEF), jac=True, method="L-BFGS-B").x


def best_baseline_ll(methods, i) -> float:
    """The best mean log-likelihood of hgmm, gpis and loggpis (its unsigned field's) in
    bin ``i`` of one scene's bench_accuracy results (``methods``): what the map's must
    exceed (issue 15)."""
    return max(methods[k]["ll_sdf" if k != "loggpis" else "ll_edf"][i]
               for k in ("hgmm", "gpis", "loggpis") if k in methods)


def sweep(seed, cache, baselines) -> str:
    """The candidate fits of eq. calibrated_var, scored on all six scenes."""
    import json

    base = {r["scene"]: r for r in json.loads(Path(baselines).read_text())["results"]}
    names = [n for n in B.SCENES if n != "bunny" or B.BUNNY.is_dir()]
    cases = {n: scene_case(n, seed, cache) for n in names}
    tuned = [cases[n] for n in names if B.SCENES[n]["tuned"]]
    street = [cases["street"]]

    def ls(cs, obs):
        X, Y = [], []
        for d in cs:
            x, e2, _, k = _design(d, obs)
            X.append(x[k])
            Y.append(np.log(e2[k] / d["h"] ** 2) + 1.27)
        return np.linalg.lstsq(np.concatenate(X), np.concatenate(Y), rcond=None)[0]

    def qf(cs, obs):
        X, Y = [], []
        for d in cs:
            x, e2, _, k = _design(d, obs)
            X.append(x[k])
            Y.append(np.log(e2[k] / d["h"] ** 2))
        return F.fit_variance_quantile(np.concatenate(X), np.concatenate(Y), 0.68)

    cands = [("before: least squares on log e^2 + 1.27, street, all queries",
              (0.5358, -0.3834, 1.1189, 0.2069, 0.1491)),
             ("least squares on log e^2 + 1.27, street, observed", ls(street, True)),
             ("least squares on log e^2 + 1.27, street + sphere, observed", ls(tuned, True)),
             ("Gaussian likelihood, street, all", _lik_fit(street)),
             ("Student-t (4 dof) likelihood, street, all", _lik_fit(street, 4.0)),
             ("0.68 quantile, street, observed", qf(street, True)),
             ("0.68 quantile, street + sphere, all", qf(tuned, False)),
             ("**0.68 quantile, street + sphere, observed**", qf(tuned, True))]
    lines = ["Per scene: 1-sigma coverage per bin [bins within 0.68 +- 0.05] / bins with 2-sigma "
             "coverage within 0.95 +- 0.03 / bins with mean LL above hgmm, gpis and loggpis "
             "(of 7).\n",
             "| fit (t0..t4) | " + " | ".join(
                 f"{n} ({'tuned' if B.SCENES[n]['tuned'] else 'held out'})" for n in names)
             + " |", "|---|" + "---|" * len(names)]
    for label, coef in cands:
        cells = []
        for n in names:
            d = cases[n]
            t = terms(d, coef)
            v = t["ll"] + t["kap"] + t["beh"] + t["ext"]
            z = np.abs(d["y"] - d["mean"]) / np.sqrt(v)
            ll = -0.5 * np.log(2 * np.pi * v) - 0.5 * z * z
            ms = base[n]["methods"]
            c1, c2, ok = [], [], 0
            for i in range(len(B.BINS) - 1):
                s = d["bin"] == i
                c1.append(np.mean(z[s] <= 1))
                c2.append(np.mean(z[s] <= 2))
                best = best_baseline_ll(ms, i)
                ok += ll[s].mean() > best
            n1 = sum(abs(c - 0.68) <= 0.05 for c in c1)
            n2 = sum(abs(c - 0.95) <= 0.03 for c in c2)
            cells.append(" ".join(f"{c:.2f}" for c in c1) + f" [{n1}] / {n2} / {ok}")
        lines.append(f"| {label} ({', '.join(f'{x:.3f}' for x in coef)}) | "
                     + " | ".join(cells) + " |")
    return "\n".join(lines)


def mixture_sweep(seed, cache, baselines, names, lams=(0.05, 0.1, 0.15, 0.25, 0.35)) -> str:
    """Eq. unseen_var against eq. unseen_mixture for several lambda, every scene and bin:
    1-sigma coverage per bin [bins within 0.68 +- 0.05], bins within 0.95 +- 0.03 at 2
    sigma, bins with mean LL above hgmm, gpis and loggpis, and the least LL margin."""
    import json

    base = {r["scene"]: r for r in json.loads(Path(baselines).read_text())["results"]}
    cases = {n: scene_case(n, seed, cache) for n in names}
    rows = [("gaussian (eq. unseen_var)", "gaussian", lam) for lam in (0.15,)] + \
        [("mixture (eq. unseen_mixture)", "mixture", lam) for lam in lams]
    lines = ["Per scene: 1-sigma coverage per bin [bins within 0.68 +- 0.05] / bins within "
             "0.95 +- 0.03 at 2 sigma / bins with mean LL above hgmm, gpis and loggpis (of 7) "
             "/ least LL margin; then the 2-sigma coverage and the mean LL per bin.\n",
             "| predictive | lambda | " + " | ".join(
                 f"{n} ({'tuned' if B.SCENES[n]['tuned'] else 'held out'})" for n in names)
             + " |", "|---|---|" + "---|" * len(names)]
    for label, pred, lam in rows:
        cells = []
        for n in names:
            d = cases[n]
            _, _, z, ll, in2 = scored(d, predictive=pred, lam=lam, two_sigma=True)
            ms = base[n]["methods"]
            c1, c2, i2, lls, margins = [], [], [], [], []
            for i in range(len(B.BINS) - 1):
                s = d["bin"] == i
                c1.append(np.mean(z[s] <= 1))
                c2.append(np.mean(z[s] <= 2))
                i2.append(np.mean(in2[s]))
                lls.append(ll[s].mean())
                best = best_baseline_ll(ms, i)
                margins.append(lls[-1] - best)
            n1 = sum(abs(c - 0.68) <= 0.05 for c in c1)
            n2 = sum(abs(c - 0.95) <= 0.03 for c in c2)
            ni = sum(abs(c - 0.95) <= 0.03 for c in i2)
            ok = sum(m > 0 for m in margins)
            cells.append(" ".join(f"{c:.2f}" for c in c1) + f" [{n1}] / {n2} / {ok} / "
                         f"{min(margins):+.2f}<br>2s " + " ".join(f"{c:.2f}" for c in c2)
                         + f"<br>95.45 % interval [{ni}] " + " ".join(f"{c:.2f}" for c in i2)
                         + "<br>LL " + " ".join(f"{x:+.2f}" for x in lls))
        lines.append(f"| {label} | {lam:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def blend_rmse(d, w_gp, mask=None):
    """Per bin RMSE (m) of the mean ``w_gp m_gp + (1 - w_gp) m_far`` (mask: a subset)."""
    m = w_gp * d["m_gp"] + (1.0 - w_gp) * d["m_far"]
    e2 = (m - d["y"]) ** 2
    out = []
    for i in range(len(B.BINS) - 1):
        s = d["bin"] == i if mask is None else (d["bin"] == i) & mask
        out.append(float(np.sqrt(e2[s].mean())) if s.any() else float("nan"))
    return out


def oracle_weight(d, s):
    """The convex weight of the GP that minimises the squared error over the queries
    ``s`` (the best one blend weight for a bin, from the truth: an oracle)."""
    a = d["m_gp"][s] - d["m_far"][s]
    b = d["y"][s] - d["m_far"][s]
    den = float(a @ a)
    return float(np.clip((a @ b) / den, 0.0, 1.0)) if den > 0 else 0.0


def growth_weight(d):
    """The GP's weight in eq. blend with ``(g r)^2`` (``far.blend = "growth"``)."""
    v_gp = d["v_gp"] + (d["gp_growth"] * d["r"]) ** 2
    return d["v_far"] / (v_gp + d["v_far"])


def field_variances(d, coef_gp=None, coef_far=None):
    """Eq. field_var for the GP and the far field at the queries of one scene."""
    cg = F.FIELD_VAR_COEF["gp"] if coef_gp is None else coef_gp
    cf = F.FIELD_VAR_COEF["far"] if coef_far is None else coef_far
    d2 = (d["m_gp"] - d["m_far"]) ** 2
    vg = F.field_variance(d["h"], d["noise"], d["r"], d["spread2"], d2, d["v_gp"], cg)
    vf = F.field_variance(d["h"], d["noise"], d["r"], d["spread2"], d2, d["v_far"], cf)
    return vg, vf


def correlated_weight(d, coef_gp=None, coef_far=None, rho=None):
    """The GP's weight in eq. blend_correlated (``far.blend = "correlated"``)."""
    vg, vf = field_variances(d, coef_gp, coef_far)
    rho = F.BLEND_CORRELATION if rho is None else rho
    c = rho * np.sqrt(vg * vf)
    return np.clip((vf - c) / (vg + vf - 2 * c), 0.0, 1.0)


def fit_blend(cases):
    """Eq. field_var_fit for each field and eq. error_correlation_fit over all queries
    of the given scenes: (u_gp, u_far, rho, mean negative log-likelihood per field)."""
    X, Eg, Ef = [], [], []
    for d in cases:
        X.append(F.variance_features(d["h"], d["noise"], d["r"], d["spread2"],
                                     (d["m_gp"] - d["m_far"]) ** 2, d["v_gp"]))
        Eg.append((d["m_gp"] - d["y"]) ** 2 / d["h"] ** 2)
        Ef.append((d["m_far"] - d["y"]) ** 2 / d["h"] ** 2)
    Xg = np.concatenate(X)
    Eg, Ef = np.concatenate(Eg), np.concatenate(Ef)
    ug = F.fit_field_variance(Xg, Eg)
    Xf = [F.variance_features(d["h"], d["noise"], d["r"], d["spread2"],
                              (d["m_gp"] - d["m_far"]) ** 2, d["v_far"]) for d in cases]
    uf = F.fit_field_variance(np.concatenate(Xf), Ef)
    zg, zf = [], []
    for d in cases:
        vg, vf = field_variances(d, ug, uf)
        zg.append((d["m_gp"] - d["y"]) / np.sqrt(vg))
        zf.append((d["m_far"] - d["y"]) / np.sqrt(vf))
    rho = F.fit_error_correlation(np.concatenate(zg), np.concatenate(zf))
    return ug, uf, rho


def blend_table(name, d, fitted=None) -> str:
    """RMSE per bin of the map's mean, of eq. blend (growth weights) and eq.
    blend_correlated recomputed from the cached ingredients, the far field alone, the
    GP field alone and the best convex blend per bin (oracle), with the GP weights."""
    wg = growth_weight(d)
    wc = correlated_weight(d, *(fitted or (None, None, None)))
    e2 = (d["mean"] - d["y"]) ** 2
    today = [float(np.sqrt(e2[d["bin"] == i].mean())) for i in range(len(B.BINS) - 1)]
    far = blend_rmse(d, np.zeros_like(wg))
    gp = blend_rmse(d, np.ones_like(wg))
    orc, worc = [], []
    for i in range(len(B.BINS) - 1):
        s = d["bin"] == i
        wo = oracle_weight(d, s)
        worc.append(wo)
        orc.append(blend_rmse(d, np.full(len(wg), wo), s)[i])
    med = lambda w: " / ".join(f"{np.median(w[d['bin'] == i]):.3f}"  # noqa: E731
                               for i in range(len(B.BINS) - 1))
    sc = B.SCENES[name]["scale"]
    labs = [f"{B.BINS[i] * sc:g}-{B.BINS[i + 1] * sc:g}" for i in range(len(B.BINS) - 1)]
    mm = lambda xs: " / ".join(f"{1000 * x:.1f}" for x in xs)  # noqa: E731
    rows = [f"\n**{name}** ({'tuned' if B.SCENES[name]['tuned'] else 'held out'}; bins "
            f"{' / '.join(labs)} m)\n", "| mean | RMSE (mm) per bin |", "|---|---|",
            f"| the map's mean | {mm(today)} |",
            f"| eq. blend, growth weights (far.blend = growth) | {mm(blend_rmse(d, wg))} |",
            f"| eq. blend_correlated (far.blend = correlated) | {mm(blend_rmse(d, wc))} |",
            f"| far field alone (robust IMLS) | {mm(far)} |",
            f"| GP field alone | {mm(gp)} |",
            f"| best convex blend per bin (oracle) | {mm(orc)} |",
            "| oracle's GP weight | " + " / ".join(f"{x:.2f}" for x in worc) + " |",
            f"| median GP weight, growth | {med(wg)} |",
            f"| median GP weight, correlated | {med(wc)} |"]
    return "\n".join(rows)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", default=",".join(B.SCENES))
    p.add_argument("--fit", action="store_true", help="fit VARIANCE_COEF on the tuned scenes")
    p.add_argument("--train-set", default="16", choices=("8", "16"),
                   help="the training scenes of --train: 8 = TRAIN_SCENES (session 7), 16 = "
                   "those and TRAIN_SCENES_NOISE (session 8: noise 1-20 mm, density "
                   "0.15-2 x; default)")
    p.add_argument("--train", action="store_true",
                   help="with --fit: fit on the random training scenes (TRAIN_SCENES, "
                   "gmmgp_app.synth.training_scenes) instead, leaving all six bench scenes "
                   "held out; with --score: score the training scenes too")
    p.add_argument("--score", default=None, metavar="BASELINES_JSON",
                   help="bins in target per scene (1 sigma, 95.45 %% interval, LL above the "
                   "hgmm/gpis/loggpis rows of this bench_accuracy.py JSON) for VARIANCE_COEF, "
                   "--coef and the coefficients fitted by --fit; the mean unchanged")
    p.add_argument("--categories", action="store_true", help="per-bin category tables")
    p.add_argument("--sweep", default=None, metavar="BASELINES_JSON",
                   help="score candidate fits on every scene; LL margins against the "
                   "hgmm/gpis/loggpis rows of this bench_accuracy.py JSON (same seed)")
    p.add_argument("--mixture", default=None, metavar="BASELINES_JSON",
                   help="eq. unseen_var against eq. unseen_mixture for several lambda; LL "
                   "margins against this bench_accuracy.py JSON (same seed)")
    p.add_argument("--fit-blend", action="store_true",
                   help="fit FIELD_VAR_COEF and BLEND_CORRELATION on the tuned scenes "
                   "(eqs. field_var_fit, error_correlation_fit); with --blend the tables "
                   "use the fitted values")
    p.add_argument("--blend", action="store_true",
                   help="RMSE per bin of the blend, the far field alone, the GP alone and "
                   "the best convex blend per bin (oracle)")
    p.add_argument("--predictive", default="gaussian", choices=("gaussian", "mixture"),
                   help="predictive of --categories (default: gaussian, eq. unseen_var)")
    p.add_argument("--tau", type=float, default=0.68)
    p.add_argument("--target", default="kappa", choices=("kappa", "plain"),
                   help="--fit's target: 'kappa' (default; eq. variance_quantile_target, the "
                   "log-linear part fitted to what the kappa and split-half terms leave) or "
                   "'plain' (log e^2, the fit of the coefficients before session 13)")
    p.add_argument("--dof", action="store_true",
                   help="with --fit: also nu of eq. unseen_mixture_t by maximum likelihood "
                   "(fit_dof) on the same scenes")
    p.add_argument("--coef", default=None,
                   help="t0,...,t4 for --categories (default: VARIANCE_COEF)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", action="append", default=[],
                   help="config override of the maps (a.b=v), e.g. far.blend=correlated")
    p.add_argument("--cache", default="out/calib")
    p.add_argument("--out", default=None, help="also write the tables to this markdown file")
    a = p.parse_args(argv)
    names = a.scenes.split(",")
    bad = [n for n in names if n not in B.SCENES]
    if bad:
        print(f"error: unknown scene(s) {', '.join(bad)}; expected some of "
              f"{', '.join(B.SCENES)}", file=sys.stderr)
        return 2
    if not (a.fit or a.categories or a.sweep or a.mixture or a.blend or a.fit_blend
            or a.score):
        print("error: nothing to do; give --fit, --categories, --sweep, --mixture and/or "
              "--blend",
              file=sys.stderr)
        return 2
    cache = Path(a.cache)
    text = []
    coef = F.VARIANCE_COEF if a.coef is None else tuple(float(x) for x in a.coef.split(","))
    fitted_coef = None
    if a.fit:
        tuned = train_set(a.train_set) if a.train else [n for n in B.SCENES if B.SCENES[n]["tuned"]]
        cs = [scene_case(n, a.seed, cache, a.set) for n in tuned]
        t = fitted_coef = fit(cs, a.tau, a.target)
        text.append(f"VARIANCE_COEF = ({', '.join(f'{x:.4f}' for x in t)})  "
                    f"# tau {a.tau}, target {a.target}, fitted on {', '.join(tuned)}")
        if a.dof:
            text.append(f"nu = {fit_dof(cs, t):.2f}  # eq. unseen_mixture_t, observed queries "
                        f"of {', '.join(tuned)}")
    if a.categories:
        for n in names:
            if n == "bunny" and not B.BUNNY.is_dir():
                print("bunny: skipped, ../shared not found", file=sys.stderr)
                continue
            text.append(category_table(n, scene_case(n, a.seed, cache, a.set), coef, a.predictive))
    fitted = None
    if a.fit_blend:
        tuned = [n for n in B.SCENES if B.SCENES[n]["tuned"]]
        ug, uf, rho = fitted = fit_blend([scene_case(n, a.seed, cache, a.set) for n in tuned])
        text.append(f'FIELD_VAR_COEF = {{"gp": ({", ".join(f"{x:.4f}" for x in ug)}),\n'
                    f'                  "far": ({", ".join(f"{x:.4f}" for x in uf)})}}\n'
                    f"BLEND_CORRELATION = {rho:.4f}  # fitted on {', '.join(tuned)}")
    if a.blend:
        for n in names:
            if n == "bunny" and not B.BUNNY.is_dir():
                continue
            text.append(blend_table(n, scene_case(n, a.seed, cache, a.set), fitted))
    if a.sweep:
        text.append(sweep(a.seed, cache, a.sweep))
    if a.mixture:
        have = [n for n in names if n != "bunny" or B.BUNNY.is_dir()]
        text.append(mixture_sweep(a.seed, cache, a.mixture, have))
    if a.score:
        coefs = {"VARIANCE_COEF": F.VARIANCE_COEF}
        if a.coef is not None:
            coefs["--coef"] = coef
        if fitted_coef is not None:
            coefs["fitted (--fit" + (" --train)" if a.train else ")")] = tuple(fitted_coef)
        text.append(score_coefs(names, coefs, cache, a.seed, a.score, a.set))
        if a.train:
            text.append(score_coefs(train_set(a.train_set), coefs, cache, a.seed, None, a.set))
    out = "\n".join(text) + "\n"
    print(out)
    if a.out:
        Path(a.out).write_text(out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
