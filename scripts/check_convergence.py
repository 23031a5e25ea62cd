"""How much check_scan's registration depends on where it starts.

For each pair (the bench's synthetic street pair, KITTI scans against the map of
000000 from the bench's perturbed guesses) the registration runs from the guess and
from ``--starts`` more guesses, each the guess moved by ``--dt`` m and ``--dr`` deg in
seeded random directions (about the guess's points' centre). Prints one JSON line per
pair: the rotation (deg) and translation (mm, at the map origin) of every result
against the first one's, their largest pairwise spread, each result's error against
the truth (the synthetic pair) or the pose file (KITTI), iterations, map predictions
(calls, points) and CPU seconds (``time.process_time``, all threads) per run.
``--set NAME=VALUE`` sets a module constant of gmmgp_app.check first.

    PYTHONPATH=$PWD .venv/bin/python scripts/check_convergence.py --cache /tmp/maps \\
        --kitti 2,4 --starts 4
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _moved(T, pts, dt, dr, rng):
    """``T`` moved by ``dt`` m and ``dr`` deg in random directions about the centre of
    ``T``'s points."""
    from scripts.bench_check import _rot

    c = pts @ T[:3, :3].T + T[:3, 3]
    c = c.mean(0)
    u = rng.normal(size=3)
    a = rng.normal(size=3)
    D = np.eye(4)
    D[:3, :3] = _rot(a, dr)
    D[:3, 3] = c - D[:3, :3] @ c + dt * u / np.linalg.norm(u)
    return D @ T


def sweep(name, smap, pts, init, ref, noise, starts, dt, dr, seed, tag):
    from gmmgp_app.check import check_scan
    from scripts.bench_check import _diff, _TimedMap

    rng = np.random.default_rng(seed)
    guesses = [init] + [_moved(init, pts, dt, dr, rng) for _ in range(starts)]
    check_scan(pts, smap, align=True, init=init, noise=noise)  # warm-up (prior cells)
    tm = _TimedMap(smap)
    runs = []
    for g in guesses:
        tm.reset()
        c = time.process_time()
        r = check_scan(pts, tm, align=True, init=g, noise=noise)
        runs.append(dict(T=r.transform, cpu=time.process_time() - c, calls=tm.calls,
                         points=tm.points, iterations=r.iterations, converged=r.converged))
    Ts = [r["T"] for r in runs]
    vs_first = [_diff(Ts[0], T) for T in Ts[1:]]
    pair = [_diff(a, b) for i, a in enumerate(Ts) for b in Ts[i + 1:]]
    err = [_diff(ref, T) for T in Ts]
    out = dict(tag=tag, pair=name, dt_m=dt, dr_deg=dr,
               spread_deg=max(p[0] for p in pair), spread_mm=1e3 * max(p[1] for p in pair),
               vs_first_deg=[v[0] for v in vs_first],
               vs_first_mm=[1e3 * v[1] for v in vs_first],
               error_deg=[e[0] for e in err], error_mm=[1e3 * e[1] for e in err],
               error_deg_median=float(np.median([e[0] for e in err])),
               cpu=[r["cpu"] for r in runs], calls=[r["calls"] for r in runs],
               points=[r["points"] for r in runs], iterations=[r["iterations"] for r in runs],
               converged=[r["converged"] for r in runs], load=os.getloadavg()[0])
    print(json.dumps(out), flush=True)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cache", default=None, help="folder of the saved maps (built there once)")
    ap.add_argument("--kitti", default="4", help="KITTI scans (comma separated; '' for none)")
    ap.add_argument("--no-synthetic", action="store_true")
    ap.add_argument("--starts", type=int, default=4)
    ap.add_argument("--dt", type=float, default=0.001, help="start moved by this (m)")
    ap.add_argument("--dr", type=float, default=0.01, help="and by this (deg)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tag", default="")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    args = ap.parse_args(argv)
    from scripts.profile_check import _kitti, _synthetic, set_check_constants

    set_check_constants(ap, args.set)
    if not args.no_synthetic:
        smap, moved, T = _synthetic(args.cache)
        sweep("synthetic", smap, moved, np.eye(4), T, 0.01, args.starts, args.dt, args.dr,
              args.seed, args.tag)
    if args.kitti:
        smap, pairs, points = _kitti(args.cache)
        for i in (int(v) for v in args.kitti.split(",")):
            init, P = pairs[i]
            sweep(f"kitti {i:06d}", smap, points(i), init, P, 0.02, args.starts, args.dt,
                  args.dr, args.seed, args.tag)
    return 0


if __name__ == "__main__":
    sys.exit(main())
