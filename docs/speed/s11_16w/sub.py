import sys, time, cProfile, pstats, numpy as np
from gmmgp_app.pipeline import load_map
smap = load_map(sys.argv[1])
what = sys.argv[3]
V = np.load(sys.argv[2])["vertices"] if what=="vert" else np.load(sys.argv[2])
B = 65536
def vert():
    for s in range(0, len(V), B):
        smap.predict(V[s:s+B])
# lattice: random subset? use vertices as lattice proxy is wrong; use lattice_mean at vertices
def lat():
    for s in range(0, len(V), B):
        smap.lattice_mean(V[s:s+B])
f = vert if what == "vert" else lat
f()  # warm
c = time.process_time(); t = time.perf_counter()
pr = cProfile.Profile(); pr.enable(); f(); pr.disable()
print("cpu", time.process_time() - c, "wall", time.perf_counter() - t)
pstats.Stats(pr).sort_stats("tottime").print_stats(25)
