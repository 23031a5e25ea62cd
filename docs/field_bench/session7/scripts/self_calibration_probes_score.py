import sys
sys.path.insert(0, "scripts")
from pathlib import Path
import numpy as np
import fit_variance as FV
from gmmgp_app.stages import farfield as F
C = Path("out/calib")
mode = sys.argv[1] if len(sys.argv) > 1 else "noise"
bench = ["street","sphere","street2","courtyard","pipes","bunny"]
train = list(FV.TRAIN_SCENES)

def cover_c(u2, vll, extra, target=0.68):
    lo, hi = -8.0, 8.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        cov = np.mean(u2 <= np.exp(mid) * vll + extra)
        if cov < target: lo = mid
        else: hi = mid
    return 0.5 * (lo + hi)

def delta(name, ngroups=3, use_noise=True, slope=True):
    d = dict(np.load(C / f"probes_{name}.npz"))
    d = {k: (v.item() if v.ndim == 0 else v) for k, v in d.items()}
    tm = FV.terms(d)
    u2 = (d["mean"] - d["y"]) ** 2
    extra = tm["kap"] + (d["noise"] ** 2 if use_noise else 0.0)
    x1 = np.log((d["r"] ** 2 + d["h"] ** 2) / d["h"] ** 2)
    if not slope:
        return np.array([cover_c(u2, tm["ll"], extra), 0.0])
    edges = np.quantile(x1, np.linspace(0, 1, ngroups + 1))
    xs, cs = [], []
    for g in range(ngroups):
        s = (x1 >= edges[g]) & (x1 <= edges[g + 1])
        xs.append(np.median(x1[s])); cs.append(cover_c(u2[s], tm["ll"][s], extra[s] if np.ndim(extra) else extra))
    A = np.stack([np.ones(ngroups), xs], 1)
    return np.linalg.lstsq(A, np.array(cs), rcond=None)[0]

base = np.asarray(F.VARIANCE_COEF)
for variant, kw in [("s6 (no self-calibration)", None), ("intercept, noise", dict(use_noise=True, slope=False)),
                    ("intercept+slope, noise", dict(use_noise=True)), ("intercept+slope, no noise", dict(use_noise=False))]:
    for group, names in (("training", train), ("bench", bench)):
        rows = []
        tot = np.zeros(3, int); held = np.zeros(3, int)
        import json
        basej = {r["scene"]: r["methods"] for r in json.loads(Path("docs/field_bench/bench_accuracy.json").read_text())["results"]}
        for n in names:
            dd = FV.scene_case(n, 0, C)
            dl = np.zeros(2) if kw is None else delta(n, **kw)
            coef = base.copy(); coef[:2] += dl
            r = FV.coverage_bins(dd, tuple(coef), basej.get(n))
            v = np.array([r["n1"], r["n2"], r["nll"] or 0]); tot += v
            if n in ("street2","courtyard","pipes","bunny"): held += v
            rows.append(f"  {n}: d=({dl[0]:+.2f},{dl[1]:+.3f}) [{r['n1']}/{r['n2']}/{r['nll']}] 1s " + " ".join(f"{c:.2f}" for c in r["c1"]) + " | 2s " + " ".join(f"{c:.2f}" for c in r["c2"]))
        print(f"{variant} / {group}: total {tot.tolist()} held-out4 {held.tolist()}")
        print("\n".join(rows))
