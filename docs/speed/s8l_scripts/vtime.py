"""vtime.py MAP MESH.npz LAT.npz: CPU and wall of the vertex predict and the lattice field (min of 2 passes)."""
import sys, time, json, os
import numpy as np
from gmmgp_app.pipeline import load_map
smap = load_map(sys.argv[1])
V = np.load(sys.argv[2])["v"]
z = np.load(sys.argv[3]); xs = [z[k] for k in z.files]
B = 65536
smap.predict(V[:1000]); smap.lattice_mean(xs[0][:1000])
out = {}
for name, f in (("vertices", lambda: [smap.predict(V[s:s + B]) for s in range(0, len(V), B)]),
                ("lattice", lambda: [smap.lattice_mean(x) for x in xs])):
    best = None
    for r in range(2):
        t, c = time.perf_counter(), time.process_time()
        f()
        w, cp = time.perf_counter() - t, time.process_time() - c
        best = (w, cp) if best is None or cp < best[1] else best
    out[name + "_wall"], out[name + "_cpu"] = round(best[0], 3), round(best[1], 3)
out["load"] = round(os.getloadavg()[0], 2)
print(json.dumps(out))
