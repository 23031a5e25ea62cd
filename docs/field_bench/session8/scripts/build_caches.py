"""Build the per-query variance ingredients (scripts/fit_variance.py scene_case) of the
bench six and the sixteen training scenes into out/calib (session 8)."""
import sys
import time
from pathlib import Path

sys.path.insert(0, "scripts")
import fit_variance as FV  # noqa: E402

names = sys.argv[1].split(",") if len(sys.argv) > 1 else \
    list(FV.B.SCENES) + list(FV.TRAIN_SCENES) + list(FV.TRAIN_SCENES_NOISE)
for n in names:
    t = time.time()
    d = FV.scene_case(n, 0, Path("out/calib"))
    print(f"{n}: {len(d['y'])} queries, h {d['h']:.4f} noise {d['noise']:.4f}, "
          f"{time.time() - t:.0f} s", flush=True)
