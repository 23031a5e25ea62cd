"""Session 8: the bin-coverage fit (feature_sweep.fit_bins) of candidate variance models,
scored on the bench six, the held-out four, the training eight and the noise eight.

    PYTHONPATH=$PWD python docs/field_bench/session8/scripts/bins_fit.py FEATS:C[:SET] ...

FEATS: extra features joined by + (empty: the five of eq. calibrated_var), C: the noise
floor, SET: train16 (default), train8, train16_tuned, tuned, bench6 (in sample: oracle).
"""
import sys
import time

sys.path.insert(0, "docs/field_bench/session8/scripts")
import feature_sweep as S  # noqa: E402

T16 = S.TRAIN8 + S.TRAIN_NOISE
on = dict(train16=T16, bench6=S.BENCH, train16_bench6=T16 + S.BENCH,
          train16_tuned=T16 + ["street", "sphere"], tuned=["street", "sphere"],
          train8=S.TRAIN8)
for spec in sys.argv[1:]:
    p = spec.split(":")
    feats = [f for f in p[0].split("+") if f]
    c = float(p[1]) if len(p) > 1 else 0.0
    names = on[p[2]] if len(p) > 2 else T16
    t = time.time()
    coef = S.fit_bins(names, feats, c)
    print(f"[bins-fit on {p[2] if len(p) > 2 else 'train16'}: {'+'.join(feats) or 'base5'} "
          f"c={c}] ({time.time() - t:.0f}s) " + " ".join(f"{x:.3f}" for x in coef),
          "\n   ", S.summary(feats, coef, c)[0], flush=True)
