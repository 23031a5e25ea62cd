"""mesh.py MAP OUT.npz [repeat]: extract the map's surface (timings), save the mesh, time the vertex predict's parts."""
import sys, time, json, os, resource
import numpy as np
from gmmgp_app.pipeline import load_map
import gmmgp_app.stages.surface as S
smap = load_map(sys.argv[1])
rep = int(sys.argv[3]) if len(sys.argv) > 3 else 2
ext = S.extract_surface
for r in range(rep):
    ph = {}
    S.extract_surface = lambda *a, **kw: ext(*a, timings=ph, **kw)
    t, c = time.perf_counter(), time.process_time()
    mesh = smap.extract_surface()
    wall, cpu = time.perf_counter() - t, time.process_time() - c
S.extract_surface = ext
np.savez(sys.argv[2], v=mesh.vertices, f=mesh.faces, var=mesh.vertex_variance)
out = {k: round(v, 3) for k, v in ph.items()}
out.update(wall=round(wall, 2), cpu=round(cpu, 2), nv=len(mesh.vertices), nf=len(mesh.faces),
           load=os.getloadavg()[0], rss=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024)
print(json.dumps(out))
if len(sys.argv) > 4:
    r = np.load(sys.argv[4])
    print("equal to", sys.argv[4], np.array_equal(r["v"], mesh.vertices), np.array_equal(r["f"], mesh.faces), np.array_equal(r["var"], mesh.vertex_variance))
