import sys, time, cProfile, pstats
import numpy as np
from gmmgp_app import pipeline
from gmmgp_app.config import MappingConfig
from gmmgp_app.datasets import read_scan
from gmmgp_app.stages import hgmm, prepare
scan = read_scan(sys.argv[1])
cfg, _ = pipeline.resolve_config(MappingConfig(), scan)
data = prepare.prepare(scan, cfg)
hgmm._map_threads = lambda fn, items: [fn(t) for t in items]
h = hgmm.fit_hgmm(data, cfg.hgmm)
t, c = time.perf_counter(), time.process_time()
pr = cProfile.Profile(time.process_time); pr.enable()
h = hgmm.fit_hgmm(data, cfg.hgmm)
pr.disable()
print("wall/cpu", time.perf_counter()-t, time.process_time()-c)
pstats.Stats(pr).sort_stats("tottime").print_stats(25)
st = pstats.Stats(pr); st.print_callers("reduce"); st.print_callers("em_loop_groups")
