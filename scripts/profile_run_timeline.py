"""Whole-process timeline of ``gmmgp run``: wall and CPU seconds per phase, from the
interpreter's start to the process's end, for one or more source trees, alternated.

Each run is a fresh process (``python -c DRIVER``, ``PYTHONPATH`` = the tree) that
records wall-clock and process-CPU marks: after the interpreter started, after
importing the command line and the pipeline, at the start and end of every stage the
pipeline reports, when the command returns; the map write (on its own thread) is timed
separately (wall and that thread's CPU). This process times the spawn and the end
(``os.wait4``: the child's total CPU and its ``ru_maxrss``, with no sampler thread in
it), so the *exit* phase (interpreter teardown, or none with ``console_main``'s
``os._exit``) is measured too.

    python scripts/profile_run_timeline.py --scan /tmp/street/scan.npz \\
        --tree main=/tmp/main_tree:python --tree branch=$PWD:console --repeats 3 \\
        --json timeline.json

``--tree LABEL=PATH[:EXIT]``: EXIT is ``python`` (``sys.exit(main(argv))``: what the
console script did until session 10) or ``console`` (``gmmgp_app.cli.console_main``).
Phases: start (interpreter), import, read (read, automatic values, grid check), each
stage (prepare, hgmm, gmr, far, gp, ...; the gap before a stage is added to it),
surface, write (PLY, waiting for the map write, config and summary), exit. Medians over
the repeats; ``uptime``'s load before each run is printed (the machine is shared).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

DRIVER = r'''
import json, sys, time, threading
marks = [("python", time.time(), time.process_time())]
import gmmgp_app.cli as cli
from gmmgp_app import pipeline
import gmmgp_app.commands.run as run_cmd
marks.append(("import", time.time(), time.process_time()))
out_json, exit_mode, argv = sys.argv[1], sys.argv[2], sys.argv[3:]
F = pipeline.FanoutObserver
s0, s1 = F.on_stage_start, F.on_stage
def on_start(self, name):
    marks.append((name + ">", time.time(), time.process_time())); return s0(self, name)
def on_stage(self, name, payload):
    marks.append(("<" + name, time.time(), time.process_time())); return s1(self, name, payload)
F.on_stage_start, F.on_stage = on_start, on_stage
save = {}
w = pipeline._write_map
def write_map(*a, **k):
    t, c = time.time(), time.thread_time()
    try:
        return w(*a, **k)
    finally:
        save.update(wall=time.time() - t, cpu=time.thread_time() - c)
pipeline._write_map = write_map
code = cli.main(argv)
marks.append(("main", time.time(), time.process_time()))
with open(out_json, "w") as f:
    json.dump({"marks": marks, "save": save, "code": code}, f)
if exit_mode == "console":
    cli._exit_now(code)
sys.exit(code)
'''


def load_average() -> float:
    return os.getloadavg()[0]


def run_once(tree: Path, exit_mode: str, scan: str, out: Path, extra, python: str) -> dict:
    with tempfile.NamedTemporaryFile(suffix=".json", delete=False) as f:
        marks_path = f.name
    env = dict(os.environ, PYTHONPATH=str(tree))
    load = load_average()
    t0 = time.time()
    proc = subprocess.Popen([python, "-c", DRIVER, marks_path, exit_mode, "run", scan,
                             "--out", str(out), "-q", *extra], cwd=tree, env=env)
    _, status, ru = os.wait4(proc.pid, 0)
    t_end = time.time()
    proc.returncode = os.waitstatus_to_exitcode(status)
    rec = json.loads(Path(marks_path).read_text())
    os.unlink(marks_path)
    if proc.returncode != 0:
        raise SystemExit(f"run in {tree} failed with exit code {proc.returncode}")
    marks = rec["marks"]
    phases = {"start": (marks[0][1] - t0, marks[0][2])}
    prev = marks[0]
    for name, t, c in marks[1:]:
        if name.endswith(">"):
            continue              # a stage's start: the gap before it goes to the stage
        # the pipeline reports "scan" when build_map starts: read, automatic values and
        # the grid check come before it
        label = {"import": "import", "main": "write", "<scan": "read"}.get(
            name, name.lstrip("<"))
        w, c_ = phases.get(label, (0.0, 0.0))
        phases[label] = (w + t - prev[1], c_ + c - prev[2])
        prev = (name, t, c)
    cpu_total = ru.ru_utime + ru.ru_stime
    phases["exit"] = (t_end - prev[1], cpu_total - prev[2])
    return {"phases": phases, "wall": t_end - t0, "cpu": cpu_total,
            "maxrss_mb": ru.ru_maxrss / 1024.0, "save": rec["save"], "load_before": load}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scan", required=True)
    ap.add_argument("--tree", action="append", required=True,
                    help="LABEL=PATH[:python|console] (repeatable; alternated)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=None, help="run folders here (default: a temp dir)")
    ap.add_argument("--json", help="write every run's phases here")
    ap.add_argument("--python", default=sys.executable)
    ap.add_argument("extra", nargs="*", help="more gmmgp run arguments (after --)")
    args = ap.parse_args(argv)
    trees = []
    for spec in args.tree:
        label, _, rest = spec.partition("=")
        path, _, mode = rest.partition(":")
        if mode not in ("", "python", "console"):
            ap.error(f"--tree {spec}: the exit mode is 'python' or 'console'")
        trees.append((label, Path(path).resolve(), mode or "console"))
    base = Path(args.out or tempfile.mkdtemp(prefix="timeline_"))
    runs = {label: [] for label, _, _ in trees}
    for r in range(args.repeats):
        for label, tree, mode in trees:
            out = base / f"{label}_{r}"
            res = run_once(tree, mode, args.scan, out, args.extra, args.python)
            import shutil

            shutil.rmtree(out, ignore_errors=True)
            runs[label].append(res)
            print(f"[{label} {r + 1}/{args.repeats}] wall {res['wall']:.2f} s, CPU "
                  f"{res['cpu']:.2f} s, maxrss {res['maxrss_mb']:.0f} MB, load before "
                  f"{res['load_before']:.2f}", flush=True)
    labels = [label for label, _, _ in trees]
    names = []
    for label in labels:
        for res in runs[label]:
            names += [n for n in res["phases"] if n not in names]
    med = statistics.median
    head = "| phase | " + " | ".join(f"{lb} wall s | {lb} CPU s" for lb in labels) + " |"
    print("\n" + head)
    print("|---" * (1 + 2 * len(labels)) + "|")
    for n in names:
        cells = []
        for lb in labels:
            ws = [r["phases"][n][0] for r in runs[lb] if n in r["phases"]]
            cs = [r["phases"][n][1] for r in runs[lb] if n in r["phases"]]
            cells += [f"{med(ws):.2f}" if ws else "", f"{med(cs):.2f}" if cs else ""]
        print(f"| {n} | " + " | ".join(cells) + " |")
    for key, fmt in (("wall", "{:.2f}"), ("cpu", "{:.2f}"), ("maxrss_mb", "{:.0f}")):
        cells = []
        for lb in labels:
            vals = [r[key] for r in runs[lb]]
            cells += [fmt.format(med(vals)) + " (" + " / ".join(fmt.format(v) for v in vals)
                      + ")", ""]
        print(f"| **{key}** | " + " | ".join(cells) + " |")
    cells = []
    for lb in labels:
        cells += [f"{med([r['save'].get('wall', 0) for r in runs[lb]]):.2f}",
                  f"{med([r['save'].get('cpu', 0) for r in runs[lb]]):.2f}"]
    print("| map write (its thread, inside surface) | " + " | ".join(cells) + " |")
    if args.json:
        Path(args.json).write_text(json.dumps({"argv": sys.argv, "runs": runs}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
