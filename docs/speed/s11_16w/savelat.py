import sys, numpy as np
from gmmgp_app.pipeline import load_map
smap = load_map(sys.argv[1])
xs = []
f = smap.lattice_mean
def rec(x):
    xs.append(np.array(x)); return f(x)
smap.lattice_mean = rec
m = smap.extract_surface()
np.save(sys.argv[2], np.concatenate(xs))
print(len(np.concatenate(xs)), [len(x) for x in xs][:5], len(xs))
