#!/usr/bin/env python
"""Speed and peak memory of build_map on a ~1.3M-point synthetic street (issue 4 item 6).

The scan is simulated once and saved; a fresh Python process then reads it and
builds the map, so that its peak RSS (VmHWM) is the mapper's alone. Repeats give
medians. Target on the 2-core reference machine: under 60 s, peak RSS under 4 GB.

Examples::

    python scripts/bench_speed.py                  # density 1 (~1.28M points), 3 repeats
    python scripts/bench_speed.py --density 0.25 --repeats 1
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CHILD = r"""
import json, sys, time
t0 = time.perf_counter()
import gmmgp_app as gm
cfg = gm.MappingConfig().replace("prepare.subsample_rate", float(sys.argv[2]))
cfg = cfg.with_overrides(sys.argv[4:])
t_import = time.perf_counter() - t0
t1 = time.perf_counter()
scan = gm.read_scan(sys.argv[1])
t_read = time.perf_counter() - t1
t2 = time.perf_counter()
smap = gm.build_map(scan, cfg, method=sys.argv[3])
t_build = time.perf_counter() - t2
hwm = next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmHWM"))
print(json.dumps({"n_points": len(scan), "import_s": t_import, "read_s": t_read,
                  "build_s": t_build, "stages_s": smap.summary["seconds"],
                  "counts": smap.summary["counts"], "peak_rss_mb": hwm / 1024}))
"""


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--density", type=float, default=1.0)
    p.add_argument("--train-rate", type=float, default=0.1)
    p.add_argument("--method", default="gmmgp")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--set", action="append", default=[])
    p.add_argument("--out", default="out/bench/bench_speed.json")
    args = p.parse_args(argv)

    from gmmgp_app.synth import scan_scene
    from gmmgp_app.synth.io import save_scan_npz

    with tempfile.TemporaryDirectory() as tmp:
        scan, _ = scan_scene("street", density=args.density, seed=0)
        path = Path(tmp) / "street.npz"
        save_scan_npz(path, scan.points, scan.origins)
        del scan
        runs = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            r = subprocess.run([sys.executable, "-c", CHILD, str(path), str(args.train_rate),
                                args.method, *args.set], capture_output=True, text=True,
                               check=True)
            res = json.loads(r.stdout.strip().splitlines()[-1])
            res["wall_s"] = time.perf_counter() - t0
            runs.append(res)
            print(f"build {res['build_s']:.1f} s, peak RSS {res['peak_rss_mb']:.0f} MB, "
                  f"stages {', '.join(f'{k} {v:.1f}' for k, v in res['stages_s'].items())}")
    med = {k: statistics.median(r[k] for r in runs)
           for k in ("build_s", "read_s", "peak_rss_mb", "wall_s")}
    stages = {k: statistics.median(r["stages_s"][k] for r in runs) for k in runs[0]["stages_s"]}
    out = {"n_points": runs[0]["n_points"], "train_rate": args.train_rate,
           "method": args.method, "overrides": args.set, "median": med,
           "median_stage_seconds": stages, "targets": {"build_s": 60, "peak_rss_mb": 4096},
           "meets_targets": med["build_s"] < 60 and med["peak_rss_mb"] < 4096, "runs": runs}
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=2))
    print(json.dumps({k: out[k] for k in ("n_points", "median", "median_stage_seconds",
                                          "meets_targets")}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
