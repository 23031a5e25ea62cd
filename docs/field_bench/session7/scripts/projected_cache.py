import sys
sys.path.insert(0, "scripts")
from pathlib import Path
import fit_variance as FV
for n in ["street","sphere","street2","courtyard","pipes","bunny"] + list(FV.TRAIN_SCENES):
    FV.scene_case(n, 0, Path("out/calib"), ["far.project_points=true"]); print(n, flush=True)
