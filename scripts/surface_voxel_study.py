"""Mesh saved maps at voxels 0.6, 0.8 and 1.0 h_t with the map's reach (its 0.6 h_t
voxel's) and score each mesh with bench_peers' metrics (JSON lines on stdout).

    PYTHONPATH=$PWD .venv/bin/python scripts/surface_voxel_study.py \\
        street=MAP_DIR:SCAN.npz:MESH.ply kitti=MAP_DIR:SCAN.npz: [--out out/study.json]

A case with no reference mesh (KITTI) is scored against its scan points. Each map must
have its automatic surface voxel (0.6 h_t); h_t is read from its summary.
"""
import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_peers import mesh_metrics, read_ref_mesh  # noqa: E402

from gmmgp_app.pipeline import load_map  # noqa: E402


def boundary_fraction(faces) -> float:
    """Fraction of the mesh's edges used by one face only."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, c = np.unique(e[:, 0].astype(np.int64) * (int(faces.max()) + 1) + e[:, 1],
                     return_counts=True)
    return float((c == 1).sum() / len(c))


def load_case(case: str):
    """``TAG=MAP_DIR:SCAN.npz:REF.ply`` (REF may be empty) -> tag, the loaded map, the scan's
    points, the reference mesh (None: score against the points) and the map's h_t."""
    tag, _, spec = case.partition("=")
    mp, scan, refp = spec.split(":")
    m = load_map(mp)
    ref = read_ref_mesh(refp) if refp else None
    return tag, m, np.load(scan)["points"], ref, m.summary["auto"]["train_spacing"]["value"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("cases", nargs="+", help="TAG=MAP_DIR:SCAN.npz:REF.ply (REF may be empty)")
    ap.add_argument("--factors", default="0.6,0.8,1.0", help="voxels in units of h_t")
    ap.add_argument("--samples", type=int, default=200_000)
    ap.add_argument("--out", default=None, help="JSON of every result")
    args = ap.parse_args(argv)
    res = {}
    for case in args.cases:
        tag, m, pts, ref, ht = load_case(case)
        if not np.isclose(m.config.surface.voxel_size, 0.6 * ht):
            print(f"{tag}: the map's voxel is not its automatic 0.6 h_t; skipped", file=sys.stderr)
            continue
        for fac in (float(x) for x in args.factors.split(",")):
            t = time.perf_counter()
            mesh = m.extract_surface(fac * ht)
            dt = time.perf_counter() - t
            r = mesh_metrics(mesh.vertices + m.offset, mesh.faces, pts, ref, args.samples, 0)
            r.update(surface_s=dt, voxel=fac * ht, h_t=ht, reach=m.surface_reach(),
                     boundary_edge_frac=boundary_fraction(mesh.faces),
                     load=os.getloadavg()[0])
            res[f"{tag} {fac}"] = r
            print(tag, fac, json.dumps(r), flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
