"""Tuning latency in the app's window: seconds from Run to the new HGMM levels (after a
split-threshold change) and to the new GP points (after a d_m change) being in the 3D
view's scene, and to the first frame drawn after them.

    xvfb-run -a -s "-screen 0 1600x1000x24" python scripts/bench_tuning_latency.py \
        [SCAN] [--repeat 3] [--out out/bench/tuning_latency.json]

Runs ``gmmgp view SCAN`` with its 3D view (CPU renderer here) and a --script that, after
the first full run, alternates the threshold between 0.01 and 0.03 and d_m between two
values, each followed by Run; reads the per-stage latencies from the app's state
(``latency``: result in the scene; ``frame_latency``: the next frame read back).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scan", nargs="?", default="assets/demo_street.npz")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--size", default="1280x800")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="tuning-"))
    steps, names = [], []
    for i in range(a.repeat):
        t = 0.03 if i % 2 == 0 else 0.01
        steps += [{"threshold": t}, {"run": True}, {"state": str(work / f"t{i}.json")}]
        names.append(("threshold", f"t{i}.json"))
        dm = 0.03 if i % 2 == 0 else 0.015
        steps += [{"d_m": dm}, {"run": True}, {"state": str(work / f"d{i}.json")}]
        names.append(("d_m", f"d{i}.json"))
    steps.append({"quit": True})
    (work / "steps.json").write_text(json.dumps(steps))
    env = dict(os.environ, GMMGP_GUI_FRAME_TIMES="1")
    r = subprocess.run([sys.executable, "-m", "gmmgp_app.viz.gui", a.scan, "--size", a.size,
                        "--script", str(work / "steps.json")], env=env, text=True,
                       capture_output=True)
    if r.returncode != 0:
        print(r.stderr[-3000:], file=sys.stderr)
        return 1
    res = {"threshold_to_hgmm": [], "threshold_to_hgmm_frame": [], "d_m_to_gp": [],
           "d_m_to_gp_frame": []}
    for kind, f in names:
        st = json.loads((work / f).read_text())
        stage = "hgmm" if kind == "threshold" else "gp"
        key = "threshold_to_hgmm" if kind == "threshold" else "d_m_to_gp"
        res[key].append(st["latency"].get(stage))
        res[key + "_frame"].append(st["frame_latency"].get(stage))
    out = {"scan": a.scan, "size": a.size, "load": os.getloadavg(),
           "seconds": res,
           "median": {k: statistics.median([x for x in v if x is not None])
                      if any(x is not None for x in v) else None for k, v in res.items()}}
    text = json.dumps(out, indent=2)
    print(text)
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
