"""field-15k: why the courtyard's far field is worse than the plane at 0.1-0.5 m.

Builds one bench scene's map (defaults, seed 0, exactly scripts/bench_accuracy.py's
protocol) and caches per query: truth, the map's mean, the far field's and the GP's
means, the plane reference, the geometric category (from the exact closest face) and
far-field variants (k, kernel growth, the plane of the nearest far point).
Usage: python docs/field_bench/session8_15k/study.py SCENE [OUT_NPZ]
"""
import sys
import warnings
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT / "scripts"))
import bench_accuracy as B  # noqa: E402
import gmmgp_app as gm  # noqa: E402
from gmmgp_app.stages import farfield as F  # noqa: E402

name = sys.argv[1]
out = Path(sys.argv[2] if len(sys.argv) > 2 else f"out/s15k/{name}.npz")
spec = B.SCENES[name]
scan, scene, handed, q, y, dist = B.scene_queries(name, spec, 0, 20000, 6000)
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    smap = gm.build_map(handed, gm.MappingConfig())
mean, var = smap.predict(q)[:2]
base = smap.gp if smap.gp is not None else smap.prior
m_gp, v_gp = base.predict(q)[:2]
far = smap.far
c = far.components(q, True)
plane, _ = B.plane_reference(handed.points, handed.origins, q)
d = dict(q=q, y=y, dist=dist, mean=mean, var=var, m_gp=m_gp, v_gp=v_gp, m_far=c["mean"],
         v_far=c["var"], r=c["r"], plane=plane, h=far.rho0, n_far_pts=len(far.points),
         n_handed=len(handed))
# variants of the far field on the same points and normals
p = far.params()
for k in (1, 4, 8, 32, 64):
    f2 = F.FarField(far.points, far.normals, **{**p, "k": k})
    d[f"far_k{k}"] = f2.components(q)["mean"]
for g in (0.5, 0.25):
    f2 = F.FarField(far.points, far.normals, **{**p, "growth": g})
    d[f"far_g{g}"] = f2.components(q)["mean"]
f2 = F.FarField(far.points, far.normals, **{**p, "k": 64, "growth": 0.5})
d["far_k64_g0.5"] = f2.components(q)["mean"]
# the far points' normals against a PCA of 16 far points (the plane's recipe)
_, nb = far.tree.query(far.points, k=16, workers=-1)
P = far.points[nb] - far.points[nb].mean(axis=1, keepdims=True)
_, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", P, P))
npca = vec[:, :, 0]
npca[np.einsum("ij,ij->i", npca, far.normals) < 0] *= -1
ri, ii = far.tree.query(q, workers=-1)
d["far_pca_nn"] = np.einsum("ij,ij->i", q - far.points[ii], npca[ii])
d["far_nn"] = np.einsum("ij,ij->i", q - far.points[ii], far.normals[ii])
d["cos_n_pca"] = np.einsum("ij,ij->i", far.normals, npca)[ii]
# the k = 16 patch: its width and the opposed normals in it
dk, ik = far.knn.query(q)
d["patch_radius"] = dk[:, -1]
d["opposed"] = (np.einsum("kjc,kc->kj", far.normals[ik], far.normals[ii]) < -0.5).mean(1)
# category from the exact closest face
_, tri, _reg = scene.distance(q, return_closest=True)
d["label"] = scene.face_labels[tri]
cen = scene.vertices[scene.faces[tri]].mean(axis=1)
d["closest_centroid"] = cen
d.update(far_points=far.points, far_normals=far.normals, handed=handed.points,
         origins=handed.origins)
out.parent.mkdir(parents=True, exist_ok=True)
np.savez(out, **d)
print("saved", out, len(q), "queries; far points", len(far.points), "handed", len(handed),
      "rho0", far.rho0)
