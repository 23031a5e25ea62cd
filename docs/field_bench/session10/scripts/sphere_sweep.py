#!/usr/bin/env python
"""Session 10 (field-15n): the sphere vote's RMSE and variance candidates from the
cached per-query ingredients of scripts/fit_variance.py (out/calib; plane caches
``<scene>_seed0.npz``, sphere caches ``<scene>_seed0_far.vote-sphere.npz``).

RMSE per bin against the bench's plane reference (docs/field_bench/bench_accuracy.json,
the same queries); variance candidates: eq. calibrated_var's five features plus the
sphere vote's per-query ingredients (eq. sphere_vote), each fitted by the 0.68-quantile
regression (eq. variance_quantile_fit) on the observed queries of the FIT scenes, then
scored with the map's predictive (eq. unseen_mixture) as bench_bins.py counts.

    PYTHONPATH=$PWD .venv/bin/python docs/field_bench/session10/scripts/sphere_sweep.py \
        [FIT=street,sphere] [CANDIDATES] [--train]

FIT: comma-separated scenes (``train16`` / ``train8``: fit_variance.py's training sets;
more than two scenes: at most 4000 observed queries each). CANDIDATES: comma-separated
``VOTE:FEATURES`` (VOTE plane or sphere; FEATURES ``base5`` or extra features joined by
``+``: curv, delta, shrink, kdelta, ssph (the spread about the sphere in place of the
plane spread), lnoise, neff, rcurv, curv8, dispp, ndisp; see :func:`extra`). ``plane:base5``
fitted on street,sphere is VARIANCE_COEF itself. ``--train``: also score the training
sixteen (1 / 2 sigma only).
"""
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[4] / "scripts"))
import bench_accuracy as B  # noqa: E402
import fit_variance as FV  # noqa: E402
from gmmgp_app.stages import farfield as F  # noqa: E402
from gmmgp_app.stages.unseen import UnseenMixture  # noqa: E402

CACHE = Path("out/calib")
SCENES = ["street", "sphere", "street2", "courtyard", "pipes", "bunny"]
BASE = {r["scene"]: r["methods"] for r in
        json.loads(Path("docs/field_bench/bench_accuracy.json").read_text())["results"]}


def load(name, tag):
    return FV.scene_case(name, 0, CACHE, ["far.vote=sphere"] if tag == "sphere" else [])


def extra(d, which):
    h2, s2 = d["h"] ** 2, d["noise"] ** 2
    cols = []
    for w in which:
        if w == "curv":
            cols.append(np.log((d["v_curv"] + s2) / h2))
        elif w == "delta":
            cols.append(np.log((d["delta"] ** 2 + s2) / h2))
        elif w == "shrink":
            cols.append(d["shrink"])
        elif w == "lnoise":  # session 8: the spread at the nearest hit point
            cols.append(np.log((d["spread2_p"] + s2) / h2))
        elif w == "neff":
            cols.append(np.log(d["n_eff"]))
        elif w == "rcurv":  # the sphere-vote distance's variance relative to the spread
            cols.append(np.log((d["v_curv"] + s2) / (d["spread2"] + s2)))
        elif w == "curv8":  # session 8's curv: r^2 x the normals' dispersion in the kernel
            cols.append(np.log((d["r"] ** 2 * d["disp"] + h2) / h2))
        elif w == "dispp":  # the normals' dispersion at the nearest hit point
            cols.append(np.log(np.maximum(d["disp_p"], 1e-12)))
        elif w == "ndisp":  # the normals' noise at the data scale times the distance
            cols.append(np.log((d["r"] ** 2 * d["disp_p"] + s2) / h2))
        elif w == "kdelta":
            cols.append(np.log((d["shrink"] * d["delta"] ** 2 + s2) / h2))
    return np.stack(cols, axis=1) if cols else np.zeros((len(d["y"]), 0))


def design(d, which):
    spread = d["spread2_sphere"] if "ssph" in which else d["spread2"]
    X = F.variance_features(d["h"], d["noise"], d["r"], spread,
                            (d["m_gp"] - d["m_far"]) ** 2, d["v_gp"])
    return np.hstack([X, extra(d, which)])


def variance(d, coef, which):
    d2 = (d["m_gp"] - d["m_far"]) ** 2
    v = d["h"] ** 2 * np.exp(design(d, which) @ np.asarray(coef))
    return v + d["kappa"] * np.exp(-(d["r"] / d["length_scale"]) ** 2) * d2


def fit(cases, which, tau=0.68, per_scene=4000):
    """Eq. variance_quantile_fit on the observed queries; at most ``per_scene`` of them
    per scene (a fixed random draw) when more than two scenes are pooled (the exact LP
    on every query of sixteen scenes takes ~25 min on this machine)."""
    X, Y = [], []
    rng = np.random.default_rng(0)
    for d in cases:
        t = FV.terms(d)
        keep = (t["w_b"] == 0) & (t["w_e"] == 0)
        if len(cases) > 2 and keep.sum() > per_scene:
            idx = rng.choice(np.flatnonzero(keep), per_scene, replace=False)
            keep = np.zeros_like(keep)
            keep[idx] = True
        e2 = np.maximum((d["y"] - d["mean"]) ** 2, 1e-30)[keep]
        X.append(design(d, which)[keep])
        Y.append(np.log(e2 / d["h"] ** 2))
    return F.fit_variance_quantile(np.concatenate(X), np.concatenate(Y), tau)


def score(d, coef, which, base=None):
    v0 = variance(d, coef, which)
    w_b = F.behind_width(d["mean"], d["t_min"])
    w_e = F.extent_width(d["mean"], d["r"], d["gap"])
    mix = UnseenMixture(d["mean"], v0, w_b, w_e, d["lam"])
    e = np.abs(d["y"] - d["mean"])
    z = e / np.sqrt(mix.var)
    in2 = e <= mix.half_width(FV.TWO_SIGMA)
    ll = mix.logpdf(d["y"])
    c1, c2, n1, n2, nl, nr, rm = [], [], 0, 0, 0, 0, []
    for i in range(len(B.BINS) - 1):
        s = d["bin"] == i
        a, b = float(np.mean(z[s] <= 1)), float(np.mean(in2[s]))
        c1.append(a)
        c2.append(b)
        n1 += abs(round(a, 2) - 0.68) <= 0.05 + 1e-9
        n2 += abs(round(b, 2) - 0.95) <= 0.03 + 1e-9
        r = float(np.sqrt(np.mean((d["y"][s] - d["mean"][s]) ** 2)))
        rm.append(r)
        if base is not None:
            nl += float(ll[s].mean()) > FV.best_baseline_ll(base, i)
            nr += r < base["plane"]["rmse_sdf"][i]
    return dict(c1=c1, c2=c2, n=(n1, n2, nl, nr), rmse=rm)


def main():
    fit_on = (sys.argv[1] if len(sys.argv) > 1 else "street,sphere").split(",")
    fit_on = [x for n in fit_on for x in (FV.train_set("16") if n == "train16" else
                                         FV.train_set("8") if n == "train8" else [n])]
    train = FV.train_set("16") if "--train" in sys.argv else []
    cands = (sys.argv[2] if len(sys.argv) > 2 else "plane:base5,sphere:base5,sphere:curv,"
             "sphere:delta,sphere:shrink,sphere:curv+delta").split(",")
    caches = {}
    for c in cands:
        tag, feats = c.split(":")
        which = [] if feats == "base5" else feats.split("+")
        for n in SCENES + fit_on + train:
            if (n, tag) not in caches:
                caches[n, tag] = load(n, tag)
        if tag == "plane" and feats == "base5" and fit_on == ["street", "sphere"]:
            coef = np.array(F.VARIANCE_COEF)
        else:
            coef = fit([caches[n, tag] for n in fit_on], which)
        tot, held = np.zeros(4, int), np.zeros(4, int)
        rows = []
        for n in SCENES:
            r = score(caches[n, tag], coef, which, BASE[n])
            tot += r["n"]
            if not B.SCENES[n]["tuned"]:
                held += r["n"]
            rows.append(f"  {n}: {r['n']} 1s " + " ".join(f"{x:.2f}" for x in r["c1"])
                        + " | 2s " + " ".join(f"{x:.2f}" for x in r["c2"])
                        + " | rmse mm " + " ".join(f"{1000 * x:.1f}" for x in r["rmse"])
                        + " (plane " + " ".join(f"{1000 * x:.1f}" for x in
                                                BASE[n]["plane"]["rmse_sdf"]) + ")")
        tr = np.zeros(2, int)
        for n in train:
            r = score(caches[n, tag], coef, which)
            tr += r["n"][:2]
            rows.append(f"  {n}: {r['n'][:2]} 1s " + " ".join(f"{x:.2f}" for x in r["c1"])
                        + " | 2s " + " ".join(f"{x:.2f}" for x in r["c2"]))
        label = "+".join(fit_on) if len(fit_on) < 4 else f"{len(fit_on)} scenes"
        print(f"{c} fit on {label}: coef {np.round(coef, 4).tolist()}")
        if train:
            print(f"  training sixteen 1s/2s {tr.tolist()} of {7 * len(train)}")
        print(f"  bins 1s/2s/LL/RMSE all {tot.tolist()} held-out four {held.tolist()}")
        print("\n".join(rows), flush=True)


if __name__ == "__main__":
    main()
