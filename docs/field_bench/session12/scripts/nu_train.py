#!/usr/bin/env python
"""Session 12 (field-15s): sensitivity of the t-component candidate to nu. The leave-self-
out vote with the @h variance fitted on street + sphere (as sweep.py loo3:base5@h), nu by
maximum likelihood on the training sixteen's observed queries instead of the tuned
scenes', scored on the bench six.

    PYTHONPATH=$PWD:docs/field_bench/session12/scripts python docs/field_bench/session12/scripts/nu_train.py
"""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.argv = ["x", "street,sphere", "loo3:base5@h"]
import sweep as S  # noqa: E402

SS = S.SS
SS.CACHE = Path("/tmp/field-15s/calib")


def load(name):
    path = SS.CACHE / f"{name}_seed0_far.vote-sphere_loo3.npz"
    d = {k: (v.item() if v.ndim == 0 else v) for k, v in np.load(path).items()}
    d["_res_path"] = SS.CACHE / f"{name}_seed0_far.vote-sphere_loo3_resample.npz"
    return d


S.KAPPA_AWARE[0] = True
S.ADD_HS[0] = True
coef = S.fit([load("street"), load("sphere")], [])
train = [load(n) for n in S.FV.train_set("16")]
nu = S.fit_nu(train, coef, [])
print("coef", np.round(coef, 4).tolist(), "nu (training sixteen)", round(nu, 2))
S.T_CORE[:] = ["all", nu]
tot, held = np.zeros(4, int), np.zeros(4, int)
for n in SS.SCENES:
    r = S.score(load(n), coef, [], SS.BASE[n])
    tot += r["n"]
    if not SS.B.SCENES[n]["tuned"]:
        held += r["n"]
    print(n, r["n"], " ".join(f"{x:.2f}" for x in r["c1"]), "|", " ".join(f"{x:.2f}" for x in r["c2"]))
print("bench", tot.tolist(), "held-out", held.tolist())
