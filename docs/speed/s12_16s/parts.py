import time, numpy as np
from gmmgp_app.pipeline import load_map
from gmmgp_app.stages import surface as S
m = load_map('/tmp/speed-16s/base/map')
s = m.seed_points; r = m.surface_reach(); h = m.config.surface.voxel_size
def T(name, f, n=3):
    f()
    ts = []
    for _ in range(n):
        c = time.process_time(); out = f(); ts.append(time.process_time() - c)
    print(name, round(min(ts), 4)); return out
T("surface_reach(map)", m.surface_reach)
T("check_grid_size", lambda: S.check_grid_size(s, h, None))
T("median_spacing", lambda: S._median_spacing(s))
T("estimate_grid_nodes", lambda: S.estimate_grid_nodes(s, h, 2))
sr = T("SeedReach", lambda: S.SeedReach(s, r))
T("unique_rows cells", lambda: S._unique_rows(np.floor(s / h).astype(np.int64)))
z = np.load('/tmp/speed-16s/base_serial.npz'); v, f = z['vertices'], z['faces']
T("centroids", lambda: v[f].mean(axis=1))
c = v[f].mean(axis=1)
T("within grid", lambda: sr.within(c))
from scipy.spatial import cKDTree
t = cKDTree(s, balanced_tree=False)
T("within tree", lambda: S.centroids_within_reach(c, t, r))
print("same", np.array_equal(sr.within(c), S.centroids_within_reach(c, t, r)))
ans = S._reach_test(c, sr.cell, sr.reach, sr.lo, sr.dims, *sr.table, r*r*(1-1e-9), r*r*(1+1e-9))
print("close calls", (ans == 2).sum(), "in", (ans==1).mean())
T("faces_within_reach grid", lambda: S.faces_within_reach(v, f, sr, r))
