"""Tuning latency in the app's window: seconds from Run to the new HGMM levels (after a
split-threshold change) and to the new GP points (after a d_m change) being in the 3D
view's scene, and to the first frame drawn after them.

    xvfb-run -a -s "-screen 0 1600x1000x24" python scripts/bench_tuning_latency.py \
        [SCAN] [--repeat 3] [--out out/bench/tuning_latency.json]

Runs ``gmmgp view SCAN`` with its 3D view (CPU renderer here) and a --script that, after
the first full run, alternates the threshold between 0.01 and 0.03 and d_m between two
values, each followed by Run; reads the per-stage latencies from the app's state
(``latency``: result in the scene; ``frame_latency``: the next frame read back).

Before each change the script sleeps ``--look`` seconds (default 5), as a user who
looks at the result before moving a slider. With ``--look 0`` Run comes as soon as the
previous run's last stage is in the scene, while the frame showing it (the surface:
~3.8 s of rasterizer CPU on Mesa's llvmpipe at 1280x800) is still being drawn, and the
new stage's frame waits behind it (a frame in flight is not cancelled; waiting for that
frame through a read-back does not help either, a read-back is followed by one more
frame of the same scene). Quiet machine, medians of 3: look 5 s: HGMM levels on
screen 0.40 s, GP points 0.86 s; look 0: 1.85 s and 2.39 s.

    python scripts/bench_tuning_latency.py [SCAN] --model [--repeat 3]

measures the same without the window: the model's re-run from the affected stage until
the HGMM (threshold) or GP points (d_m) arrive, and the time to build their geometry.
The thresholds alternate 0.03 / 0.005 around the default 0.01 run. The model keeps its
HGMM node fits between runs (``pipeline.HGMMFitCache``): a higher threshold splits only
nodes fitted before (no EM), the first move to 0.005 fits the nodes 0.01 left unsplit
(the slow entry of ``seconds.threshold_to_hgmm``), later moves reuse them.
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
    ap.add_argument("--look", type=float, default=5.0,
                    help="seconds between a run's end and the next change (a user looking "
                         "at the result; 0: back to back)")
    ap.add_argument("--model", action="store_true",
                    help="measure the model and the geometry builders, no window")
    a = ap.parse_args(argv)
    if a.model:
        out = model_latency(a.scan, a.repeat)
        return _emit(out, a.out)
    work = Path(tempfile.mkdtemp(prefix="tuning-"))
    steps, names = [], []
    look = [{"sleep": a.look}] if a.look > 0 else []  # the user looks at the result
    for i in range(a.repeat):
        t = 0.03 if i % 2 == 0 else 0.01
        steps += look + [{"threshold": t}, {"run": True}, {"state": str(work / f"t{i}.json")}]
        names.append(("threshold", f"t{i}.json"))
        dm = 0.03 if i % 2 == 0 else 0.015
        steps += look + [{"d_m": dm}, {"run": True}, {"state": str(work / f"d{i}.json")}]
        names.append(("d_m", f"d{i}.json"))
    steps.append({"quit": True})
    (work / "steps.json").write_text(json.dumps(steps))
    r = subprocess.run([sys.executable, "-m", "gmmgp_app.viz.gui", a.scan, "--size", a.size,
                        "--script", str(work / "steps.json")], text=True,
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
           "look_seconds": a.look,
           "seconds": res,
           "median": {k: statistics.median([x for x in v if x is not None])
                      if any(x is not None for x in v) else None for k, v in res.items()}}
    return _emit(out, a.out)


def _emit(out: dict, path) -> int:
    """Print the result as JSON and write it to ``path`` when given."""
    text = json.dumps(out, indent=2)
    print(text)
    if path:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(text)
    return 0


def model_latency(scan: str, repeat: int) -> dict:
    """Seconds from a setting change to the stage's result (model.compute from the first
    affected stage, stopped after it) and to its geometry (the layer's builder)."""
    import time

    from gmmgp_app.viz.gui_model import Cancelled, ViewerModel, first_affected_stage
    from gmmgp_app.viz.gui_screenshot import SceneState

    m = ViewerModel.open(scan, voxel_size=0.1)
    t = time.perf_counter()
    m.results = m.compute("prepare", m.results.config, 0.1)
    full = time.perf_counter() - t

    def until(stage, cfg):
        t0, got = time.perf_counter(), {}

        def on_stage(n, r):
            if n == stage and "t" not in got:
                got["t"], got["r"] = time.perf_counter() - t0, r
        base = m.results
        try:
            m.compute(first_affected_stage(base, cfg, 0.1), cfg, 0.1, base=base,
                      on_stage=on_stage, cancelled=lambda: "t" in got)
        except Cancelled:
            pass
        st = SceneState(ViewerModel(got["r"], "x"), stage, level=2)
        t1 = time.perf_counter()
        st.layer_geometry("ellipsoids" if stage == "hgmm" else "gp_points")[1]()
        return got["t"], time.perf_counter() - t1

    res = {"threshold_to_hgmm": [], "hgmm_geometry": [], "d_m_to_gp": [], "gp_geometry": []}
    for i in range(repeat):
        c = m.results.config
        a, b = until("hgmm", c.replace("hgmm.split_threshold", 0.03 if i % 2 == 0 else 0.005))
        res["threshold_to_hgmm"].append(a)
        res["hgmm_geometry"].append(b)
        a, b = until("gp", c.replace("gp.d_m", 0.03 if i % 2 == 0 else 0.015))
        res["d_m_to_gp"].append(a)
        res["gp_geometry"].append(b)
    return {"scan": scan, "full_run_s": full, "seconds": res, "load": os.getloadavg(),
            "median": {k: statistics.median(v) for k, v in res.items()}}


if __name__ == "__main__":
    sys.exit(main())
