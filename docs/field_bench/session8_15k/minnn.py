"""field-15k: the far field with normals from the map's radius search made to hold at least
M points (PCA of the 30 nearest within max(normal_radius, distance to the M-th)).
Usage: minnn.py SCENE NORMAL_RADIUS"""
import sys

import numpy as np
from scipy.spatial import cKDTree

from gmmgp_app.stages import farfield as F

name, R = sys.argv[1], float(sys.argv[2])
d = dict(np.load(f"out/s15k/{name}.npz"))
y, b = d["y"], np.digitize(d["dist"], (0, .05, .1, .2, .3, .5, 1, 2)) - 1
P, N, q, h = d["far_points"], d["far_normals"], d["q"], float(d["h"])
dk, nb = cKDTree(P).query(P, k=30, workers=-1)


def normals(M):
    keep = (dk <= np.maximum(R, dk[:, M - 1])[:, None]).astype(float)
    X = P[nb]
    c = (X * keep[..., None]).sum(1) / keep.sum(1)[:, None]
    Q = (X - c[:, None]) * keep[..., None]
    _, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", Q, Q))
    n = vec[:, :, 0].copy()
    n[np.einsum("ij,ij->i", n, N) < 0] *= -1  # the map's orientation
    return n


def row(lab, m):
    print(f"| {lab} | " + " / ".join(
        f"{1000 * np.sqrt(np.mean((m[b == i] - y[b == i]) ** 2)):.1f}" for i in range(7)) + " |")


print(f"| {name} | RMSE (mm) per bin |\n|---|---|")
row("map's mean", d["mean"])
row("plane", d["plane"])
kw = dict(robust_scale=1.0, robust_iterations=3)
for M in (3, 8, 12, 16, 24):
    row(f"far, normals of >= {M} points within R", F.FarField(P, normals(M), h, 0.006, **kw)
        .components(q)["mean"])
