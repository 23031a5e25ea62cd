"""Mesh saved maps with a cheap lattice field and the vertices projected onto the map's
zero level, at several voxels, and score each mesh with bench_peers' metrics.

    PYTHONPATH=$PWD .venv/bin/python scripts/surface_projection_study.py \\
        street=MAP_DIR:SCAN.npz:MESH.ply kitti=MAP_DIR:SCAN.npz: \\
        --modes map,far,far+p1 --factors 0.6,1.0 [--out out/study.json]

Modes: ``map`` (the lattice evaluated with the map's mean, linear interpolation: main's
mesh), ``far`` (the lattice with the far field's mean alone, no projection), ``X+pN``
(lattice field X, then N Newton steps of every vertex onto the map's zero level along
the map's gradient, clamped to half a voxel). Each mesh: wall and CPU seconds of the
surface extraction, bench_peers' metrics (accuracy of area-weighted mesh samples to the
exact mesh, KITTI: to its scan; completeness within 1/2/5 cm; chamfer), the fraction of
boundary edges, and the map's |mean| at a seeded sample of 20k vertices (how far from
the map's zero level the vertices lie). A case with no reference mesh is scored
against its scan points. h_t is read from the map's summary.
"""
import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_peers import mesh_metrics  # noqa: E402
from surface_voxel_study import boundary_fraction, load_case  # noqa: E402

from gmmgp_app.stages.surface import extract_surface  # noqa: E402


def cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def lattice_field(m, name: str):
    if name == "map":
        return m.predict_mean
    if name == "far":
        return lambda x: m.far.components(x)["mean"]
    raise ValueError(f"unknown lattice field {name!r}")


def mesh_with(m, voxel: float, mode: str, clamp: float = 0.5):
    lat, _, p = mode.partition("+p")
    steps = int(p) if p else 0
    return extract_surface(m.predict, m.seed_points, voxel, max_std=m.config.surface.max_std,
                           reach=m.surface_reach(), predict_mean=lattice_field(m, lat),
                           project=(lambda x: m.predict(x, return_grad=True)) if steps
                           else None, project_steps=max(steps, 1), project_clamp=clamp)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("cases", nargs="+", help="TAG=MAP_DIR:SCAN.npz:REF.ply (REF may be empty)")
    ap.add_argument("--factors", default="0.6,0.8,1.0,1.2", help="voxels in units of h_t")
    ap.add_argument("--modes", default="map,far,far+p1,far+p2")
    ap.add_argument("--clamp", type=float, default=0.5, help="largest step, in voxels")
    ap.add_argument("--samples", type=int, default=200_000)
    ap.add_argument("--no-metrics", action="store_true", help="time only")
    ap.add_argument("--out", default=None, help="JSON of every result (appended per mesh)")
    args = ap.parse_args(argv)
    res = {}
    if args.out and Path(args.out).is_file():
        res = json.loads(Path(args.out).read_text())
    for case in args.cases:
        tag, m, pts, ref, ht = load_case(case)
        m.predict(m.seed_points[:1000])   # lazy structures (GMR cells, k-NN grid) built once
        for fac in (float(x) for x in args.factors.split(",")):
            for mode in args.modes.split(","):
                load = os.getloadavg()[0]
                t, c = time.perf_counter(), cpu_seconds()
                mesh = mesh_with(m, fac * ht, mode, args.clamp)
                dt, dc = time.perf_counter() - t, cpu_seconds() - c
                r = {} if args.no_metrics else mesh_metrics(
                    mesh.vertices + m.offset, mesh.faces, pts, ref, args.samples, 0)
                rng = np.random.default_rng(0)
                sv = mesh.vertices[rng.choice(len(mesh.vertices),
                                              min(20000, len(mesh.vertices)), replace=False)]
                resid = np.abs(m.predict_mean(sv)) / (fac * ht)
                r.update(surface_s=dt, surface_cpu_s=dc, voxel=fac * ht, h_t=ht,
                         factor=fac, mode=mode, vertices_n=len(mesh.vertices),
                         faces_n=len(mesh.faces),
                         boundary_edge_frac=boundary_fraction(mesh.faces),
                         resid_over_voxel_median=float(np.median(resid)),
                         resid_over_voxel_p99=float(np.quantile(resid, 0.99)),
                         resid_over_voxel_max=float(resid.max()),
                         load=load, load_end=os.getloadavg()[0])
                res[f"{tag} {fac} {mode}"] = r
                print(tag, fac, mode, json.dumps(r), flush=True)
                if args.out:
                    Path(args.out).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
