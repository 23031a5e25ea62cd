"""The sparse cases' surface (issue 16): its CPU, where the mesh lies relative to the data,
and how accurate each part is, as a function of the voxel and of how far from the data the
surface is followed.

    PYTHONPATH=$PWD .venv/bin/python scripts/sparse_surface_study.py \\
        street10=MAP_DIR:SCAN.npz:MESH.ply kitti=MAP_DIR:SCAN.npz: \\
        --voxels 0.6,0.8,1.0,1.5 --extents 0.6,0.3 [--repeats 1] --out out/sparse.json

Each case is a map saved by ``gmmgp run`` (its folder), the scan it was made from and the
exact mesh (empty for a real scan: KITTI is scored against its scan points). For every
voxel factor ``f`` (voxel = f h_t, h_t the map's training spacing) and extent factor ``g``
(``surface.extent_cell`` = g h_t: the seeds, one scan point per cell of g h_t / 2, and the
reach ``(sqrt(3)/2) g h_t + s_seed`` around them, docs/speed.md 'Fourth pass' / 'Seventh
pass') the map is meshed with its own lattice field and settings otherwise, and we record:

- ``surface_cpu_s`` / ``surface_wall_s``: the extraction's CPU seconds (all threads,
  ``resource.getrusage``) and wall seconds (median of ``--repeats``, every run listed);
- bench_peers' metrics (``mesh_metrics``: accuracy of 200k area-weighted mesh samples to the
  exact mesh / the scan, completeness of the observed exact surface / scan points within
  1/2/5 cm, chamfer);
- ``bins``: the mesh binned by the distance to the nearest scan point (< 5 cm, 5-20 cm,
  20-50 cm, > 50 cm): its faces (counted by centroid) and area there, and the accuracy of
  the area-weighted samples falling there (mean / RMSE / p95 of the distance to the exact
  mesh; for KITTI the distance to the scan, which is the bin's own distance);
- the boundary-edge fraction (holes' rims).

``--trims`` also scores each mesh with the faces further than T from the scan (or the
reach, from the scan points or from the seeds, the latter timed) removed: an emulation of
a cap on how far coarse cells carry the mesh. ``--score`` scores an existing mesh (e.g.
bench_peers' VDBFusion ``mesh.npz``) with the same metrics and bins.

The seeds of an extent other than the map's own are recomputed from the scan's points
(``stages.surface.surface_seeds``); the map's own extent uses the map's stored seeds.
"""
import argparse
import dataclasses
import json
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_peers import mesh_metrics, read_ref_mesh  # noqa: E402
from surface_voxel_study import boundary_fraction, load_case  # noqa: E402

from gmmgp_app.evaluation import Reference, sample_mesh_surface  # noqa: E402
from gmmgp_app.stages import surface as _surface  # noqa: E402

BINS = (0.05, 0.20, 0.50)   # m: < 5 cm, 5-20 cm, 20-50 cm, > 50 cm
BIN_NAMES = ("<5cm", "5-20cm", "20-50cm", ">50cm")


def cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def seeds_and_reach(m, pts_local: np.ndarray, extent: float, own: bool):
    """The seeds and the reach of extent cell ``extent`` (m)."""
    if own:
        seeds = m.seed_points
    else:
        cfg = dataclasses.replace(m.config.surface, extent_cell=float(extent))
        seeds = _surface.surface_seeds(pts_local, cfg)
    return seeds, _surface.surface_reach(seeds, float(extent))


def mesh_once(m, seeds, reach, voxel):
    c0, t0 = cpu_seconds(), time.perf_counter()
    mesh = _surface.mesh_field(m.predict, seeds, m.config.surface, voxel, None, None, reach,
                               predict_mean=m.lattice_mean, overlap=False)
    return mesh, cpu_seconds() - c0, time.perf_counter() - t0


def binned(v, f, tree, ref, n_samples: int, seed: int) -> dict:
    """Faces, area and accuracy of the mesh by the distance to the nearest scan point."""
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    d_face = tree.query(tri.mean(axis=1), k=1, workers=1)[0]
    b_face = np.searchsorted(BINS, d_face)
    s = sample_mesh_surface(v, f, n_samples, np.random.default_rng(seed))
    d_s = tree.query(s, k=1, workers=1)[0]
    b_s = np.searchsorted(BINS, d_s)
    acc = np.abs(ref.sdf(s)) if ref is not None else d_s
    out = {}
    for i, name in enumerate(BIN_NAMES):
        sel = b_s == i
        a = acc[sel]
        out[name] = {
            "faces": int(np.sum(b_face == i)), "face_frac": float(np.mean(b_face == i)),
            "area_m2": float(area[b_face == i].sum()),
            "area_frac": float(area[b_face == i].sum() / area.sum()),
            "sample_frac": float(np.mean(sel)),
            "acc_mean_mm": 1e3 * float(a.mean()) if len(a) else None,
            "acc_rmse_mm": 1e3 * float(np.sqrt(np.mean(a ** 2))) if len(a) else None,
            "acc_p95_mm": 1e3 * float(np.quantile(a, 0.95)) if len(a) else None}
    return out


def local_voxel_estimate(v, f, pts, tree, base: float, caps=(1.0, 1.5, 2.5, 4.0),
                         k: int = 8) -> dict:
    """Faces a mesh would have with a voxel from the local spacing, estimated from this one.

    The local spacing at a face is the radius of its nearest scan point's ``k`` nearest
    neighbours relative to that radius's median over the scan's points (where h_t comes
    from: ratio 1 is the spacing h_t is set by, the dense ground near a LiDAR); the local
    voxel is ``base * clip(ratio, 1, cap)`` (``base``: this mesh's voxel, e.g. 0.6 h_t),
    and a face stands for ``(base / local voxel)^2`` faces of the local mesh (faces go as
    area / voxel^2). Returned per cap: the estimated face count and its ratio to this mesh's.
    """
    rng = np.random.default_rng(0)
    sub = pts[rng.choice(len(pts), min(len(pts), 100_000), replace=False)]
    r_med = float(np.median(tree.query(sub, k=k + 1, workers=1)[0][:, -1]))
    cen = v[f].mean(axis=1)
    _, i = tree.query(cen, k=1, workers=1)
    r_pt = tree.query(pts[i], k=k + 1, workers=1)[0][:, -1]
    ratio = r_pt / r_med
    out = {"ratio_quantiles_10_50_90": [float(x) for x in np.quantile(ratio, [0.1, 0.5, 0.9])]}
    for cap in caps:
        w = 1.0 / np.clip(ratio, 1.0, cap) ** 2
        out[f"cap{cap:g}"] = {"faces_est": float(w.sum()), "faces_ratio": float(w.mean())}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("cases", nargs="*", help="TAG=MAP_DIR:SCAN.npz:REF.ply (REF may be empty)")
    ap.add_argument("--score", action="append", default=[],
                    help="TAG=MESH:SCAN.npz:REF.ply: only score an existing mesh (.ply, or a "
                         ".npz with vertices and faces, e.g. bench_peers' VDBFusion mesh)")
    ap.add_argument("--voxels", default="0.6,0.8,1.0,1.5", help="voxels in units of h_t")
    ap.add_argument("--extents", default="0.6", help="extent cells in units of h_t "
                    "(0.6: the map's own)")
    ap.add_argument("--repeats", type=int, default=1, help="meshings per setting (timing)")
    ap.add_argument("--samples", type=int, default=200_000)
    ap.add_argument("--trims", default="", help="also score each mesh with the faces whose "
                    "centroid lies further than T m from the nearest scan point removed "
                    "(comma-separated T, or 'reach': the extent's reach; 'seeds': the reach from the "
                    "seeds rather than the scan points; a post-hoc emulation of a cap on the fill)")
    ap.add_argument("--no-metrics", action="store_true", help="timing only")
    ap.add_argument("--out", required=True, help="JSON of every result (rewritten per mesh)")
    args = ap.parse_args(argv)
    from scipy.spatial import cKDTree

    res = {"settings": vars(args), "cases": {}, "scored": {}}
    for spec in args.score:
        tag, _, rest = spec.partition("=")
        mp, scan, refp = rest.split(":")
        if mp.endswith(".npz"):
            with np.load(mp) as z:
                v, f = np.asarray(z["vertices"], np.float64), np.asarray(z["faces"], np.int64)
        else:
            mesh = _surface.read_mesh_ply(mp)
            v, f = mesh.vertices, mesh.faces
        pts = np.asarray(np.load(scan)["points"], np.float64)
        ref_mesh = read_ref_mesh(refp) if refp else None
        tree = cKDTree(pts)
        ref = Reference.from_mesh(*ref_mesh) if ref_mesh is not None else None
        res["scored"][tag] = {"mesh": mp, "faces": int(len(f)),
                              "metrics": mesh_metrics(v, f, pts, ref_mesh, args.samples, 0),
                              "bins": binned(v, f, tree, ref, args.samples, 1),
                              "boundary_edge_frac": boundary_fraction(f)}
        print(f"scored {tag}", file=sys.stderr, flush=True)
        Path(args.out).write_text(json.dumps(res, indent=1))
    for case in args.cases:
        tag, m, pts, ref_mesh, ht = load_case(case)
        pts = np.asarray(pts, np.float64)
        own_e = m.config.surface.extent_cell
        own_e = float(m.config.surface.voxel_size) if isinstance(own_e, str) else float(own_e)
        tree = cKDTree(pts)
        ref = Reference.from_mesh(*ref_mesh) if ref_mesh is not None else None
        rc = res["cases"][tag] = {"h_t": ht, "own_extent": own_e, "n_points": len(pts),
                                  "runs": []}
        for g in (float(x) for x in args.extents.split(",")):
            own = bool(np.isclose(g * ht, own_e))
            seeds, reach = seeds_and_reach(m, pts - m.offset, g * ht, own)
            for fac in (float(x) for x in args.voxels.split(",")):
                cpus, walls = [], []
                for _ in range(args.repeats):
                    mesh, c, w = mesh_once(m, seeds, reach, fac * ht)
                    cpus.append(c), walls.append(w)
                r = {"voxel_factor": fac, "voxel": fac * ht, "extent_factor": g,
                     "extent": g * ht, "reach": reach, "n_seeds": int(len(seeds)),
                     "surface_cpu_s": float(np.median(cpus)), "surface_cpu_s_runs": cpus,
                     "surface_wall_s": float(np.median(walls)), "surface_wall_s_runs": walls,
                     "load_avg": list(os.getloadavg()),
                     "vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces))}
                if not args.no_metrics and len(mesh.faces):
                    v = mesh.vertices + m.offset
                    r["metrics"] = mesh_metrics(v, mesh.faces, pts, ref_mesh, args.samples, 0)
                    r["bins"] = binned(v, mesh.faces, tree, ref, args.samples, 1)
                    r["boundary_edge_frac"] = boundary_fraction(mesh.faces)
                    for tt in (x.strip() for x in args.trims.split(",") if x.strip()):
                        t = reach if tt in ("reach", "seeds") else float(tt)
                        c0 = cpu_seconds()
                        if tt == "seeds":   # as a stage would: the seeds' tree, the reach
                            d = cKDTree(seeds + m.offset).query(
                                v[mesh.faces].mean(axis=1), k=1, workers=1)[0]
                        else:
                            d = tree.query(v[mesh.faces].mean(axis=1), k=1, workers=1)[0]
                        ft = mesh.faces[d <= t]
                        trim_cpu = cpu_seconds() - c0
                        r["trim_reach" if tt == "reach" else "trim_seeds" if tt == "seeds"
                          else f"trim_{t:g}"] = {
                            "cpu_s": trim_cpu,
                            "faces": int(len(ft)),
                            "metrics": mesh_metrics(v, ft, pts, ref_mesh, args.samples, 0),
                            "bins": binned(v, ft, tree, ref, args.samples, 1),
                            "boundary_edge_frac": boundary_fraction(ft)}
                    if fac == min(float(x) for x in args.voxels.split(",")):
                        r["local_voxel_estimate"] = local_voxel_estimate(
                            v, mesh.faces, pts, tree, fac * ht)
                rc["runs"].append(r)
                print(f"{tag} voxel {fac:g} h_t extent {g:g} h_t: cpu {r['surface_cpu_s']:.1f} s "
                      f"faces {r['faces']:,} load {r['load_avg'][0]:.1f}", file=sys.stderr,
                      flush=True)
                del mesh
                Path(args.out).parent.mkdir(parents=True, exist_ok=True)
                Path(args.out).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
