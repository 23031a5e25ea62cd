import sys, numpy as np
from gmmgp_app.pipeline import load_map
smap = load_map(sys.argv[1])
L, V = [], []
lm, pr = smap.lattice_mean, smap.predict
smap.lattice_mean = lambda x: (L.append(np.array(x)), lm(x))[1]
smap.predict = lambda x, **kw: (V.append(np.array(x)), pr(x, **kw))[1]
m = smap.extract_surface(overlap=False)
np.savez(sys.argv[2], lat=np.concatenate(L), vert=np.concatenate(V), lat_sizes=np.array([len(a) for a in L]), vert_sizes=np.array([len(a) for a in V]))
print(len(np.concatenate(L)), len(np.concatenate(V)), [len(a) for a in L][:10], [len(a) for a in V][:10])
