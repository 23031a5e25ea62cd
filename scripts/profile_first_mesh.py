#!/usr/bin/env python
"""The first and second surface of a saved map in one process: wall and CPU seconds,
numba compilation, page faults and peak RSS of each (issue 16: "the first mesh in a
process is slower").

Loads a map written by ``gmmgp run`` (``DIR/map``) and extracts its surface twice,
counting numba's compile events as ``scripts/warm_cache.py --measure`` does (cache
loads do not count). Run it on a checkout whose numba cache is cold (a fresh
``git archive``) and on a warm one to separate compilation from the rest.

    PYTHONPATH=$PWD .venv/bin/python scripts/profile_first_mesh.py out/street_run/map
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.append(str(ROOT))
sys.path.append(str(ROOT / "scripts"))


def _usage():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_minflt, r.ru_majflt, r.ru_maxrss / 1024.0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("map", help="a saved map folder (gmmgp run's DIR/map)")
    ap.add_argument("--repeat", type=int, default=2, help="surfaces to extract")
    args = ap.parse_args(argv)
    from warm_cache import CompileClock

    from gmmgp_app.pipeline import load_map

    t = time.perf_counter()
    m = load_map(args.map)
    print(f"load_map {time.perf_counter() - t:.2f} s", flush=True)
    for rep in range(args.repeat):
        f0, c0 = _usage(), time.process_time()
        with CompileClock() as cc:
            t = time.perf_counter()
            mesh = m.extract_surface()
            dt = time.perf_counter() - t
        f1 = _usage()
        print(f"mesh {rep + 1}: wall {dt:.2f} s, cpu {time.process_time() - c0:.2f} s, numba "
              f"compiling {cc.seconds:.2f} s ({cc.count} compilations), minor faults "
              f"{f1[0] - f0[0]}, major {f1[1] - f0[1]}, max RSS {f1[2]:.0f} MB, "
              f"{len(mesh.vertices)} vertices", flush=True)
        del mesh
    return 0


if __name__ == "__main__":
    sys.exit(main())
