#!/usr/bin/env python
"""Bins in target per scene from ``scripts/bench_accuracy.py`` JSON files (issue 15):
1-sigma coverage within 0.68 +- 0.05, the central 95.45 % interval's coverage within
0.95 +- 0.03 (as printed, two decimals, band ends inside), gmmgp's mean log-likelihood above hgmm, gpis and
loggpis, gmmgp's RMSE below the tangent plane's; one row per file and scene.

Example::

    python scripts/bench_bins.py docs/field_bench/blend_before/bench_accuracy.json \\
        docs/field_bench/bench_accuracy.json
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fit_variance import best_baseline_ll  # noqa: E402


def bins_in_target(res) -> dict:
    """The four counts (of the scene's bins) for one scene's bench result."""
    g, ms = res["methods"]["gmmgp"], res["methods"]
    n = len(g["rmse_sdf"])
    # coverages as printed (two decimals), band ends inside: the closing notes' count
    return dict(
        cov1=sum(abs(round(c, 2) - 0.68) <= 0.05 + 1e-9 for c in g["cov1_sdf"]),
        cov2=sum(abs(round(c, 2) - 0.95) <= 0.03 + 1e-9 for c in g["cov2_sdf"]),
        ll=sum(g["ll_sdf"][i] > best_baseline_ll(ms, i) for i in range(n)),
        rmse=sum(g["rmse_sdf"][i] < ms["plane"]["rmse_sdf"][i] for i in range(n)), n=n)


def main(argv=None) -> int:
    paths = (argv if argv is not None else sys.argv[1:])
    if not paths:
        print("error: give one or more bench_accuracy.json files", file=sys.stderr)
        return 2
    runs = {}
    for p in paths:
        try:
            runs[p] = json.loads(Path(p).read_text())["results"]
        except (OSError, ValueError, KeyError, TypeError) as e:
            print(f"error: {p} is not a bench_accuracy JSON file ({type(e).__name__}); give "
                  "the file scripts/bench_accuracy.py --out wrote", file=sys.stderr)
            return 2
    print("| file | scene | 1 sigma | 2 sigma | LL above baselines | RMSE below plane |")
    print("|---|---|---|---|---|---|")
    for p, results in runs.items():
        for r in results:
            c = bins_in_target(r)
            print(f"| {p} | {r['scene']} | {c['cov1']}/{c['n']} | {c['cov2']}/{c['n']} | "
                  f"{c['ll']}/{c['n']} | {c['rmse']}/{c['n']} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
