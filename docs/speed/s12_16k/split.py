import sys, time, numpy as np, numba as nb
nb.set_num_threads(1)
from gmmgp_app.pipeline import load_map
from gmmgp_app.stages.knn import GridKNN, _knn_grid
smap = load_map(sys.argv[1]); z = np.load(sys.argv[2]); far = smap.far
kn = GridKNN(far.points, far.k, tree=far.tree)
kn.query(z["lat"][:1000])
for name in ("lat", "vert"):
    x = z[name]
    for rep in range(2):
        c = time.process_time(); d, i, done = kn._query_groups(x); t1 = time.process_time() - c
        rest = x[~done]
        c = time.process_time()
        _, _, dn = _knn_grid(rest, kn.k, kn.cell, kn.lo, kn.dims, kn.table_keys, kn.table_start, kn.table_end, kn.sorted_points, kn.order, kn.max_ring)
        t2 = time.process_time() - c
        r2 = rest[~dn]
        c = time.process_time(); kn.tree.query(r2, k=kn.k, workers=1); t3 = time.process_time() - c
        c = time.process_time(); kn.tree.query(r2, k=kn.k, workers=-1); t4 = time.process_time() - c
        print(name, f"groups {t1:.3f} ({done.sum()} q)  grid-rest {t2:.3f} ({len(rest)} q)  kd {t3:.3f} / workers=-1 {t4:.3f} ({len(r2)} q)")
