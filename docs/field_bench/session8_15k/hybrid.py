"""field-15k: the far field with the 16-nearest PCA normal only where the map's radius
neighbourhood is nearly collinear (middle / largest eigenvalue below t), the map's normal
elsewhere. Usage: hybrid.py SCENE NORMAL_RADIUS"""
import sys

import numpy as np
from scipy.spatial import cKDTree

from gmmgp_app.stages import farfield as F

name, R = sys.argv[1], float(sys.argv[2])
d = dict(np.load(f"out/s15k/{name}.npz"))
y, b = d["y"], np.digitize(d["dist"], (0, .05, .1, .2, .3, .5, 1, 2)) - 1
P, N, q, h = d["far_points"], d["far_normals"], d["q"], float(d["h"])
tree = cKDTree(P)
dk, nb = tree.query(P, k=30, workers=-1)
keep = (dk <= R).astype(float)
X = P[nb]
c = (X * keep[..., None]).sum(1) / keep.sum(1)[:, None]
Q = (X - c[:, None]) * keep[..., None]
lam = np.linalg.eigvalsh(np.einsum("nki,nkj->nij", Q, Q))
lin = lam[:, 1] / np.maximum(lam[:, 2], 1e-300)
Q = P[nb[:, :16]] - P[nb[:, :16]].mean(1, keepdims=True)
_, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", Q, Q))
n16 = vec[:, :, 0].copy()
n16[np.einsum("ij,ij->i", n16, N) < 0] *= -1


def row(lab, m):
    print(f"| {lab} | " + " / ".join(
        f"{1000 * np.sqrt(np.mean((m[b == i] - y[b == i]) ** 2)):.1f}" for i in range(7)) + " |")


print(f"| {name} | RMSE (mm) per bin |\n|---|---|")
row("map's mean", d["mean"])
row("plane", d["plane"])
kw = dict(robust_scale=1.0, robust_iterations=3)
for t in (0.02, 0.05, 0.1, 0.2):
    s = lin < t
    n = np.where(s[:, None], n16, N)
    row(f"PCA-16 normal where l_mid / l_max < {t} ({s.mean():.3f} of the points)",
        F.FarField(P, n, h, 0.006, **kw).components(q)["mean"])
