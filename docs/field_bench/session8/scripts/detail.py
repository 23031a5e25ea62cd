"""Session 8: per-bin 1 / 2-sigma coverages of one candidate on every scene.

    PYTHONPATH=$PWD python docs/field_bench/session8/scripts/detail.py FEATS C t0,t1,...
"""
import sys

sys.path.insert(0, "docs/field_bench/session8/scripts")
import feature_sweep as S  # noqa: E402

feats = [f for f in sys.argv[1].split("+") if f]
c = float(sys.argv[2])
coef = [float(x) for x in sys.argv[3].split(",")]
s, det = S.summary(feats, coef, c, detail=True)
print(s)
print(det)
