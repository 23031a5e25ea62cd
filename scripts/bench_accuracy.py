#!/usr/bin/env python
"""The field on scans it was tuned on and on scans it never saw (issue 15 protocol).

For every scene: simulate a scan, hand a random 10 % of it to ``build_map`` with the
*default* configuration (the defaults decide what to use of it), and score the field
at queries spread uniformly through the volume near the exact surface:

* near queries: a random point of the full scan (where the scan observed the
  surface) plus an offset uniform in a ball of radius 0.5 m x scale, kept when the
  exact |SDF| <= 0.5 m x scale (both signs);
* far queries: the same with a 2 m x scale ball, |SDF| <= 2 m x scale, kept when at
  least 0.5 m x scale from the handed points;
* every query's closest point on the exact surface lies within 0.1 m x scale of the
  full scan: the truth is a distance to observed surface (the closed synthetic
  meshes also have faces no scanner sees, e.g. the underside of the ground slab).

Queries are binned by their distance to the handed points (0-0.05 / 0.05-0.1 /
0.1-0.2 / 0.2-0.3 / 0.3-0.5 / 0.5-1 / 1-2 m, times the scene's scale). Per bin and
method: RMSE against the exact SDF, mean log-likelihood (the log density of the map's
predictive distribution, ``SurfaceMap.distribution``: eq. unseen_mixture where the
scan did not see, a Gaussian elsewhere and for the baselines), and the fractions of
queries with |y - mu| <= 1 sigma (sigma the reported std) and inside the central
95.45 % interval (a Gaussian's 2 sigma; calibrated: 0.68 and 0.95); gmmgp's row
"within 2 std" is |y - mu| <= 2 sigma as it stands.

Methods: gmmgp, hgmm, gpis, loggpis (unsigned: RMSE and LL of the EDF, no signed
coverage) and ``plane``: the signed distance to the tangent plane of the nearest
handed point (PCA normal of its 16 nearest handed neighbours, oriented to the
sensor; Hoppe et al. 1992); its log-likelihood uses a constant variance (the
scanner's range noise) and is only indicative.

Scenes are split into the ones the defaults were tuned on (``street``, ``sphere``)
and held-out ones never used for any choice (``street2``, ``courtyard``, ``pipes``,
``bunny``). ``bunny`` is real: the ten Stanford range scans from ``../shared`` (about
0.5 mm spacing, 15 cm tall, bins x 0.02), truth the distance to the zippered
reference mesh signed by its pseudo-normals (the mesh is itself a reconstruction,
within about 0.55 mm of the scans; it is open at the bottom, so queries whose
closest mesh point is not near a scan point are dropped as for the other scenes).
It is skipped with one line when ``../shared`` is absent.

Writes ``out/bench/bench_accuracy.json``, a markdown table beside it and one
reliability diagram per scene (PNG, expected against observed coverage).

Examples::

    python scripts/bench_accuracy.py                                  # all scenes
    python scripts/bench_accuracy.py --scenes courtyard,pipes --methods gmmgp,plane
    python scripts/bench_accuracy.py --scenes street --set gp.d_m=0.0 --out out/bench/dm0.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

import gmmgp_app as gm
from gmmgp_app.evaluation import (binned_metrics, closest_point_on_triangles,
                                  plot_reliability, reliability)

ROOT = Path(__file__).resolve().parents[1]
BINS = (0.0, 0.05, 0.1, 0.2, 0.3, 0.5, 1.0, 2.0)
#: (density of the simulated scan, scale of the query band and bins, range noise, tuned?)
SCENES = {
    "street": dict(density=0.3, scale=1.0, noise=0.008, tuned=True),
    "sphere": dict(density=1.0, scale=1.0, noise=0.008, tuned=True),
    "street2": dict(density=0.3, scale=1.0, noise=0.008, tuned=False),
    "courtyard": dict(density=0.3, scale=1.0, noise=0.008, tuned=False),
    "pipes": dict(density=1.0, scale=0.2, noise=0.002, tuned=False),
    "bunny": dict(density=None, scale=0.02, noise=0.0005, tuned=False),
}
BUNNY = ROOT.parent / "shared" / "data" / "stanford_bunny"
METHODS = ("gmmgp", "hgmm", "gpis", "loggpis", "plane")


class MeshTruth:
    """A real scan's reference mesh posing as a synthetic scene for the query sampler:
    ``distance(q, return_closest=True)`` -> signed distance, closest triangle, closest
    point (the sign from the mesh's pseudo-normals, see evaluation.TriangleDistance)."""

    def __init__(self, vertices, faces):
        from gmmgp_app.evaluation import TriangleDistance

        self.vertices, self.faces = vertices, faces
        self._dist = TriangleDistance(vertices, faces)

    def distance(self, q, return_closest=False):
        import open3d as o3d

        d = self._dist(q)
        if not return_closest:
            return d
        ans = self._dist.scene.compute_closest_points(
            o3d.core.Tensor((q - self._dist.centre).astype(np.float32)))
        return d, ans["primitive_ids"].numpy().astype(np.int64), None


def make_scan(name: str, density: float, seed: int):
    if name == "bunny":
        import open3d as o3d

        from gmmgp_app import read_scan

        scan = read_scan(BUNNY / "raw_scans")
        mesh = o3d.io.read_triangle_mesh(str(BUNNY / "reconstruction" / "bun_zipper.ply"))
        return scan, MeshTruth(np.asarray(mesh.vertices, dtype=np.float64),
                               np.asarray(mesh.triangles, dtype=np.int64))
    if name in ("courtyard", "pipes"):
        from gmmgp_app.synth.field_scenes import scan_field_scene

        return scan_field_scene(name, density=density, seed=seed)
    from gmmgp_app.synth import scan_scene

    return scan_scene(name, density=density, seed=seed)


def sample_band(scene, surface_pts, surface_tree, n, radius, seen, rng, batch=100_000):
    """``n`` queries: random surface point + uniform ball offset, |sdf| <= radius, and
    the closest point of the exact surface within ``seen`` of the scan (the truth is
    the distance to a surface the scan observed, not to the underside of a slab)."""
    out, truth = [], []
    got = 0
    v, f = scene.vertices, scene.faces
    while got < n:
        i = rng.integers(0, len(surface_pts), batch)
        u = rng.normal(size=(batch, 3))
        u *= (radius * rng.random(batch) ** (1 / 3) / np.linalg.norm(u, axis=1))[:, None]
        q = surface_pts[i] + u
        d, tri, _ = scene.distance(q, return_closest=True)
        c = closest_point_on_triangles(q, v[f[tri]])
        keep = (np.abs(d) <= radius) & (surface_tree.query(c)[0] <= seen)
        out.append(q[keep])
        truth.append(d[keep])
        got += int(keep.sum())
    return np.concatenate(out)[:n], np.concatenate(truth)[:n]


def plane_reference(points, origins, queries, k=16):
    """Signed distance to the tangent plane of the nearest point (Hoppe et al. 1992)."""
    tree = cKDTree(points)
    _, nb = tree.query(points, k=min(k, len(points)))
    P = points[nb] - points[nb].mean(axis=1, keepdims=True)
    _, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", P, P))
    n = vec[:, :, 0]
    if origins is not None:
        flip = np.einsum("ij,ij->i", n, origins - points) < 0
    else:
        flip = np.einsum("ij,ij->i", n, points - points.mean(0)) < 0
    n[flip] *= -1
    dist, i = tree.query(queries)
    return np.einsum("ij,ij->i", queries - points[i], n[i]), dist


def scene_queries(name, spec, seed, n_near, n_far, made=None):
    """One scene's protocol (module docstring): its simulated scan, the random 10 %
    handed to the map, and the scored queries with their exact SDF and distance to
    the handed points. ``made``: (scan, scene) made elsewhere (e.g. a training scene of
    scripts/fit_variance.py) instead of :func:`make_scan`. Returns (scan, scene, handed,
    q, y, dist)."""
    scan, scene = made if made is not None else make_scan(name, spec["density"], seed)
    rng = np.random.default_rng(seed + 1)
    handed = scan.select(np.sort(rng.choice(len(scan), len(scan) // 10, replace=False)))
    sc = spec["scale"]
    full = cKDTree(scan.points)
    qn, yn = sample_band(scene, scan.points, full, n_near, 0.5 * sc, 0.1 * sc, rng)
    qf, yf = sample_band(scene, scan.points, full, n_far, 2.0 * sc, 0.1 * sc, rng)
    tree = cKDTree(handed.points)
    dn, df = tree.query(qn)[0], tree.query(qf)[0]
    near, far = dn < 0.5 * sc, df >= 0.5 * sc
    q = np.concatenate([qn[near], qf[far]])
    y = np.concatenate([yn[near], yf[far]])
    dist = np.concatenate([dn[near], df[far]])
    return scan, scene, handed, q, y, dist


def run_scene(name, spec, methods, cfg, seed, n_near, n_far, out_dir):
    t0 = time.perf_counter()
    scan, scene, handed, q, y, dist = scene_queries(name, spec, seed, n_near, n_far)
    sc = spec["scale"]
    bins = [b * sc for b in BINS]
    res = {"scene": name, "tuned_on": spec["tuned"], "scale": sc,
           "n_scan_points": len(scan), "n_handed_points": len(handed),
           "n_queries": int(len(q)), "bins": bins, "methods": {},
           "setup_seconds": time.perf_counter() - t0}
    curves = {}
    for method in methods:
        t0 = time.perf_counter()
        if method == "plane":
            mean, dq = plane_reference(handed.points, handed.origins, q)
            var = np.full(len(q), spec["noise"] ** 2)
            m = binned_metrics(mean, var, y, dist, bins)
            m["train_seconds"] = 0.0
        else:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                smap = gm.build_map(handed, cfg, method=method)
            t_train = time.perf_counter() - t0
            signed = method != "loggpis"
            # the map's predictive distribution (eq. unseen_mixture where the scan did not
            # see, a Gaussian elsewhere and for the baselines)
            pred = smap.distribution(q) if signed else None
            mean, var = (pred.mean, pred.var) if signed else smap.predict(q)[:2]
            m = binned_metrics(mean, var, y, dist, bins, signed_prediction=signed,
                               distribution=pred)
            m["train_seconds"] = t_train
            m["counts"] = smap.summary.get("counts", {})
            if "auto" in smap.summary:
                m["auto"] = smap.summary["auto"]
        if method != "loggpis":
            curves[method] = reliability(y, mean, var,
                                         distribution=pred if method != "plane" else None)
            m["reliability"] = curves[method]
        m["seconds"] = time.perf_counter() - t0
        res["methods"][method] = m
        print(f"  {name} {method}: {m['seconds']:.1f} s", file=sys.stderr, flush=True)
    plot_reliability(curves, out_dir / f"reliability_{name}.png",
                     f"{name} ({'tuned on' if spec['tuned'] else 'held out'})")
    return res


def fmt(v, spec):
    return "-" if v is None or v != v else format(v, spec)


def markdown(results) -> str:
    lines = []
    for r in results:
        sc = r["scale"]
        bins = [f"{a:g}-{b:g}" for a, b in zip(r["bins"][:-1], r["bins"][1:])]
        tag = "tuned on" if r["tuned_on"] else "HELD OUT"
        lines.append(f"\n**{r['scene']}** ({tag}; {r['n_scan_points']:,} scan points, "
                     f"{r['n_handed_points']:,} handed to the map, {r['n_queries']:,} queries, "
                     f"bins in m{'' if sc == 1 else f' (scale {sc:g})'})\n")
        lines.append("| method | metric | " + " | ".join(bins) + " |")
        lines.append("|---|---|" + "---|" * len(bins))
        for meth, m in r["methods"].items():
            key = "rmse_sdf" if meth != "loggpis" else "rmse_edf"
            ll = "ll_sdf" if meth != "loggpis" else "ll_edf"
            lines.append(f"| {meth} | RMSE{' EDF' if meth == 'loggpis' else ''} (mm) | "
                         + " | ".join(fmt(1000 * v, ".1f") for v in m[key]) + " |")
            if meth != "plane":
                lines.append(f"| {meth} | mean LL{' EDF' if meth == 'loggpis' else ''} | "
                             + " | ".join(fmt(v, "+.2f") for v in m[ll]) + " |")
            if meth not in ("loggpis", "plane"):
                lines.append(f"| {meth} | cov 1s / 2s | " + " | ".join(
                    f"{fmt(a, '.2f')}/{fmt(b, '.2f')}" for a, b in zip(m["cov1_sdf"],
                                                                      m["cov2_sdf"])) + " |")
                if meth == "gmmgp" and "cov2sig_sdf" in m:
                    lines.append(f"| {meth} | within 2 std | " + " | ".join(
                        fmt(a, ".2f") for a in m["cov2sig_sdf"]) + " |")
        auto = r["methods"].get("gmmgp", {}).get("auto")
        if auto:
            lines.append("\nauto values: " + ", ".join(
                f"{k} = {v['value']:.4g}" for k, v in auto.items()
                if isinstance(v, dict) and isinstance(v.get("value"), (int, float))))
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", default=",".join(SCENES))
    p.add_argument("--methods", default=",".join(METHODS))
    p.add_argument("--near", type=int, default=20000, help="near-band queries")
    p.add_argument("--far", type=int, default=6000, help="far-band queries (before the cut)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", action="append", default=[], help="config override (a.b=v)")
    p.add_argument("--out", default="out/bench/bench_accuracy.json")
    args = p.parse_args(argv)
    cfg = gm.MappingConfig().with_overrides(args.set)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    results = []
    for name in args.scenes.split(","):
        if name not in SCENES:
            print(f"error: unknown scene {name!r}; expected some of {', '.join(SCENES)}",
                  file=sys.stderr)
            return 2
        if name == "bunny" and not BUNNY.is_dir():
            print(f"bunny: skipped, {BUNNY} not found (the real scans live in ../shared)",
                  file=sys.stderr)
            continue
        print(f"{name} ...", file=sys.stderr, flush=True)
        results.append(run_scene(name, SCENES[name], args.methods.split(","), cfg, args.seed,
                                 args.near, args.far, out.parent))
    table = markdown(results)
    out.write_text(json.dumps({"overrides": args.set, "bins_m": list(BINS),
                               "results": results}, indent=1, default=float))
    out.with_suffix(".md").write_text(table)
    print(table)
    print(f"wrote {out}, {out.with_suffix('.md')} and reliability_*.png", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
