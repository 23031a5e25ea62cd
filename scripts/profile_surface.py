#!/usr/bin/env python
"""Where the surface stage's time goes, on a saved map (issue 16).

Loads a map written by ``gmmgp run`` (or ``SurfaceMap.save``), extracts its surface
(the map's own voxel unless ``--voxel``; ``--voxel-ht F`` for F times the training
spacing h_t) with the field wrapped to count and time every evaluation, and reports:

* field evaluations on the lattice (``SurfaceMap.lattice_mean``) and at the mesh
  vertices (the variance pass, ``SurfaceMap.predict``), the seconds (wall and CPU, all
  threads) in each and per evaluation;
* the lattice nodes that are an end of a sign-changing lattice edge (the only ones a
  vertex is interpolated from) and the rest (evaluated to find out that no surface
  crosses there);
* the rest of the stage (surface following, marching cubes, stitching) and the time
  to write the PLY;
* the CPU seconds of each phase of ``extract_surface`` (``timings``: setup, follow (the
  lattice field included; ``follow_bookkeeping_cpu_s`` without it), block_nodes,
  marching_cubes, stitch, vertices, final);
* the wall seconds of the same phases (``wall_timings``, where the profiled code has
  it), and the process's peak RSS (``ru_maxrss``);
* with ``--repeat N``: the extraction N times in the process, the last one reported
  (the first pays numba's cache loading);
* with ``--serial``: ``extract_surface(overlap=False)``, everything in one thread in
  order (the default overlaps the vertex pass with marching cubes on a worker thread);
* with ``--save-mesh F.npz``: the mesh's vertices, faces and variances, to compare
  two trees or the two paths bit for bit (``--compare F.npz`` does it and reports it);
* with ``--mesh-ref`` (exact mesh) and ``--scan``: bench_peers' mesh metrics.

    PYTHONPATH=$PWD .venv/bin/python scripts/profile_surface.py out/street_run/map \\
        --json out/prof_surface.json
    PYTHONPATH=/path/to/other/checkout .venv/bin/python scripts/profile_surface.py ...
    PYTHONPATH=$PWD .venv/bin/python scripts/profile_surface.py out/street_run/map \\
        --voxel-ht 1.0 --scan out/bench/peers_work/street_d1_s0/scan.npz \\
        --mesh-ref out/bench/peers_work/street_d1_s0/mesh.ply
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
# appended, so PYTHONPATH decides which gmmgp_app is profiled (e.g. another checkout's)
sys.path.append(str(ROOT))
sys.path.append(str(ROOT / "scripts"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("map", help="map directory (gmmgp run --out DIR writes DIR/map)")
    ap.add_argument("--voxel", type=float, help="surface voxel (m); default the map's")
    ap.add_argument("--voxel-ht", type=float, help="surface voxel as a multiple of h_t")
    ap.add_argument("--scan", help="scan .npz (points) for the mesh metrics")
    ap.add_argument("--mesh-ref", help="exact mesh .ply for the mesh metrics")
    ap.add_argument("--json", help="write the report here")
    ap.add_argument("--repeat", type=int, default=1, help="extractions (the last reported)")
    ap.add_argument("--serial", action="store_true", help="extract_surface(overlap=False)")
    ap.add_argument("--save-mesh", help="write vertices, faces, variances (.npz) here")
    ap.add_argument("--compare", help="a --save-mesh file: report whether the mesh equals it")
    args = ap.parse_args(argv)

    from gmmgp_app.pipeline import load_map
    from gmmgp_app.stages.surface import write_mesh_ply

    smap = load_map(args.map)
    h = smap.config.surface.voxel_size
    if args.voxel_ht:
        if smap.far is None:
            ap.error("--voxel-ht needs a map with a far field (its kernel floor is h_t)")
        h = float(args.voxel_ht) * float(smap.far.rho0)
    elif args.voxel:
        h = float(args.voxel)
    calls = []                                   # (n, seconds, cpu seconds, xyz, mean, lattice?)
    field, lattice = smap.predict, smap.lattice_mean

    def counted(f, on_lattice):
        def run(x, **kw):
            t, c = time.perf_counter(), time.process_time()
            out = f(x, **kw)
            calls.append((len(x), time.perf_counter() - t, time.process_time() - c,
                          np.asarray(x), out if on_lattice else out[0], on_lattice))
            return out
        return run

    smap.predict, smap.lattice_mean = counted(field, False), counted(lattice, True)
    import gmmgp_app.stages.surface as surface_stage

    import inspect

    extract = surface_stage.extract_surface
    phases, walls = {}, {}
    extra = {}
    known = inspect.signature(extract).parameters
    if "wall_timings" in known:
        extra["wall_timings"] = walls
    if "overlap" in known:
        # the overlap as `gmmgp run` asks for it (the map's extract_surface defaults to
        # the serial path since session 10), or the serial path with --serial
        extra["overlap"] = not args.serial
    elif args.serial:
        ap.error("--serial: this gmmgp_app's extract_surface has no overlap (serial "
                 "already)")
    # the phases' CPU seconds (the pipeline reaches extract_surface through the module);
    # this script's overlap choice wins over the caller's
    surface_stage.extract_surface = lambda *a, **kw: extract(*a, timings=phases,
                                                             **{**kw, **extra})
    for _ in range(max(args.repeat, 1)):
        calls.clear()
        phases.clear()
        walls.clear()
        t0, c0 = time.perf_counter(), time.process_time()
        mesh = smap.extract_surface(h)
        total, total_cpu = time.perf_counter() - t0, time.process_time() - c0
    surface_stage.extract_surface = extract
    smap.predict, smap.lattice_mean = field, lattice
    n_vert = len(mesh.vertices)
    # the last calls evaluate the vertices (variance pass): as many points as the
    # stitched vertices before faces were dropped; count from the end
    n_pts = np.array([c[0] for c in calls])
    secs = np.array([c[1] for c in calls])
    cpu = np.array([c[2] for c in calls])
    on_lattice = np.array([c[5] for c in calls])
    lat_pts = np.concatenate([c[3] for c, ok in zip(calls, on_lattice) if ok])
    lat_val = np.concatenate([c[4] for c, ok in zip(calls, on_lattice) if ok])
    useful = _sign_change_nodes(np.round(lat_pts / h).astype(np.int64), lat_val)
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        write_mesh_ply(mesh, Path(tmp) / "m.ply")
        t_write = time.perf_counter() - t
    rep = {
        "voxel_m": h, "surface_s": total, "surface_cpu_s": total_cpu, "write_ply_s": t_write,
        "vertices": n_vert, "faces": int(len(mesh.faces)),
        "lattice_evaluations": int(n_pts[on_lattice].sum()),
        "lattice_field_s": float(secs[on_lattice].sum()),
        "lattice_field_cpu_s": float(cpu[on_lattice].sum()),
        "vertex_evaluations": int(n_pts[~on_lattice].sum()),
        "vertex_field_s": float(secs[~on_lattice].sum()),
        "vertex_field_cpu_s": float(cpu[~on_lattice].sum()),
        "field_us_per_evaluation": float(1e6 * secs.sum() / max(n_pts.sum(), 1)),
        "lattice_nodes_on_a_sign_change": int(useful.sum()),
        "lattice_nodes_without": int((~useful).sum()),
        "rest_s": float(total - secs.sum()),
        "rest_cpu_s": float(total_cpu - cpu.sum()),
        "phases_cpu_s": phases,
        "phases_wall_s": walls,
        "overlap": not args.serial and "overlap" in known,
        "ru_maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "follow_bookkeeping_cpu_s": float(phases.get("follow", 0.0) - cpu[on_lattice].sum()),
        "load_avg": list(os.getloadavg()),
    }
    if args.scan and args.mesh_ref:
        from bench_peers import mesh_metrics, read_ref_mesh

        with np.load(args.scan) as z:
            pts = np.ascontiguousarray(z["points"], np.float64)
        rep["mesh"] = mesh_metrics(mesh.vertices + smap.offset, mesh.faces, pts,
                                   read_ref_mesh(Path(args.mesh_ref)), 200_000, 0)
    if args.save_mesh:
        np.savez(args.save_mesh, vertices=mesh.vertices, faces=mesh.faces,
                 variance=mesh.vertex_variance)
    if args.compare:
        with np.load(args.compare) as z:
            rep["equal_to"] = {"file": args.compare, **{
                k: bool(np.array_equal(z[k], a)) for k, a in
                (("vertices", mesh.vertices), ("faces", mesh.faces),
                 ("variance", mesh.vertex_variance))}}
    import gmmgp_app

    rep["gmmgp_app"] = str(Path(gmmgp_app.__file__).parent)
    text = json.dumps(rep, indent=1)
    print(text)
    if args.json:
        Path(args.json).write_text(text)
    return 0


def _sign_change_nodes(ijk: np.ndarray, val: np.ndarray) -> np.ndarray:
    """True for nodes that share a lattice edge with an evaluated node of the other sign."""
    lo = ijk.min(0) - 1
    dims = ijk.max(0) - lo + 2
    key = ((ijk[:, 0] - lo[0]) * dims[1] + (ijk[:, 1] - lo[1])) * dims[2] + (ijk[:, 2] - lo[2])
    order = np.argsort(key)
    ks, vs = key[order], val[order]
    useful = np.zeros(len(ks), bool)
    for step in (dims[1] * dims[2], dims[2], 1):
        pos = np.minimum(np.searchsorted(ks, ks + step), len(ks) - 1)
        has = ks[pos] == ks + step
        ch = has & (np.sign(vs) != np.sign(vs[pos]))
        useful |= ch
        useful[pos[ch]] = True
    out = np.empty(len(ks), bool)
    out[order] = useful
    return out


if __name__ == "__main__":
    sys.exit(main())
