"""CPU seconds per phase of one ``check_scan(align=True)`` (alignment plus its check).

Pairs: KITTI 000004 against the map of KITTI 000000 (the bench's perturbed guess,
noise 0.02) and the bench's synthetic street pair (noise 0.01). Each run is profiled
with cProfile on ``time.process_time`` (CPU seconds of all threads: numba's parallel
kernels count on both cores), after one unprofiled warm-up run on the loaded map (the
first run also fills the GMR prior's cell lists). Per phase: the cumulative CPU
seconds of the functions below (nested phases are included in their parents), medians
over ``--repeat`` runs; with ``--json`` the rows as JSON lines.

    PYTHONPATH=$PWD .venv/bin/python scripts/profile_check.py --cache /tmp/maps --repeat 3
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: (phase, file suffix, function name): cumulative CPU seconds of that function
PHASES = [
    ("check_scan (all)", "check.py", "check_scan"),
    ("  registration (_register)", "check.py", "_register"),
    ("    stages (_coarse_to_fine)", "check.py", "_coarse_to_fine"),
    ("      surface correction", "check.py", "_surface_correction"),
    ("      linearised IRLS", "check.py", "_linear_irls"),
    ("      cell factors", "check.py", "_factors_here"),
    ("    information at the solution", "check.py", "_information"),
    ("    degeneracy probes", "check.py", "_finite_information"),
    ("    jackknife", "check.py", "_cluster_consistency"),
    ("    map-error model", "check.py", "_map_error_covariance"),
    ("  near field for the check", "check.py", "_near_field_at"),
    ("  surface std (feet)", "check.py", "_surface_std"),
    ("  segments", "check.py", "_segments"),
    ("map predict (all calls)", "check.py", "_predict"),
    ("  GP field predict", "gp.py", "predict"),
    ("  far field components", "farfield.py", "components"),
    ("    far-field k-NN", "knn.py", "query"),
    ("    far-field IMLS kernel", "farfield.py", "_imls"),
    ("  blend variance model", "farfield.py", "calibrated_variance"),
]


def _phase_seconds(prof) -> dict:
    st = pstats.Stats(prof)
    out = {}
    for name, suffix, fn in PHASES:
        tot = 0.0
        for (file, _line, func), (_cc, _nc, _tt, ct, _callers) in st.stats.items():
            if func == fn and file.endswith(suffix):
                tot += ct
        out[name] = tot
    return out


def cached_map(path, build):
    """The map saved at ``path`` (a folder) when it exists, else ``build()``, saved there
    and loaded again (a freshly loaded map, as the CLI has it) when ``path`` is given."""
    import gmmgp_app as gm

    if path is not None and Path(path).exists():
        return gm.load_map(path)
    smap = build()
    if path is not None:
        smap.save(path)
        smap = gm.load_map(path)
    return smap


def kitti_pairs() -> dict:
    """KITTI scan i (0-5) -> (start, pose): the pose file's estimate perturbed by 0.3 m
    and 2 deg, bench_check's seeded perturbations (its --seed 0)."""
    from gmmgp_app.datasets.kitti import read_poses
    from scripts.bench_check import KITTI, _rot

    poses = read_poses(KITTI / "poses_gicp_estimated.txt")
    rng = np.random.default_rng(0)  # bench_check's perturbations (its --seed 0)
    pairs = {}
    for i in range(6):
        P = np.eye(4)
        P[:3] = poses[i]
        u, a = rng.normal(size=3), rng.normal(size=3)
        dT = np.eye(4)
        dT[:3, :3] = _rot(a, 2.0)
        dT[:3, 3] = 0.3 * u / np.linalg.norm(u)
        pairs[i] = (dT @ P, P)
    return pairs


def set_check_constants(ap, items) -> None:
    """``--set NAME=VALUE``: set module constants of gmmgp_app.check (Python literals)."""
    import ast

    import gmmgp_app.check as check

    for item in items:
        name, _, value = item.partition("=")
        if not hasattr(check, name):
            ap.error(f"gmmgp_app.check has no constant {name!r}")
        setattr(check, name, ast.literal_eval(value))


def _kitti(cache):
    import gmmgp_app as gm
    from gmmgp_app.datasets import read_scan
    from scripts.bench_check import KITTI

    smap = cached_map(Path(cache) / "kitti0" if cache else None,
                      lambda: gm.build_map(read_scan(KITTI / "velodyne" / "000000.bin")))
    return smap, kitti_pairs(), \
        lambda i: read_scan(KITTI / "velodyne" / f"{i:06d}.bin").points


def _synthetic(cache):
    import gmmgp_app as gm
    from gmmgp_app.synth import scan_scene
    from scripts.bench_check import _rot

    first, _ = scan_scene("street", density=0.1, seed=0, scene_params=dict(length=36.0))
    smap = cached_map(Path(cache) / "synth" if cache else None, lambda: gm.build_map(first))
    second, _ = scan_scene("street_van", density=0.1, seed=1, scene_params=dict(length=36.0),
                           lane_y=-1.5)
    T = np.eye(4)
    T[:3, :3] = _rot((0.3, -0.5, 0.8), 0.5)
    T[:3, 3] = (0.03, -0.035, 0.02)
    moved = (second.points - T[:3, 3]) @ T[:3, :3]
    return smap, moved, T


def run(name, smap, pts, init, truth, noise, repeat, tag):
    from gmmgp_app.check import check_scan
    from scripts.bench_check import _diff

    check_scan(pts, smap, align=True, init=init, noise=noise)  # warm-up, not counted
    rows = []
    for k in range(repeat):
        prof = cProfile.Profile(time.process_time)
        c0, t0 = time.process_time(), time.perf_counter()
        prof.enable()
        res = check_scan(pts, smap, align=True, init=init, noise=noise)
        prof.disable()
        cpu, wall = time.process_time() - c0, time.perf_counter() - t0
        deg, m = _diff(truth, res.transform)
        rows.append(dict(tag=tag, pair=name, rep=k, cpu=cpu, wall=wall,
                         align_wall=res.summary["seconds"]["align"],
                         phases=_phase_seconds(prof), deg=deg, mm=1e3 * m,
                         iterations=res.iterations, load=os.getloadavg()[0],
                         transform=res.transform.tolist()))
    return rows


def table(rows) -> str:
    pairs = sorted({r["pair"] for r in rows})
    out = ["| phase | " + " | ".join(pairs) + " |", "|---|" + "---|" * len(pairs)]
    med = lambda sel: float(np.median(sel)) if sel else float("nan")  # noqa: E731
    out.append("| CPU s (process_time, whole call) | " + " | ".join(
        f"{med([r['cpu'] for r in rows if r['pair'] == p]):.2f}" for p in pairs) + " |")
    out.append("| wall s | " + " | ".join(
        f"{med([r['wall'] for r in rows if r['pair'] == p]):.2f}" for p in pairs) + " |")
    for name, _, _ in PHASES:
        out.append(f"| {name} | " + " | ".join(
            f"{med([r['phases'][name] for r in rows if r['pair'] == p]):.2f}"
            for p in pairs) + " |")
    out.append("| error vs truth / pose file, deg / mm | " + " | ".join(
        f"{rows[[r['pair'] for r in rows].index(p)]['deg']:.5f} / "
        f"{rows[[r['pair'] for r in rows].index(p)]['mm']:.3f}" for p in pairs) + " |")
    out.append("| load (1 min) | " + " | ".join(
        f"{min(r['load'] for r in rows if r['pair'] == p):.1f}-"
        f"{max(r['load'] for r in rows if r['pair'] == p):.1f}" for p in pairs) + " |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cache", default=None, help="folder of the saved maps (built there once)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--scans", default="4", help="KITTI scans (comma separated; '' for none)")
    ap.add_argument("--no-synthetic", action="store_true")
    ap.add_argument("--tag", default="")
    ap.add_argument("--json", default=None, help="append the rows (JSON lines) to this file")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="set a module constant of gmmgp_app.check first (a Python literal), "
                         "e.g. --set REUSE_NEIGHBOURS=False")
    args = ap.parse_args(argv)
    set_check_constants(ap, args.set)
    rows = []
    if args.scans:
        smap, pairs, points = _kitti(args.cache)
        for i in (int(v) for v in args.scans.split(",")):
            init, P = pairs[i]
            rows += run(f"kitti {i:06d}", smap, points(i), init, P, 0.02, args.repeat, args.tag)
    if not args.no_synthetic:
        smap, moved, T = _synthetic(args.cache)
        rows += run("synthetic", smap, moved, np.eye(4), T, 0.01, args.repeat, args.tag)
    if args.json:
        with open(args.json, "a") as f:
            for r in rows:
                f.write(json.dumps(r) + "\n")
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
