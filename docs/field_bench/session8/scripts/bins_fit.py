import sys, time
sys.path.insert(0, 'docs/field_bench/session8/scripts')
import numpy as np
import feature_sweep as S
T16 = S.TRAIN8 + S.TRAIN_NOISE
on = dict(train16=T16, bench6=S.BENCH, train16_bench6=T16 + S.BENCH, train16_tuned=T16 + ["street", "sphere"], tuned=["street", "sphere"], train8=S.TRAIN8)
for spec in sys.argv[1:]:
    p = spec.split(":")
    feats = [f for f in p[0].split("+") if f]
    c = float(p[1]) if len(p) > 1 else 0.0
    names = on[p[2]] if len(p) > 2 else T16
    t = time.time()
    coef = S.fit_bins(names, feats, c)
    print(f"[bins-fit on {p[2] if len(p) > 2 else 'train16'}: {'+'.join(feats) or 'base5'} c={c}] ({time.time()-t:.0f}s) " + " ".join(f"{x:.3f}" for x in coef),
          "\n   ", S.summary(feats, coef, c)[0], flush=True)
