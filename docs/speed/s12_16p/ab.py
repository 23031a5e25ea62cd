"""A/B: alternated gmmgp run of SCAN for trees; wall, user, sys (wait4), summary seconds."""
import json, os, subprocess, sys, time, statistics, shutil
scan, reps, extra = sys.argv[1], int(sys.argv[2]), sys.argv[3].split() if len(sys.argv) > 3 and sys.argv[3] else []
trees = [t.split("=") for t in sys.argv[4:]]
py = "/work/main/.venv/bin/python"
res = {lab: [] for lab, _ in trees}
for r in range(reps):
    for lab, path in trees:
        out = f"/tmp/speed-16p/ab_{lab}"
        load = os.getloadavg()[0]
        t = time.perf_counter()
        p = subprocess.Popen([py, "-m", "gmmgp_app.cli", "run", scan, "--out", out, "-q", *extra],
                             env=dict(os.environ, PYTHONPATH=path), cwd=path)
        _, st, ru = os.wait4(p.pid, 0)
        wall = time.perf_counter() - t
        s = json.load(open(f"{out}/summary.json"))["seconds"]
        row = dict(wall=wall, user=ru.ru_utime, sys=ru.ru_stime, cpu=ru.ru_utime + ru.ru_stime,
                   rss=ru.ru_maxrss / 1024, load=load, **{k: round(v, 3) for k, v in s.items()})
        res[lab].append(row)
        print(lab, r, {k: round(v, 2) if isinstance(v, float) else v for k, v in row.items()}, flush=True)
print("medians:")
for lab, rows in res.items():
    print(lab, {k: round(statistics.median(x[k] for x in rows), 3) for k in rows[0]})
json.dump(res, open(os.environ.get("ABJSON", "/tmp/speed-16p/ab_last.json"), "w"), indent=1)
