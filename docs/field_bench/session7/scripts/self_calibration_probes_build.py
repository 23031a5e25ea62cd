"""Prototype: per-map self-calibration from probes along the normals of left-out hit points."""
import sys, copy, time, warnings, json
sys.path.insert(0, "scripts")
from pathlib import Path
import numpy as np
import bench_accuracy as B, fit_variance as FV
import gmmgp_app as gm
from gmmgp_app.config import concrete
from gmmgp_app.stages import farfield as F

C = Path("out/calib")
names = sys.argv[1].split(",")
out = {}
for name in names:
    t0 = time.time()
    if name in B.SCENES:
        _, _, handed, *_ = B.scene_queries(name, B.SCENES[name], 0, 20000, 6000)
    else:
        scan, scene, spec = FV.training_scan(name)
        _, _, handed, *_ = B.scene_queries(name, spec, int(name.split("_")[2]), 20000, 6000, made=(scan, scene))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        smap = gm.build_map(handed, gm.MappingConfig())
    far = smap.far
    h = far.rho0
    rng = np.random.default_rng(12345)
    P = len(far.points)
    src = rng.choice(P, min(3000, P // 10), replace=False)
    keep = np.ones(P, bool); keep[src] = False
    fp = far.params(); fp.pop("rho0"); fp.pop("noise")
    lo = F.FarField(far.points[keep], far.normals[keep], far.rho0, far.noise, **fp)
    m2 = copy.copy(smap); m2.far = lo
    t = h * np.exp(rng.uniform(np.log(0.5), np.log(100.0), len(src)))
    q = far.points[src] + t[:, None] * far.normals[src]
    r_lo = lo.distance_to_data(q)
    ok = r_lo >= 0.8 * t  # no other surface much nearer than the source's
    q, t = q[ok], t[ok]
    mean, var = m2.predict(q)[:2]
    base = m2.gp if m2.gp is not None else m2.prior
    m_gp, v_gp = base.predict(q)[:2]
    c = lo.components(q, True)
    f = smap.config.far
    d = dict(y=t, mean=mean, var=var, m_gp=m_gp, v_gp=v_gp, m_far=c["mean"], v_far=c["var"], r=c["r"],
             spread2=c["spread2"], h=h, noise=far.noise, length_scale=concrete(smap.config.gp).length_scale,
             kappa=f.disagreement_weight, lam=f.unseen_weight, t_min=f.min_thickness * h, gap=f.edge_gap * h)
    out[name] = d
    np.savez(C / f"probes_{name}.npz", **d)
    print(name, "probes", len(t), f"{time.time()-t0:.0f}s", flush=True)
