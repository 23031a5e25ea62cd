"""Session 8 (speed-16o): CPU seconds of BlockGrid.cover and SurfaceMap.predict (mean,
variance, gradient) on the demo scan's points plus small offsets (~409k queries).

    gmmgp run assets/demo_street.npz --out D --no-mesh
    NUMBA_NUM_THREADS=1 PYTHONPATH=<tree> python docs/speed/s8_16o/bench_cover.py D/map LABEL

Run once per tree (a copy of main's gmmgp_app, then this branch), alternating, in fresh
processes; one JSON line per run. The GMR prior's cell cache is cleared before timing.
"""
import json
import resource
import sys

import numpy as np

import gmmgp_app.pipeline as P


def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


smap = P.load_map(sys.argv[1])
pts = np.load("assets/demo_street.npz")["points"] - smap.offset
rng = np.random.default_rng(0)
q = np.concatenate([pts + rng.normal(0, 0.05, pts.shape) for _ in range(4)])
grid = smap.gp.grid
grid.cover(q[:100])
smap.predict(q[:2000], return_grad=True)        # compile / load the kernels
smap.prior.clear_cache()
t = cpu()
pi, bi = grid.cover(q)
t_cover = cpu() - t
t = cpu()
smap.predict(q, return_grad=True)
t_pred = cpu() - t
print(json.dumps(dict(tree=sys.argv[2], n_queries=len(q), n_blocks=grid.n_blocks,
                      n_pairs=len(pi), cover_cpu_s=round(t_cover, 4),
                      predict_cpu_s=round(t_pred, 4))))
