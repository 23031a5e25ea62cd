import numpy as np, time, resource
import gmmgp_app as gm
from gmmgp_app.stages import farfield as F
from gmmgp_app.commands import run as R
orig = F.FarField.components
cnt = {"half": 0, "nohalf": 0, "t_half": 0.0}
def comp(self, xyz, return_grad=False, neighbours=None, split_half=False):
    t = time.process_time()
    out = orig(self, xyz, return_grad, neighbours, split_half)
    cnt["half" if split_half else "nohalf"] += len(out["mean"])
    if split_half: cnt["t_half"] += time.process_time() - t
    return out
F.FarField.components = comp
import subprocess, sys
from gmmgp_app.cli import main
try:
    main(["run", "/tmp/st11/scan.npz", "--out", "/tmp/field-15t/run_count", "-q"])
except SystemExit:
    pass
print(cnt)
