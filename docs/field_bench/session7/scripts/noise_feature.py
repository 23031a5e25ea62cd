import sys, json, time
sys.path.insert(0, "scripts")
from pathlib import Path
import numpy as np
import fit_variance as FV
from gmmgp_app.stages import farfield as F
C = Path("out/calib")
bench = ["street","sphere","street2","courtyard","pipes","bunny"]
train = list(FV.TRAIN_SCENES)
cases = {n: FV.scene_case(n, 0, C) for n in bench + train}
basej = {r["scene"]: r["methods"] for r in json.loads(Path("docs/field_bench/bench_accuracy.json").read_text())["results"]}
rng = np.random.default_rng(0)
def design(names, frac=0.4):
    X, Y = [], []
    for n in names:
        d = cases[n]; t = FV.terms(d)
        keep = (t["w_b"] == 0) & (t["w_e"] == 0)
        keep &= rng.random(len(keep)) < frac
        x = F.variance_features(d["h"], d["noise"], d["r"][keep], d["spread2"][keep], ((d["m_gp"] - d["m_far"]) ** 2)[keep], d["v_gp"][keep])
        x6 = np.full((len(x), 1), np.log(d["noise"] ** 2 / d["h"] ** 2))
        X.append(np.hstack([x, x6])); Y.append(np.log(np.maximum((d["y"] - d["mean"]) ** 2, 1e-30)[keep] / d["h"] ** 2))
    return np.concatenate(X), np.concatenate(Y)
def score(label, coef6, names):
    tot = np.zeros(3, int); held = np.zeros(3, int); rows = []
    for n in names:
        d = cases[n]; c = np.array(coef6[:5], float)
        if len(coef6) > 5: c[0] += coef6[5] * np.log(d["noise"] ** 2 / d["h"] ** 2)
        r = FV.coverage_bins(d, tuple(c), basej.get(n))
        v = np.array([r["n1"], r["n2"], r["nll"] or 0]); tot += v
        if n in ("street2","courtyard","pipes","bunny"): held += v
        rows.append(f"  {n} [{r['n1']}/{r['n2']}/{r['nll']}] 1s " + " ".join(f"{x:.2f}" for x in r["c1"]) + " | 2s " + " ".join(f"{x:.2f}" for x in r["c2"]))
    print(f"{label}: total {tot.tolist()} held-out4 {held.tolist()}"); print("\n".join(rows), flush=True)
for lab, names, six in [("5 feat, training 8", train, False), ("6 feat, training 8", train, True), ("6 feat, street+sphere+training 8", ["street","sphere"] + train, True)]:
    X, Y = design(names)
    if not six: X = X[:, :5]
    t0 = time.time(); co = F.fit_variance_quantile(X, Y, 0.68)
    print(lab, np.round(co, 4), f"{time.time()-t0:.0f}s rows {len(Y)}")
    score(lab + " | training", co, train)
    score(lab + " | bench", co, bench)
