"""Where the HGMM stage's time goes: every EM fit of ``fit_hgmm`` on a scan, per level.

Reads a scan, resolves the automatic values and prepares the training rows as
``gmmgp run`` does, then fits the hierarchy ``--repeat`` times and reports, for the
last fit, each level's fits (rows, tied groups, components, EM iterations, wall and
CPU seconds of the thread that ran it, whether it ran wide: its E-step on all numba
threads) and the whole fit's wall and process CPU seconds. Used for docs/speed.md
"Session 8".

    PYTHONPATH=$PWD .venv/bin/python scripts/profile_hgmm.py SCAN.npz --json out/hgmm.json
    NUMBA_NUM_THREADS=1 ... scripts/profile_hgmm.py SCAN.npz    # one thread: the work
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scan", help="a scan gmmgp run reads (.npz, .ply, .las, ...)")
    ap.add_argument("--repeat", type=int, default=2, help="fits (the first loads numba's "
                    "caches; the last is reported, every one's totals listed)")
    ap.add_argument("--json", help="write the report here")
    args = ap.parse_args(argv)

    import numpy as np

    from gmmgp_app import pipeline
    from gmmgp_app.config import MappingConfig
    from gmmgp_app.datasets import read_scan
    from gmmgp_app.stages import hgmm, prepare

    scan = read_scan(args.scan)
    cfg, _ = pipeline.resolve_config(MappingConfig(), scan)
    data = prepare.prepare(scan, cfg)
    fits = []
    real = hgmm.fit_gmm

    def timed(X, k, **kw):
        t, c = time.perf_counter(), time.thread_time()
        out = real(X, k, **kw)
        gptr = kw.get("group_ptr")
        fits.append(dict(rows=len(X), groups=None if gptr is None else len(gptr) - 1,
                         components=int(k), em_iter=out[1]["n_iter"],
                         wide=bool(kw.get("parallel")), wall=time.perf_counter() - t,
                         cpu_thread=time.thread_time() - c,
                         thread=threading.get_ident()))
        return out

    hgmm.fit_gmm = timed
    import numba

    threads = int(numba.get_num_threads())
    totals = []
    for _ in range(args.repeat):
        fits.clear()
        t, c = time.perf_counter(), time.process_time()
        h = hgmm.fit_hgmm(data, cfg.hgmm)
        totals.append(dict(wall=time.perf_counter() - t, cpu=time.process_time() - c))
    # fits in call order: the first level's one fit, then each level's (level_fits)
    per_level, i = [], 0
    for lev, st in enumerate(h.info["level_fits"]):
        lf = fits[i:i + st["n_fits"]]
        i += st["n_fits"]
        per_level.append(dict(
            level=lev, fits=len(lf), wide=sum(f["wide"] for f in lf),
            rows=sum(f["rows"] for f in lf), em_iter=sum(f["em_iter"] for f in lf),
            cpu_thread=sum(f["cpu_thread"] for f in lf),
            largest=max(lf, key=lambda f: f["cpu_thread"]) if lf else None))
    print(f"{'level':>5} {'fits':>5} {'wide':>4} {'rows':>8} {'EM it':>6} {'CPU s':>7}  "
          "largest fit (rows, groups, K, iterations, CPU s)")
    for p in per_level:
        b = p["largest"] or {}
        print(f"{p['level']:>5} {p['fits']:>5} {p['wide']:>4} {p['rows']:>8} "
              f"{p['em_iter']:>6} {p['cpu_thread']:>7.3f}  ({b.get('rows')}, "
              f"{b.get('groups')}, {b.get('components')}, {b.get('em_iter')}, "
              f"{b.get('cpu_thread', float('nan')):.3f})")
    print("fit_hgmm wall / CPU s: " + ", ".join(f"{t['wall']:.2f} / {t['cpu']:.2f}"
                                                 for t in totals)
          + f"; load {os.getloadavg()[0]:.2f}; numba threads {threads}; "
          f"leaves {h.leaves.n_components}")
    if args.json:
        Path(args.json).write_text(json.dumps(dict(
            scan=str(args.scan), totals=totals, levels=per_level, fits=fits,
            leaves=int(h.leaves.n_components), load=os.getloadavg(),
            numba_threads=threads,
            leaf_means_sha256=__import__("hashlib").sha256(
                np.ascontiguousarray(h.leaves.means).tobytes()).hexdigest()), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
