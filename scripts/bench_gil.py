"""How long the stages keep Python's other threads (the app's window) waiting.

    python scripts/bench_gil.py [SCAN] [--out FILE.json]

Maps ``SCAN`` (default: the demo scan) and meshes it in a worker thread, as the app
does, while the main thread ticks every 10 ms and records how late each tick comes.
A compiled kernel that holds the GIL delays every tick until it returns: the app's
window (its callbacks, mouse handling, the frame read-backs) waits the same way.
Reports the largest delay and the 99th percentile, and the mapping's wall time.
"""

from __future__ import annotations

import argparse
import json
import os
import threading
import time

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scan", nargs="?", default="assets/demo_street.npz")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    import gmmgp_app as gm

    scan = gm.read_scan(a.scan)
    gm.build_map(scan)  # warm: imports, numba cache loads, lazy tables
    box = {}

    def work():
        t = time.perf_counter()
        smap = gm.build_map(scan)
        box["build_s"] = time.perf_counter() - t
        t = time.perf_counter()
        smap.extract_surface()
        box["surface_s"] = time.perf_counter() - t

    th = threading.Thread(target=work)
    late = []
    th.start()
    tick = 0.010
    while th.is_alive():
        t0 = time.perf_counter()
        time.sleep(tick)
        late.append(time.perf_counter() - t0 - tick)
    th.join()
    late = np.asarray(late)
    out = {"scan": a.scan, "load": os.getloadavg(), **box, "ticks": int(len(late)),
           "late_max_s": float(late.max()), "late_p99_s": float(np.percentile(late, 99)),
           "late_over_0.1s": int((late > 0.1).sum())}
    print(json.dumps(out, indent=2))
    if a.out:
        with open(a.out, "w") as f:
            json.dump(out, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
