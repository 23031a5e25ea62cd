import sys, json
sys.path.insert(0, "scripts")
from pathlib import Path
import numpy as np
import fit_variance as FV
from gmmgp_app.stages import farfield as F
bench = ["street","sphere","street2","courtyard","pipes","bunny"]
train = list(FV.TRAIN_SCENES)
basej = {r["scene"]: r["methods"] for r in json.loads(Path("docs/field_bench/bench_accuracy.json").read_text())["results"]}
A = {n: FV.scene_case(n, 0, Path("out/calib")) for n in bench + train}
Pz = {n: FV.scene_case(n, 0, Path("out/calib_p0")) for n in bench + train}
def rm(d): 
    e2 = (d["mean"] - d["y"]) ** 2; return [np.sqrt(e2[d["bin"] == i].mean()) for i in range(7)]
for n in bench + train:
    a, p = rm(A[n]), rm(Pz[n])
    pl = basej[n]["plane"]["rmse_sdf"] if n in basej else None
    print(f"{n:18s} now " + "/".join(f"{1000*x:.1f}" for x in a) + "  p0-nbrs " + "/".join(f"{1000*x:.1f}" for x in p)
          + ("" if pl is None else "  plane " + "/".join(f"{1000*x:.1f}" for x in pl) + f"  below plane {sum(x<y for x,y in zip(a,pl))}->{sum(x<y for x,y in zip(p,pl))}"))
    d = Pz[n]; m = d["mean"]; y = d["y"]; e = y - m
    d0 = A[n]; e0 = d0["y"] - d0["mean"]
    if n in ("sphere", "pipes", "street"):
        for i in range(7):
            s = d["bin"] == i
            print(f"   bin {i}: mean err front {1000*e0[s & (y>0)].mean():+.1f} -> {1000*e[s & (y>0)].mean():+.1f}  inside {1000*e0[s & (y<0)].mean() if (s&(y<0)).any() else 0:+.1f} -> {1000*e[s & (y<0)].mean() if (s&(y<0)).any() else 0:+.1f}")
coefs = {"s6": F.VARIANCE_COEF, "tuned refit": tuple(FV.fit([Pz["street"], Pz["sphere"]]))}
print("tuned refit", np.round(coefs["tuned refit"], 4))
for cl, coef in coefs.items():
    for group in (bench, train):
        tot = np.zeros(4, int); held = np.zeros(4, int); rows = []
        for n in group:
            d = Pz[n]; r = FV.coverage_bins(d, coef, basej.get(n))
            nr = sum(x < y for x, y in zip(rm(d), basej[n]["plane"]["rmse_sdf"])) if n in basej else 0
            v = np.array([r["n1"], r["n2"], r["nll"] or 0, nr]); tot += v
            if n in ("street2","courtyard","pipes","bunny"): held += v
            rows.append(f"  {n} [{r['n1']}/{r['n2']}/{r['nll']}/{nr}] 1s " + " ".join(f"{x:.2f}" for x in r["c1"]) + " | 2s " + " ".join(f"{x:.2f}" for x in r["c2"]))
        print(f"p0-nbrs {cl}: total (1s/2s/LL/RMSE) {tot.tolist()} held-out4 {held.tolist()}"); print("\n".join(rows), flush=True)
