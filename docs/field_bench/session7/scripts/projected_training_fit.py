import sys, json, time
sys.path.insert(0, "scripts")
from pathlib import Path
import numpy as np
import fit_variance as FV, bench_accuracy as B
from gmmgp_app.stages import farfield as F
C = Path("out/calib")
bench = ["street","sphere","street2","courtyard","pipes","bunny"]
train = list(FV.TRAIN_SCENES)
basej = {r["scene"]: r["methods"] for r in json.loads(Path("docs/field_bench/bench_accuracy.json").read_text())["results"]}
def run(ov, label, coefs):
    cases = {n: FV.scene_case(n, 0, C, ov) for n in bench + train}
    for cl, coef in coefs.items():
        if coef == "train":
            coef = tuple(FV.fit([cases[n] for n in train])); print("fitted on training:", np.round(coef, 4))
        if coef == "tuned":
            coef = tuple(FV.fit([cases[n] for n in ("street", "sphere")])); print("fitted on tuned:", np.round(coef, 4))
        for group in (bench, train):
            tot = np.zeros(4, int); held = np.zeros(4, int); rows = []
            for n in group:
                d = cases[n]; r = FV.coverage_bins(d, coef, basej.get(n))
                nr = 0
                if n in basej:
                    e2 = (d["mean"] - d["y"]) ** 2
                    nr = sum(np.sqrt(e2[d["bin"] == i].mean()) < basej[n]["plane"]["rmse_sdf"][i] for i in range(7))
                v = np.array([r["n1"], r["n2"], r["nll"] or 0, nr]); tot += v
                if n in ("street2","courtyard","pipes","bunny"): held += v
                rows.append(f"  {n} [{r['n1']}/{r['n2']}/{r['nll']}/{nr}] 1s " + " ".join(f"{x:.2f}" for x in r["c1"]) + " | 2s " + " ".join(f"{x:.2f}" for x in r["c2"]))
            print(f"{label} {cl}: total (1s/2s/LL/RMSE) {tot.tolist()} held-out4 {held.tolist()}"); print("\n".join(rows), flush=True)
run(["far.project_points=true"], "projected points", {"VARIANCE_COEF_PROJECTED (s6, tuned)": F.VARIANCE_COEF_PROJECTED, "training fit": "train"})
