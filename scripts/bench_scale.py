"""City-scale benchmark: time and peak memory vs street length, serial vs Dask.

A synthetic street 1x, 2x, 4x, 8x longer at the same scanner density is written
to a LAZ file (georeferenced, sensor origins as extra dimensions), then mapped by
streaming it into tiles (``build_tiled_map_from_las``) in a fresh process per run,
so that the peak RSS (``ru_maxrss``) of each run is its own. The serial run and a
Dask ``LocalCluster`` with 2 workers map the same file; their fields are compared
at random points.

    python scripts/bench_scale.py                        # writes out/bench/bench_scale.json
    python scripts/bench_scale.py --sizes 1,2 --density 0.01   # quicker
    python scripts/bench_scale.py --dask-sizes 0 --mesh streamed,memory   # + the mesh

With ``--mesh`` the serial run's tiled map is saved and meshed in a fresh process per
mode (``streamed``: region by region into the PLY, what ``gmmgp run --tile-size`` does;
``memory``: the whole stitched lattice and mesh at once, the path before), and the two
meshes are compared; a tiled run's peak RSS with its mesh is the larger of the build's
and the mesh's.

Every process runs with one BLAS thread (as Dask workers do): multithreaded BLAS on
a loaded 2-core machine slows the blocks' Cholesky factorisations down ~100x.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"

import numpy as np  # noqa: E402

OFFSET = np.array([500000.0, 5400000.0, 0.0])


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def make_laz(path: Path, length: float, density: float, seed: int = 0) -> dict:
    """Simulate the street and write it as LAZ (child process: its memory is not counted)."""
    from gmmgp_app.datasets import write_las
    from gmmgp_app.synth import scan_scene
    from gmmgp_app.types import Scan

    scan, _ = scan_scene("street", density=density, seed=seed,
                         scene_params=dict(length=float(length)))
    write_las(path, Scan(points=scan.points, origins=scan.origins, offset=OFFSET))
    return dict(n_points=len(scan), bytes=path.stat().st_size)


def _cpu_s() -> float:
    return time.process_time()


def _numba_threads_here() -> int:
    import numba

    return int(numba.get_num_threads())


def tile_timeline(stats: list, t0: float, t1: float, workers: int) -> dict:
    """Per-worker busy time, CPU, idle, the parent's share and the scheduling latency
    from the per-tile records of ``build_tiled_map_from_las(tile_stats=...)``, and the
    wall the build would take with each worker on a free core of its own (an estimate:
    the reading before the first tile, then the tiles' measured CPU seconds handed
    largest first to the next free worker, then the storing of the last tile)."""
    import heapq

    wall = t1 - t0
    per = {}
    for s in stats:
        w = per.setdefault(s["pid"], dict(tiles=0, busy_s=0.0, cpu_s=0.0, read_s=0.0,
                                          map_s=0.0, save_s=0.0, first_start=None,
                                          last_end=None, numba_threads=s["numba_threads"]))
        w["tiles"] += 1
        w["busy_s"] += s["seconds"]
        w["cpu_s"] += s["cpu_s"]
        w["read_s"] += s["read_s"]
        w["map_s"] += s.get("map_s", 0.0)
        w["save_s"] += s["save_s"]
        st, en = s["start"] - t0, s["end"] - t0
        w["first_start"] = st if w["first_start"] is None else min(w["first_start"], st)
        w["last_end"] = en if w["last_end"] is None else max(w["last_end"], en)
    for w in per.values():
        w["idle_s"] = wall - w["busy_s"]
        w["cpu_per_busy"] = w["cpu_s"] / max(w["busy_s"], 1e-9)
    before = min(s["start"] for s in stats) - t0 if stats else 0.0
    after = t1 - max(s["end"] for s in stats) if stats else 0.0
    # the tiles' CPU seconds, in the order they were handed out (largest first)
    order = sorted(stats, key=lambda s: s["start"])
    free = [0.0] * max(1, workers)
    heapq.heapify(free)
    for s in order:
        heapq.heappush(free, heapq.heappop(free) + s["cpu_s"])
    makespan = max(free)
    return dict(
        wall_s=wall, before_first_tile_s=before, after_last_tile_s=after,
        workers=list(per.values()),
        tiles_cpu_s=sum(s["cpu_s"] for s in stats),
        tiles_thread_cpu_s=sum(s["thread_cpu_s"] for s in stats),
        threading_layer=sorted({s["threading_layer"] for s in stats}),
        # a process with several numba threads: its calling thread's CPU (its share of
        # each parallel loop and every serial part) stands for the wall on free cores
        est_wall_free_cores_calling_thread_s=before + after + sum(s["thread_cpu_s"]
                                                                  for s in stats),
        tiles_busy_s=sum(s["seconds"] for s in stats),
        parent_store_s=sum(s["store_s"] for s in stats),
        bytes_returned=sum(s["bytes_returned"] for s in stats),
        latency_end_to_received_s=dict(
            median=float(np.median([s["received"] - s["end"] for s in stats])),
            max=float(max(s["received"] - s["end"] for s in stats))),
        est_wall_free_cores_s=before + makespan + after,
        est_makespan_free_cores_s=makespan,
        tiles=[dict(key=s["key"], pid=s["pid"], n_points=s["n_points"],
                    start=s["start"] - t0, seconds=s["seconds"], cpu_s=s["cpu_s"],
                    thread_cpu_s=s["thread_cpu_s"],
                    read_s=s["read_s"], save_s=s["save_s"]) for s in order])


def run_map(laz: Path, work: Path, tile: float, overlap: float, workers: int,
            chunk: int, queries: Path, pred_out: Path, save: str = "",
            numba_threads: int = 0, return_maps: bool = False) -> dict:
    """Stream-map one file (child process) and report time, CPU, peak RSS, counts, the
    per-tile timeline (:func:`tile_timeline`); with ``save`` also save the tiled map
    there (for the mesh runs). ``numba_threads``: each Dask worker's numba threads
    (0: ``open_executor``'s default, cores // workers). ``return_maps``: the workers
    send each tile map's files back and this process writes them (the path before
    session 8), for comparison."""
    import gmmgp_app as gm
    from gmmgp_app.distributed import open_executor
    from gmmgp_app.tiling import TileSpec, build_tiled_map_from_las

    if return_maps:
        from gmmgp_app.tiling import las, tasks

        las.map_tiles_to_store = lambda *a, **k: tasks.map_tiles_to_store(
            *a, **dict(k, workers_write=False))
    rss0 = _rss_mb()
    cfg = gm.MappingConfig()
    spec = TileSpec(size=tile, overlap=overlap)
    t_open = time.perf_counter()
    cpu0 = time.process_time()
    worker_rss = worker_cpu = None
    stats: list = []
    with open_executor(workers=workers or None, numba_threads=numba_threads or None) as ex:
        client = getattr(ex, "_client", None)
        if client is not None:
            # import the package in every worker first: the serial run has it already
            client.run(_warm_up)
            wc0 = client.run(_cpu_s)
            worker_numba = sorted(client.run(_numba_threads_here).values())
        else:
            worker_numba = [_numba_threads_here()]
        t0 = time.perf_counter()
        w0 = time.time()
        tm = build_tiled_map_from_las(laz, cfg, spec, work_dir=work, executor=ex,
                                      chunk_size=chunk, offset=OFFSET, tile_stats=stats)
        t1 = time.perf_counter()
        w1 = time.time()
        cpu1 = time.process_time()
        if client is not None:
            worker_rss = max(client.run(_rss_mb).values())
            wc1 = client.run(_cpu_s)
            worker_cpu = {k: wc1[k] - wc0[k] for k in wc1}
    build_rss = _rss_mb()
    if save:
        tm.save(save)
    q = np.load(queries)
    m, v = tm.predict(q)
    np.save(pred_out, np.column_stack([m, v]))
    return dict(seconds=t1 - t0, cluster_start_seconds=t0 - t_open,
                cpu_seconds=cpu1 - cpu0, build_peak_rss_mb=build_rss,
                peak_rss_mb=_rss_mb(), rss_after_imports_mb=rss0,
                worker_peak_rss_mb=worker_rss, worker_process_cpu_s=worker_cpu,
                numba_threads=worker_numba,
                timeline=tile_timeline(stats, w0, w1, workers or 1),
                n_tiles=tm.summary["n_tiles"], n_points=tm.summary["n_points"],
                skipped_tiles=len(tm.summary["skipped_tiles"]))


def _rss_now_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2 ** 20


class _RegionTrace:
    """A progress bar for write_tiled_surface_ply that records, after each region, the
    current RSS, the peak so far and (with tracemalloc on) the traced numpy/Python
    memory now and its peak since the previous region."""

    def __init__(self, trace: list, snapshot_at: int = -1):
        self.trace = trace
        self.snapshot_at = snapshot_at
        self.snapshot: list = []

    def __call__(self, total, label):
        return self

    def update(self, n=1):
        import tracemalloc

        rec = dict(region=len(self.trace), rss_mb=_rss_now_mb(), peak_rss_mb=_rss_mb())
        if tracemalloc.is_tracing():
            cur, peak = tracemalloc.get_traced_memory()
            rec.update(traced_mb=cur / 2 ** 20, traced_peak_mb=peak / 2 ** 20)
            tracemalloc.reset_peak()
            if len(self.trace) == self.snapshot_at:   # what the traced memory is, by line
                top = tracemalloc.take_snapshot().statistics("lineno")[:15]
                self.snapshot = [dict(where=str(st.traceback[0]), mb=st.size / 2 ** 20,
                                      blocks=st.count) for st in top]
        self.trace.append(rec)

    def close(self):
        pass


def run_mesh(tiled: Path, mode: str, ply: Path, trace: int = 0) -> dict:
    """Mesh a saved tiled map (child process) as ``gmmgp run --tile-size`` does after its
    build: ``memory``, the whole stitched lattice and mesh held at once
    (TiledMap.extract_surface + write_mesh_ply, the path before session 7), or
    ``streamed``, region by region into the PLY (tiling/mesh.py). Reports wall and CPU
    seconds, peak RSS (the map opened as gmmgp run reopens it, without points); with
    ``trace`` (streamed) the RSS after each region (1) and tracemalloc's figures (2)."""
    from gmmgp_app.pipeline import std_colour_max, write_mesh_ply
    from gmmgp_app.tiling import load_tiled_map
    from gmmgp_app.tiling.mesh import write_tiled_surface_ply

    rss0 = _rss_mb()
    tm = load_tiled_map(tiled, load_points=False)
    rss_open = _rss_now_mb()
    t0, c0 = time.perf_counter(), time.process_time()
    if mode == "memory":
        mesh = tm.extract_surface()
        write_mesh_ply(mesh, ply, offset=tm.offset, vmax=std_colour_max([mesh]))
        info = dict(vertices=len(mesh.vertices), faces=len(mesh.faces))
        del mesh
    else:
        rt: list = []
        if trace >= 2:
            import tracemalloc

            tracemalloc.start()
        bar = _RegionTrace(rt, snapshot_at=10 if trace >= 3 else -1)
        info = write_tiled_surface_ply(tm, ply, offset=tm.offset,
                                       progress=bar if trace else None)
        if trace:
            info["region_trace"] = rt
            info["traced_by_line_at_region_10"] = bar.snapshot
            info["rss_before_mesh_mb"] = rss_open
    return dict(info, mode=mode, seconds=time.perf_counter() - t0,
                cpu_seconds=time.process_time() - c0, peak_rss_mb=_rss_mb(),
                rss_after_imports_mb=rss0)


def compare_meshes(a: Path, b: Path) -> dict:
    """Two PLY meshes of the same surface compared (child process): counts, whether the
    vertex sets and the face sets (faces as their vertices' coordinates) are equal bit
    for bit, and the largest vertex-to-vertex distance between them otherwise."""
    from scipy.spatial import cKDTree

    from gmmgp_app.pipeline import read_mesh_ply

    ma, mb = read_mesh_ply(a), read_mesh_ply(b)
    out = dict(vertices=[len(ma.vertices), len(mb.vertices)],
               faces=[len(ma.faces), len(mb.faces)])
    va = ma.vertices[np.lexsort(ma.vertices.T[::-1])]
    vb = mb.vertices[np.lexsort(mb.vertices.T[::-1])]
    out["vertices_equal"] = bool(va.shape == vb.shape and np.array_equal(va, vb))

    def faces(m):
        tri = m.vertices[m.faces]
        key = np.lexsort(tri.transpose(2, 0, 1)[::-1], axis=1)
        tri = np.take_along_axis(tri, key[:, :, None], axis=1).reshape(len(tri), 9)
        return tri[np.lexsort(tri.T[::-1])]

    out["faces_equal"] = bool(out["faces"][0] == out["faces"][1]
                              and np.array_equal(faces(ma), faces(mb)))
    if not (out["vertices_equal"] and out["faces_equal"]):
        out["max_vertex_distance_m"] = float(max(cKDTree(vb).query(va)[0].max(),
                                                 cKDTree(va).query(vb)[0].max()))
    return out


def _warm_up() -> None:
    import gmmgp_app.pipeline  # noqa: F401
    import gmmgp_app.stages.gp  # noqa: F401
    import gmmgp_app.stages.hgmm  # noqa: F401


def _child(args) -> None:
    kw = json.loads(args.child_args)
    fn = {"make_laz": make_laz, "run_map": run_map, "run_mesh": run_mesh,
          "compare_meshes": compare_meshes}[args.child]
    for k in ("path", "laz", "work", "queries", "pred_out", "tiled", "ply", "a", "b"):
        if k in kw:
            kw[k] = Path(kw[k])
    print("RESULT " + json.dumps(fn(**kw)))


def _spawn(name: str, **kw) -> dict:
    out = subprocess.run([sys.executable, __file__, "--child", name, "--child-args",
                          json.dumps({k: str(v) if isinstance(v, Path) else v
                                      for k, v in kw.items()})],
                         capture_output=True, text=True)
    for line in out.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    raise RuntimeError(f"{name} failed:\n{out.stderr[-3000:]}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="1,2,4,8", help="street length multiples")
    ap.add_argument("--base-length", type=float, default=25.0, help="1x street length (m)")
    ap.add_argument("--density", type=float, default=0.02, help="scan_scene density")
    ap.add_argument("--tile", type=float, default=15.0, help="tile size (m)")
    ap.add_argument("--overlap", type=float, default=2.0, help="tile overlap (m)")
    ap.add_argument("--chunk", type=int, default=20000, help="LAS points per chunk")
    ap.add_argument("--workers", type=int, default=2, help="Dask LocalCluster workers")
    ap.add_argument("--numba-threads", type=int, default=0, help="numba threads of each "
                    "Dask worker (0: cores // workers)")
    ap.add_argument("--order", default="serial,dask", help="runs per size, in this order "
                    "(alternate with e.g. 'serial,dask,dask,serial')")
    ap.add_argument("--return-maps", action="store_true", help="workers send the tile "
                    "maps' files back to be written by the parent (before session 8)")
    ap.add_argument("--dask-sizes", default="", help="sizes also run on Dask (default: "
                    "the largest)")
    ap.add_argument("--repeat", type=int, default=3, help="runs per setting (median)")
    ap.add_argument("--mesh", default="", help="also mesh the serial run's saved map, in "
                    "a fresh process per mode: 'streamed', 'memory' or 'streamed,memory' "
                    "(the meshes compared)")
    ap.add_argument("--trace-regions", type=int, default=0, help="streamed mesh: 1 records "
                    "the RSS after each region, 2 also tracemalloc's (slower), 3 also the "
                    "traced memory by source line after region 10")
    ap.add_argument("--out", default="out/bench/bench_scale.json")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--child-args", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        _child(args)
        return 0
    out = Path(args.out)
    cache = out.parent / "bench_scale_cache"
    cache.mkdir(parents=True, exist_ok=True)
    sizes = [int(s) for s in args.sizes.split(",")]
    dask_sizes = ([int(s) for s in args.dask_sizes.split(",")] if args.dask_sizes
                  else [max(sizes)])
    rows = []
    for k in sizes:
        length = args.base_length * k
        laz = cache / f"street_{length:g}m_d{args.density:g}.laz"
        info = (_spawn("make_laz", path=laz, length=length, density=args.density)
                if not laz.exists() else dict(n_points=None, bytes=laz.stat().st_size))
        rng = np.random.default_rng(k)
        q = np.column_stack([rng.uniform(0, length, 4000), rng.uniform(-8, 8, 4000),
                             rng.uniform(0, 6, 4000)])
        qf = cache / f"queries_{k}.npy"
        np.save(qf, q)
        row = dict(multiple=k, length_m=length, laz_bytes=info["bytes"])
        names = [n for n in args.order.split(",") if n == "serial" or k in dask_sizes]
        runs = {n: (0 if n == "serial" else args.workers) for n in names}
        preds = {}
        allreps: dict = {n: [] for n in runs}
        for r in range(args.repeat):
            for j, name in enumerate(names):  # alternated: serial, dask, ... per repeat
                w = runs[name]
                saved = cache / f"map_{k}" if (args.mesh and name == "serial") else ""
                rr = _spawn("run_map", laz=laz, work=cache / f"work_{k}_{name}_{r}_{j}",
                            tile=args.tile, overlap=args.overlap, workers=w,
                            chunk=args.chunk, queries=qf,
                            pred_out=cache / f"pred_{k}_{name}.npy", save=str(saved),
                            numba_threads=args.numba_threads,
                            return_maps=args.return_maps)
                rr["load"] = os.getloadavg()[0]
                allreps[name].append(rr)
                print(f"  {k}x {name} run {r}: {rr['seconds']:.1f} s, est. free cores "
                      f"{rr['timeline']['est_wall_free_cores_s']:.1f} s, load "
                      f"{rr['load']:.1f}", flush=True)
        for name, reps in allreps.items():
            pf = cache / f"pred_{k}_{name}.npy"
            # the machine is shared: medians of fresh-process runs
            res = dict(reps[0], seconds=float(np.median([r["seconds"] for r in reps])),
                       seconds_all=[r["seconds"] for r in reps],
                       cpu_seconds=float(np.median([r["cpu_seconds"] for r in reps])),
                       build_peak_rss_mb=float(np.median([r["build_peak_rss_mb"]
                                                          for r in reps])),
                       peak_rss_mb=float(np.median([r["peak_rss_mb"] for r in reps])),
                       est_wall_free_cores_s=float(np.median(
                           [r["timeline"]["est_wall_free_cores_s"] for r in reps])),
                       runs=reps, load=os.getloadavg()[0])
            row[name] = res
            preds[name] = np.load(pf)
            print(f"{k}x {length:g} m {name}: {res['seconds']:.1f} s, peak RSS "
                  f"{res['peak_rss_mb']:.0f} MB, {res['n_tiles']} tiles, "
                  f"{res['n_points']} points", flush=True)
        for mode in [m for m in args.mesh.split(",") if m]:
            ms = [_spawn("run_mesh", tiled=cache / f"map_{k}", mode=mode,
                         ply=cache / f"mesh_{k}_{mode}.ply",
                         trace=args.trace_regions if mode == "streamed" else 0)
                  for _ in range(args.repeat)]
            row[f"mesh_{mode}"] = dict(ms[0], seconds=float(np.median([m["seconds"] for m in ms])),
                                       cpu_seconds=float(np.median([m["cpu_seconds"]
                                                                    for m in ms])),
                                       cpu_all=[m["cpu_seconds"] for m in ms],
                                       peak_rss_mb=float(np.median([m["peak_rss_mb"]
                                                                    for m in ms])),
                                       load=os.getloadavg()[0])
            # the peak of a tiled run with its mesh: the build's or the mesh's
            row[f"run_peak_rss_mb_{mode}"] = max(row["serial"]["build_peak_rss_mb"],
                                                 row[f"mesh_{mode}"]["peak_rss_mb"])
            m = row[f"mesh_{mode}"]
            print(f"{k}x mesh {mode}: {m['seconds']:.1f} s, {m['cpu_seconds']:.1f} CPU-s, "
                  f"peak RSS {m['peak_rss_mb']:.0f} MB, {m['vertices']} vertices, "
                  f"{m['faces']} faces", flush=True)
        if {"streamed", "memory"} <= set(args.mesh.split(",")):
            row["mesh_compare"] = _spawn("compare_meshes", a=cache / f"mesh_{k}_memory.ply",
                                         b=cache / f"mesh_{k}_streamed.ply")
            print(f"{k}x meshes: {row['mesh_compare']}", flush=True)
        if "dask" in preds and "serial" not in preds:
            pf = cache / f"pred_{k}_serial.npy"   # an earlier serial run's, if any
            if pf.exists():
                preds["serial"] = np.load(pf)
        if "dask" in preds and "serial" in preds:
            d = np.abs(preds["dask"] - preds["serial"])
            row["dask_vs_serial_max_abs_diff"] = dict(mean=float(d[:, 0].max()),
                                                      var=float(d[:, 1].max()))
        if "dask" in row and "serial" in row:
            row["dask_speedup"] = row["serial"]["seconds"] / row["dask"]["seconds"]
            row["dask_speedup_est_free_cores"] = (row["serial"]["est_wall_free_cores_s"]
                                                  / row["dask"]["est_wall_free_cores_s"])
        rows.append(row)
    base = rows[0]
    for r in rows:
        if "serial" not in r or "serial" not in base:   # --order without serial
            continue
        ratio = r["multiple"] / base["multiple"]
        r["time_vs_linear"] = r["serial"]["seconds"] / (base["serial"]["seconds"] * ratio)
        r["rss_vs_1x"] = r["serial"]["peak_rss_mb"] / base["serial"]["peak_rss_mb"]
        n, n0 = r["serial"]["n_points"], base["serial"]["n_points"]
        r["cpu_us_per_point"] = 1e6 * r["serial"]["cpu_seconds"] / n
        r["cpu_per_point_vs_1x"] = r["cpu_us_per_point"] / (1e6 * base["serial"]["cpu_seconds"] / n0)
        for mode in [m for m in args.mesh.split(",") if m]:
            key = f"mesh_{mode}"
            r[key]["cpu_us_per_point"] = 1e6 * r[key]["cpu_seconds"] / n
            r[key]["cpu_per_point_vs_1x"] = (r[key]["cpu_us_per_point"]
                                             / (1e6 * base[key]["cpu_seconds"] / n0))
            r[f"run_rss_vs_1x_{mode}"] = (r[f"run_peak_rss_mb_{mode}"]
                                          / base[f"run_peak_rss_mb_{mode}"])
    result = dict(settings=vars(args) | {"child": None, "child_args": None},
                  machine=dict(cpus=os.cpu_count(), load=os.getloadavg()), rows=rows)
    out.write_text(json.dumps(result, indent=2))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
