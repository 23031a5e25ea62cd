#!/usr/bin/env python
"""Accuracy of the SDF on synthetic streets with an exact SDF (the paper's protocol).

Train on 10 % of a simulated mobile-mapping scan; query points within 0.5 m of the
observed surfaces; RMSE and mean predictive log-likelihood binned by the query's
distance to the training points, for

* ``gmmgp``: HGMM prior + local GPs (the paper's method),
* ``hgmm``: Gaussian mixture regression alone,
* ``plane``: no learning - the signed distance to the tangent plane of the nearest
  training point (a strong local reference near the data; its log-likelihood uses
  the sensor noise as a constant variance, so it is only indicative).

Writes ``out/bench/bench_accuracy.json`` and a markdown table next to it.

Examples::

    python scripts/bench_accuracy.py                       # street and street2, density 0.1
    python scripts/bench_accuracy.py --scenes street --density 0.2 --set gp.d_m=0.01
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

import gmmgp_app as gm
from gmmgp_app.evaluation import (DEFAULT_BINS, Reference, binned_metrics, evaluate_field,
                                  sample_queries)
from gmmgp_app.synth import scan_scene


def run_scene(name: str, density: float, seed: int, n_queries: int, cfg) -> dict:
    scan, scene = scan_scene(name, density=density, seed=seed)
    data = gm.prepare(scan, cfg)
    rng = np.random.default_rng(seed + 1)
    queries = sample_queries(data.points, data.normals, n_queries, max_distance=0.5, rng=rng)
    ref = Reference.from_sdf(scene.sdf, f"exact SDF of '{name}'")
    out = {"scene": name, "n_scan_points": len(scan), "n_train_points": len(data.points),
           "n_queries": n_queries, "methods": {}}
    for method in ("hgmm", "gmmgp"):
        t0 = time.perf_counter()
        smap = gm.build_map(scan, cfg, method=method)
        t_train = time.perf_counter() - t0
        t0 = time.perf_counter()
        metrics = evaluate_field(smap.predict, ref, queries, data.points)
        t_test = time.perf_counter() - t0
        metrics.update(train_seconds=t_train, test_seconds=t_test,
                       stage_seconds=smap.summary["seconds"], counts=smap.summary["counts"])
        out["methods"][method] = metrics
    # The tangent-plane reference.
    dist, i = cKDTree(data.points).query(queries)
    plane = np.einsum("ij,ij->i", queries - data.points[i], data.normals[i])
    noise_var = 0.008 ** 2
    out["methods"]["plane"] = binned_metrics(plane, np.full(len(plane), noise_var),
                                             ref.sdf(queries), dist)
    return out


def markdown(results: list) -> str:
    bins = [f"{a:.2f}-{b:.2f}" for a, b in zip(DEFAULT_BINS[:-1], DEFAULT_BINS[1:])]
    lines = []
    for r in results:
        lines.append(f"\n**{r['scene']}** ({r['n_scan_points']:,} scan points, "
                     f"{r['n_train_points']:,} training points, {r['n_queries']:,} queries)\n")
        lines.append("| method | metric | " + " | ".join(bins) + " m |")
        lines.append("|---|---|" + "---|" * len(bins))
        for m, met in r["methods"].items():
            lines.append(f"| {m} | RMSE (m) | " + " | ".join(f"{v:.4f}" for v in met["rmse_sdf"])
                         + " |")
            lines.append(f"| {m} | mean log-lik | " + " | ".join(f"{v:+.2f}" for v in
                                                                  met["ll_sdf"]) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", default="street,street2")
    p.add_argument("--density", type=float, default=0.1, help="scan density (1 = ~1.3M points)")
    p.add_argument("--train-rate", type=float, default=0.1, help="fraction used for training")
    p.add_argument("--queries", type=int, default=30000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", action="append", default=[], help="config override")
    p.add_argument("--out", default="out/bench/bench_accuracy.json")
    args = p.parse_args(argv)
    cfg = gm.MappingConfig().replace("prepare.subsample_rate", args.train_rate)
    cfg = cfg.with_overrides(args.set)
    results = [run_scene(s, args.density, args.seed, args.queries, cfg)
               for s in args.scenes.split(",")]
    table = markdown(results)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"config": cfg.to_dict(), "bins": list(DEFAULT_BINS),
                               "results": results}, indent=2, default=float))
    out.with_suffix(".md").write_text(table)
    print(table)
    print(f"wrote {out} and {out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
