#!/usr/bin/env python
"""Benchmark the GMR: GMRField (numba, indexed) vs the brute-force numpy oracle vs
the `gmr` PyPI package (medians of repeats, warm cell cache; the first call, which
builds the cells, is reported too), a realistic case (the demo street's HGMM through
the pipeline, one batch of 200k queries) and a calibration table of the far-field
variance growth.

The mixture is realistic for a street: hit points on planar patches (ground, two
facades, a few boxes as parked cars) with virtual points at +-0.25 m along the
normal, cut into K tiles; each component is the moment-matched Gaussian of the 4D
rows of its tile (what an HGMM leaf is). Queries lie within 0.3 m of the surfaces.

Examples
--------
    python scripts/bench_gmr.py                       # K = 256 and 1024
    python scripts/bench_gmr.py --components 256 --queries 20000 --repeats 5
    python scripts/bench_gmr.py --skip-calibration --out out/bench/gmr.json
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

from gmmgp_app.stages.gmr import GMRField, gmr_bruteforce
from gmmgp_app.types import GaussianMixture


def street(n_points: int, rng: np.random.Generator):
    """Hit points and normals on a 40 m street: ground, facades at y = +-6, 8 cars."""
    parts = []
    def plane(n, origin, u, v, normal):
        a, b = rng.uniform(0, 1, size=(2, n))
        p = origin + a[:, None] * u + b[:, None] * v
        parts.append((p, np.tile(normal, (n, 1))))
    n = n_points
    plane(n // 2, np.array([0, -6, 0.0]), np.array([40, 0, 0.0]), np.array([0, 12, 0.0]),
          np.array([0, 0, 1.0]))
    plane(n // 6, np.array([0, -6, 0.0]), np.array([40, 0, 0.0]), np.array([0, 0, 8.0]),
          np.array([0, 1, 0.0]))
    plane(n // 6, np.array([0, 6, 0.0]), np.array([40, 0, 0.0]), np.array([0, 0, 8.0]),
          np.array([0, -1, 0.0]))
    rest = n - n // 2 - 2 * (n // 6)
    for c in range(8):
        x0, y0 = 2 + 5 * c, (-4.0 if c % 2 else 3.0)
        k = rest // 8
        # top and the four sides of a 4 x 1.8 x 1.5 m box
        plane(k // 3, np.array([x0, y0, 1.5]), np.array([4, 0, 0.0]), np.array([0, 1.8, 0]),
              np.array([0, 0, 1.0]))
        for (o, u, v, nn) in (
                ([x0, y0, 0], [4, 0, 0], [0, 0, 1.5], [0, -1, 0]),
                ([x0, y0 + 1.8, 0], [4, 0, 0], [0, 0, 1.5], [0, 1, 0]),
                ([x0, y0, 0], [0, 1.8, 0], [0, 0, 1.5], [-1, 0, 0]),
                ([x0 + 4, y0, 0], [0, 1.8, 0], [0, 0, 1.5], [1, 0, 0])):
            plane(k // 6, np.array(o, float), np.array(u, float), np.array(v, float),
                  np.array(nn, float))
    p = np.vstack([a for a, _ in parts])
    nrm = np.vstack([b for _, b in parts])
    p += 0.008 * rng.normal(size=(len(p), 1)) * nrm
    return p, nrm


def tile_mixture(points, normals, k: int, s: float = 0.25, seed: int = 0) -> GaussianMixture:
    """K moment-matched 4D Gaussians over k-means-like tiles of the hit points."""
    from scipy.cluster.vq import kmeans2
    rows = np.vstack([np.c_[points, np.zeros(len(points))],
                      np.c_[points + s * normals, np.full(len(points), s)],
                      np.c_[points - s * normals, np.full(len(points), -s)]])
    # cluster on position + scaled normal so a tile does not straddle a corner
    feat = np.c_[points, 2.0 * normals]
    _, lab = kmeans2(feat, k, minit="++", seed=seed, iter=20)
    lab = np.tile(lab, 3)
    w, mu, cov = [], [], []
    for j in range(k):
        r = rows[lab == j]
        if len(r) < 12:
            continue
        w.append(len(r))
        mu.append(r.mean(axis=0))
        cov.append(np.cov(r.T) + 1e-6 * np.eye(4))
    w = np.array(w, dtype=float)
    return GaussianMixture(w / w.sum(), np.array(mu), np.array(cov))


def near_queries(points, normals, n, rng):
    i = rng.integers(0, len(points), n)
    t = rng.uniform(-0.3, 0.3, n)
    jitter = rng.normal(scale=0.1, size=(n, 3))
    return points[i] + t[:, None] * normals[i] + jitter * (1 - np.abs(normals[i]))


def timed(fn, repeats):
    out, times = None, []
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return out, float(np.median(times)), times


def bench_one(mix, q, repeats, n_brute, n_pkg):
    field = GMRField(mix)
    t = time.perf_counter()
    field.predict(q, return_grad=True)                # compile / build the cells once
    first = time.perf_counter() - t
    res = {"n_components": mix.n_components, "n_queries": len(q)}
    (m, v, g), t_field, ts = timed(lambda: field.predict(q, return_grad=True), repeats)
    res["gmrfield"] = dict(seconds_median=t_field, seconds=ts, first_call_seconds=first,
                           queries_per_s=len(q) / t_field, info=field.info)
    qb = q[:n_brute]
    (mb, vb, gb), t_b, ts = timed(lambda: gmr_bruteforce(mix, qb, return_grad=True), repeats)
    res["bruteforce"] = dict(seconds_median=t_b, seconds=ts, n_queries=len(qb),
                             queries_per_s=len(qb) / t_b)
    res["ratio_vs_bruteforce"] = res["gmrfield"]["queries_per_s"] / (len(qb) / t_b)
    res["max_abs_diff_mean_vs_bruteforce"] = float(np.max(np.abs(m[:n_brute] - mb)))
    res["max_abs_diff_var_vs_bruteforce"] = float(np.max(np.abs(v[:n_brute] - vb)))
    res["max_abs_diff_grad_vs_bruteforce"] = float(np.max(np.abs(g[:n_brute] - gb)))
    # mean only (what the gmr package returns), same queries
    (m0, _), t_m, _ = timed(lambda: field.predict(q), repeats)
    res["gmrfield_mean_var_only_queries_per_s"] = len(q) / t_m
    try:
        import gmr as gmr_pkg
        pkg = gmr_pkg.GMM(n_components=mix.n_components, priors=mix.weights,
                          means=mix.means, covariances=mix.covariances)
        qp = q[:n_pkg]
        mp, t_p, ts = timed(lambda: pkg.predict(np.array([0, 1, 2]), qp)[:, 0], repeats)
        res["gmr_package"] = dict(version=getattr(gmr_pkg, "__version__", "?"),
                                  seconds_median=t_p, seconds=ts, n_queries=len(qp),
                                  queries_per_s=len(qp) / t_p)
        res["ratio_vs_gmr_package"] = res["gmrfield_mean_var_only_queries_per_s"] / (
            len(qp) / t_p)
        res["max_abs_diff_mean_vs_gmr_package"] = float(np.max(np.abs(m0[:n_pkg] - mp)))
    except Exception as exc:  # noqa: BLE001 - recorded in the JSON, not fatal
        res["gmr_package"] = dict(error=f"{type(exc).__name__}: {exc}")
    return res


def demo_case(path, n_queries, repeats, n_brute, rng):
    """The realistic case: the HGMM leaves of the demo street through the pipeline,
    queried at scan points moved by up to +-0.5 m along the GMR gradient, in one
    batch as surface extraction does (first call builds the cells, later ones reuse)."""
    import gmmgp_app as gm
    scan = gm.read_scan(path)
    field = gm.build_map(scan, method="hgmm").prior
    mix = field.mixture
    p = scan.points[rng.integers(0, len(scan.points), n_queries)]
    g = field.predict(p, return_grad=True)[2]
    g /= np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-12)
    q = p + rng.uniform(-0.5, 0.5, size=(len(p), 1)) * g
    fresh = GMRField.from_config(mix, gm.MappingConfig().gmr)
    t = time.perf_counter()
    fresh.predict(q)
    first = time.perf_counter() - t
    (m, v), t_warm, ts = timed(lambda: fresh.predict(q), repeats)
    qb = q[:n_brute]
    (mb, vb), t_b, _ = timed(lambda: gmr_bruteforce(mix, qb), repeats)
    return dict(path=str(path), n_components=mix.n_components, n_queries=len(q),
                first_call_seconds=first, cells_cached=fresh.cells_cached,
                warm_seconds_median=t_warm, warm_seconds=ts,
                us_per_query_warm=1e6 * t_warm / len(q),
                bruteforce_queries_per_s=len(qb) / t_b,
                ratio_vs_bruteforce=(len(q) / t_warm) / (len(qb) / t_b),
                ratio_vs_bruteforce_first_call=(len(q) / first) / (len(qb) / t_b),
                max_abs_diff_mean_vs_bruteforce=float(np.max(np.abs(m[:n_brute] - mb))),
                info=fresh.info)


def calibration(mix, points, normals, rng, growths=(0.0, 0.5, 1.0),
                starts=(1.5, 2.0, 2.5)):
    """Mean log-likelihood and median z^2 of the GMR by distance to the data.

    The truth is the distance to the nearest hit point's tangent plane along the
    normal offset used to make the query (exact for the planar street away from
    edges); bins by distance to the nearest hit point.
    """
    from scipy.spatial import cKDTree
    n = 40000
    i = rng.integers(0, len(points), n)
    t = rng.uniform(-1.0, 1.0, n)
    q = points[i] + t[:, None] * normals[i]
    tree = cKDTree(points)
    dist, j = tree.query(q)
    truth = np.einsum("ij,ij->i", q - points[j], normals[j])
    bins = [0, 0.05, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0]
    table = []
    for gam in growths:
        for d0 in starts:
            if gam == 0 and d0 != starts[0]:
                continue
            m, v = GMRField(mix, far_variance_growth=gam, far_growth_start=d0).predict(q)
            ll = -0.5 * np.log(2 * np.pi * v) - 0.5 * (m - truth) ** 2 / v
            z2 = (m - truth) ** 2 / v
            row = dict(far_variance_growth=gam, far_growth_start=d0, bins=[])
            for a, b in zip(bins[:-1], bins[1:]):
                sel = (dist >= a) & (dist < b)
                if sel.any():
                    row["bins"].append(dict(lo=a, hi=b, n=int(sel.sum()),
                                            mean_loglik=float(np.mean(ll[sel])),
                                            rmse=float(np.sqrt(np.mean((m - truth)[sel] ** 2))),
                                            median_z2=float(np.median(z2[sel]))))
            table.append(row)
    return table


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--components", type=int, nargs="+", default=[256, 1024],
                    help="mixture sizes K to benchmark (default: 256 1024)")
    ap.add_argument("--points", type=int, default=60000, help="street hit points")
    ap.add_argument("--queries", type=int, default=50000, help="queries for GMRField")
    ap.add_argument("--brute-queries", type=int, default=5000,
                    help="queries for the brute force (throughput is per query)")
    ap.add_argument("--package-queries", type=int, default=2000,
                    help="queries for the gmr package")
    ap.add_argument("--repeats", type=int, default=5, help="repeats; medians are quoted")
    ap.add_argument("--skip-calibration", action="store_true",
                    help="skip the far-field variance calibration table")
    ap.add_argument("--demo", default="assets/demo_street.npz",
                    help="scan for the realistic case ('' to skip)")
    ap.add_argument("--demo-queries", type=int, default=200000,
                    help="queries of the realistic case (one batch)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="out/bench/bench_gmr.json", help="JSON output path")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    pts, nrm = street(args.points, rng)
    q = near_queries(pts, nrm, args.queries, rng)
    report = dict(machine=dict(python=platform.python_version(), cpu_count=__import__(
        "os").cpu_count()), args=vars(args), runs=[])
    for k in args.components:
        mix = tile_mixture(pts, nrm, k, seed=args.seed)
        r = bench_one(mix, q, args.repeats, args.brute_queries, args.package_queries)
        report["runs"].append(r)
        pkg = r.get("ratio_vs_gmr_package")
        print(f"K={r['n_components']}: GMRField {r['gmrfield']['queries_per_s']:.3g} q/s, "
              f"brute {r['bruteforce']['queries_per_s']:.3g} q/s "
              f"(x{r['ratio_vs_bruteforce']:.0f}, max|dm| "
              f"{r['max_abs_diff_mean_vs_bruteforce']:.2g}), gmr package "
              + (f"x{pkg:.0f} (max|dm| {r['max_abs_diff_mean_vs_gmr_package']:.2g})"
                 if pkg else r["gmr_package"].get("error", "")))
    if args.demo and Path(args.demo).exists():
        d = demo_case(args.demo, args.demo_queries, args.repeats, args.brute_queries, rng)
        report["demo_street"] = d
        print(f"demo street K={d['n_components']}: {d['us_per_query_warm']:.2f} us/query "
              f"warm (x{d['ratio_vs_bruteforce']:.0f} vs brute), first call "
              f"{d['first_call_seconds']:.2f} s (x{d['ratio_vs_bruteforce_first_call']:.0f}), "
              f"max|dm| {d['max_abs_diff_mean_vs_bruteforce']:.2g}")
    if not args.skip_calibration:
        mix = tile_mixture(pts, nrm, args.components[0], seed=args.seed)
        report["variance_calibration"] = calibration(mix, pts, nrm, rng)
        for row in report["variance_calibration"]:
            cells = " ".join(f"{b['mean_loglik']:7.2f}/{b['median_z2']:.2f}"
                             for b in row["bins"])
            print(f"gamma={row['far_variance_growth']:<5} D0={row['far_growth_start']:<4} "
                  f"{cells}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
