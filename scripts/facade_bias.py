"""Where the synthetic street's map puts its facades, against the exact planes.

The bench pair of scripts/bench_check.py: the default map of the first drive through
``street`` (lane +1.5, seed 0, 36 m, density 0.1). Its two long facades are known planes:
the 18 m building's front at y = -8 (normal +y) and the three buildings' fronts at
y = +8 (normal -y), both with 0.2 m window recesses and balconies. At the noise-free
points of the second drive (lane -1.5, seed 1, ``range_noise=0``) that lie on those
planes, this script evaluates the map's mean and its parts (the GP field, i.e.
``predict(far=False)`` which the registration uses; the GMR prior alone; the far
field's IMLS; the blended mean of ``predict``) and their zero level's displacement
along the plane's normal, ``delta = m / (g . n)`` after two Newton steps (positive:
the map's surface lies behind the true plane, inside the building; the street is
wider), per facade, per component and by the distance of the point from the nearest
edge of the plane (window recess, balcony, building end).

It also measures the data's own offset: the mean signed distance from the true plane
of the first drive's hit points there, of the voxel subsample prepare keeps, of the
GP's training points (those the prior misses by more than d_m), and of the virtual
points' labels against their true distance.

    PYTHONPATH=$PWD .venv/bin/python scripts/facade_bias.py --map out/maps/street36
    PYTHONPATH=$PWD .venv/bin/python scripts/facade_bias.py --map DIR --json out/fb.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

FACADES = (("y = -8 (18 m, normal +y)", -8.0, np.array([0.0, 1.0, 0.0])),
           ("y = +8 (9-15 m, normal -y)", 8.0, np.array([0.0, -1.0, 0.0])))


def bench_map(path, density=0.1, length=36.0, settings=None, **scan_kw):
    import gmmgp_app as gm
    from gmmgp_app.config import MappingConfig
    from gmmgp_app.synth import scan_scene

    if path and Path(path).exists():
        return gm.load_map(path)
    first, _ = scan_scene("street", density=density, seed=0,
                          scene_params=dict(length=length), **scan_kw)
    smap = gm.build_map(first, MappingConfig().replace(settings or {}))
    if path:
        smap.save(path)
    return smap


def parse_settings(items) -> dict:
    """``["gp.select_neighbours=16", ...]`` -> {key: number or string}."""
    out = {}
    for it in items:
        k, _, v = it.partition("=")
        if not _:
            raise SystemExit(f"--set expects KEY=VALUE, found {it!r}")
        try:
            out[k] = int(v)
        except ValueError:
            try:
                out[k] = float(v)
            except ValueError:
                out[k] = {"true": True, "false": False}.get(v.lower(), v)
    return out


def plane_points(scene, pts, y0, n, labels=None):
    """Rows of ``pts`` on the plane y = y0 (to 1e-9 m) and their clearance: the largest
    of 0.02, 0.05, 0.1, 0.2, 0.4 m within which the scene is that plane alone (the true
    signed distance at +-t along the normal is +-t)."""
    on = np.abs(pts[:, 1] - y0) < 1e-9
    if labels is not None:
        on &= labels == 2  # FACADE
    idx = np.flatnonzero(on)
    clear = np.zeros(len(idx))
    ok = np.ones(len(idx), bool)
    for t in (0.02, 0.05, 0.1, 0.2, 0.4):
        p = pts[idx]
        good = ok.copy()
        for s in (t, -t):
            d = scene.sdf(p + s * n)
            good &= np.abs(d - s) < 1e-6
        clear[good] = t
        ok = good
    return idx, clear


def zero_offset(predict, p, n, steps=2):
    """Displacement of the field's zero level along ``n`` from ``p`` (``-t`` with
    f(p + t n) = 0 by Newton steps along n; positive: behind the plane), the mean at p
    and the gradient's component along n."""
    t = np.zeros(len(p))
    m0 = gn0 = None
    for k in range(steps + 1):
        m, _, g = predict(p + t[:, None] * n)
        gn = g @ n
        if k == 0:
            m0, gn0 = m, gn
        if k < steps:
            t = t - m / np.where(np.abs(gn) > 1e-3, gn, 1e-3)
    return -t, m0, gn0


def components(smap):
    """The map's fields by name: (mean, var, grad) = f(points)."""
    far = smap.far

    def far_field(x):
        return far.predict(x, return_grad=True)

    return {
        "GP field (registration)": lambda x: smap.predict(x, return_grad=True, far=False),
        "GMR prior": lambda x: smap.prior.predict(x, return_grad=True),
        "far field (IMLS)": far_field,
        "blend (predict)": lambda x: smap.predict(x, return_grad=True),
        "last stage (GP + correction)": lambda x: last_stage(smap, x),
    }


def last_stage(smap, x):
    """The field the registration's last stage fits (check._surface_correction): the GP
    field's mean plus the blended mean's difference where the blended variance is the
    smaller, with the GP field's variance and gradient."""
    from gmmgp_app.check import _surface_correction

    m, var, g = smap.predict(x, return_grad=True, far=False)
    corr = _surface_correction(smap, x, m, var, g)
    return (m if corr is None else m + corr), var, g


def data_offsets(smap, first_scan, scene, y0, n, region):
    """Mean signed distance (mm) from the plane of the first drive's points near it
    (within 5 cm, in ``region`` clearance >= 0.1 m) and of what prepare kept."""
    out = {}
    for name, pts in (("first drive, all hits", first_scan.points),
                      ("voxel subsample (training hits)", smap.far.points),
                      ("GP training points", smap.gp_points)):
        near = np.abs(pts[:, 1] - y0) < 0.05
        q = pts[near]
        # clean: project to the plane and require clearance 0.1 m there
        proj = q.copy()
        proj[:, 1] = y0
        _, clear = plane_points(scene, proj, y0, n)
        sel = clear >= region
        d = (q[sel] - proj[sel]) @ n  # signed distance from the plane, free space +
        out[name] = {"n": int(sel.sum()), "mean_mm": float(1e3 * d.mean()),
                     "se_mm": float(1e3 * d.std() / np.sqrt(max(sel.sum(), 1)))}
    return out


def weighted_summary(smap, second, scene):
    """Per facade, at the noise-free second drive's points on the plane: the share of
    check_scan's registration weight (shared 1 m counts, cell factors, Tukey; noise 1 cm)
    and the weighted mean of the GP field's and the GMR prior's mean there (mm; the
    registration's residual at the truth), the median map std, and the GP field's
    zero-level displacement binned by the distance to the nearest GP training point."""
    from scipy.spatial import cKDTree

    from gmmgp_app.check import _factors_here, _share_counts, _weights

    y = second.points - smap.offset
    m, var, g = smap.predict(y, return_grad=True, far=False)
    n2 = 1e-4
    ns, cell = _share_counts(y, 1.0, return_cells=True)
    fac = _factors_here(y, m, var, g, n2, 0.1, cell)
    w, _ = _weights(m, var, n2, np.sqrt(var) < 0.1, 4.685, "tukey", ns, fac)
    mp = smap.prior.predict(y)[0]
    mc = last_stage(smap, y)[0]
    tree = cKDTree(smap.gp_points)
    out = {}
    for fname, y0, n in FACADES:
        idx, clear = plane_points(scene, second.points, y0, n, second.labels)
        ww = w[idx]
        r, _ = tree.query(y[idx])
        delta = m[idx] / np.maximum(g[idx] @ n, 1e-3)
        bins = {}
        for lo, hi in ((0, 0.05), (0.05, 0.1), (0.1, 0.2), (0.2, np.inf)):
            sel = (r >= lo) & (r < hi) & (clear >= 0.05)
            if sel.sum() > 20:
                bins[f"{lo:g}-{hi:g} m"] = {"n": int(sel.sum()),
                                            "median_delta_mm": float(1e3 * np.median(delta[sel])),
                                            "weight_share": float(ww[sel].sum() / w.sum())}
        out[fname] = {"weight_share": float(ww.sum() / w.sum()),
                      "weighted_mean_m_gp_mm": float(1e3 * np.average(m[idx], weights=ww)),
                      "weighted_mean_m_prior_mm": float(1e3 * np.average(mp[idx], weights=ww)),
                      "weighted_mean_m_last_stage_mm": float(1e3 * np.average(mc[idx],
                                                                             weights=ww)),
                      "median_std_mm": float(1e3 * np.median(np.sqrt(var[idx]))),
                      "by_distance_to_gp_points": bins}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--map", default=None, help="map directory (built and saved if absent)")
    ap.add_argument("--json", default=None)
    ap.add_argument("--first-noise", type=float, default=None,
                    help="range noise of the first drive when the map is built here")
    ap.add_argument("--data", action="store_true", help="also the data's own offsets")
    ap.add_argument("--weighted", action="store_true",
                    help="only the registration-weighted summary (see weighted_summary)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a MappingConfig field of the map when it is built here "
                         "(e.g. gp.select_neighbours=16)")
    args = ap.parse_args(argv)
    from gmmgp_app.synth import scan_scene

    kw = {} if args.first_noise is None else dict(range_noise=args.first_noise)
    smap = bench_map(args.map, settings=parse_settings(args.set), **kw)
    second, scene = scan_scene("street_van", density=0.1, seed=1,
                               scene_params=dict(length=36.0), lane_y=-1.5, range_noise=0.0)
    if args.weighted:
        ws = weighted_summary(smap, second, scene)
        for fname, v in ws.items():
            print(f"{args.map} | {fname} | weight {v['weight_share']:.3f} | GP field "
                  f"{v['weighted_mean_m_gp_mm']:+.2f} mm | last stage "
                  f"{v['weighted_mean_m_last_stage_mm']:+.2f} mm | prior "
                  f"{v['weighted_mean_m_prior_mm']:+.2f} mm"
                  f" | std {v['median_std_mm']:.1f} mm | by distance to GP points: "
                  + "; ".join(f"{k}: {b['median_delta_mm']:+.2f} mm (w {b['weight_share']:.4f})"
                              for k, b in v["by_distance_to_gp_points"].items()))
        if args.json:
            Path(args.json).parent.mkdir(parents=True, exist_ok=True)
            Path(args.json).write_text(json.dumps(ws, indent=1))
        return 0
    comps = components(smap)
    res = {"map": args.map, "facades": {}}
    print("| facade | component | clearance >= | points | mean delta (mm) | median | "
          "mean m (mm) | mean g.n |")
    print("|---|---|---|---|---|---|---|---|")
    for fname, y0, n in FACADES:
        idx, clear = plane_points(scene, second.points, y0, n, second.labels)
        p = second.points[idx] - smap.offset
        rows = {}
        for cname, f in comps.items():
            delta, m0, gn = zero_offset(f, p, n)
            for lo in (0.0, 0.05, 0.1, 0.2):
                sel = clear >= lo if lo > 0 else np.ones(len(p), bool)
                if not sel.any():
                    continue
                r = {"n": int(sel.sum()), "mean_delta_mm": float(1e3 * delta[sel].mean()),
                     "median_delta_mm": float(1e3 * np.median(delta[sel])),
                     "mean_m_mm": float(1e3 * m0[sel].mean()),
                     "mean_gn": float(gn[sel].mean())}
                rows[f"{cname} | {lo:g}"] = r
                print(f"| {fname} | {cname} | {lo:g} | {r['n']} | {r['mean_delta_mm']:+.2f} | "
                      f"{r['median_delta_mm']:+.2f} | {r['mean_m_mm']:+.2f} | "
                      f"{r['mean_gn']:.3f} |")
        # by height band (GP field only, clearance >= 0.05)
        delta, _, _ = zero_offset(comps["GP field (registration)"], p, n)
        bands = {}
        for z0, z1 in ((0, 3), (3, 6), (6, 9), (9, 12), (12, 18)):
            sel = (p[:, 2] >= z0) & (p[:, 2] < z1) & (clear >= 0.05)
            if sel.sum() > 20:
                bands[f"{z0}-{z1} m"] = (int(sel.sum()), float(1e3 * delta[sel].mean()))
        print(f"  {fname}, GP field by height (clearance >= 0.05): "
              + "; ".join(f"{k}: {v[1]:+.2f} mm ({v[0]})" for k, v in bands.items()))
        res["facades"][fname] = {"components": rows, "gp_by_height": bands}
        if args.data:
            first, _ = scan_scene("street", density=0.1, seed=0,
                                  scene_params=dict(length=36.0), **kw)
            d = data_offsets(smap, first, scene, y0, n, 0.1)
            res["facades"][fname]["data"] = d
            for k, v in d.items():
                print(f"  {fname}, {k}: {v['mean_mm']:+.3f} +- {v['se_mm']:.3f} mm ({v['n']})")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
