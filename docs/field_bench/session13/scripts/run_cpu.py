"""Alternate main-default and candidate `gmmgp run` on the street scan; CPU s of the child, summary seconds."""
import json, os, resource, subprocess, sys, time, shutil
WT = "/work/wt-15t"
PY = "/work/main/.venv/bin/python"
CAND = ["--set", "far.vote=sphere", "--set", "far.leave_self_out=3", "--set", "far.split_half=true",
        "--set", "far.predictive_dof=7.1"]
rows = []
for rep in range(int(sys.argv[1]) if len(sys.argv) > 1 else 3):
    OLD = ["--set", "far.vote=plane", "--set", "far.leave_self_out=0", "--set", "far.split_half=false", "--set", "far.predictive_dof=0"]
    CONFS = (("main", OLD), ("nosplit", ["--set", "far.split_half=false"]), ("new", []))
    for name, extra in [c for c in CONFS if c[0] in (sys.argv[2].split(",") if len(sys.argv) > 2 else ("default", "candidate"))]:
        out = f"/tmp/field-15t/run_{name}"
        shutil.rmtree(out, ignore_errors=True)
        r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.time()
        subprocess.run([PY, "-m", "gmmgp_app.cli", "run", "/tmp/st11/scan.npz", "--out", out, "-q"] + extra,
                       check=True, env=dict(os.environ, PYTHONPATH=WT), cwd=WT)
        wall = time.time() - t0
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
        s = json.loads(open(f"{out}/summary.json").read())
        sec = s.get("seconds", {})
        load = os.getloadavg()[0]
        print(name, f"wall {wall:.2f} cpu {cpu:.2f} load {load:.1f}", json.dumps({k: round(v, 2) for k, v in sec.items()} if isinstance(sec, dict) else sec), flush=True)
