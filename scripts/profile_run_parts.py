"""CPU and wall seconds of the named parts of one ``gmmgp run`` outside the surface stage.

Wraps functions of the run (read, the scan's k-d tree, the scale measurement, the
automatic subsample voxel, the surface grid check, the map's save or background write,
the PLY colours and write, numba's cache loads) with timers (wall, and CPU of the calling
thread: the HGMM's threads and a background save are not charged to the main thread's
parts), and the stages through the pipeline's stage events (process CPU). With
``--stub-surface MESH.npz`` (vertices, faces, vertex_variance) the surface extraction
returns that mesh instead, so the rest of a street run can be repeated in ~15 s.

    PYTHONPATH=$PWD .venv/bin/python scripts/profile_run_parts.py out/parts.json \\
        --stub-surface out/street_mesh.npz -- run street/scan.npz --out out/parts_run -q

Run it from the tree measured (a checkout of main has no ``_write_map``: its
``SurfaceMap.save`` is timed instead). Used for docs/speed.md "Start-up and stages
outside the surface, session 7".
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from _proc import maxrss_mb, parse_command, time_stages

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


class Parts:
    """Seconds (wall, CPU) and calls per named part."""

    def __init__(self):
        self.acc: dict = {}

    def add(self, name: str, wall: float, cpu: float) -> None:
        a = self.acc.setdefault(name, [0.0, 0.0, 0])
        a[0] += wall
        a[1] += cpu
        a[2] += 1

    def wrap(self, obj, attr: str, name: str | None = None) -> None:
        """Time ``obj.attr`` (its outermost calls; CPU of the calling thread)."""
        f, name = getattr(obj, attr), name or attr
        depth = [0]

        def timed(*a, **k):
            if depth[0]:
                return f(*a, **k)
            depth[0] += 1
            t, c = time.perf_counter(), time.thread_time()
            try:
                return f(*a, **k)
            finally:
                self.add(name, time.perf_counter() - t, time.thread_time() - c)
                depth[0] -= 1

        setattr(obj, attr, timed)


def main(argv=None) -> int:
    t_start, c_start = time.perf_counter(), time.process_time()
    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("json", help="write the parts here")
    ap.add_argument("--stub-surface", metavar="MESH.npz",
                    help="return this mesh (vertices, faces, vertex_variance) instead of "
                         "extracting the surface")
    args, cli = parse_command(ap, argv)
    parts = Parts()
    t, c = time.perf_counter(), time.process_time()
    import gmmgp_app.cli as climod
    parts.add("import cli", time.perf_counter() - t, time.process_time() - c)
    t, c = time.perf_counter(), time.process_time()
    import numba.core.caching as caching

    from gmmgp_app import pipeline
    parts.add("import pipeline (+numba, scipy)", time.perf_counter() - t,
              time.process_time() - c)
    import numpy as np

    from gmmgp_app.commands import run as runmod
    from gmmgp_app.stages import autoscale
    from gmmgp_app.stages import surface as surf
    from gmmgp_app.types import SurfaceMesh

    parts.wrap(caching.Cache, "load_overload", "numba cache loads")
    parts.wrap(runmod, "read_scan_args", "read")
    parts.wrap(pipeline, "scan_tree")
    parts.wrap(autoscale, "measure_scan")
    parts.wrap(autoscale, "_voxel_for_budget")
    parts.wrap(surf, "check_surface_grid", "surface.check_surface_grid")
    parts.wrap(pipeline, "check_surface_grid", "pipeline.check_surface_grid (incl. resolve)")
    parts.wrap(pipeline.SurfaceMap, "save", "map save")
    if hasattr(pipeline, "_write_map"):
        parts.wrap(pipeline, "_write_map", "map write (its thread)")
    parts.wrap(pipeline, "write_mesh_ply")
    parts.wrap(surf, "variance_colors")
    parts.wrap(runmod, "_write_meshes", "_write_meshes (surface + PLY)")
    if args.stub_surface:
        def stored_mesh(self, *a, **k):
            with np.load(args.stub_surface) as z:
                return SurfaceMesh(z["vertices"], z["faces"].astype(np.int64),
                                   z["vertex_variance"])

        pipeline.SurfaceMap.extract_surface = stored_mesh
    parts.wrap(pipeline.SurfaceMap, "extract_surface", "surface (extract_surface)")
    time_stages(lambda name, wall, cpu: parts.add("stage " + name, wall, cpu))
    t, c = time.perf_counter(), time.process_time()
    rc = climod.main(cli)
    parts.add("cli.main", time.perf_counter() - t, time.process_time() - c)
    parts.add("process (from this script's start)", time.perf_counter() - t_start,
              time.process_time() - c_start)
    rss = maxrss_mb()
    print(f"{'part':<46}{'wall s':>8}{'CPU s':>8}{'calls':>6}")
    for k, (w, cpu, n) in parts.acc.items():
        print(f"{k:<46}{w:8.3f}{cpu:8.3f}{n:6d}")
    print(f"ru_maxrss {rss:.0f} MB, load {os.getloadavg()[0]:.2f}")
    Path(args.json).write_text(json.dumps({"parts": parts.acc, "ru_maxrss_mb": rss,
                                           "load": os.getloadavg(), "argv": cli, "rc": rc},
                                          indent=1))
    return rc


if __name__ == "__main__":
    sys.exit(main())
