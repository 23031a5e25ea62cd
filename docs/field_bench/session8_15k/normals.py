"""field-15k: angular error of the far field's normals (the map's: prepare's PCA within
normal_radius, at most normal_max_nn) against the plane reference's recipe (PCA of the 16
nearest), from the exact face of each point. Usage: normals.py SCENE"""
import sys

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, "scripts")
import bench_accuracy as B  # noqa: E402

name = sys.argv[1]
d = dict(np.load(f"out/s15k/{name}.npz"))
P, N, H, O = d["far_points"], d["far_normals"], d["handed"], d["origins"]
scene = B.make_scan(name, B.SCENES[name]["density"], 0)[1]
_, tri, _ = scene.distance(P, return_closest=True)
V = scene.vertices[scene.faces[tri]]
nt = np.cross(V[:, 1] - V[:, 0], V[:, 2] - V[:, 0])
nt /= np.linalg.norm(nt, axis=1, keepdims=True)
lab = scene.face_labels[tri]


def pca(k):
    _, nb = cKDTree(P).query(P, k=k, workers=-1)
    Q = P[nb] - P[nb].mean(1, keepdims=True)
    _, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", Q, Q))
    return vec[:, :, 0]


def ang(n, s):
    return np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", n[s], nt[s])), 0, 1)))


sets = {"map": N, "PCA8": pca(8), "PCA16": pca(16), "PCA30": pca(30)}
print(f"## {name}: angle (deg) between a far point's normal and its exact face's, "
      "median / p90 / p99 / share > 10 deg\n")
print("| points | n | " + " | ".join(sets) + " |")
print("|---|---|" + "---|" * len(sets))
groups = {"all": np.ones(len(P), bool)}
for lv in np.unique(lab):
    groups[f"label {lv}"] = lab == lv
if name == "courtyard":
    groups["building front z > 3 m"] = (lab == 2) & (P[:, 1] > 2.5) & (P[:, 2] > 3)
for g, s in groups.items():
    if s.sum() < 50:
        continue
    cells = []
    for n in sets.values():
        a = ang(n, s)
        cells.append(f"{np.median(a):.1f} / {np.quantile(a, .9):.1f} / {np.quantile(a, .99):.1f} / "
                     f"{np.mean(a > 10):.3f}")
    print(f"| {g} | {s.sum()} | " + " | ".join(cells) + " |")
