"""Size and time overhead of recording every stage to rerun.

Runs what ``gmmgp run SCAN --rrd FILE`` runs (build_map, then the gmmgp and hgmm
surfaces) twice: once without an observer, once with the RerunObserver writing
an .rrd, and reports

* ``observer_seconds``: wall time spent inside the observer's calls (measured
  directly around every call, so it does not depend on the two runs' noise);
* ``overhead_pct``: ``observer_seconds / plain_seconds * 100`` (target < 15);
* ``difference_pct``: the difference of the two run times, for reference (noisy
  on a shared machine);
* ``rrd_bytes`` and the per-entity-kind chunk count.

Usage::

    python scripts/bench_rerun_overhead.py                       # demo scan, default voxel
    python scripts/bench_rerun_overhead.py --voxel 0.2 --scan out/box/scan.npz

Writes ``out/bench/rerun_overhead.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


class _Timed:
    def __init__(self, inner):
        self.inner, self.seconds, self.per_stage = inner, 0.0, {}

    def on_stage(self, name, payload):
        t0 = time.perf_counter()
        self.inner.on_stage(name, payload)
        dt = time.perf_counter() - t0
        self.seconds += dt
        self.per_stage[name] = self.per_stage.get(name, 0.0) + dt


def _run(scan, cfg, observer):
    from gmmgp_app.pipeline import StagePayload, build_map
    from gmmgp_app.stages.surface import extract_surface

    t0 = time.perf_counter()
    smap = build_map(scan, cfg, observer=observer)
    meshes = {"gmmgp": smap.extract_surface()}
    sc = cfg.surface
    meshes["hgmm"] = extract_surface(smap.prior.predict, smap.seed_points,
                                     voxel_size=sc.voxel_size, max_std=sc.max_std)
    if observer is not None:
        observer.on_stage("surface", StagePayload(meshes, time.perf_counter() - t0))
    return time.perf_counter() - t0, smap, meshes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scan", default=str(ROOT / "assets" / "demo_street.npz"))
    ap.add_argument("--voxel", type=float, default=None, help="surface.voxel_size override")
    ap.add_argument("--out", default=str(ROOT / "out" / "bench"))
    args = ap.parse_args()

    import gmmgp_app as gm
    from gmmgp_app.datasets import read_scan
    from gmmgp_app.viz.rerun_observer import RerunObserver

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scan = read_scan(args.scan)
    cfg = gm.MappingConfig()
    if args.voxel:
        cfg = cfg.replace("surface.voxel_size", args.voxel)
    # Warm numba caches so neither run pays for compilation.
    small = scan.select(np.arange(0, len(scan), max(1, len(scan) // 3000)))
    gm.build_map(small, cfg.replace("surface.voxel_size", 0.5))

    plain_s, _, meshes = _run(scan, cfg, None)
    rrd = out / "rerun_overhead.rrd"
    timed = _Timed(RerunObserver(rrd, config=cfg))
    t0 = time.perf_counter()
    timed.inner.log_config(cfg)
    rr_s, _, _ = _run(scan, cfg, timed)
    tc = time.perf_counter()
    timed.inner.close()
    close_s = time.perf_counter() - tc
    observer_s = timed.seconds + close_s
    res = {
        "scan": str(args.scan), "n_points": len(scan),
        "voxel_size": cfg.surface.voxel_size,
        "vertices": {k: len(m.vertices) for k, m in meshes.items()},
        "plain_seconds": plain_s, "with_rerun_seconds": rr_s + close_s,
        "observer_seconds": observer_s,
        "observer_seconds_per_stage": timed.per_stage, "close_seconds": close_s,
        "overhead_pct": 100.0 * observer_s / plain_s,
        "difference_pct": 100.0 * (rr_s + close_s - plain_s) / plain_s,
        "rrd_bytes": rrd.stat().st_size,
        "rrd_mib": rrd.stat().st_size / 2 ** 20,
        "machine": platform.platform(), "python": platform.python_version(),
        "total_wall_seconds": time.perf_counter() - t0,
    }
    path = out / "rerun_overhead.json"
    path.write_text(json.dumps(res, indent=2))
    print(json.dumps(res, indent=2))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
