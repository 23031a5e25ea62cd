import sys, json, glob, os, numpy as np
d = sys.argv[1]
rows = {}
for side in ("main", "wt-16s"):
    for t in sorted(glob.glob(f"{d}/{side}_*.time")):
        base = t[:-5]
        if not os.path.exists(base + "/summary.json"): continue
        u, s, e, m = open(t).read().split()[-4:]
        sec = json.load(open(base + "/summary.json"))["seconds"]
        load = open(base + ".load").read().split("load average:")[1].strip()
        sha = open(base + ".sha").read().strip() if os.path.exists(base + ".sha") else "?"
        rows.setdefault(side, []).append((float(u) + float(s), float(e), float(m) / 1024, sec["surface"], sec["total"], sha, load))
        print(side, os.path.basename(base), "cpu %.2f wall %.2f rss %.0f surface %.2f total %.2f" % rows[side][-1][:5], sha, load)
for side, r in rows.items():
    a = np.array([x[:5] for x in r])
    print(side, "median cpu %.2f wall %.2f rss %.0f surface %.2f total %.2f" % tuple(np.median(a, 0)))
