import sys, time, resource, numpy as np
sys.path.insert(0, "/tmp/field-15t")
import ff_prev
from gmmgp_app.stages import farfield as ff_new
from gmmgp_app.pipeline import load_map
m = load_map("/tmp/field-15t/run_candidate/map")
f0 = m.far
rng = np.random.default_rng(0)
i = rng.integers(0, len(f0.points), 450_000)
q = f0.points[i] + rng.normal(0, 0.03, (450_000, 3))
d, nb = f0.knn.query(q)
fs = {}
for name, mod in (("prev", ff_prev), ("new", ff_new)):
    fp = f0.params()
    fs[name] = mod.FarField(f0.points, f0.normals, fp.pop("rho0"), fp.pop("noise"), vote_points=f0.vote_points, **fp)
    fs[name].components(q[:100], neighbours=(d[:100], nb[:100]), split_half=True)
def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF); return r.ru_utime + r.ru_stime
res = {}
for rep in range(5):
    for name in ("prev", "new"):
        for sh in (False, True):
            c0 = cpu(); out = fs[name].components(q, neighbours=(d, nb), split_half=sh); res.setdefault((name, sh), []).append(cpu() - c0)
            if sh: res.setdefault(name + "_half", out["half"])
for k, v in res.items():
    if isinstance(v, list): print(k, "median cpu", round(float(np.median(v)), 3), [round(x, 3) for x in v])
print("equal", np.array_equal(res["prev_half"], res["new_half"]))
