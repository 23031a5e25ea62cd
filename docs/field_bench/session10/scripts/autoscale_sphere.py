#!/usr/bin/env python
"""tests/test_autoscale.py::test_coverage_on_a_sphere_scene_is_near_calibrated with each
far.vote (the test runs the default): coverage outside and inside, RMSE outside.
Run from the repo root with PYTHONPATH=$PWD."""
import numpy as np, warnings, sys
sys.path.insert(0, 'tests')
import gmmgp_app as gm
from gmmgp_app.synth import scan_scene
from test_autoscale import sphere_sdf
for vote in ("plane", "sphere"):
    scan, scene = scan_scene("sphere", density=0.05, seed=5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        smap = gm.build_map(scan, gm.MappingConfig().with_overrides([f"far.vote={vote}"]))
    rng = np.random.default_rng(3)
    p = scan.points[rng.integers(0, len(scan), 6000)]
    u = rng.normal(size=p.shape)
    u *= (0.3 * rng.random(len(p)) ** (1 / 3) / np.linalg.norm(u, axis=1))[:, None]
    q = p + u
    y = sphere_sdf(q, (0, 0, 0), 1.0)
    mean, var = smap.predict(q)
    z = np.abs(y - mean) / np.sqrt(var)
    out = mean > 0
    print(vote, "out 1s %.3f 2s %.3f, in 2s %.3f, rmse out mm %.2f" % (np.mean(z[out] <= 1), np.mean(z[out] <= 2), np.mean(z[~out] <= 2), 1000*np.sqrt(np.mean((y-mean)[out]**2))), flush=True)
