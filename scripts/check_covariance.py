"""Is the registration's covariance honest? Pairs with known truth, the truth's
Mahalanobis^2 in the reported covariance, and the reported sigmas.

Pairs (truth known exactly):
  bench H/N   the pair of scripts/bench_check.py (36 m street, default map with its far
              field, ``hgmm.seed`` H), second drive through ``street_van`` with noise
              seed N, moved by 0.5 deg / 5.1 cm; ``noise=0.01``.
  test H/N    the pair of tests/test_check.py (20 m street, paper's field with the fixed
              urban values, far field off, ``hgmm.seed`` H), noise seed N.
  kitti self  KITTI 000000 registered onto its own map from the bench's perturbed guess
              (0.3 m, 2 deg; ``noise=0.02``); truth: the identity.
  kitti half  KITTI 000000's points split in two (every other point of the file): the map
              of the even points, the odd points registered onto it (truth: the identity;
              real data whose noise the map did not see).

``--collect DIR`` runs check_scan(align=True) on the pairs and keeps per pair (DIR/*.npz)
the registration's state at its solution (the points, the GP field's mean, variance and
gradient, the last stage's surface correction, the weights, the cell factors, the share
counts, the pivot, the scaling, the frozen directions) and the truth; ``--analyse DIR``
prints per pair the truth's Mahalanobis^2 and the sigmas of the covariance check_scan
reported and of its parts and alternatives (:func:`covariances`).

``--variants DIR`` moves each kept solution by the IRLS solution of its residuals
linearised there with other weights (:func:`variants`); ``--reuse-var`` with
``--collect``: the dense stage's later iterations keep its first variance (a study of a
mean-and-gradient-only prediction, ``check._REUSE_DENSE_VAR``).

    PYTHONPATH=$PWD python scripts/check_covariance.py --collect /tmp/cov --maps /tmp/maps
    PYTHONPATH=$PWD python scripts/check_covariance.py --analyse /tmp/cov
    PYTHONPATH=$PWD python scripts/check_covariance.py --variants /tmp/cov
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
KITTI = ROOT.parent / "shared" / "data" / "kitti_odometry_seq00"


def _truth_T():
    from gmmgp_app.check import _rotvec_to_matrix

    a = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    T = np.eye(4)
    T[:3, :3] = _rotvec_to_matrix(np.radians(0.5) * a)
    T[:3, 3] = (0.03, -0.035, 0.02)
    return T


def _xi(T_true, res):
    """The truth's xi about the reported pivot (map frame): T_true = exp(xi) T."""
    from scipy.spatial.transform import Rotation

    D = T_true @ np.linalg.inv(res.transform)
    phi = Rotation.from_matrix(D[:3, :3]).as_rotvec()
    return np.r_[D[:3, :3] @ res.pivot + D[:3, 3] - res.pivot, phi]


def _map(cache: Path, name, build):
    import gmmgp_app as gm

    p = cache / name
    if p.exists():
        return gm.load_map(p)
    smap = build()
    smap.save(p)
    return smap


def _settings(items) -> dict:
    """``["gp.select_neighbours=16", ...]`` -> {key: int, float, bool or string}."""
    out = {}
    for it in items or ():
        k, eq, v = it.partition("=")
        if not eq:
            raise SystemExit(f"--set expects KEY=VALUE, found {it!r}")
        for conv in (int, float):
            try:
                out[k] = conv(v)
                break
            except ValueError:
                continue
        else:
            out[k] = {"true": True, "false": False}.get(v.lower(), v)
    return out


def pairs(a):
    """(name, map, scan points, init, truth, noise) for the pairs asked for."""
    import gmmgp_app as gm
    from gmmgp_app.config import MappingConfig, concrete
    from gmmgp_app.synth import scan_scene

    cache = Path(a.maps)
    cache.mkdir(parents=True, exist_ok=True)
    T = _truth_T()
    want = set(a.only.split(",")) if a.only else None

    def on(kind):
        return want is None or kind in want

    extra = _settings(a.set)  # --set: map settings of a study (maps kept in their own --maps)
    for kind, length, cfgf in (("bench", 36.0, lambda h: MappingConfig().replace(
                                   {"hgmm.seed": h, **extra})),
                               ("test", 20.0, lambda h: concrete(MappingConfig()).replace(
                                   {"far.enabled": False, "hgmm.seed": h, **extra}))):
        if not on(kind):
            continue
        for h in a.hseeds:
            def build(h=h, length=length, cfgf=cfgf):
                first, _ = scan_scene("street", density=0.1, seed=0,
                                      scene_params=dict(length=length))
                return gm.build_map(first, cfgf(h))

            smap = _map(cache, f"{kind}_h{h}", build)
            for n in a.nseeds:
                second, _ = scan_scene("street_van", density=0.1, seed=n,
                                       scene_params=dict(length=length), lane_y=-1.5)
                moved = (second.points - T[:3, 3]) @ T[:3, :3]
                yield f"{kind} h{h} n{n}", smap, moved, np.eye(4), T, 0.01
    dT = None
    if (on("kitti") or on("half") or a.half_scans) and KITTI.is_dir():
        from bench_check import _rot
        from gmmgp_app.datasets import read_scan
        from gmmgp_app.datasets.kitti import read_poses

        poses = read_poses(KITTI / "poses_gicp_estimated.txt")
        scan = read_scan(KITTI / "velodyne" / "000000.bin")
        P = np.eye(4)
        P[:3] = poses[0]
        rng = np.random.default_rng(0)  # the bench's first perturbation (its seed 0)
        u, ax = rng.normal(size=3), rng.normal(size=3)
        dT = np.eye(4)
        dT[:3, :3] = _rot(ax, 2.0)
        dT[:3, 3] = 0.3 * u / np.linalg.norm(u)
        init = dT @ P
        pts = scan.points
        if on("kitti"):
            smap = _map(cache, "kitti0", lambda: gm.build_map(scan, MappingConfig().replace(extra)))
            yield "kitti self", smap, pts, init, np.eye(4), 0.02
        if on("half"):
            from gmmgp_app.types import Scan

            org = None if scan.origins is None else scan.origins[0::2]
            even = Scan(pts[0::2], origins=org, offset=scan.offset)
            smap = _map(cache, "kitti0_even", lambda: gm.build_map(even, MappingConfig().replace(extra)))
            yield "kitti half", smap, pts[1::2], init, np.eye(4), 0.02
    for k in a.half_scans if KITTI.is_dir() else ():
        # another scan's halves, in that scan's own frame: the guess is the perturbation
        from gmmgp_app.datasets import read_scan
        from gmmgp_app.types import Scan

        scan = read_scan(KITTI / "velodyne" / f"{k:06d}.bin")
        pts = scan.points
        org = None if scan.origins is None else scan.origins[0::2]
        even = Scan(pts[0::2], origins=org, offset=scan.offset)
        smap = _map(cache, f"kitti{k}_even", lambda: gm.build_map(even, MappingConfig().replace(extra)))
        yield f"kitti half {k}", smap, pts[1::2], dT, np.eye(4), 0.02


def collect(a) -> int:
    import gmmgp_app.check as ck

    out = Path(a.collect)
    out.mkdir(parents=True, exist_ok=True)
    grab = {}
    orig_cons = ck._cluster_consistency

    def consistency(info, P, size):
        grab.update(info=info, P=P, size=size)
        return orig_cons(info, P, size)

    ck._cluster_consistency = consistency
    for name, smap, pts, init, truth, noise in pairs(a):
        grab.clear()
        t = time.perf_counter()
        res = ck.check_scan(pts, smap, align=True, init=init, noise=noise)
        sec = time.perf_counter() - t
        info = grab["info"]
        corr = info["corr"]
        y = info["y"]
        np.savez(out / (name.replace(" ", "_") + ".npz"),
                 name=name, xi=_xi(truth, res), cov=res.covariance,
                 y=y, m=info["m_field"], var=info["var"], g=info["J"][:, :3], w_fit=info["w_fit"],
                 w_geo=info["w_geo"], pivot=info["pivot"], D=info["D"], P=grab["P"],
                 size=grab["size"], noise=noise,
                 corr=np.zeros(len(y)) if corr is None else corr,
                 factor=np.ones(len(y)) if info.get("factor") is None else info["factor"],
                 n_share=info["n_share"], seconds=sec, converged=res.converged,
                 iterations=res.iterations)
        xi = _xi(truth, res)
        print(json.dumps(dict(pair=name, seconds=round(sec, 2),
                              mahal2=round(float(xi @ np.linalg.pinv(res.covariance) @ xi), 2),
                              rot_mdeg=round(float(np.degrees(np.linalg.norm(xi[3:]))) * 1e3, 3),
                              t_pivot_mm=round(float(np.linalg.norm(xi[:3])) * 1e3, 3))),
              flush=True)
    return 0


def covariances(d) -> dict:
    """The kept pair's covariances (m, rad): check_scan's (``cov``: jackknife of the
    minimised residuals and the map-error model, whichever is larger per direction),
    and its parts and alternatives: the jackknife of the GP field's residuals (session
    7's), of the minimised ones, the map-error model with other cells."""
    import gmmgp_app.check as ck

    y, m, var, g, pivot, D, P = (d[k] for k in ("y", "m", "var", "g", "pivot", "D", "P"))
    noise2 = float(d["noise"]) ** 2
    corr, factor, n_share = d["corr"], d["factor"], d["n_share"]
    known = np.sqrt(var) < 0.1
    kw = dict(c_robust=4.685, loss="tukey", n_share=n_share, factor=factor)
    w_f, _ = ck._weights(m, var, noise2, known, **kw)
    w_c, _ = ck._weights(m + corr, var, noise2, known, **kw)
    J, _, _ = ck._normal_matrix(y, g, w_c, m + corr, pivot)
    Ds = D[:, None] * D[None, :]
    info = dict(y=y, J=J, D=D, w_fit=w_c, var=var, factor=factor, noise2=noise2)
    out, scaled = {"reported": d["cov"]}, {}
    size = float(d["size"])
    for tag, mm, ww in (("field", m, w_f), ("fit", m + corr, w_c)):
        cons = ck._cluster_consistency(dict(D=D, w=ww, m=mm, J=J, y=y), P, size)
        scaled["jackknife " + tag] = cons["jackknife"]
    for cell in (0.5, 1.0, 2.0):
        scaled[f"model {cell:g} m"] = ck._map_error_covariance(info, P, cell)
    scaled["max(jackknife fit, model 1 m)"] = ck._cov_max(scaled["jackknife fit"],
                                                         scaled["model 1 m"], P)
    scaled["max(jackknife field, model 1 m)"] = ck._cov_max(scaled["jackknife field"],
                                                           scaled["model 1 m"], P)
    out.update({k: v * Ds for k, v in scaled.items()})
    return out


def analyse(a) -> int:
    rows = []
    for f in sorted(Path(a.analyse).glob("*.npz")):
        d = dict(np.load(f, allow_pickle=True))
        xi = d["xi"]
        row = {"pair": str(d["name"]),
               "err_t_mm": round(float(np.linalg.norm(xi[:3])) * 1e3, 3),
               "err_r_mdeg": round(float(np.degrees(np.linalg.norm(xi[3:]))) * 1e3, 3)}
        for k, C in covariances(d).items():
            sd = np.sqrt(np.clip(np.diag(C), 0, None))
            row[k] = dict(mahal2=round(float(xi @ np.linalg.pinv(C) @ xi), 2),
                          sigma_t_mm=(sd[:3] * 1e3).round(3).tolist(),
                          sigma_r_mdeg=(np.degrees(sd[3:]) * 1e3).round(3).tolist())
        rows.append(row)
        print(json.dumps(row), flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


def variants(a) -> int:
    """``--variants DIR``: per kept pair, the registration's estimate moved by the IRLS
    solution of its residuals linearised at the solution (:func:`check._linear_irls`)
    with other weights (robust constant, loss, share cell, no cell factors, the GP
    field's residuals without the correction, a smaller ``known_std``: fewer points); the truth's error after it (rotation
    mdeg / translation at the pivot mm). Linearised: a map's field over the few
    millimetres moved is linear to microns apart from the GP's block jumps."""
    import gmmgp_app.check as ck

    sets = {"as run": {}, "tukey 3": dict(c_robust=3.0), "tukey 7": dict(c_robust=7.0),
            "cauchy": dict(loss="cauchy", c_robust=2.3849), "share 0.5": dict(share=0.5),
            "share 2": dict(share=2.0), "no factors": dict(nofactor=True),
            "no correction": dict(nocorr=True), "share 0 (1/(s2+n2))": dict(share=-1),
            "known_std 0.05": dict(known=0.05), "known_std 0.03": dict(known=0.03),
            "unit gradient": dict(unit=True), "no robust loss": dict(c_robust=1e6)}
    rows = []
    for f in sorted(Path(a.variants).glob("*.npz")):
        d = dict(np.load(f, allow_pickle=True))
        xi, y, g, m, var, pivot, D = d["xi"], d["y"], d["g"], d["m"], d["var"], d["pivot"], d["D"]
        noise2 = float(d["noise"]) ** 2
        row = {"pair": str(d["name"])}
        for label, v in sets.items():
            mc = m if v.get("nocorr") else m + d["corr"]
            if v.get("unit"):  # residual and Jacobian per unit gradient: distances
                gn = np.maximum(np.linalg.norm(g, axis=1), 1e-12)
                mc, g = mc / gn, g / gn[:, None]
            else:
                g = d["g"]
            n_share = d["n_share"]
            if "share" in v:
                n_share = np.ones(len(y)) if v["share"] < 0 else ck._share_counts(y, v["share"])
            factor = None if v.get("nofactor") else d["factor"]
            kn = v.get("known", 0.1)
            kw = dict(noise2=noise2, known_std=kn, c_robust=v.get("c_robust", 4.685),
                      loss=v.get("loss", "tukey"))
            w, _ = ck._weights(mc, var, noise2, np.sqrt(var) < kn, kw["c_robust"], kw["loss"],
                               n_share, factor)
            J, H, b = ck._normal_matrix(y, g, w, mc, pivot)
            step = ck._solve_step(H, b, D, d["P"])
            step, _ = ck._linear_irls(J, mc, var, step, D, d["P"], n_share=n_share,
                                      factor=factor, max_iter=50, tol_t=1e-7, tol_r=1e-8, **kw)
            e = xi - step  # T_true = exp(xi) T, T' = exp(step) T: error left ~ xi - step
            row[label] = [round(float(np.degrees(np.linalg.norm(e[3:]))) * 1e3, 3),
                          round(float(np.linalg.norm(e[:3])) * 1e3, 3)]
        rows.append(row)
        print(json.dumps(row), flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--collect", default=None, help="run the pairs, keep their state here")
    ap.add_argument("--analyse", default=None, help="covariances of the kept pairs")
    ap.add_argument("--variants", default=None, help="other weights on the kept pairs")
    ap.add_argument("--maps", default="/tmp/check_cov_maps", help="built maps kept here")
    ap.add_argument("--hseeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--nseeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--only", default=None, help="comma list of bench,test,kitti,half")
    ap.add_argument("--json", default=None, help="--analyse: write the rows here")
    ap.add_argument("--half-scans", type=int, nargs="*", default=[],
                    help="also these KITTI scans' odd points onto the maps of their even "
                         "points (each in its own frame)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a MappingConfig field of every map built (a study's maps: give "
                         "them their own --maps directory)")
    ap.add_argument("--reuse-var", action="store_true",
                    help="the dense stage's later iterations take its first one's variance "
                         "(check._REUSE_DENSE_VAR, a study)")
    a = ap.parse_args(argv)
    if a.reuse_var:
        import gmmgp_app.check as ck

        ck._REUSE_DENSE_VAR = True
    if a.collect:
        return collect(a)
    if a.analyse:
        return analyse(a)
    if a.variants:
        return variants(a)
    ap.error("give --collect DIR or --analyse DIR")
    return 2


if __name__ == "__main__":
    sys.exit(main())
