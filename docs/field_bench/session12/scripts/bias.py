#!/usr/bin/env python
"""Session 12 (field-15s): the far field's signed bias per bin. Median of (y - m_far)
sign(m_far) over sigma for queries in front (m_far > 0) / behind, per bin, from the
caches of build_caches.py / foot_vote.py (positive: the field is too short).

    PYTHONPATH=$PWD python docs/field_bench/session12/scripts/bias.py SCENES [TAG]
    (TAG: "" plane vote, _far.vote-sphere, _far.vote-sphere_far.project_points-true,
     _far.vote-sphere_loo3)
"""
import sys, numpy as np
from pathlib import Path
TAG = sys.argv[2] if len(sys.argv) > 2 else "_far.vote-sphere"
C = Path("/tmp/field-15s/calib")
for s in sys.argv[1].split(","):
    d = np.load(C / f"{s}_seed0{TAG}.npz")
    h = float(d["h"]); sig = float(d["noise"])
    e = (d["y"] - d["m_far"]) * np.sign(d["m_far"])
    out = []
    for b in range(7):
        m = d["bin"] == b
        o = m & (d["m_far"] > 0); i = m & (d["m_far"] < 0)
        out.append(f"{np.median(e[o])/sig:+.2f}/{np.median(e[i])/sig:+.2f}")
    print(f"{s:28s} s/h {sig/h:.2f} med signed err/sigma out/in per bin: " + " ".join(out))
