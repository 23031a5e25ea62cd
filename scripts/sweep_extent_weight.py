#!/usr/bin/env python
"""Would a separate weight for the extent term help? (docs/field.md, "The predictive
behind the located surface", item 2 of the field-15e brief; not adopted.)

Eq. unseen_mixture gives the unseen component one probability q = 3 lambda^2 for both
widths. Here the behind and the extent widths get their own Gaussian components,
``(1 - q_b - q_e) N(0, v) + q_b N(0, v + w_b^2 / 3) + q_e N(0, v + w_e^2 / 3)``
(q_b = 3 lambda^2 fixed), and

* ``--sweep``: q_e in 0.0675 / 0.15 / 0.3 / 0.5 is scored on every scene (1-sigma
  coverage per bin with [bins within 0.68 +- 0.05], coverage of the central 95.45 %
  interval per bin with [bins within 0.95 +- 0.03], mean LL per bin, bins with LL
  above hgmm, gpis and loggpis and the least margin);
* ``--ml``: q_e by maximum likelihood on the queries with w_e > 0, per scene and on
  the tuned scenes together;
* ``--dispersion``: q_e per query from the neighbours' normal dispersion
  D = 1 - |n_bar| (planes ~0, corners and curved surfaces more),
  ``q_e = q + (q_max - q) D / (D + d_half)``, (q_max <= 0.9, d_half) by maximum
  likelihood on the tuned scenes, then scored on every scene as ``--sweep`` does
  (needs a cache written with the dispersion: ``fit_variance.py`` since field-15e).

Reads the per-query cache of ``scripts/fit_variance.py`` (same protocol; built there
when missing).

Examples::

    python scripts/sweep_extent_weight.py --sweep docs/field_bench/mixture_before/bench_accuracy.json
    python scripts/sweep_extent_weight.py --ml --cache out/calib
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.special import ndtr

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_accuracy as B  # noqa: E402
import fit_variance as FV  # noqa: E402

ONE, TWO = 0.6826894921370859, 0.9544997361036416
Q_B = 3 * 0.15 ** 2


def components(d, qe):
    t = FV.terms(d)
    v = t["ll"] + t["kap"]
    wb2, we2 = t["w_b"] ** 2, t["w_e"] ** 2
    comps = [(np.where(wb2 > 0, Q_B, 0.0), v + wb2 / 3), (np.where(we2 > 0, qe, 0.0), v + we2 / 3)]
    return v, comps, wb2, we2


def scored(d, qe):
    v, comps, wb2, we2 = components(d, qe)
    w0 = 1 - comps[0][0] - comps[1][0]
    e = d["y"] - d["mean"]

    def lp(vv):
        return -0.5 * e * e / vv - 0.5 * np.log(2 * np.pi * vv)

    ll = np.log(w0) + lp(v)
    for q, vv in comps:
        ll = np.where(q > 0, np.logaddexp(ll, np.log(np.maximum(q, 1e-300)) + lp(vv)), ll)

    def mass(h):
        m = w0 * (2 * ndtr(h / np.sqrt(v)) - 1)
        for q, vv in comps:
            m = m + q * (2 * ndtr(h / np.sqrt(vv)) - 1)
        return m

    def half_width(level):
        lo, hi = np.zeros_like(v), 4 * (np.sqrt(v + (wb2 + we2) / 3) + np.sqrt(v))
        for _ in range(50):
            mid = 0.5 * (lo + hi)
            below = mass(mid) < level
            lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
        return 0.5 * (lo + hi)

    a = np.abs(e)
    return a <= half_width(ONE), a <= half_width(TWO), ll


def dispersion_prior(D, q_max, d_half):
    return Q_B + (q_max - Q_B) * D / (D + d_half)


def fit_dispersion(names, cache, seed=0):
    from scipy.optimize import minimize

    packs = []
    for n in names:
        d = FV.scene_case(n, seed, cache)
        v, comps, wb2, we2 = components(d, 0.0)
        e2 = (d["y"] - d["mean"]) ** 2
        on = we2 > 0

        def N(vv):
            return np.exp(-0.5 * e2[on] / vv[on]) / np.sqrt(2 * np.pi * vv[on])
        packs.append((N(v), N(v + wb2 / 3), N(v + we2 / 3), comps[0][0][on], d["disp"][on]))

    def nll(th):
        q_max, d_half = 0.9 / (1 + np.exp(-th[0])), np.exp(th[1])
        return -sum(np.log(np.maximum((1 - qb - dispersion_prior(D, q_max, d_half)) * n0
                                      + qb * nb + dispersion_prior(D, q_max, d_half) * ne,
                                      1e-300)).sum() for n0, nb, ne, qb, D in packs)

    best = min((minimize(nll, x0, method="Nelder-Mead",
                         options=dict(xatol=1e-4, fatol=1e-6, maxiter=2000))
                for x0 in ([0.0, np.log(0.01)], [2.0, np.log(0.001)], [-1.0, np.log(0.05)])),
               key=lambda r: r.fun)
    return 0.9 / (1 + np.exp(-best.x[0])), float(np.exp(best.x[1]))


def sweep(names, cache, baselines, seed=0, rules=None):
    base = {r["scene"]: r for r in json.loads(Path(baselines).read_text())["results"]}
    lines = []
    rules = rules or [(f"q_e = {qe:g}", (lambda d, qe=qe: qe)) for qe in (Q_B, 0.15, 0.3, 0.5)]
    for label, rule in rules:
        lines.append(f"\n{label}\n")
        for n in names:
            d = FV.scene_case(n, seed, cache)
            c1, c2, ll = scored(d, rule(d))
            ms = base[n]["methods"]
            r1, r2, rl, mg = [], [], [], []
            for i in range(len(B.BINS) - 1):
                s = d["bin"] == i
                r1.append(c1[s].mean())
                r2.append(c2[s].mean())
                rl.append(ll[s].mean())
                best = FV.best_baseline_ll(ms, i)
                mg.append(rl[-1] - best)
            n1 = sum(abs(x - 0.68) <= 0.05 for x in r1)
            n2 = sum(abs(x - 0.95) <= 0.03 for x in r2)
            lines.append(f"- {n}: 1s {' '.join(f'{x:.2f}' for x in r1)} [{n1}]; 95.45 % "
                         f"{' '.join(f'{x:.2f}' for x in r2)} [{n2}]; LL "
                         f"{' '.join(f'{x:+.2f}' for x in rl)}; above baselines "
                         f"{sum(m > 0 for m in mg)}, least margin {min(mg):+.2f}")
    return "\n".join(lines)


def ml(names, cache, seed=0):
    def parts(n):
        d = FV.scene_case(n, seed, cache)
        v, comps, wb2, we2 = components(d, 0.0)
        e = d["y"] - d["mean"]

        def N(vv):
            return np.exp(-0.5 * e * e / vv) / np.sqrt(2 * np.pi * vv)
        on = we2 > 0
        return dict(n0=N(v)[on], nb=N(v + wb2 / 3)[on], ne=N(v + we2 / 3)[on],
                    qb=np.where(wb2 > 0, Q_B, 0.0)[on])

    tuned = [n for n in names if B.SCENES[n]["tuned"]]
    lines = []
    for group in [[n] for n in names] + [tuned]:
        P = [parts(n) for n in group]

        def nll(qe):
            return -sum(np.log(np.maximum((1 - p["qb"] - qe) * p["n0"] + p["qb"] * p["nb"]
                                          + qe * p["ne"], 1e-300)).sum() for p in P)
        r = minimize_scalar(nll, bounds=(1e-4, 0.9), method="bounded")
        lines.append(f"- {' + '.join(group)}: {sum(len(p['n0']) for p in P)} queries with "
                     f"w_e > 0, ML q_e = {r.x:.3f}")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", default=",".join(B.SCENES))
    p.add_argument("--sweep", default=None, metavar="BASELINES_JSON")
    p.add_argument("--ml", action="store_true")
    p.add_argument("--dispersion", default=None, metavar="BASELINES_JSON")
    p.add_argument("--cache", default="out/calib")
    a = p.parse_args(argv)
    names = [n for n in a.scenes.split(",") if n != "bunny" or B.BUNNY.is_dir()]
    if not (a.sweep or a.ml or a.dispersion):
        print("error: nothing to do; give --sweep, --ml and/or --dispersion", file=sys.stderr)
        return 2
    if a.sweep:
        print(sweep(names, Path(a.cache), a.sweep))
    if a.ml:
        print(ml(names, Path(a.cache)))
    if a.dispersion:
        tuned = [n for n in names if B.SCENES[n]["tuned"]]
        qm, dh = fit_dispersion(tuned, Path(a.cache))
        print(f"\nq_e from the dispersion: q_max = {qm:.4f}, d_half = {dh:.5f} (ML on "
              f"{', '.join(tuned)})")
        print(sweep(names, Path(a.cache), a.dispersion, rules=[
            (f"q_e = {Q_B:g} (the default)", lambda d: Q_B),
            (f"q_e from the dispersion ({qm:.3f}, {dh:.5f})",
             lambda d: dispersion_prior(d["disp"], qm, dh))]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
