import time, numpy as np, sys
from gmmgp_app._memory import fix_mmap_threshold; fix_mmap_threshold()
from gmmgp_app.pipeline import load_map
m = load_map(sys.argv[1])
m.predict(m.seed_points[:1000]); m.lattice_mean(m.seed_points[:1000])
out = []
for i in range(2):
    c = time.process_time(); t = time.perf_counter()
    m.extract_surface(overlap=True)
    out.append((time.process_time() - c, time.perf_counter() - t))
print(sys.argv[2], "first cpu %.2f wall %.2f / second cpu %.2f wall %.2f" % (out[0] + out[1]))
