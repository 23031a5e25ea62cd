"""Wall time and resident memory of each stage of one ``gmmgp run``, in one process.

A sampler thread reads the process's resident set size (``/proc/self/status``,
VmRSS) every few milliseconds while ``gmmgp run ARGS...`` runs in this process;
the pipeline's stage events (start and end of each stage, the map save in between)
mark the segments. Printed and written as JSON: per segment its seconds, the process's
CPU seconds (all threads; on a machine shared with other jobs a steadier measure of the
work than the wall time), the RSS at its start and the highest RSS sampled within it;
and the process's ``ru_maxrss``.

    PYTHONPATH=$PWD .venv/bin/python scripts/profile_run.py --json out/prof.json -- \\
        run out/peers_work/street_d1_s0/scan.npz --out out/prof_run -q

Linux only (``/proc``). ``--tracemalloc`` also reports the traced (Python and numpy)
peak, separating array memory from libraries' own; it slows the run down.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from _proc import Sampler, hook_stage_events, maxrss_mb, parse_command

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    if argv is None:
        argv = sys.argv[1:]
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", help="write the segments here")
    ap.add_argument("--period", type=float, default=0.01, help="RSS sampling period (s)")
    ap.add_argument("--tracemalloc", action="store_true",
                    help="also report the traced (Python + numpy) peak")
    args, cli = parse_command(ap, argv)

    from gmmgp_app.cli import main as gmmgp_main

    marks = [(time.perf_counter(), "start", time.process_time())]
    hook_stage_events(
        lambda name: marks.append((time.perf_counter(), f"{name}>", time.process_time())),
        lambda name: marks.append((time.perf_counter(), f"<{name}", time.process_time())))
    if args.tracemalloc:
        import tracemalloc
        tracemalloc.start()
    sampler = Sampler(args.period)
    sampler.start()
    rc = gmmgp_main(cli)
    marks.append((time.perf_counter(), "end", time.process_time()))
    sampler.stop.set()
    sampler.join()
    samples = sampler.samples
    segs = []
    for (t0, a, c0), (t1, b, c1) in zip(marks[:-1], marks[1:]):
        inside = [r for t, r in samples if t0 <= t < t1]
        before = [r for t, r in samples if t < t0]
        segs.append({"from": a, "to": b, "seconds": t1 - t0, "cpu_seconds": c1 - c0,
                     "rss_start_mb": before[-1] if before else None,
                     "rss_peak_mb": max(inside) if inside else None})
    maxrss = maxrss_mb()
    print(f"{'segment':<28}{'s':>8}{'cpu s':>8}{'RSS start':>11}{'RSS peak':>10}")
    for s in segs:
        if s["seconds"] < 0.005:
            continue
        fmt = lambda x: f"{x:10.0f}" if x is not None else f"{'-':>10}"  # noqa: E731
        print(f"{s['from'] + ' .. ' + s['to']:<28}{s['seconds']:8.2f}{s['cpu_seconds']:8.2f} "
              f"{fmt(s['rss_start_mb'])}"
              f"{fmt(s['rss_peak_mb'])}")
    print(f"ru_maxrss {maxrss:.0f} MB; sampled peak {max(r for _, r in samples):.0f} MB")
    if args.tracemalloc:
        import tracemalloc
        cur, peak = tracemalloc.get_traced_memory()
        print(f"tracemalloc: current {cur / 2**20:.0f} MB, peak {peak / 2**20:.0f} MB")
    if args.json:
        Path(args.json).write_text(json.dumps({"segments": segs, "ru_maxrss_mb": maxrss,
                                               "argv": cli, "rc": rc}, indent=2))
    return rc


if __name__ == "__main__":
    sys.exit(main())
