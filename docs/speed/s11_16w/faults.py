import sys, time, resource, threading, numpy as np
from gmmgp_app.pipeline import load_map
from gmmgp_app import _memory
if sys.argv[2] == "fix": _memory.fix_mmap_threshold()
smap = load_map(sys.argv[1])
acc = {}
lock = threading.Lock()
def ru():
    r = resource.getrusage(resource.RUSAGE_SELF); return np.array([r.ru_minflt, r.ru_utime, r.ru_stime, time.perf_counter()])
def wrap(f, name):
    def g(x, *a, **k):
        r0 = ru(); out = f(x, *a, **k); d = ru() - r0
        with lock: acc[name] = acc.get(name, 0) + d
        return out
    return g
smap.predict = wrap(smap.predict, "vertex"); smap.lattice_mean = wrap(smap.lattice_mean, "lattice")
for rep in range(int(sys.argv[3])):
    acc.clear(); r0 = ru(); t = time.perf_counter()
    m = smap.extract_surface(overlap=("serial" not in sys.argv[4:]))
    d = ru() - r0
    print(rep, "total faults %d user %.2f sys %.2f wall %.2f" % (d[0], d[1], d[2], time.perf_counter() - t),
          {k: "faults %d user %.2f sys %.2f wall %.2f" % tuple(v) for k, v in acc.items()})
