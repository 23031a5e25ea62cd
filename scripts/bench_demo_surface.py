#!/usr/bin/env python
"""Surface completeness and accuracy on the bundled demo scan, for config variants.

The demo (assets/demo_street.npz) is a simulated mobile-mapping scan of the
synthetic street with its exact mesh (assets/demo_street_mesh.ply). For each
variant the map is built, its surface extracted (default 5 cm voxels) and scored:

* completeness: of 400k points sampled on the exact mesh, those within 5 cm of a
  scan point (the observed surface) that have a mesh vertex within one voxel;
* accuracy: |exact signed distance| at the mesh vertices (median, RMS, share > 5 cm);
* the build and surface times and the training hit points.

Examples
--------
    python scripts/bench_demo_surface.py
    python scripts/bench_demo_surface.py --variant voxel10cm:prepare.subsample_voxel=0.1
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--variant", action="append", default=[],
                    help="NAME:key=value[,key=value] (repeatable); 'default' always runs")
    ap.add_argument("--samples", type=int, default=400_000)
    ap.add_argument("--out", default=str(REPO / "out" / "bench" / "bench_demo_surface.json"))
    args = ap.parse_args(argv)
    variants = {"default": []}
    for v in args.variant or ["rate65:prepare.subsample_rate=0.65",
                              "voxel10cm:prepare.subsample_voxel=0.1"]:
        name, _, sets = v.partition(":")
        variants[name] = [s for s in sets.split(",") if s]

    import open3d as o3d
    from scipy.spatial import cKDTree

    import gmmgp_app as gm
    from gmmgp_app.datasets import read_scan
    from gmmgp_app.synth import make_scene

    scan = read_scan(REPO / "assets" / "demo_street.npz")
    mesh = o3d.io.read_triangle_mesh(str(REPO / "assets" / "demo_street_mesh.ply"))
    o3d.utility.random.seed(0)
    gt = np.asarray(mesh.sample_points_uniformly(number_of_points=args.samples).points)
    near, _ = cKDTree(scan.points + scan.offset).query(gt)
    observed = gt[near < 0.05] - scan.offset
    sdf = make_scene("street").sdf
    res = {"n_scan_points": len(scan), "n_observed_samples": len(observed), "variants": {}}
    for name, sets in variants.items():
        cfg = gm.MappingConfig().with_overrides(sets) if sets else gm.MappingConfig()
        t = time.perf_counter()
        smap = gm.build_map(scan, cfg)
        t_build = time.perf_counter() - t
        t = time.perf_counter()
        surf = smap.extract_surface()
        t_surf = time.perf_counter() - t
        h = cfg.surface.voxel_size
        dv, _ = cKDTree(surf.vertices).query(observed)
        err = np.abs(sdf(surf.vertices + scan.offset))
        r = {"set": sets, "hit_points": smap.summary["counts"]["prepare"]["hit_points"],
             "gp_points": smap.summary["counts"]["gmr"]["gp_points"],
             "build_seconds": t_build, "surface_seconds": t_surf,
             "vertices": len(surf.vertices),
             "completeness": float(np.mean(dv < h)),
             "vertex_error_median_mm": float(np.median(err) * 1e3),
             "vertex_error_rms_mm": float(np.sqrt(np.mean(err ** 2)) * 1e3),
             "vertex_error_over_5cm": float(np.mean(err > 0.05))}
        res["variants"][name] = r
        print(f"{name}: {json.dumps(r)}", flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
