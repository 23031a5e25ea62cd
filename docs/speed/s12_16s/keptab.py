import sys, time, importlib.util, numpy as np, numba as nb
nb.set_num_threads(1)
from gmmgp_app.pipeline import load_map
from gmmgp_app.stages.knn import GridKNN as New
spec = importlib.util.spec_from_file_location("oldknn", "/work/main/gmmgp_app/stages/knn.py")
old = importlib.util.module_from_spec(spec); spec.loader.exec_module(old)
smap = load_map(sys.argv[1]); z = np.load(sys.argv[2]); far = smap.far
B = 65536
def run(kn, x):
    c = time.process_time()
    out = [kn.query(x[s:s+B]) for s in range(0, len(x), B)]
    t = time.process_time() - c
    return t, np.concatenate([o[0] for o in out]), np.concatenate([o[1] for o in out])
res = {}
for rep in range(3):
    for name in ("old", "new", "kept"):
        kn = (old.GridKNN if name == "old" else New)(far.points, far.k, tree=far.tree)
        kn.query(z["lat"][:B])
        if name == "kept": kn.keep_lists()
        tl, dl, il = run(kn, z["lat"]); tv, dv, iv = run(kn, z["vert"])
        res.setdefault(name, []).append((tl, tv))
        if name == "old": ref = (dl, il, dv, iv)
        else: assert all(np.array_equal(a, b) for a, b in zip(ref, (dl, il, dv, iv))), name
        if name == "kept": print("kept lists", kn._kept.count, "entries", kn._kept.starts[kn._kept.count], "open", kn._kept.open)
for k, v in res.items():
    v = np.array(v); print(k, "lat min", v[:, 0].min().round(3), "vert min", v[:, 1].min().round(3), "median", np.median(v, 0).round(3))
