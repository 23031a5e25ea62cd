#!/usr/bin/env python
"""Session 12 (field-15s) prototype: the sphere vote from neighbourhoods chosen around the
query's foot point instead of around the query (the nearest-neighbour selection bias).

Far from the data the far field's kernel is as wide as the distance r (rho = r), so its
weights over the k nearest hit points are all about 1, and which points are "nearest" is
decided by their noise: |x - p|^2 ~ r^2 + l^2 - 2 r e (l lateral, e the displacement
along the normal); beyond r ~ l^2 / (2 sigma) the k nearest are the k points displaced
most towards the query among ~ 2 pi r sigma / h^2 candidates, and every plane distance
comes out short. Here the k2 nearest hit points of the foot point f = x - m g / |g|
(m, g the sphere vote's mean and the plane vote's weighted normal at x) vote instead,
with eq. rimls / eq. sphere_vote's weights from their distances to x. The map's blend
(eq. blend) is redone with that far mean; the variance's features take the new spread.
Writes ``<stem>_foot<k2>.npz`` beside the cache (keys of fit_variance's cache replaced).

    PYTHONPATH=$PWD python docs/field_bench/session12/scripts/foot_vote.py CACHE K2 [SCENES]
"""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[4] / "scripts"))
import fit_variance as FV  # noqa: E402
from gmmgp_app.stages import farfield as F  # noqa: E402


def foot_case(cache, name, k2, tag="_far.vote-sphere"):
    d = dict(np.load(cache / f"{name}_seed0{tag}.npz"))
    f = np.load(cache / f"{name}_seed0{tag}_far.npz")
    kw = dict(k=int(f["k"]), growth=float(f["growth"]), spread_weight=float(f["spread_weight"]),
              beta=float(f["beta"]), robust_scale=float(f["robust_scale"]),
              robust_iterations=int(f["robust_iterations"]), vote=str(f["vote"]))
    ff = F.FarField(f["points"], f["normals"], float(f["rho0"]), float(f["noise"]), **kw)
    q = f["q"]
    c = ff.components(q, True)
    assert np.array_equal(c["mean"], d["m_far"])
    g = c["grad"] / np.maximum(np.linalg.norm(c["grad"], axis=1), 1e-300)[:, None]
    foot = q - c["mean"][:, None] * g
    _, idx = ff.tree.query(foot, k=k2, workers=-1)
    dist = np.linalg.norm(q[:, None, :] - ff.points[idx], axis=2)
    o = np.argsort(dist, axis=1, kind="stable")
    dist = np.take_along_axis(dist, o, 1)
    idx = np.take_along_axis(idx, o, 1)
    kw["k"] = k2
    ff2 = F.FarField(f["points"], f["normals"], float(f["rho0"]), float(f["noise"]), **kw)
    c2 = ff2.components(q, False, neighbours=(dist, idx))
    v_gp = d["v_gp"] + (d["gp_growth"] * d["r"]) ** 2
    m0, _ = F.blend_fields(d["m_gp"], v_gp, d["m_far"], d["v_far"])
    assert np.allclose(m0, d["mean"], rtol=0, atol=1e-12), np.abs(m0 - d["mean"]).max()
    mean, _ = F.blend_fields(d["m_gp"], v_gp, c2["mean"], c2["var"])
    d.update(m_far=c2["mean"], v_far=c2["var"], mean=mean, spread2=c2["spread2"],
             spread2_sphere=c2["spread2_sphere"], n_eff=c2["n_eff"], delta=c2["delta"],
             shrink=c2["shrink"], v_curv=c2["v_curv"])
    return d


def main():
    cache, k2 = Path(sys.argv[1]), int(sys.argv[2])
    names = sys.argv[3].split(",") if len(sys.argv) > 3 else list(FV.B.SCENES)
    for n in names:
        out = cache / f"{n}_seed0_far.vote-sphere_foot{k2}.npz"
        if not out.exists():
            np.savez(out, **foot_case(cache, n, k2))
        d = np.load(out)
        e = d["y"] - d["mean"]
        rm = [1000 * np.sqrt(np.mean(e[d["bin"] == b] ** 2)) for b in range(7)]
        print(n, k2, "rmse mm", " ".join(f"{x:.1f}" for x in rm), flush=True)


if __name__ == "__main__":
    main()


def reproject_case(cache, name, passes=1, tag="_far.vote-sphere_far.project_points-true"):
    """The projected-points sphere vote with the hit points projected ``passes`` more
    times (eq. point_projection again on the projected points: the residual noise of a
    projected point, which the query's nearest-neighbour selection still favours, is
    averaged once more); the map's blend redone as in :func:`foot_case`."""
    d = dict(np.load(cache / f"{name}_seed0{tag}.npz"))
    f = np.load(cache / f"{name}_seed0{tag}_far.npz")
    kw = dict(k=int(f["k"]), growth=float(f["growth"]), spread_weight=float(f["spread_weight"]),
              beta=float(f["beta"]), robust_scale=float(f["robust_scale"]),
              robust_iterations=int(f["robust_iterations"]), vote=str(f["vote"]))
    p = f["points"]
    for _ in range(passes):
        p = F.project_to_local_planes(p, f["normals"], float(f["rho0"]), k=int(f["k"]))
    ff = F.FarField(p, f["normals"], float(f["rho0"]), float(f["noise"]), **kw)
    c2 = ff.components(f["q"], False)
    v_gp = d["v_gp"] + (d["gp_growth"] * d["r"]) ** 2
    m0, _ = F.blend_fields(d["m_gp"], v_gp, d["m_far"], d["v_far"])
    assert np.allclose(m0, d["mean"], rtol=0, atol=1e-12), np.abs(m0 - d["mean"]).max()
    mean, _ = F.blend_fields(d["m_gp"], v_gp, c2["mean"], c2["var"])
    d.update(m_far=c2["mean"], v_far=c2["var"], mean=mean, spread2=c2["spread2"], r=c2["r"],
             spread2_sphere=c2["spread2_sphere"], n_eff=c2["n_eff"], delta=c2["delta"],
             shrink=c2["shrink"], v_curv=c2["v_curv"])
    return d


def leave_self_out_projection(points, normals, rho0, k=16, min_cos=0.7, cap=None):
    """Each hit point moved along its normal onto the plane through the weighted centroid
    of its neighbours *without itself* (eq. point_projection with w_ii = 0): its new
    distance along the normal no longer contains its own displacement, which is what
    made the query's nearest-neighbour selection choose it."""
    from scipy.spatial import cKDTree
    tree = cKDTree(points)
    d, i = tree.query(points, k=k + 1, workers=-1)
    d, i = d[:, 1:], i[:, 1:]
    ok = np.einsum("ij,ikj->ik", normals, normals[i]) > min_cos
    w = np.exp(-(d / rho0) ** 2) * ok
    ws = w.sum(axis=1)
    c = np.einsum("ik,ikj->ij", w, points[i]) / np.maximum(ws, 1e-300)[:, None]
    t = np.where(ws > 0, np.einsum("ij,ij->i", points - c, normals), 0.0)
    if cap is not None:  # a move larger than the noise explains: the neighbours are elsewhere
        t = np.where(np.abs(t) <= cap, t, 0.0)
    return points - t[:, None] * normals


def loo_case(cache, name, tag="_far.vote-sphere", cap=None):
    """The sphere vote with neighbours chosen by the raw hit points (as the map does) and
    voting with their leave-self-out projections (:func:`leave_self_out_projection`):
    the noise that chose a neighbour is not in its vote. Blend redone as in
    :func:`foot_case`."""
    d = dict(np.load(cache / f"{name}_seed0{tag}.npz"))
    f = np.load(cache / f"{name}_seed0{tag}_far.npz")
    kw = dict(k=int(f["k"]), growth=float(f["growth"]), spread_weight=float(f["spread_weight"]),
              beta=float(f["beta"]), robust_scale=float(f["robust_scale"]),
              robust_iterations=int(f["robust_iterations"]), vote=str(f["vote"]))
    ff = F.FarField(f["points"], f["normals"], float(f["rho0"]), float(f["noise"]), **kw)
    q = f["q"]
    dist, idx = ff.knn.query(q)
    p2 = leave_self_out_projection(f["points"], f["normals"], float(f["rho0"]), int(f["k"]),
                                   cap=None if cap is None else cap * float(f["noise"]))
    ff2 = F.FarField(p2, f["normals"], float(f["rho0"]), float(f["noise"]), **kw)
    c2 = ff2.components(q, False, neighbours=(dist, idx))
    v_gp = d["v_gp"] + (d["gp_growth"] * d["r"]) ** 2
    mean, _ = F.blend_fields(d["m_gp"], v_gp, c2["mean"], c2["var"])
    d.update(m_far=c2["mean"], v_far=c2["var"], mean=mean, spread2=c2["spread2"],
             spread2_sphere=c2["spread2_sphere"], n_eff=c2["n_eff"], delta=c2["delta"],
             shrink=c2["shrink"], v_curv=c2["v_curv"])
    return d
