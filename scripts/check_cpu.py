"""CPU time of check_scan on KITTI scans against the map of scan 000000 (JSON lines).

The pairs of scripts/bench_check.py (each scan starting from the pose file's estimate
perturbed by 0.3 m and 2 deg, the same seeded perturbations); per repeat the alignment
and the check only at its result, both as wall-clock and as ``time.process_time``
(CPU seconds of all threads: on a machine shared with other jobs wall-clock says
little, CPU time is the work). Repeat 0 is the first alignment on the freshly loaded
map (it also builds the GMR prior's cell lists for the cells the scan enters). Run the
same command from two worktrees alternately to compare them; ``--summary FILE``
prints the medians of a file of such lines by scan and tag.

    PYTHONPATH=$PWD .venv/bin/python scripts/check_cpu.py --map out/kitti0 --scans 2,4 \\
        --repeat 3 --tag branch >> out/cpu.jsonl
    .venv/bin/python scripts/check_cpu.py --summary out/cpu.jsonl
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def summary(path) -> int:
    rows = [json.loads(line) for line in open(path) if line.strip()]
    groups = collections.defaultdict(list)
    for r in rows:
        groups[(r["scan"], r["tag"])].append(r)
    print("| scan | tag | runs | align CPU s, first / later | check CPU s | align wall s | "
          "deg / mm vs pose file | load |")
    print("|---|---|---|---|---|---|---|---|")
    for (scan, tag), v in sorted(groups.items()):
        def med(sel, key):
            return float(np.median([x[key] for x in sel])) if sel else float("nan")
        first = [x for x in v if x["rep"] == 0]
        later = [x for x in v if x["rep"] > 0]
        print(f"| {scan:06d} | {tag} | {len(v)} | {med(first, 'align_cpu'):.2f} / "
              f"{med(later, 'align_cpu'):.2f} | {med(v, 'check_cpu'):.2f} | "
              f"{med(v, 'align_wall'):.2f} | {v[0]['deg']:.4f} / {v[0]['mm']:.2f} | "
              f"{min(x['load'] for x in v):.1f}-{max(x['load'] for x in v):.1f} |")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--map", default=None, help="map directory of scan 000000 (built and "
                                                "saved there if absent)")
    ap.add_argument("--scans", default="0,1,2,3,4,5")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--tag", default="")
    ap.add_argument("--summary", default=None, help="print the medians of this file")
    args = ap.parse_args(argv)
    if args.summary:
        return summary(args.summary)
    import gmmgp_app as gm
    from gmmgp_app.check import check_scan
    from gmmgp_app.datasets import read_scan
    from scripts.bench_check import KITTI, _diff
    from scripts.profile_check import cached_map, kitti_pairs

    inits = kitti_pairs()
    smap = cached_map(args.map or None,   # built and saved there if absent
                      lambda: gm.build_map(read_scan(KITTI / "velodyne" / "000000.bin")))
    for i in (int(v) for v in args.scans.split(",")):
        scan = read_scan(KITTI / "velodyne" / f"{i:06d}.bin")
        init, P = inits[i]
        for k in range(args.repeat):
            t, c = time.perf_counter(), time.process_time()
            res = check_scan(scan.points, smap, align=True, init=init, noise=0.02)
            wa, ca = time.perf_counter() - t, time.process_time() - c
            t, c = time.perf_counter(), time.process_time()
            check_scan(scan.points, smap, init=res.transform, noise=0.02)
            wc, cc = time.perf_counter() - t, time.process_time() - c
            deg, m = _diff(P, res.transform)
            print(json.dumps(dict(tag=args.tag, scan=i, rep=k, align_wall=wa, align_cpu=ca,
                                  check_wall=wc, check_cpu=cc, deg=deg, mm=1e3 * m,
                                  iterations=res.iterations, load=os.getloadavg()[0])),
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
