#!/usr/bin/env python
"""Session 12 (field-15s): build fit_variance.py's per-query caches and keep, beside each,
the map's far field (hit points, normals, parameters) and the queries, so that new
per-query variance features can be computed offline without rebuilding the map.

    PYTHONPATH=$PWD python docs/field_bench/session12/scripts/build_caches.py CACHE \
        SCENES [--set far.vote=sphere]

SCENES: comma-separated bench scenes, ``bench6``, ``train16``. Writes
``CACHE/<scene>_seed0[_far.vote-sphere].npz`` (fit_variance.scene_case) and
``CACHE/<same stem>_far.npz``.
"""
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[4] / "scripts"))
import fit_variance as FV  # noqa: E402
import gmmgp_app as gm  # noqa: E402

_last = {}
_build = gm.build_map


def _capture(*a, **k):
    m = _build(*a, **k)
    _last["map"] = m
    return m


gm.build_map = _capture


def main():
    cache = Path(sys.argv[1])
    names = []
    for n in sys.argv[2].split(","):
        names += (list(FV.B.SCENES) if n == "bench6" else FV.train_set("16") if n == "train16"
                  else [n])
    overrides = [a.split("=", 1)[1] if a.startswith("--set=") else a for a in sys.argv[3:]
                 if a != "--set"]
    tag = "".join(f"_{o.replace('=', '-')}" for o in overrides)
    for n in names:
        far_path = cache / f"{n}_seed0{tag}_far.npz"
        if far_path.exists():
            continue
        t = time.time()
        (cache / f"{n}_seed0{tag}.npz").unlink(missing_ok=True)
        _last.clear()
        d = FV.scene_case(n, 0, cache, overrides)
        far = _last["map"].far
        np.savez(far_path, points=far.points, normals=far.normals, q=d["q"],
                 **{k: np.asarray(v) for k, v in far.params().items()})
        print(f"{n}{tag}: {time.time() - t:.0f} s", flush=True)


if __name__ == "__main__":
    main()
