#!/usr/bin/env python
"""Sweep of the unseen-geometry variance (stages/farfield.py, eq. unseen_var).

The term only adds to the variance, so one map per scene suffices: the script builds
each scene's map exactly as ``scripts/bench_accuracy.py`` does (same scan, same 10 %
handed, same queries, defaults) with the term off (``far.unseen_weight=0``), keeps the
blended mean, the calibrated variance and the distance to the nearest hit point, and
scores every (t_min / h, c, lambda) of the grid per bin: mean log-likelihood, the
margin to the best of hgmm, gpis and loggpis (read from a bench_accuracy.py JSON of
the same seed), coverage within 1 and 2 sigma. The RMSE does not depend on the term.

Examples::

    python scripts/sweep_unseen.py --baselines docs/field_bench/bench_accuracy.json
    python scripts/sweep_unseen.py --scenes courtyard --baselines out/bench/bench_accuracy.json
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_accuracy as B  # noqa: E402

import gmmgp_app as gm  # noqa: E402
from gmmgp_app.stages import farfield as _farfield  # noqa: E402

GRID = dict(min_thickness=(2.0, 3.0, 4.0), edge_gap=(1.0, 2.0),
            unseen_weight=(0.0, 0.15, 0.25, 0.35, 0.5))


def scene_case(name, seed):
    """Queries, truth, bins and the term-off prediction of one bench scene."""
    spec = B.SCENES[name]
    scan, scene, handed, q, y, dist = B.scene_queries(name, spec, seed, 20000, 6000)
    sc = spec["scale"]
    cfg = gm.MappingConfig().with_overrides(["far.unseen_weight=0"])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        smap = gm.build_map(handed, cfg)
    mean, var = smap.predict(q)[:2]
    r = smap.far.distance_to_data(q)
    b = np.digitize(dist, [x * sc for x in B.BINS]) - 1
    return dict(y=y, bin=b, mean=mean, var=var, r=r, h=smap.far.rho0)


def score(case, t, c, lam):
    m = case["mean"]
    v = case["var"] + _farfield.unseen_variance(
        _farfield.behind_width(m, t * case["h"]),
        _farfield.extent_width(m, case["r"], c * case["h"]), lam)
    z = (case["y"] - m) / np.sqrt(v)
    ll = -0.5 * np.log(2 * np.pi * v) - 0.5 * z * z
    b = case["bin"]
    per = [(float(ll[b == i].mean()), float(np.mean(np.abs(z[b == i]) <= 1)),
            float(np.mean(np.abs(z[b == i]) <= 2))) for i in range(len(B.BINS) - 1)]
    return per


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", default="street,sphere,street2,courtyard,pipes,bunny")
    p.add_argument("--baselines", required=True,
                   help="bench_accuracy.py JSON with hgmm, gpis, loggpis (same seed)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="out/bench/sweep_unseen.json")
    args = p.parse_args(argv)
    try:
        base = {r["scene"]: r for r in json.loads(Path(args.baselines).read_text())["results"]}
    except (OSError, ValueError, KeyError) as exc:
        print(f"error: cannot read baselines {args.baselines!r} ({exc}); give the JSON "
              "that scripts/bench_accuracy.py wrote", file=sys.stderr)
        return 2
    rows, lines = [], []
    for name in args.scenes.split(","):
        if name not in B.SCENES or name not in base:
            print(f"error: scene {name!r} unknown or not in the baselines", file=sys.stderr)
            return 2
        if name == "bunny" and not B.BUNNY.is_dir():
            print("bunny: skipped, ../shared not found", file=sys.stderr)
            continue
        print(f"{name} ...", file=sys.stderr, flush=True)
        case = scene_case(name, args.seed)
        ms = base[name]["methods"]
        best = [max(ms[k]["ll_sdf" if k != "loggpis" else "ll_edf"][i]
                    for k in ("hgmm", "gpis", "loggpis") if k in ms) for i in range(7)]
        for t, c, lam in itertools.product(*GRID.values()):
            if lam == 0 and (t, c) != (2.0, 1.0):
                continue
            per = score(case, t, c, lam)
            rows.append(dict(scene=name, tuned=B.SCENES[name]["tuned"], min_thickness=t,
                             edge_gap=c, unseen_weight=lam, ll=[a for a, _, _ in per],
                             cov1=[b for _, b, _ in per], cov2=[x for _, _, x in per],
                             margin=min(a - bb for (a, _, _), bb in zip(per, best))))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(rows, indent=1))
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    lines.append("Least margin over the 7 bins of the mean LL to the best of hgmm, gpis, "
                 "loggpis (positive: above all three in every bin); 1-sigma coverage range "
                 "over the bins.\n")
    lines.append("| t_min / h | c | lambda | " + " | ".join(
        f"{s} ({'tuned' if B.SCENES[s]['tuned'] else 'held out'})" for s in scenes) + " |")
    lines.append("|---|---|---|" + "---|" * len(scenes))
    keys = list(dict.fromkeys((r["min_thickness"], r["edge_gap"], r["unseen_weight"])
                              for r in rows))
    for k in keys:
        cells = []
        for s in scenes:
            r = next(x for x in rows if x["scene"] == s and
                     (x["min_thickness"], x["edge_gap"], x["unseen_weight"]) == k)
            cells.append(f"{r['margin']:+.2f} ({min(r['cov1']):.2f}-{max(r['cov1']):.2f})")
        lines.append(f"| {k[0]:g} | {k[1]:g} | {k[2]:g} | " + " | ".join(cells) + " |")
    table = "\n".join(lines) + "\n"
    Path(args.out).with_suffix(".md").write_text(table)
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
