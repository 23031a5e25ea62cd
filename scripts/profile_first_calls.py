"""First-call cost of gmmgp_app's numba kernels in a fresh process (JSON output).

A warm ``gmmgp run`` compiles nothing, but the first call of each kernel in a
process still loads it from the on-disk cache: numba resolves the argument types,
looks the signature up in the cache index, unpickles the library, hands its object
code to LLVM and links it; a ``parallel=True`` kernel also starts the threading
layer on its first launch. This script runs one ``gmmgp`` command N times in ONE
process (``--repeat``, default 2) and reports

* per kernel: the wall and CPU seconds of numba's ``Dispatcher._compile_for_args``
  (a call whose signature the dispatcher has not loaded yet: type resolution, cache
  load, or compilation when the cache misses), of which ``Cache.load_overload``
  (the disk load proper), by run; and the seconds spent compiling (``numba:compile``
  events, 0 on a warm cache);
* per stage (the pipeline's stage events, and ``SurfaceMap.extract_surface`` as
  "surface") and per run: wall seconds, so run 1 minus
  run 2 is the whole first-call cost (kernels, threading layer, lazy imports, first
  touches), of which the kernels' share is the sum above.

    PYTHONPATH=$PWD .venv/bin/python scripts/profile_first_calls.py out/first.json \\
        -- run /tmp/street/scan.npz --out out/first_run -q

The command's ``--out`` gets a suffix per run (``_1``, ``_2``) so the runs do not
overwrite each other. ``--sync-save`` (a diagnostic) saves the map before meshing
instead of on a thread beside it, to see what the overlap costs the surface stage. Used for docs/speed.md "Session 10 (first calls)".
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import threading
import time
from pathlib import Path

from _proc import parse_command, time_stages

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


class Acc:
    """Seconds (wall, CPU of the calling thread) and calls per key, per run."""

    def __init__(self):
        self.run = 0
        self.acc: dict = {}

    def add(self, key: str, wall: float, cpu: float) -> None:
        a = self.acc.setdefault(key, {}).setdefault(str(self.run), [0.0, 0.0, 0])
        a[0] += wall
        a[1] += cpu
        a[2] += 1


def _kernel_name(dispatcher) -> str:
    f = dispatcher.py_func
    return f"{f.__module__.rsplit('.', 1)[-1]}.{f.__qualname__}"


#: the dispatchers that missed, by name (their loaded signatures go in the JSON)
SEEN: dict = {}


def install(kernels: Acc, loads: Acc, stages: Acc):
    """Wrap numba's dispatcher miss path, the cache load and the pipeline's stage events."""
    import numba.core.caching as caching
    from numba.core import dispatcher as nd

    from gmmgp_app import pipeline

    local = threading.local()
    lock = threading.Lock()
    orig_cfa = nd.Dispatcher._compile_for_args

    def compile_for_args(self, *args, **kws):
        SEEN[_kernel_name(self)] = self
        outer = not getattr(local, "depth", 0)
        local.depth = getattr(local, "depth", 0) + 1
        t, c = time.perf_counter(), time.thread_time()
        try:
            return orig_cfa(self, *args, **kws)
        finally:
            local.depth -= 1
            if outer:  # nested misses (rare) are charged to the outermost kernel
                with lock:
                    kernels.add(_kernel_name(self), time.perf_counter() - t,
                                time.thread_time() - c)

    nd.Dispatcher._compile_for_args = compile_for_args
    orig_load = caching.Cache.load_overload

    def load_overload(self, *a, **k):
        t, c = time.perf_counter(), time.thread_time()
        try:
            return orig_load(self, *a, **k)
        finally:
            with lock:
                loads.add(self._name, time.perf_counter() - t, time.thread_time() - c)

    caching.Cache.load_overload = load_overload
    time_stages(stages.add)
    orig_extract = pipeline.SurfaceMap.extract_surface

    def extract_surface(self, *a, **k):
        t, c = time.perf_counter(), time.process_time()
        try:
            return orig_extract(self, *a, **k)
        finally:
            stages.add("surface", time.perf_counter() - t, time.process_time() - c)

    pipeline.SurfaceMap.extract_surface = extract_surface


def save_before_meshing(stages: Acc):
    """Diagnostic: ``SurfaceMap.save_in_background`` saves at once, on the calling
    thread (timed as stage "map save (sync)"), so the surface stage runs alone."""
    from concurrent.futures import Future

    from gmmgp_app import pipeline

    def save_now(self, directory):
        t, c = time.perf_counter(), time.process_time()
        done = Future()
        done.set_result(self.save(directory))
        stages.add("map save (sync)", time.perf_counter() - t, time.process_time() - c)
        return done

    pipeline.SurfaceMap.save_in_background = save_now


def set_mmap_threshold(nbytes: int):
    """Diagnostic: the run's ``fix_mmap_threshold()`` fixes ``nbytes`` instead of 128 KiB
    (0: leaves glibc's dynamic threshold alone)."""
    from gmmgp_app import _memory

    orig = _memory.fix_mmap_threshold
    _memory.fix_mmap_threshold = (lambda *a, **k: False) if nbytes == 0 else \
        (lambda *a, **k: orig(nbytes))


def _by_run(acc: dict, run: int) -> dict:
    return {k: v[str(run)] for k, v in acc.items() if str(run) in v}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("json", help="write the figures here")
    ap.add_argument("--repeat", type=int, default=2, help="runs of the command in this process")
    ap.add_argument("--top", type=int, default=15, help="kernels listed on stdout")
    ap.add_argument("--sync-save", action="store_true",
                    help="diagnostic: save the map before meshing instead of beside it")
    ap.add_argument("--mmap-threshold", type=int, metavar="BYTES",
                    help="diagnostic: the run fixes glibc's mmap threshold at BYTES instead "
                         "of 128 KiB (0: glibc's dynamic default)")
    args, cli = parse_command(ap, argv, need_out=True)
    t_start = time.perf_counter()
    import gmmgp_app.cli as climod
    from warm_cache import CompileClock

    kernels, loads, stages, runs = Acc(), Acc(), Acc(), Acc()
    install(kernels, loads, stages)
    if args.sync_save:
        save_before_meshing(stages)
    if args.mmap_threshold is not None:
        set_mmap_threshold(args.mmap_threshold)
    t_import = time.perf_counter() - t_start
    out_at = cli.index("--out") + 1
    compile_s, rcs, faults = [], [], []
    for r in range(1, args.repeat + 1):
        for a in (kernels, loads, stages, runs):
            a.run = r
        argv_r = list(cli)
        argv_r[out_at] = f"{cli[out_at]}_{r}"
        t, c = time.perf_counter(), time.process_time()
        ru = resource.getrusage(resource.RUSAGE_SELF)
        with CompileClock() as clock:
            rcs.append(climod.main(argv_r))
        runs.add("cli.main", time.perf_counter() - t, time.process_time() - c)
        ru2 = resource.getrusage(resource.RUSAGE_SELF)
        faults.append([ru2.ru_stime - ru.ru_stime, ru2.ru_minflt - ru.ru_minflt,
                       ru2.ru_maxrss / 1024])
        compile_s.append([clock.seconds, clock.count])
    report = {"argv": cli, "sync_save": args.sync_save, "mmap_threshold": args.mmap_threshold, "rc": rcs, "load": os.getloadavg(), "import_s": t_import,
              "runs": {}, "kernels": kernels.acc, "cache_loads": loads.acc,
              "stages": stages.acc}
    for r in range(1, args.repeat + 1):
        k = _by_run(kernels.acc, r)
        ld = _by_run(loads.acc, r)
        report["runs"][str(r)] = {
            "wall_s": runs.acc["cli.main"][str(r)][0],
            "cpu_s": runs.acc["cli.main"][str(r)][1],
            "dispatch_miss_wall_s": sum(v[0] for v in k.values()),
            "dispatch_miss_calls": sum(v[2] for v in k.values()),
            "cache_load_wall_s": sum(v[0] for v in ld.values()),
            "cache_loads": sum(v[2] for v in ld.values()),
            "sys_cpu_s": faults[r - 1][0], "minor_faults": faults[r - 1][1],
            "ru_maxrss_mb": faults[r - 1][2],
            "compile_s": compile_s[r - 1][0], "compiles": compile_s[r - 1][1],
            "stages_wall_s": {s: v[0] for s, v in _by_run(stages.acc, r).items()},
        }
    report["signatures"] = {n: [str(s) for s in d.signatures] for n, d in sorted(SEEN.items())}
    first = _by_run(kernels.acc, 1)
    report["top_kernels_run1"] = sorted(([n, v[0], v[2]] for n, v in first.items()),
                                        key=lambda x: -x[1])
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(report, indent=1))
    print(f"import {t_import:.2f} s, load {os.getloadavg()[0]:.2f}")
    for r, v in report["runs"].items():
        st = " ".join(f"{s} {w:.2f}" for s, w in v["stages_wall_s"].items())
        print(f"run {r}: wall {v['wall_s']:.2f} s, CPU {v['cpu_s']:.2f} (sys {v['sys_cpu_s']:.2f},"
              f" {v['minor_faults']} minor faults), maxrss {v['ru_maxrss_mb']:.0f} MB, dispatch misses {v['dispatch_miss_calls']} "
              f"{v['dispatch_miss_wall_s']:.2f} s (cache loads {v['cache_loads']} "
              f"{v['cache_load_wall_s']:.2f} s, compiles {v['compiles']} {v['compile_s']:.2f} s)"
              f" | {st}")
    print("top kernels, run 1 (wall s, misses):")
    for n, w, c in report["top_kernels_run1"][:args.top]:
        print(f"  {n:<52}{w:7.3f}{c:4d}")
    return max(rcs)


if __name__ == "__main__":
    sys.exit(main())
