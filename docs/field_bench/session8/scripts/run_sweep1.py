"""Session 8: the quantile fit (eq. variance_quantile_fit, smoothed pinball) of candidate
variance models on the training sixteen, scored as bins_fit.py scores.

    PYTHONPATH=$PWD python docs/field_bench/session8/scripts/run_sweep1.py FEATS:C[:MASK] ...
"""
import sys, time
sys.path.insert(0, 'docs/field_bench/session8/scripts')
import feature_sweep as S
from gmmgp_app.stages import farfield as F
T16 = S.TRAIN8 + S.TRAIN_NOISE
print("today (VARIANCE_COEF):", S.summary([], F.VARIANCE_COEF)[0], flush=True)
models = [a.split(":") for a in sys.argv[1:]]
for spec in models:
    feats = [f for f in spec[0].split("+") if f]
    c = float(spec[1]) if len(spec) > 1 else 0.0
    mask = spec[2] if len(spec) > 2 else "obs"
    t = time.time()
    coef = S.fit(T16, feats, c, mask)
    print(f"[{'+'.join(feats) or 'base5'} c={c} mask={mask}] ({time.time()-t:.0f}s) coef "
          + " ".join(f"{x:.3f}" for x in coef), "\n   ", S.summary(feats, coef, c)[0], flush=True)
