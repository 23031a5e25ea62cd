import sys, time, importlib.util, numpy as np, numba as nb
nb.set_num_threads(1)
from gmmgp_app.pipeline import load_map
from gmmgp_app.stages.knn import GridKNN as New
spec = importlib.util.spec_from_file_location("oldknn", "/work/main/gmmgp_app/stages/knn.py")
old = importlib.util.module_from_spec(spec); spec.loader.exec_module(old)
smap = load_map(sys.argv[1]); z = np.load(sys.argv[2]); far = smap.far
def batches(x, sizes):
    s = 0
    for n in sizes:
        yield x[s:s+n]; s += n
res = {}
for rep in range(3):
    for name in ("old", "new"):
        kn = (old.GridKNN if name == "old" else New)(far.points, far.k, tree=far.tree)
        kn.query(z["lat"][:2000])
        kn.keep_lists()
        c = time.process_time(); ol = [kn.query(b) for b in batches(z["lat"], z["lat_sizes"])]; tl = time.process_time() - c
        c = time.process_time(); ov = [kn.query(b) for b in batches(z["vert"], z["vert_sizes"])]; tv = time.process_time() - c
        out = [np.concatenate([o[j] for o in ol]) for j in (0, 1)] + [np.concatenate([o[j] for o in ov]) for j in (0, 1)]
        res.setdefault(name, []).append((tl, tv))
        if name == "old": ref = out
        else: assert all(np.array_equal(a, b) and a.dtype == b.dtype for a, b in zip(ref, out)), name
for k, v in res.items():
    v = np.array(v); print(k, "lat/vert median", np.median(v, 0).round(3), "all", v.round(3).tolist())
print("same: yes")
