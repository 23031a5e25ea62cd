#!/usr/bin/env python
"""Session 12 (field-15s): main's plane vote and VARIANCE_COEF with the Student-t
components of sweep.py (TMixture), nu by maximum likelihood on street + sphere; scored
on the bench six from the plane-vote caches.

    PYTHONPATH=$PWD python docs/field_bench/session12/scripts/plane_t.py
"""
import sys
from pathlib import Path
import numpy as np
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.argv = ["x", "street,sphere", "plane:base5"]
import sweep as S
SS = S.SS
SS.CACHE = Path("/tmp/field-15s/calib")
from gmmgp_app.stages import farfield as F
cases = {n: S.FV.scene_case(n, 0, SS.CACHE, []) for n in SS.SCENES}
coef = np.array(F.VARIANCE_COEF)
nu = S.fit_nu([cases["street"], cases["sphere"]], coef, [])
print("nu", nu)
S.T_CORE[:] = ["all", nu]
tot = np.zeros(4, int); held = np.zeros(4, int)
for n, d in cases.items():
    r = S.score(d, coef, [], SS.BASE[n])
    tot += r["n"]
    if not SS.B.SCENES[n]["tuned"]: held += r["n"]
    print(n, r["n"], " ".join(f"{x:.2f}" for x in r["c1"]), "|", " ".join(f"{x:.2f}" for x in r["c2"]))
print("plane + t components: bench", tot, "held-out", held)
