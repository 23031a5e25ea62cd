"""Alternated whole ``gmmgp run`` runs of two source trees (session 13, speed-16b).

    python docs/speed/s13_16b/ab.py SCAN REPEATS "EXTRA ARGS" main=/work/main br=/work/wt-16b \
        [--json OUT.json]

Each run is a fresh ``gmmgp run SCAN --out /tmp/speed-16b/ab_LABEL_I -q EXTRA`` with
``PYTHONPATH`` the tree (the shared venv's console script); ``os.wait4`` gives its wall
time, user + sys CPU seconds and peak RSS; the 1-minute load average is taken before
each run, and the summary's stage seconds are kept. Medians per tree are printed.
"""

import json
import os
import shutil
import statistics
import subprocess
import sys
import time

GMMGP = "/work/main/.venv/bin/gmmgp"


def run_once(tree, scan, out, extra):
    env = dict(os.environ, PYTHONPATH=tree)
    load = os.getloadavg()[0]
    t = time.time()
    p = subprocess.Popen([GMMGP, "run", scan, "--out", out, "-q", *extra], env=env)
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.time() - t
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"run in {tree} failed")
    secs = json.load(open(os.path.join(out, "summary.json")))["seconds"]
    return {"wall": wall, "user": ru.ru_utime, "sys": ru.ru_stime,
            "cpu": ru.ru_utime + ru.ru_stime, "maxrss_mb": ru.ru_maxrss / 1024,
            "load": load, "seconds": secs}


def main(argv):
    js = None
    if "--json" in argv:
        js = argv[argv.index("--json") + 1]
        argv = argv[:argv.index("--json")]
    scan, reps, extra = argv[0], int(argv[1]), argv[2].split()
    trees = [a.split("=", 1) for a in argv[3:]]
    res = {lb: [] for lb, _ in trees}
    for r in range(reps):
        for lb, tree in trees:
            out = f"/tmp/speed-16b/ab_{lb}_{r}"
            shutil.rmtree(out, ignore_errors=True)
            x = run_once(tree, scan, out, extra)
            res[lb].append(x)
            print(f"[{lb} {r}] wall {x['wall']:.2f} cpu {x['cpu']:.2f} (sys {x['sys']:.2f}) "
                  f"rss {x['maxrss_mb']:.0f} load {x['load']:.1f} | " +
                  " ".join(f"{k} {v:.2f}" for k, v in x["seconds"].items()), flush=True)
    med = statistics.median
    for lb, _ in trees:
        rs = res[lb]
        print(f"{lb}: wall {med(r['wall'] for r in rs):.2f} cpu {med(r['cpu'] for r in rs):.2f} "
              f"rss {min(r['maxrss_mb'] for r in rs):.0f}-{max(r['maxrss_mb'] for r in rs):.0f} "
              f"load {min(r['load'] for r in rs):.1f}-{max(r['load'] for r in rs):.1f}")
    if js:
        with open(js, "w") as f:
            json.dump(res, f, indent=1)


if __name__ == "__main__":
    main(sys.argv[1:])
