#!/usr/bin/env python
"""How much each field weighs in the blended mean at the surface lattice (issue 16).

The map's mean mixes the GP field and the far field by inverse variance (eq. blend,
``stages/farfield.py``): ``w_far = v_gp' / (v_gp' + v_far)``, ``v_gp' = v_gp + (g r)^2``.
Skipping one field's evaluation where its weight is negligible would save its cost
(the far field's 16-NN and IMLS, or the GP's pair solves and GMR prior); this script
measures whether it is negligible. It meshes a saved map, records the lattice nodes
the surface stage evaluates, and on a seeded sample of them reports the quantiles of
both weights, of the two means' difference ``|m_gp - m_far|`` and of the change of the
blended mean were either field dropped (``w |m_gp - m_far|``), with the upper bound
of the GP's weight that needs no GP evaluation (``v_gp >= 0``).

    PYTHONPATH=$PWD .venv/bin/python scripts/blend_weights.py out/street_run/map \\
        [--sample 300000] [--json out/blend_street.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

QUANTILES = (0.0, 0.01, 0.1, 0.5, 0.9, 0.99, 1.0)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("map", help="saved map folder (gmmgp run --out DIR writes DIR/map)")
    ap.add_argument("--sample", type=int, default=300_000, help="lattice nodes evaluated")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", help="write the report here")
    args = ap.parse_args(argv)

    from gmmgp_app.pipeline import load_map

    smap = load_map(args.map)
    nodes = []
    predict_mean = smap.predict_mean

    def recording(x):
        nodes.append(np.array(x))
        return predict_mean(x)

    smap.predict_mean = recording
    t = time.perf_counter()
    mesh = smap.extract_surface()
    seconds = time.perf_counter() - t
    x = np.concatenate(nodes)
    rng = np.random.default_rng(args.seed)
    s = x[rng.choice(len(x), min(len(x), args.sample), replace=False)]
    bf = smap._blended()
    m_gp, v_gp = bf.base.predict(s)
    far = bf.far.components(s)
    v_gp_w = v_gp + (bf.gp_growth * far["r"]) ** 2      # the GP's variance for the weights
    w_far = v_gp_w / (v_gp_w + far["var"])
    diff = np.abs(m_gp - far["mean"])
    q = lambda a: [float(v) for v in np.quantile(a, QUANTILES)]  # noqa: E731
    rep = dict(map=str(args.map), lattice_nodes=int(len(x)), sampled=int(len(s)),
               vertices=int(len(mesh.vertices)), surface_s=seconds, quantiles=list(QUANTILES),
               w_far=q(w_far), w_gp=q(1 - w_far),
               w_gp_upper_bound=q(far["var"] / ((bf.gp_growth * far["r"]) ** 2 + far["var"])),
               abs_mean_difference_m=q(diff),
               change_without_far_m=q(w_far * diff), change_without_gp_m=q((1 - w_far) * diff),
               r_m=q(far["r"]), v_gp=q(v_gp), v_far=q(far["var"]),
               frac_change_without_far_below={str(t): float(np.mean(w_far * diff < t))
                                              for t in (1e-6, 1e-5, 1e-4)},
               frac_change_without_gp_below={str(t): float(np.mean((1 - w_far) * diff < t))
                                             for t in (1e-6, 1e-5, 1e-4)})
    print(json.dumps(rep, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(rep, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
