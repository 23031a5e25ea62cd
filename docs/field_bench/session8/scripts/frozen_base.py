"""Session 8: VARIANCE_COEF frozen, one extra feature's coefficient fitted on the
training sixteen (bin-coverage objective, feature_sweep.bin_objective), scored as
bins_fit.py scores.

    PYTHONPATH=$PWD python docs/field_bench/session8/scripts/frozen_base.py FEAT ...
"""
import sys

import numpy as np
from scipy.optimize import minimize_scalar

sys.path.insert(0, "docs/field_bench/session8/scripts")
import feature_sweep as S  # noqa: E402
from gmmgp_app.stages import farfield as F  # noqa: E402

T16 = S.TRAIN8 + S.TRAIN_NOISE
base = np.asarray(F.VARIANCE_COEF)
for f in sys.argv[1:]:
    packs = S._packs(T16, [f], 0.0)
    lo, hi = (-12.0, 2.0) if f == "acurv" else (-2.0, 2.0)
    res = minimize_scalar(lambda t: S.bin_objective(np.r_[base, t], packs), bounds=(lo, hi),
                          method="bounded", options=dict(xatol=1e-3))
    coef = np.r_[base, res.x]
    print(f"[VARIANCE_COEF + {f}: {res.x:.3f}]", S.summary([f], coef)[0], flush=True)
