"""Session 8 (speed-16o): predict (mean, variance, gradient; blended and far=False) on the demo
scan points + offsets (408,752) and 5,000 uniform queries in the scan's bounding box grown by 5 m; saved to argv[2]
for np.array_equal between trees:
    NUMBA_NUM_THREADS=1 PYTHONPATH=<tree> python docs/speed/s8_16o/equal_predict.py D/map OUT.npz
"""
import sys, numpy as np
import gmmgp_app.pipeline as P
smap = P.load_map(sys.argv[1])
pts = np.load('assets/demo_street.npz')['points'] - smap.offset
rng = np.random.default_rng(0)
q = np.concatenate([pts + rng.normal(0, 0.05, pts.shape) for _ in range(4)])
lo, hi = pts.min(0), pts.max(0)
r = np.random.default_rng(1).uniform(lo - 5, hi + 5, (5000, 3))
o = {}
for name, x in (('scan', q), ('rand', r)):
    m, v, g = smap.predict(x, return_grad=True)
    o[name + '_m'], o[name + '_v'], o[name + '_g'] = m, v, g
    m2, v2, g2 = smap.predict(x, return_grad=True, far=False)
    o[name + '_nm'], o[name + '_nv'], o[name + '_ng'] = m2, v2, g2
np.savez(sys.argv[2], **o)
