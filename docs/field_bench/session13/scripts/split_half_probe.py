import numpy as np
from gmmgp_app.stages.farfield import FarField
rng = np.random.default_rng(2)
sigma = 0.008
n=16000
p = np.c_[rng.uniform(-2, 2, (n, 2)), rng.normal(0.0, sigma, n)]
nn = np.tile([0.0, 0.0, 1.0], (n, 1))
for lo,hi in ((0,0.05),(0.05,0.3),(0.5,2.0)):
    s = rng.choice([-1.0, 1.0], 3000)
    q = np.c_[rng.uniform(-0.5, 0.5, (3000, 2)), s * rng.uniform(lo, hi, 3000)]
    for vote in ("plane","sphere"):
      for cap in (0.0, 3.0):
        c = FarField(p, nn, 0.032, sigma, robust_scale=1.0, vote=vote, self_out_cap=cap).components(q, split_half=True)
        e = (c["mean"] - q[:, 2]) * s
        print(lo,hi,vote,cap, "median %.2f mm rmse %.2f mm sd %.2f  sqrt(mean hs) %.2f mse/hs %.2f" % (1e3*np.median(e), 1e3*np.sqrt(np.mean(e**2)), 1e3*e.std(), 1e3*np.sqrt(np.mean(c["half"])), np.mean(e**2)/np.mean(c["half"])))
