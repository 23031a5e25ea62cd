"""Peak VmRSS of one `gmmgp run -q` by phase (10 ms samples), for a source tree:
    python docs/speed/s13_16b/rss.py TREE SCAN OUT_DIR
(phases from scripts/profile_run_timeline.py's driver marks; a row "NAME>" is the time
from that stage's start to the next mark)."""
import json, os, subprocess, sys, tempfile, time
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "..", "scripts"))
from profile_run_timeline import DRIVER
tree, scan, out = sys.argv[1], sys.argv[2], sys.argv[3]
marks_path = tempfile.mktemp(suffix=".json")
env = dict(os.environ, PYTHONPATH=tree)
t0 = time.time()
p = subprocess.Popen([sys.executable, "-c", DRIVER, marks_path, "console", "run", scan, "--out", out, "-q"], cwd=tree, env=env)
samples = []
while p.poll() is None:
    try:
        for line in open(f"/proc/{p.pid}/status"):
            if line.startswith("VmRSS"):
                samples.append((time.time(), int(line.split()[1]) / 1024)); break
    except OSError: break
    time.sleep(0.01)
marks = json.load(open(marks_path))["marks"]
evs = [(t, n) for n, t, c in marks]
# print per phase the max rss
allev = sorted([(t, "M", n) for t, n in evs] + [(t, "S", r) for t, r in samples])
cur = "start"; mx = {}
order = []
for t, k, v in allev:
    if k == "M":
        cur = v; order.append(v)
    else:
        mx[cur] = max(mx.get(cur, 0), v)
for n in order:
    if n in mx: print(f"{n:12s} max rss {mx[n]:.0f} MB")
print("peak", max(r for _, r in samples))
