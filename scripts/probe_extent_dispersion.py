#!/usr/bin/env python
"""Does the scan tell where a surface stops continuing as its tangent plane? (docs/field.md,
field-15e, item 2: a cue measured, not built.)

For the queries past the end of the data (extent width w_e > h, eq. unseen_extent) of
each bench scene (``scripts/bench_accuracy.py`` protocol, defaults, seed 0), the share
whose error exceeds 0.3 w_e ("ended": the surface did not continue as the located
plane), per quartile of the neighbours' normal dispersion ``1 - |n_bar|`` (n_bar the far
field's weighted mean normal, ``FarField.components(..., return_grad=True)``): planes
give ~0, corners and curved surfaces more.

Example::

    python scripts/probe_extent_dispersion.py --scenes street,sphere,courtyard,pipes
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_accuracy as B  # noqa: E402
import fit_variance as FV  # noqa: E402

import gmmgp_app as gm  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", default="street,sphere,courtyard,pipes")
    p.add_argument("--cache", default="out/calib")
    a = p.parse_args(argv)
    for name in a.scenes.split(","):
        spec = B.SCENES[name]
        _, _, handed, q, _, _ = B.scene_queries(name, spec, 0, 20000, 6000)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            smap = gm.build_map(handed)
        disp = 1.0 - np.linalg.norm(smap.far.components(q, True)["grad"], axis=1)
        d = FV.scene_case(name, 0, Path(a.cache))
        t = FV.terms(d)
        on = t["w_e"] > d["h"]
        ended = np.abs(d["y"] - d["mean"])[on] > 0.3 * t["w_e"][on]
        qs = np.quantile(disp[on], [0.25, 0.5, 0.75])
        edges = [0.0, *qs, np.inf]
        shares = [ended[(disp[on] >= lo) & (disp[on] < hi)].mean()
                  for lo, hi in zip(edges[:-1], edges[1:])]
        print(f"| {name} | {on.sum()} | {ended.mean():.2f} | "
              + " / ".join(f"{x:.4f}" for x in qs) + " | "
              + " / ".join(f"{x:.2f}" for x in shares) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
