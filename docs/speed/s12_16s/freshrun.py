# gmmgp run's path in one process, the surface stage's CPU on the fresh map (as built)
import sys, time, resource
from gmmgp_app._memory import fix_mmap_threshold; fix_mmap_threshold()
import numpy as np
import gmmgp_app as gm
scan = gm.read_scan("/tmp/st11/scan.npz")
cfg = gm.MappingConfig()
c = time.process_time(); t = time.perf_counter()
smap = gm.build_map(scan, cfg)
b = time.process_time() - c
c = time.process_time(); t = time.perf_counter()
mesh = smap.extract_surface(overlap=True)
print(sys.argv[1], "build cpu %.2f surface cpu %.2f wall %.2f faces %d rss %.0f" % (b, time.process_time() - c, time.perf_counter() - t, len(mesh.faces), resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024))
