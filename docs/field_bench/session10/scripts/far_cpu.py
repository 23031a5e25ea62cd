#!/usr/bin/env python
"""CPU time of the far field's kernel (FarField.components, k-NN search included)
with the plane and the sphere vote: the bench street's handed 10 %, its map built once
with the defaults, then the same far-field points queried at the bench's 20000 near
queries and at a 0.2 m lattice within 0.5 m of the data; medians of 5 runs each,
interleaved, process CPU seconds (time.process_time: both cores' time summed)."""
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[4] / "scripts"))
import bench_accuracy as B  # noqa: E402
import gmmgp_app as gm  # noqa: E402
from gmmgp_app.stages.farfield import FarField  # noqa: E402

_, _, handed, q, y, dist = B.scene_queries("street", B.SCENES["street"], 0, 20000, 100)
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    smap = gm.build_map(handed, gm.MappingConfig())
far = smap.far
lo, hi = far.points.min(0), far.points.max(0)
g = np.mgrid[lo[0]:hi[0]:0.2, lo[1]:hi[1]:0.2, lo[2]:hi[2]:0.2].reshape(3, -1).T
g = g[far.tree.query(g, workers=-1)[0] < 0.5]
g = np.concatenate([q, g])
p = far.params()
fields = {v: FarField(far.points, far.normals, p.pop("rho0"), p.pop("noise"),
                      **{**p, "vote": v}) for v in ("plane", "sphere") if (p := far.params())}
for f in fields.values():
    f.components(g[:1000])  # compile / warm
t = {v: [] for v in fields}
for _ in range(5):
    for v, f in fields.items():
        t0 = time.process_time()
        f.components(g)
        t[v].append(time.process_time() - t0)
mp, ms = np.median(t["plane"]), np.median(t["sphere"])
print(f"{len(q)} bench + {len(g) - len(q)} lattice queries; CPU s plane {mp:.3f} (runs {np.round(t['plane'], 3).tolist()}), "
      f"sphere {ms:.3f} (runs {np.round(t['sphere'], 3).tolist()}): x{ms / mp:.2f}")
