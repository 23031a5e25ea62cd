#!/usr/bin/env python
"""Session 12 (field-15s): per bin, the share of observed queries (both unseen widths 0)
and the 1-sigma coverage of the log-linear part of eq. calibrated_var alone against the
log-linear part + kappa d^2 (what the map reports), VARIANCE_COEF_SPHERE, sphere-vote caches.

    PYTHONPATH=$PWD python docs/field_bench/session12/scripts/kappa_share.py bunny,pipes,sphere,street
"""
import sys, numpy as np
sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
import sweep as S
SS, FV, F = S.SS, S.FV, S.SS.F
from pathlib import Path
SS.CACHE = Path("/tmp/field-15s/calib")
coef = np.array(F.VARIANCE_COEF_SPHERE)
for n in sys.argv[1].split(","):
    d = SS.load(n, "sphere")
    t = FV.terms(d, coef)
    obs = (t["w_b"] == 0) & (t["w_e"] == 0)
    e = np.abs(d["y"] - d["mean"])
    v_ll = t["ll"]; v_k = t["kap"]
    print(n)
    for b in range(7):
        s = d["bin"] == b
        o = s & obs; u = s & ~obs
        z_ll = e / np.sqrt(v_ll)
        z_llk = e / np.sqrt(v_ll + v_k)
        print(f" bin{b} obs {o.sum()/s.sum():.2f} cov1(ll only, obs) {np.mean(z_ll[o]<=1):.2f} cov1(ll+kap, obs) {np.mean(z_llk[o]<=1):.2f} "
              f"unseen cov1(ll+kap) {np.mean(z_llk[u]<=1) if u.any() else float('nan'):.2f} kap share obs {np.median(v_k[o]/(v_ll[o]+v_k[o])):.2f}")
