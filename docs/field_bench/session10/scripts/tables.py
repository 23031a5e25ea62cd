#!/usr/bin/env python
"""docs/field.md 'Session 10' tables: RMSE main -> sphere vote with the plane reference,
and the sphere vote's coverages / LL, from two bench_accuracy.py JSON files."""
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[4] / "scripts"))
from bench_bins import bins_in_target  # noqa: E402

main, sph = (json.loads(Path(p).read_text())["results"] for p in sys.argv[1:3])
held = {"street": "tuned", "sphere": "tuned"}
print("| scene | gmmgp main (plane vote) | gmmgp sphere vote | plane reference | bins below plane main -> sphere |")
print("|---|---|---|---|---|")
for a, b in zip(main, sph):
    f = lambda r, m="gmmgp": " / ".join(f"{1000 * x:.1f}" for x in r["methods"][m]["rmse_sdf"])  # noqa
    print(f"| {a['scene']} ({held.get(a['scene'], 'held out')}) | {f(a)} | {f(b)} | {f(a, 'plane')} "
          f"| {bins_in_target(a)['rmse']} -> {bins_in_target(b)['rmse']} |")
print()
print("| scene | 1 sigma (sphere vote) | 2 sigma (sphere vote) | mean LL (sphere vote) | bins 1s / 2s / LL main -> sphere |")
print("|---|---|---|---|---|")
tot = [[0, 0, 0, 0], [0, 0, 0, 0]]
for a, b in zip(main, sph):
    g = b["methods"]["gmmgp"]
    ca, cb = bins_in_target(a), bins_in_target(b)
    for t, c in zip(tot, (ca, cb)):
        for i, k in enumerate(("cov1", "cov2", "ll", "rmse")):
            t[i] += c[k]
    print(f"| {b['scene']} | " + " / ".join(f"{x:.2f}" for x in g["cov1_sdf"]) + " | "
          + " / ".join(f"{x:.2f}" for x in g["cov2_sdf"]) + " | "
          + " / ".join(f"{x:+.2f}" for x in g["ll_sdf"])
          + f" | {ca['cov1']} / {ca['cov2']} / {ca['ll']} -> {cb['cov1']} / {cb['cov2']} / {cb['ll']} |")
print(f"\nTotals (1s / 2s / LL / RMSE bins of 42): main {tot[0]}, sphere vote {tot[1]}")
