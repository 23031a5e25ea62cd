import sys, json, glob, os, numpy as np
d = sys.argv[1]
for side in ("main", "wt-16a"):
    rs = []
    for f in sorted(glob.glob(f"{d}/{side}_*.json")):
        j = json.load(open(f))
        rs.append((j["surface_cpu_s"], j["surface_s"], j["lattice_field_cpu_s"], j["vertex_field_cpu_s"], j["rest_cpu_s"], j["ru_maxrss_mb"], j["load_avg"][0]))
        print(side, os.path.basename(f), " ".join("%.2f" % v for v in rs[-1]))
    if rs:
        print(side, "median cpu %.2f wall %.2f lattice %.2f vertex %.2f rest %.2f rss %.0f load %.1f" % tuple(np.median(np.array(rs), 0)))
