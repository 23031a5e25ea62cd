import sys
sys.path.insert(0, 'docs/field_bench/session8/scripts')
import numpy as np
import feature_sweep as S
feats = [f for f in sys.argv[1].split("+") if f]
c = float(sys.argv[2]); coef = [float(x) for x in sys.argv[3].split(",")]
s, det = S.summary(feats, coef, c, detail=True)
print(s); print(det)
