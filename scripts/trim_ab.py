"""A/B of the surface stage on a saved map: the automatic voxel untrimmed (the default)
against a coarser voxel with ``surface.trim_to_reach`` (docs/speed.md, speed-16z).

Meshes the map of ``gmmgp run --out DIR`` (``DIR/map``) alternately with each setting,
as ``gmmgp run`` does (``extract_surface(overlap=True)``), and prints the process's
CPU seconds (getrusage, all threads) and wall seconds per mesh, their medians, and the
faces and vertices::

    PYTHONPATH=$PWD .venv/bin/python scripts/trim_ab.py /tmp/r/demo_def --factor 1.0 --repeats 3
"""

import argparse
import dataclasses
import json
import resource
import statistics
import time
from pathlib import Path


def cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", help="a gmmgp run output folder (with map/ and summary.json)")
    ap.add_argument("--factor", type=float, default=1.0,
                    help="the trimmed mesh's voxel in units of h_t (default 1.0)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", help="write the figures here")
    args = ap.parse_args(argv)

    from gmmgp_app.pipeline import load_map

    run = Path(args.run)
    summary = json.loads((run / "summary.json").read_text())
    ht = float(summary["auto"]["train_spacing"]["value"])
    smap = load_map(run / "map")
    base_cfg = smap.config
    trim_cfg = dataclasses.replace(
        base_cfg, surface=dataclasses.replace(base_cfg.surface, trim_to_reach=True))
    cases = {"default": (base_cfg, None), "trim": (trim_cfg, args.factor * ht)}
    out = {k: {"cpu_s": [], "wall_s": []} for k in cases}
    for _ in range(args.repeats):
        for name, (cfg, voxel) in cases.items():
            smap.config = cfg
            c0, w0 = cpu_seconds(), time.perf_counter()
            mesh = smap.extract_surface(voxel, overlap=True)
            out[name]["wall_s"].append(time.perf_counter() - w0)
            out[name]["cpu_s"].append(cpu_seconds() - c0)
            out[name].update(faces=int(len(mesh.faces)), vertices=int(len(mesh.vertices)),
                             voxel=float(voxel or cfg.surface.voxel_size))
            del mesh
    for name, r in out.items():
        r["cpu_median"] = statistics.median(r["cpu_s"])
        r["wall_median"] = statistics.median(r["wall_s"])
        print(f"{name:8s} voxel {r['voxel']:.5f} m  CPU {r['cpu_median']:.2f} s "
              f"{[round(x, 2) for x in r['cpu_s']]}  wall {r['wall_median']:.2f} s "
              f"{[round(x, 2) for x in r['wall_s']]}  faces {r['faces']:,}  "
              f"vertices {r['vertices']:,}")
    print(f"CPU ratio trim/default {out['trim']['cpu_median'] / out['default']['cpu_median']:.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
