#!/usr/bin/env python
"""Make the small bundled demo scan ``assets/demo_street.npz`` and its mesh.

What it writes
--------------
``assets/demo_street.npz``
    A simulated mobile-mapping scan of the synthetic ``street`` scene
    (:func:`gmmgp_app.synth.scan_scene`, two tilted profile scanners, 8 mm
    range noise, 5 % dropouts) with the keys

    ``points``  (N, 3) float32, metres, local frame
    ``origins`` (N, 3) float32, the scanner position at each pulse
    ``labels``  (N,) int64, object class (1 ground, 2 facade, 3 balcony,
                4 pole, 5 car, 6 window; see ``gmmgp_app.synth.LABELS``)

    Coordinates are stored as **float32** to keep the asset small (all
    coordinates are below 50 m, so the rounding is under 4 micrometres, far
    below the 8 mm noise); readers convert them to float64.
``assets/demo_street_mesh.ply``
    The exact ground-truth mesh (binary PLY, float64 vertices). Its signed
    distance (free space positive) is ``gmmgp_app.synth.make_scene("street").sdf``.

The output is deterministic: the same ``--seed`` and ``--density`` give the
same bytes of array data. The script checks the total size stays under 5 MB.

Usage
-----
    python scripts/make_demo_asset.py                 # defaults: density 0.08, seed 0
    python scripts/make_demo_asset.py --out /tmp/assets --density 0.05
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAX_BYTES = 5_000_000


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description="Make the bundled demo scan assets/demo_street.npz (+ ground-truth mesh).",
        epilog="example: python scripts/make_demo_asset.py --density 0.08 --seed 0")
    ap.add_argument("--out", default=str(ROOT / "assets"), help="output folder (default: assets/)")
    ap.add_argument("--density", type=float, default=0.08,
                    help="scan density relative to the 1.3M-point street (default 0.08, ~100k points)")
    ap.add_argument("--seed", type=int, default=0, help="noise/dropout seed (default 0)")
    args = ap.parse_args(argv)

    import numpy as np

    from gmmgp_app.synth import save_mesh_ply, save_scan_npz, scan_scene

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scan, scene = scan_scene("street", density=args.density, seed=args.seed)
    npz = save_scan_npz(out / "demo_street.npz", scan.points, scan.origins, scan.labels,
                        dtype=np.float32)
    ply = save_mesh_ply(out / "demo_street_mesh.ply", scene)
    total = npz.stat().st_size + ply.stat().st_size
    summary = {"points": len(scan), "density": args.density, "seed": args.seed,
               "npz_bytes": npz.stat().st_size, "ply_bytes": ply.stat().st_size,
               "faces": int(len(scene.faces))}
    print(json.dumps(summary))
    if total >= MAX_BYTES:
        print(f"error: the demo assets take {total} bytes, more than {MAX_BYTES}; "
              "lower --density.", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
