"""field-15k: the far field's mean with other normals and k, on study.py's cache.
Usage: variants.py SCENE  (reads out/s15k/SCENE.npz, writes out/s15k/SCENE_variants.npz
and prints RMSE (mm) per bin 0-0.05 ... 1-2 m)."""
import sys

import numpy as np
from scipy.spatial import cKDTree

from gmmgp_app.stages import farfield as F

name = sys.argv[1]
d = dict(np.load(f"out/s15k/{name}.npz"))
y, b = d["y"], np.digitize(d["dist"], (0, .05, .1, .2, .3, .5, 1, 2)) - 1
P, N, H, O, q = d["far_points"], d["far_normals"], d["handed"], d["origins"], d["q"]
h = float(d["h"])


def pca(k):
    """The plane reference's normals (PCA of k nearest, oriented to the sensor) at the
    far field's points."""
    _, nb = cKDTree(P).query(P, k=k, workers=-1)
    Q = P[nb] - P[nb].mean(1, keepdims=True)
    _, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", Q, Q))
    n = vec[:, :, 0].copy()
    _, ii = cKDTree(H).query(P, workers=-1)
    n[np.einsum("ij,ij->i", n, O[ii] - P) < 0] *= -1
    return n


def rmse(m, s):
    return 1000 * np.sqrt(np.mean((m[s] - y[s]) ** 2))


out = {}


def row(lab, m):
    out[lab] = m
    print(f"| {lab} | " + " / ".join(f"{rmse(m, b == i):.1f}" for i in range(7)) + " |",
          flush=True)


print("| far field | RMSE (mm) 0-0.05 / 0.05-0.1 / 0.1-0.2 / 0.2-0.3 / 0.3-0.5 / 0.5-1 / 1-2 m |")
print("|---|---|")
row("map's mean (default)", d["mean"])
row("plane reference", d["plane"])
kw = dict(robust_scale=1.0, robust_iterations=3)  # the map's defaults
nsets = {"map": N}
for kn in (8, 16, 24):
    nsets[f"PCA{kn}"] = pca(kn)
for lab, n in nsets.items():
    for k in (8, 16, 32):
        row(f"{lab} normals, k {k}", F.FarField(P, n, h, 0.006, k=k, **kw).components(q)["mean"])
np.savez(f"out/s15k/{name}_variants.npz", **out)
