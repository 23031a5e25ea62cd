"""The lattice's far-field mean with fewer robust passes (issue 16, session 13, speed-16a):
a measured study, not the library's default. For each variant the street map's surface is
extracted serially with the lattice evaluated by ``_imls_mean(..., robust_iterations=R)``
(R = the map's 3: the default mesh); reports the lattice's CPU seconds (one numba thread
when run with NUMBA_NUM_THREADS=1), the lattice values' change against R = 3 and
bench_peers' mesh metrics (`mesh_metrics`, 200k samples, seed 0).

    NUMBA_NUM_THREADS=1 PYTHONPATH=$PWD python docs/speed/s13_16a/lattice_iters.py MAP \
        /tmp/st11/scan.npz /tmp/st11/mesh.ply --iters 3,1,0 --json out.json
"""
import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[3]
sys.path.append(str(ROOT / "scripts"))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("map")
    ap.add_argument("scan")
    ap.add_argument("mesh_ref")
    ap.add_argument("--iters", default="3,1,0")
    ap.add_argument("--json")
    a = ap.parse_args()
    from gmmgp_app.pipeline import load_map
    from gmmgp_app.stages import farfield as ff
    from bench_peers import mesh_metrics, read_ref_mesh

    smap = load_map(a.map)
    with np.load(a.scan) as z:
        pts = np.ascontiguousarray(z["points"], np.float64)
    exact = read_ref_mesh(Path(a.mesh_ref))
    f = smap.far
    rows, ref = [], None
    for it in [int(v) for v in a.iters.split(",")]:
        cpu, xs, ms = [0.0], [], []

        def lat(x, it=it):
            c = time.process_time()
            x = np.ascontiguousarray(x, dtype=np.float64)
            d, i = f.knn.query(x)
            m = ff._imls_mean(x, d, i, f.points, f.normals, f.rho0, f.growth,
                              f.robust_scale if it > 0 else 0.0, it, f.vote == "sphere")
            cpu[0] += time.process_time() - c
            xs.append(x)
            ms.append(m)
            return m
        smap.lattice_mean = lat
        c0 = time.process_time()
        mesh = smap.extract_surface(overlap=False)
        total = time.process_time() - c0
        x, m = np.concatenate(xs), np.concatenate(ms)
        row = dict(robust_iterations=it, surface_cpu_s=total, lattice_cpu_s=cpu[0],
                   lattice_nodes=len(x), vertices=len(mesh.vertices), faces=len(mesh.faces))
        if ref is None:
            ref = dict(zip(map(tuple, np.round(x / smap.config.surface.voxel_size).astype(int)), m))
        else:
            keys = map(tuple, np.round(x / smap.config.surface.voxel_size).astype(int))
            dv = np.abs(np.array([ref.get(k, np.nan) for k in keys]) - m)
            dv = dv[np.isfinite(dv)] * 1000
            row.update(lattice_change_mm_median=float(np.median(dv)),
                       lattice_change_mm_p99=float(np.quantile(dv, 0.99)),
                       lattice_change_mm_max=float(dv.max()))
        vm = smap.predict(mesh.vertices[::5])[0]
        r = np.abs(vm) / smap.config.surface.voxel_size
        row.update(map_mean_at_vertices_over_voxel_median=float(np.median(r)),
                   p99=float(np.quantile(r, 0.99)))
        row.update(mesh_metrics(mesh.vertices + smap.offset, mesh.faces, pts, exact,
                                200_000, 0))
        rows.append(row)
        print(json.dumps(row), flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
