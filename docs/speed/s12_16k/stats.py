import sys, time, numpy as np, numba as nb
nb.set_num_threads(1)
from gmmgp_app.pipeline import load_map
from gmmgp_app.stages.knn import GridKNN
from scipy.spatial import cKDTree
smap = load_map(sys.argv[1]); z = np.load(sys.argv[2]); far = smap.far
kn = GridKNN(far.points, far.k, tree=far.tree)
for name in ("lat", "vert"):
    x = z[name]
    d, i, done = kn._query_groups(x)
    print(name, "not done by groups", (~done).sum(), "of", len(x))
    rest = x[~done]
    if len(rest):
        from gmmgp_app.stages.knn import _knn_grid
        _, _, dn = _knn_grid(rest, kn.k, kn.cell, kn.lo, kn.dims, kn.table_keys, kn.table_start, kn.table_end, kn.sorted_points, kn.order, kn.max_ring)
        print("   of those to k-d tree", (~dn).sum())
    g = kn.group * kn.cell
    c = np.floor(x / g)
    uc, inv, cnt = np.unique(c, axis=0, return_inverse=True, return_counts=True)
    cen = (uc + 0.5) * g
    D = far.tree.query(cen, k=kn.k)[0][:, -1]
    half = g * np.sqrt(3) / 2
    R = D + half
    # cells per axis scanned
    ncell = (np.floor((cen + g/2 + R[:, None]) / kn.cell) - np.floor((cen - g/2 - R[:, None]) / kn.cell) + 1).prod(1)
    ncand = np.array([len(a) for a in far.tree.query_ball_point(cen[::20], R[::20] + half)])  # approx upper (ball around centre R+half)
    w = cnt  # weight by members
    def q(a, ww=None): return np.percentile(a, [50, 90, 99]).round(3)
    print(f"  groups {len(uc)} members/group mean {cnt.mean():.1f}; D/cell pct50/90/99 {q(D/kn.cell)}; cells scanned per group pct {q(ncell)} mean {ncell.mean():.0f} (weighted per query {np.sum(ncell*w)/w.sum():.0f}); cand(approx) mean {ncand.mean():.0f} pct {q(ncand)}")
    print(f"  total cells scanned {ncell.sum():.3g}, cand approx total {ncand.mean()*len(uc):.3g}, member scans approx {np.sum(w*np.interp(np.arange(len(uc)), np.arange(0,len(uc),20), ncand)):.3g}")
