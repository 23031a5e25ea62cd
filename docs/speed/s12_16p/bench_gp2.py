import sys, pickle, time, resource, hashlib, numpy as np
from gmmgp_app.stages import gp
a, k = pickle.load(open("/tmp/speed-16p/gp_in.pkl", "rb"))
prog = (lambda d, t: None) if sys.argv[1] == "prog" else None
b, flat = gp._fit_many(*a, progress=prog, **k)
h = hashlib.sha256(b"".join(np.ascontiguousarray(flat[x]).tobytes() for x in ("L", "alpha")) + b.jitter.tobytes()).hexdigest()[:16]
del b, flat
for _ in range(3):
    r0 = resource.getrusage(resource.RUSAGE_SELF); t = time.perf_counter()
    b, flat = gp._fit_many(*a, progress=prog, **k)
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    print(sys.argv[1], h, "wall %.3f user %.3f sys %.3f" % (time.perf_counter() - t, r1.ru_utime - r0.ru_utime, r1.ru_stime - r0.ru_stime))
    del b, flat
