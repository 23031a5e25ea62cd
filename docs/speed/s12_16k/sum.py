import json, glob, sys, numpy as np
D = sys.argv[1]
print(open(D + "/uptime_start.txt").read().strip(), "|", open(D + "/uptime_end.txt").read().strip() if glob.glob(D + "/uptime_end.txt") else "")
for c in ("kitti", "street10", "street"):
    row = {}
    for t in ("main", "wt"):
        fs = sorted(glob.glob(f"{D}/{t}_{c}_*.json"))
        ds = [json.load(open(f)) for f in fs]
        eq = all(all(v for k, v in d["equal_to"].items() if k != "file") for d in ds)
        s = [d["surface_cpu_s"] for d in ds]; l = [d["lattice_field_cpu_s"] for d in ds]; v = [d["vertex_field_cpu_s"] for d in ds]
        row[t] = np.median(s)
        print(f"{c:9s} {t:4s} surface CPU s {[round(x,2) for x in s]} med {np.median(s):.2f} | lattice {np.median(l):.2f} vertex {np.median(v):.2f} rest {np.median([d['rest_cpu_s'] for d in ds]):.2f} | equal {eq} n={len(ds)}")
    print(f"   ratio {row['wt']/row['main']:.3f}")
