import sys, time, numpy as np, numba as nb
from gmmgp_app.pipeline import load_map
from gmmgp_app.stages import farfield as ff
smap = load_map(sys.argv[1]); q = np.load(sys.argv[2])['lat'][:400000]
f = smap.far
d, i = f.knn.query(q)
args = (q, d, i, getattr(f, "vote_points", f.points), f.normals, f.rho0, f.growth)
full = lambda: f.components(q, neighbours=(d, i))["mean"]
mo = lambda: ff._imls_mean(*args, f.robust_scale, f.robust_iterations, f.vote == "sphere")
a, b = full(), mo()
print("vote", f.vote, "robust", f.robust_scale, f.robust_iterations, "k", f.k, "equal", np.array_equal(a, b))
for fn_name in ["full", "mo"] * 4:
    fn = full if fn_name == "full" else mo
    c = time.process_time(); fn(); print(fn_name, round(time.process_time() - c, 3))
c = time.process_time(); f.knn.query(q); print("knn", round(time.process_time() - c, 3))
