import sys, time, numpy as np, numba as nb
nb.set_num_threads(1)
from gmmgp_app.pipeline import load_map
from gmmgp_app.stages.knn import GridKNN
smap = load_map(sys.argv[1]); z = np.load(sys.argv[2]); far = smap.far
lat, vert = z["lat"], z["vert"]
ls, vs = z["lat_sizes"], z["vert_sizes"]
def batches(x, sizes):
    s = 0
    for n in sizes:
        yield x[s:s+n]; s += n
def T(f):
    c = time.process_time(); out = f(); return time.process_time() - c, out
kn = GridKNN(far.points, far.k, tree=far.tree)
kn.query(lat[:1000])
print("k", kn.k, "cell", kn.cell, "group cube", kn.group*kn.cell, "rho0", far.rho0, "P", len(far.points))
res = {}
for rep in range(2):
    kn.keep_lists(True)
    tl, outl = T(lambda: [kn.query(b) for b in batches(lat, ls)])
    tv, outv = T(lambda: [kn.query(b) for b in batches(vert, vs)])
    kn.keep_lists(False)
    dl = np.concatenate([o[0] for o in outl]); il = np.concatenate([o[1] for o in outl])
    ti, _ = T(lambda: [far.components(b, neighbours=(dl[s:s+len(b)], il[s:s+len(b)])) for s, b in zip(np.r_[0, np.cumsum(ls)[:-1]], batches(lat, ls))])
    gp = smap._near_field
    tg, _ = T(lambda: [gp.predict(b) for b in batches(vert, vs)])
    tp, _ = T(lambda: [smap.predict(b) for b in batches(vert, vs)])
    tm, _ = T(lambda: [smap.lattice_mean(b) for b in batches(lat, ls)])
    print(f"rep{rep}: lat knn {tl:.3f} imls {ti:.3f} | lattice_mean total {tm:.3f} | vert knn(kept) {tv:.3f} gp {tg:.3f} predict total {tp:.3f}")
# stats of groups
g = kn.group * kn.cell
for name, x in (("lat", lat), ("vert", vert)):
    c = np.floor(x / g).astype(np.int64)
    _, cnt = np.unique(c, axis=0, return_counts=True)
    print(name, "N", len(x), "groups", len(cnt), "mean size", cnt.mean().round(2), "median", np.median(cnt))
d, i = kn.query(lat[::50])
print("lattice d1 median", np.median(d[:, 0]).round(4), "dk median", np.median(d[:, -1]).round(4), "dk p90", np.percentile(d[:, -1], 90).round(4), "dk/cell", (np.median(d[:, -1])/kn.cell).round(2))
