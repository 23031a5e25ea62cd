#!/usr/bin/env python
"""Benchmark the hierarchical GMM against scikit-learn's flat GaussianMixture.

For each scene (a synthetic street, and KITTI odometry 00 scan 000000 when
../shared/data is present) the scan is prepared into 4D rows, split 90/10 with
a seed by hit point (a hit point and its virtual points stay on one side), and:

* the HGMM is fitted on the 90 % (default config: tied EM), timing it; the same
  hierarchy with free EM (``hgmm.tie_virtual = false``) is fitted too and scored;
* scikit-learn ``GaussianMixture(covariance_type="full")`` with as many
  components as the HGMM has leaves is fitted on the same rows (``max_iter``,
  default k-means init, same seed), timing it;
* both are scored on the held-out 10 % (mean log-likelihood per row), and by the
  held-out log-likelihood of d given xyz under each mixture's GMR; the tied HGMM
  also by the likelihood of whole held-out observations (a hit point with its
  virtual points, the unit tied EM models; ``hgmm.score_groups``), per row;
* a reg_covar probe (``--reg-probe``, on the scene with fewer rows): scikit-learn
  and the HGMM again with smaller ``reg_covar``. The rows' d takes three values
  (-s, 0, +s), so a mixture that gives each sheet its own component has a d
  variance of ``reg_covar`` there and a held-out log-likelihood that grows without
  bound as ``reg_covar`` shrinks (about +0.5 log(100) = 2.3 nats per row for 1e-6
  -> 1e-8); the JSON records the weight fraction in such one-sheet components.

scikit-learn costs O(rows x leaves x iterations) and takes minutes with
hundreds of components (about 20-40 min for the default street on 2 cores): it
fits the same rows as the HGMM unless ``--sk-max-rows`` caps them (rows drawn
from the training rows); ``--sk-max-iter`` bounds its iterations; the JSON
records what was used.
When it is given fewer rows than the HGMM, the time ratio is also quoted per
row (sk seconds / sk rows vs HGMM seconds / HGMM rows).

Then the HGMM fit time against the number of rows (50k ... 400k rows drawn from
a denser street scan), each repeated ``--repeats`` times (median quoted), and
the effect of dropping inconsistent virtual points on the row labels (RMS of
``d - sdf(x)`` on a thin-wall scene and on the street, exact SDF).

Examples
--------
    python scripts/bench_hgmm.py                       # everything, ~1 h on 2 cores
    python scripts/bench_hgmm.py --quick --out /tmp/b.json
    python scripts/bench_hgmm.py --sizes 50000 100000 --repeats 1
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
KITTI = SHARED / "kitti_odometry_seq00" / "velodyne" / "000000.bin"


# ------------------------------------------------------------ simple scenes
def _box_sdf(q, lo, hi):
    """Exact signed distance to an axis-aligned box (positive outside), (N,)."""
    c = (lo + hi) / 2
    h = (hi - lo) / 2
    d = np.abs(q - c) - h
    out = np.linalg.norm(np.maximum(d, 0.0), axis=1)
    ins = np.minimum(d.max(axis=1), 0.0)
    return out + ins


class BoxScene:
    """Union of axis-aligned boxes; sdf = min over boxes (exact outside the
    solids, a bound inside where boxes overlap)."""

    def __init__(self, boxes):
        self.boxes = [(np.asarray(a, float), np.asarray(b, float)) for a, b in boxes]

    def sdf(self, q):
        return np.min([_box_sdf(q, a, b) for a, b in self.boxes], axis=0)

    def sample(self, n, trajectory, rng, noise=0.01):
        """Points on the box faces visible (by facing, ignoring occlusion) from
        the nearest trajectory point, with that point as sensor origin, and on
        the scene surface (sdf ~ 0)."""
        faces = []
        for a, b in self.boxes:
            for ax in range(3):
                for side, val in ((-1, a[ax]), (1, b[ax])):
                    u, v = [i for i in range(3) if i != ax]
                    area = (b[u] - a[u]) * (b[v] - a[v])
                    faces.append((ax, side, val, u, v, a, b, area))
        areas = np.array([f[-1] for f in faces])
        counts = rng.multinomial(int(n * 3), areas / areas.sum())
        pts, nrm = [], []
        for f, c in zip(faces, counts):
            ax, side, val, u, v, a, b, _ = f
            p = np.empty((c, 3))
            p[:, ax] = val
            p[:, u] = rng.uniform(a[u], b[u], c)
            p[:, v] = rng.uniform(a[v], b[v], c)
            nn = np.zeros((c, 3))
            nn[:, ax] = side
            pts.append(p)
            nrm.append(nn)
        p, nn = np.concatenate(pts), np.concatenate(nrm)
        on_surface = np.abs(self.sdf(p)) < 1e-9  # drop faces buried in other boxes
        p, nn = p[on_surface], nn[on_surface]
        ti = np.clip(np.searchsorted(trajectory[:, 0], p[:, 0]), 0, len(trajectory) - 1)
        org = trajectory[ti]
        visible = np.einsum("ij,ij->i", nn, org - p) > 0
        p, nn, org = p[visible], nn[visible], org[visible]
        if len(p) > n:
            sel = rng.choice(len(p), n, replace=False)
            p, nn, org = p[sel], nn[sel], org[sel]
        p = p + nn * rng.normal(scale=noise, size=(len(p), 1))
        return p, org


def simple_street(length=60.0):
    """Road, two facades with thin balconies, parked cars (boxes)."""
    boxes = [((-5, -10, -1), (length + 5, 10, 0))]                # road slab
    boxes += [((-5, 8, 0), (length + 5, 12, 12)), ((-5, -12, 0), (length + 5, -8, 12))]
    for x0 in np.arange(3.0, length - 3, 9.0):                  # balconies, 0.15 m slabs
        for z in (4.0, 8.0):
            boxes.append(((x0, 6.8, z), (x0 + 3.0, 8.0, z + 0.15)))
            boxes.append(((x0 + 4, -8.0, z), (x0 + 7.0, -6.8, z + 0.15)))
    for x0 in np.arange(2.0, length - 5, 7.0):                  # cars
        boxes.append(((x0, 3.5, 0), (x0 + 4.2, 5.3, 1.5)))
    return BoxScene(boxes)


def street_scan(n_points, seed, length=60.0):
    """(points, origins, scene) of the simple street, sensor at 2 m along y = 0."""
    from gmmgp_app.types import Scan

    rng = np.random.default_rng(seed)
    scene = simple_street(length)
    traj = np.c_[np.linspace(-2, length + 2, 200), np.zeros(200), np.full(200, 2.0)]
    p, org = scene.sample(n_points, traj, rng)
    return Scan(points=p, origins=org, source="bench simple street"), scene


def get_street(n_points, seed):
    """(scan, scene, source) of a street: gmmgp_app.synth's MMS-scanned "street"
    (density chosen for about ``n_points`` hits; 1.0 gives ~1.3 M) when that module
    is there, else the simple box street of this script."""
    try:
        from gmmgp_app.synth import scan_scene

        density = min(max(n_points / 1.3e6, 1e-4), 100.0)
        scan, scene = scan_scene("street", density=density, seed=seed)
        return scan, scene, f"gmmgp_app.synth.scan_scene('street', density={density:.3f})"
    except ImportError:
        scan, scene = street_scan(n_points, seed)
        return scan, scene, "scripts/bench_hgmm.py simple_street (gmmgp_app.synth missing)"


def thin_wall_scene():
    """A 0.1 m thick free-standing wall on a ground plane, scanned from both sides."""
    return BoxScene([((-5, -5, -1), (5, 5, 0)), ((-2, -0.05, 0), (2, 0.05, 2.5))])


def thin_wall_scan(n_points, seed):
    from gmmgp_app.types import Scan

    rng = np.random.default_rng(seed)
    scene = thin_wall_scene()
    pts, orgs = [], []
    for y in (-3.0, 3.0):   # one pass on each side of the wall
        traj = np.c_[np.linspace(-5, 5, 50), np.full(50, y), np.full(50, 1.5)]
        p, o = scene.sample(n_points // 2, traj, rng, noise=0.005)
        pts.append(p)
        orgs.append(o)
    return Scan(points=np.concatenate(pts), origins=np.concatenate(orgs)), scene


def read_kitti(path=KITTI):
    from gmmgp_app.types import Scan

    try:
        from gmmgp_app.datasets import read_scan

        return read_scan(path), "gmmgp_app.datasets.read_scan"
    except Exception:
        raw = np.fromfile(path, dtype=np.float32).reshape(-1, 4)[:, :3].astype(np.float64)
        raw = raw[np.linalg.norm(raw, axis=1) > 2.5]  # the car's own roof returns
        return Scan(points=raw, origins=np.zeros_like(raw), source=str(path)), \
            "numpy fromfile (sensor origin 0, returns within 2.5 m dropped)"


# ------------------------------------------------------------------ helpers
def split_rows(rows, groups, seed, frac=0.1):
    """Hold out ``frac`` of the hit points with all their rows (a group stays whole).

    Returns train rows, their groups, test rows, their groups.
    """
    rng = np.random.default_rng(seed)
    ids = np.unique(groups)
    test_ids = rng.choice(ids, int(round(frac * len(ids))), replace=False)
    test = np.isin(groups, test_ids)
    return rows[~test], groups[~test], rows[test], groups[test]


def one_sheet_weight(weights, covariances, s=0.25):
    """Weight fraction of components whose d spread is under a fifth of s: they sit on
    one sheet (d = -s, 0 or +s) and their d variance is about reg_covar."""
    sd = np.sqrt(np.asarray(covariances)[:, 3, 3])
    return float(np.sum(np.asarray(weights)[sd < 0.2 * s]))


def sample_groups(rows, groups, n_rows, seed):
    """About ``n_rows`` rows made of whole groups drawn at random, (rows, groups)."""
    ids = np.unique(groups)
    per = len(rows) / len(ids)
    pick = np.random.default_rng(seed).choice(ids, min(len(ids), int(round(n_rows / per))),
                                              replace=False)
    keep = np.isin(groups, pick)
    return rows[keep], groups[keep]


def label_error(data, scene):
    """RMS and 95 % of |d - sdf(x)| over the virtual rows of a TrainingSet."""
    v = data.kinds != 0
    err = data.rows[v, 3] - scene.sdf(data.rows[v, :3])
    sign_wrong = np.sign(data.rows[v, 3]) != np.sign(scene.sdf(data.rows[v, :3]))
    return dict(n_virtual=int(v.sum()), rms=float(np.sqrt(np.mean(err ** 2))),
                p95_abs=float(np.quantile(np.abs(err), 0.95)),
                frac_over_5cm=float(np.mean(np.abs(err) > 0.05)),
                frac_sign_wrong=float(np.mean(sign_wrong)))


def conditional_loglik(mixture, rows) -> float:
    """Mean log N(d | m(x), sigma^2(x)) over rows under the GMR of a mixture.

    On held-out *training-style* rows (hits at d = 0, virtual points at exactly +-s):
    a mixture that gives each sheet its own component predicts these rows best, which
    says little about the field between the sheets (see bench_accuracy / bench_sphere).
    """
    from gmmgp_app.stages.gmr import GMRField

    m, v = GMRField(mixture, far_variance_growth=0.0).predict(rows[:, :3])
    return float(np.mean(-0.5 * np.log(2 * np.pi * v) - 0.5 * (rows[:, 3] - m) ** 2 / v))


def bench_scene(name, rows, groups, hcfg, seed, sk_max_rows, sk_max_iter, run_sklearn=True,
                reg_probe=()):
    from gmmgp_app.stages.hgmm import fit_hgmm, format_level_history, hgmm_diagnostics, score

    train, train_groups, test, test_groups = split_rows(rows, groups, seed)
    t = time.perf_counter()
    h = fit_hgmm(train, hcfg, groups=train_groups)
    t_h = time.perf_counter() - t
    diag = hgmm_diagnostics(h, test, test_groups)
    # The same hierarchy with free (untied) EM, for the record: it is the better
    # density, the worse regression prior (see HGMMConfig.tie_virtual).
    t = time.perf_counter()
    h_free = fit_hgmm(train, hcfg)
    t_free = time.perf_counter() - t
    free = dict(seconds=t_free, n_leaves=h_free.leaves.n_components,
                heldout_mean_loglik=score(h_free.leaves, test),
                heldout_conditional_loglik=conditional_loglik(h_free.leaves, test))
    print(f"[{name}] untied HGMM: {t_free:.2f} s, {free['n_leaves']} leaves, held-out "
          f"{free['heldout_mean_loglik']:.4f}")
    print(f"[{name}] {len(train)} train rows: HGMM {t_h:.2f} s, {h.leaves.n_components} leaves, "
          f"held-out {diag['heldout_mean_loglik']:.4f}")
    print(format_level_history(h))
    ll_obs = diag["heldout_observation_loglik"]
    print(f"[{name}] held-out observations (tied likelihood) {ll_obs:.4f} per row")
    out = dict(n_rows=len(rows), n_train=len(train), n_test=len(test),
               hgmm=dict(seconds=t_h, heldout_mean_loglik=diag["heldout_mean_loglik"],
                         heldout_observation_loglik_per_row=ll_obs,
                         one_sheet_weight=one_sheet_weight(h.leaves.weights,
                                                           h.leaves.covariances),
                         heldout_conditional_loglik=conditional_loglik(h.leaves, test),
                         diagnostics=diag, level_fits=h.info["level_fits"],
                         tied_groups=h.info.get("tied_groups"),
                         level_history=format_level_history(h).splitlines()),
               hgmm_untied=free)
    if not run_sklearn:
        return out
    from sklearn.mixture import GaussianMixture as SKGMM

    K = h.leaves.n_components
    sk_rows = train
    if sk_max_rows and len(train) > sk_max_rows:
        sk_rows = train[np.random.default_rng(seed + 1).choice(len(train), sk_max_rows,
                                                                replace=False)]
    sk = SKGMM(n_components=K, covariance_type="full", max_iter=sk_max_iter, random_state=seed,
               reg_covar=hcfg.reg_covar, tol=hcfg.tol)
    t = time.perf_counter()
    sk.fit(sk_rows)
    t_sk = time.perf_counter() - t
    ll_sk = float(sk.score(test))
    from gmmgp_app.types import GaussianMixture as GM
    sk_mix = GM(sk.weights_, sk.means_, sk.covariances_)
    ll_h = diag["heldout_mean_loglik"]
    out["sklearn"] = dict(seconds=t_sk, n_components=K, n_rows=len(sk_rows),
                          max_iter=sk_max_iter, n_iter=int(sk.n_iter_),
                          converged=bool(sk.converged_), heldout_mean_loglik=ll_sk,
                          heldout_conditional_loglik=conditional_loglik(sk_mix, test),
                          one_sheet_weight=one_sheet_weight(sk.weights_, sk.covariances_),
                          init="kmeans (sklearn default), random_state=seed")
    out["time_ratio_sklearn_over_hgmm"] = t_sk / t_h
    out["time_ratio_per_row"] = (t_sk / len(sk_rows)) / (t_h / len(train))
    # Relative shortfall of the HGMM against sklearn (positive = HGMM worse).
    out["heldout_rel_shortfall"] = (ll_sk - ll_h) / abs(ll_sk)
    out["score_hgmm_on_its_leaves"] = score(h.leaves, test)
    out["heldout_rel_shortfall_observations"] = (ll_sk - ll_obs) / abs(ll_sk)
    probe = []
    for reg in reg_probe:
        hp = fit_hgmm(train, dataclasses.replace(hcfg, reg_covar=reg), groups=train_groups)
        skp = SKGMM(n_components=hp.leaves.n_components, covariance_type="full",
                    max_iter=sk_max_iter, random_state=seed, reg_covar=reg,
                    tol=hcfg.tol).fit(sk_rows)
        probe.append(dict(reg_covar=reg, n_components=hp.leaves.n_components,
                          hgmm_heldout_mean_loglik=score(hp.leaves, test),
                          sklearn_heldout_mean_loglik=float(skp.score(test)),
                          sklearn_one_sheet_weight=one_sheet_weight(skp.weights_,
                                                                    skp.covariances_)))
        print(f"[{name}] reg_covar {reg:g}: {json.dumps(probe[-1])}")
    if probe:
        out["reg_covar_probe"] = [dict(reg_covar=hcfg.reg_covar, n_components=K,
                                       hgmm_heldout_mean_loglik=ll_h,
                                       sklearn_heldout_mean_loglik=ll_sk,
                                       sklearn_one_sheet_weight=out["sklearn"][
                                           "one_sheet_weight"])] + probe
    print(f"[{name}] sklearn K={K} on {len(sk_rows)} rows: {t_sk:.1f} s ({sk.n_iter_} it), "
          f"held-out {ll_sk:.4f}; ratio {t_sk / t_h:.1f}x (per row "
          f"{out['time_ratio_per_row']:.1f}x), shortfall {out['heldout_rel_shortfall']:+.4f}; "
          f"log p(d | x): HGMM {out['hgmm']['heldout_conditional_loglik']:.3f}, untied "
          f"{free['heldout_conditional_loglik']:.3f}, sklearn "
          f"{out['sklearn']['heldout_conditional_loglik']:.3f}")
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(REPO / "out" / "bench" / "bench_hgmm.json"),
                    help="JSON output path (default: out/bench/bench_hgmm.json)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--street-points", type=int, default=300_000,
                    help="hit points of the street scan before the 15 %% subsampling")
    ap.add_argument("--sizes", type=int, nargs="*", default=[50_000, 100_000, 200_000, 400_000],
                    help="row counts of the scaling table")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--sk-max-rows", type=int, default=0,
                    help="cap on scikit-learn's training rows, drawn from the HGMM's "
                         "(default 0: the same rows)")
    ap.add_argument("--reg-probe", type=float, nargs="*", default=[1e-8],
                    help="smaller reg_covar values to refit both with, on the scene with "
                         "fewer rows (KITTI when present; none: skip)")
    ap.add_argument("--sk-max-iter", type=int, default=100)
    ap.add_argument("--quick", action="store_true",
                    help="small sizes, one repeat, scikit-learn capped (a smoke run)")
    ap.add_argument("--no-kitti", action="store_true")
    args = ap.parse_args(argv)
    if args.quick:
        args.street_points, args.sizes, args.repeats = 150_000, [20_000, 40_000], 1
        args.sk_max_iter, args.reg_probe = 20, []

    from gmmgp_app.config import MappingConfig
    from gmmgp_app.stages.hgmm import fit_hgmm
    from gmmgp_app.stages.prepare import prepare

    cfg = MappingConfig()
    res = dict(config=cfg.to_dict(), machine=dict(python=platform.python_version(),
                                                  cpu_count=__import__("os").cpu_count()),
               args=vars(args))
    # Warm the numba cache so no compile time lands in the first timing.
    fit_hgmm(np.random.default_rng(0).normal(size=(5000, 4)), cfg.hgmm)

    # 1. dropping inconsistent virtual points: label error against the exact SDF
    drop = {}
    for label, (scan, scene) in {
        "thin_wall": thin_wall_scan(100_000, args.seed),
        "street": get_street(300_000, args.seed)[:2],
    }.items():
        d = {}
        for flag in (False, True):
            c = cfg.replace({"prepare.drop_inconsistent_virtual": flag,
                             "prepare.subsample_rate": 0.3})
            data = prepare(scan, c)
            d["with_drop" if flag else "without_drop"] = dict(
                label_error(data, scene), n_dropped_virtual=data.n_dropped_virtual)
        drop[label] = d
        print(f"[virtual {label}] {json.dumps(d)}")
    res["virtual_point_dropping"] = drop

    # 2. HGMM vs scikit-learn on the street and on KITTI
    with_kitti = KITTI.exists() and not args.no_kitti
    scan, scene, street_src = get_street(args.street_points, args.seed)
    data = prepare(scan, cfg)
    res["street"] = dict(source=street_src, n_points=len(scan),
                         **bench_scene("street", data.rows, data.groups, cfg.hgmm, args.seed,
                                       args.sk_max_rows, args.sk_max_iter,
                                       reg_probe=[] if with_kitti else args.reg_probe))
    if with_kitti:
        kscan, ksrc = read_kitti()
        kdata = prepare(kscan, cfg)
        res["kitti_000000"] = dict(source=ksrc, n_points=len(kscan),
                                   **bench_scene("kitti", kdata.rows, kdata.groups, cfg.hgmm,
                                                 args.seed, args.sk_max_rows,
                                                 args.sk_max_iter, reg_probe=args.reg_probe))
    else:
        res["kitti_000000"] = dict(skipped=f"{KITTI} not found or --no-kitti")

    # 3. HGMM time against rows (rows from a denser street, rate chosen per size)
    big, _, _ = get_street(max(args.sizes) // 3 * 2 + 10, args.seed + 7)
    bigdata = prepare(big, cfg.replace("prepare.subsample_rate", 1.0))
    scaling = []
    for n in args.sizes:
        rows, groups = sample_groups(bigdata.rows, bigdata.groups, n, n)
        times, leaves = [], []
        for r in range(args.repeats):
            t = time.perf_counter()
            h = fit_hgmm(rows, cfg.hgmm, groups=groups)
            times.append(time.perf_counter() - t)
            leaves.append(h.leaves.n_components)
        scaling.append(dict(rows=len(rows), seconds_median=float(np.median(times)),
                            seconds=times, leaves=leaves,
                            us_per_row=float(np.median(times)) / len(rows) * 1e6))
        print(f"[scaling] {len(rows)} rows: {np.median(times):.2f} s, leaves {leaves}")
    res["scaling"] = scaling
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1, default=float))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
