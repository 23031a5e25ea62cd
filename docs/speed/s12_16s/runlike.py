# gmmgp run itself, with the surface stage's CPU seconds printed (wrapper around SurfaceMap.extract_surface)
import sys, time
from gmmgp_app import pipeline
orig = pipeline.SurfaceMap.extract_surface
def timed(self, *a, **kw):
    c = time.process_time(); t = time.perf_counter()
    m = orig(self, *a, **kw)
    print(sys.argv[1], "surface cpu %.2f wall %.2f" % (time.process_time() - c, time.perf_counter() - t), file=sys.stderr)
    return m
pipeline.SurfaceMap.extract_surface = timed
from gmmgp_app.cli import main
sys.exit(main(["run", "/tmp/st11/scan.npz", "--out", "/tmp/speed-16s/rl_" + sys.argv[1], "-q"]))
