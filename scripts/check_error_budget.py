"""Error budget of check_scan's registration on the synthetic second drive.

The Gauss-Newton step taken from the true transform, ``-(J^T W J)^-1 J^T W d``, is the
registration's linearised error there: what the weights, the points used and the
map's gradient make of the map's bias and the scan's noise. This script prints it
(rotation in deg x 1e-3, translation at the points' weighted centre in mm) for the
bench pair of scripts/bench_check.py (36 m street, default map; second drive through
``street_van``, lane -1.5, noise seeds 1-3 and a noise-free one) under:

- weights: ``old`` 1 / (std^2 + noise^2); ``shared C`` 1 / (std^2 + noise^2 / n), n
  the points in the point's C m cell (check_scan's share_cell); ``density C``
  1 / (n std^2 + noise^2) (each cell one vote);
- points: one per 0.1 m cell (the fine stage's voxel sample) or all (the dense stage);
- gradient: the map's analytic one or forward differences of its mean (h = 1e-5 m;
  points where the difference and the analytic gradient differ by more than 0.5, the
  mean jumping at a block's region boundary, left out).

``--foot`` (bench pair, check_scan's weights, all points, at the truth): the weights from
the std at each point's foot on the zero level set (one Newton projection) or at the
noise-free point (an oracle), residuals against the foot (``m / |g|``, the distance to
the two-step foot), a 7th parameter for a common offset of some faces' distances, and
the noise-free drive's error split by the faces' orientation (the gradient's dominant
axis and sign) with their weight share and weighted mean residual.

``--decompose`` (bench pair) splits the error instead, with check_scan's weights (shared
1 m counts, cell variance factors, Tukey), all points, at the truth; rotation vectors in
deg x 1e-3 (x is the street's axis), translation at the points' weighted centre in mm:

- ``noise-free``: the step from the truth for a noise-free second drive (same rays);
- ``noisy``: the same for the noisy drive, and its two parts (the step is linear in the
  residuals): ``map part`` (the noise-free drive's residuals, with the noisy drive's
  points and weights) and ``noise part`` (the noisy minus the noise-free residuals),
  the latter also with uniform weights (how much the weighting amplifies the noise);
- ``fixed point``: Gauss-Newton/IRLS iterated from the truth to a tight tolerance (the
  estimator's own error, no starting point, no convergence tolerance) with the Tukey
  constant 4.685 (default), 20 (nearly no robust loss) and the Cauchy loss, and with
  the check's tolerance (0.1 mm, 10 urad).

    PYTHONPATH=$PWD .venv/bin/python scripts/check_error_budget.py --out out/budget.json
    PYTHONPATH=$PWD .venv/bin/python scripts/check_error_budget.py --scene street2
    PYTHONPATH=$PWD .venv/bin/python scripts/check_error_budget.py --decompose
    PYTHONPATH=$PWD .venv/bin/python scripts/check_error_budget.py --foot --cache out/maps

``--final`` (bench pair, or ``--map DIR``): the same at the truth for the field the
registration's last stage fits (check._surface_correction: the GP field's mean plus the
blended mean's difference where the blend's variance is the smaller, with the GP
field's gradient and variance, and the shape's squared bias in the weights as
check.SHAPE_BIAS says): the step from the truth, its map part (noise-free
residuals) and noise part, and the map part split by face orientation (weight share,
weighted mean residual, share of those points the correction reaches).

    PYTHONPATH=$PWD .venv/bin/python scripts/check_error_budget.py --final --map DIR
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="street", help="street (bench) or street2 (held out)")
    ap.add_argument("--length", type=float, default=36.0)
    ap.add_argument("--density", type=float, default=0.1)
    ap.add_argument("--noise", type=float, default=0.01, help="check_scan's noise (m)")
    ap.add_argument("--out", default=None, help="JSON file (optional)")
    ap.add_argument("--foot", action="store_true",
                    help="weights from the std at each point's foot, residuals against the "
                         "foot, the map's bias by face class (see above)")
    ap.add_argument("--cache", default=None, help="directory to keep the bench map in")
    ap.add_argument("--decompose", action="store_true",
                    help="split the error into map bias, noise and the robust loss's fixed "
                         "point (see above)")
    ap.add_argument("--final", action="store_true",
                    help="the last stage's field (GP mean + surface correction): the step "
                         "from the truth, its map and noise parts, the map part by face")
    ap.add_argument("--map", default=None,
                    help="--foot / --final: this saved map instead of the bench map")
    args = ap.parse_args(argv)
    if args.final:
        return final(args)
    if args.foot:
        return foot(args)
    if args.decompose:
        return decompose(args)

    import gmmgp_app as gm
    from gmmgp_app.check import _normal_matrix, _share_counts, _voxel_sample, _weights
    from gmmgp_app.synth import scan_scene

    params = dict(length=args.length)
    first, _ = scan_scene(args.scene, density=args.density, seed=0, scene_params=params)
    smap = gm.build_map(first)
    second_scene = "street_van" if args.scene == "street" else args.scene
    n2 = args.noise ** 2
    variants = [("old", None), ("shared 1", 1.0), ("shared 6", 6.0), ("density 1", -1.0)]
    rows = []
    for seed, rn in ((1, None), (2, None), (3, None), (1, 0.0)):
        kw = {} if rn is None else dict(range_noise=rn)
        second, _ = scan_scene(second_scene, density=args.density, seed=seed,
                               scene_params=params, lane_y=-1.5, **kw)
        y_all = second.points - smap.offset  # the truth: the scan in the map frame
        m_a, var_a, g_a = smap.predict(y_all, return_grad=True, far=False)
        h = 1e-5
        gfd_a = np.stack([(smap.predict(y_all + h * e, far=False)[0] - m_a) / h
                          for e in np.eye(3)], axis=1)
        jump = np.linalg.norm(gfd_a - g_a, axis=1) > 0.5
        for points, voxel in (("voxel 0.1", 0.1), ("all", None)):
            idx = np.arange(len(y_all)) if voxel is None else \
                _voxel_sample(y_all, voxel, 30000, np.random.default_rng(0))
            y, m, var = y_all[idx], m_a[idx], var_a[idx]
            for wname, cell in variants:
                if cell is None:
                    w, _ = _weights(m, var, n2, np.sqrt(var) < 0.1, 4.685)
                elif cell > 0:
                    w, _ = _weights(m, var, n2, np.sqrt(var) < 0.1, 4.685, "tukey",
                                    _share_counts(y, cell))
                else:
                    w, _ = _weights(m, var, n2, np.sqrt(var) < 0.1, 4.685)
                    w = w * (var + n2) / (_share_counts(y, -cell) * var + n2)
                for gname, G, ww in (("analytic", g_a[idx], w),
                                     ("differences", gfd_a[idx], np.where(jump[idx], 0, w))):
                    pivot = (ww[:, None] * y).sum(0) / ww.sum()
                    _, H, b = _normal_matrix(y, G, ww, m, pivot)
                    xi = np.linalg.solve(H, b)
                    rows.append({"seed": seed, "scan_noise": "default" if rn is None else rn,
                                 "points": points, "n": int(len(idx)), "weights": wname,
                                 "gradient": gname,
                                 "rot_mdeg": float(1e3 * np.degrees(np.linalg.norm(xi[3:]))),
                                 "transl_mm": float(1e3 * np.linalg.norm(xi[:3])),
                                 "gradient_jumps_left_out": int(jump[idx].sum())})
        print(f"  seed {seed} (range noise {'default' if rn is None else rn}): done",
              file=sys.stderr, flush=True)
    print("| points | weights | gradient | seeds 1 / 2 / 3 / noise-free 1: rot (deg x 1e-3) "
          "/ transl (mm) |")
    print("|---|---|---|---|")
    keys = sorted({(r["points"], r["weights"], r["gradient"]) for r in rows},
                  key=lambda k: (k[0], [v[0] for v in variants].index(k[1]), k[2]))
    for k in keys:
        cells = [f"{r['rot_mdeg']:.2f} / {r['transl_mm']:.2f}" for r in rows
                 if (r["points"], r["weights"], r["gradient"]) == k]
        print(f"| {k[0]} | {k[1]} | {k[2]} | {'; '.join(cells)} |")
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps({"argv": sys.argv[1:], "rows": rows}, indent=1))
    return 0


def _print_rows(rows, out, translation_note="") -> int:
    """Print the per-seed table of ``rows`` (dicts with "seed", "what", "xi" = translation
    mm then rotation deg x 1e-3, optional "extra") and write them to ``out`` (JSON) if
    given."""
    print("| what | seeds 1 / 2 / 3: rotation vector (deg x 1e-3) [norm]; translation (mm)"
          f"{translation_note} |")
    print("|---|---|")
    for what in dict.fromkeys(r["what"] for r in rows):
        cells = []
        for r in rows:
            if r["what"] == what:
                xi = r["xi"]
                cells.append(f"({xi[3]:+.2f}, {xi[4]:+.2f}, {xi[5]:+.2f}) "
                             f"[{np.linalg.norm(xi[3:]):.2f}]; {np.linalg.norm(xi[:3]):.2f}"
                             + (f" ({r['extra']})" if "extra" in r else ""))
        print(f"| {what} | {' / '.join(cells)} |")
    if out:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_text(json.dumps(
            {"argv": sys.argv[1:], "rows": [dict(r, xi=r["xi"].tolist()) for r in rows]},
            indent=1))
    return 0


def _one_step(y, m, g, w):
    """One Gauss-Newton step of the registration from the identity (residuals ``m`` with
    gradients ``g`` at points ``y``, weights ``w``, pivot at their weighted centre):
    (translation mm, rotation deg x 1e-3), the normal matrix and the pivot."""
    from gmmgp_app.check import _normal_matrix

    pivot = (w[:, None] * y).sum(0) / w.sum()
    _, H, b = _normal_matrix(y, g, w, m, pivot)
    xi = np.linalg.solve(H, b)
    return np.r_[1e3 * xi[:3], 1e3 * np.degrees(xi[3:])], H, pivot


def _drive_pair(args, params, seed, offset):
    """The second drive (the van, another lane) with noise seed ``seed``, and the same
    rays without range noise: (noisy, noise-free) points relative to the map's offset."""
    from gmmgp_app.synth import scan_scene

    drives = {}
    for rn in (None, 0.0):
        kw = {} if rn is None else dict(range_noise=rn)
        drives[rn], _ = scan_scene("street_van", density=args.density, seed=seed,
                                   scene_params=params, lane_y=-1.5, **kw)
    yn = drives[None].points - offset
    yc = drives[0.0].points - offset
    if len(yn) != len(yc):
        raise SystemExit("the noise-free drive has other rays; cannot pair the points")
    return yn, yc


def decompose(args) -> int:
    """The ``--decompose`` table (see the module docstring)."""
    import gmmgp_app as gm
    from gmmgp_app.check import (_factors_here, _gauss_newton,
                                 _share_counts, _weights)
    from gmmgp_app.synth import scan_scene
    from scipy.spatial.transform import Rotation

    params = dict(length=args.length)
    first, _ = scan_scene("street", density=args.density, seed=0, scene_params=params)
    smap = gm.build_map(first)
    n2 = args.noise ** 2
    rows = []

    def step(y, m, g, w):
        return _one_step(y, m, g, w)[0]

    for seed in (1, 2, 3):
        yn, yc = _drive_pair(args, params, seed, smap.offset)
        out = {}
        for name, y in (("noise-free", yc), ("noisy", yn)):
            m, var, g = smap.predict(y, return_grad=True, far=False)
            n_share, cell = _share_counts(y, 1.0, return_cells=True)
            fac = _factors_here(y, m, var, g, n2, 0.1, cell)
            w, _ = _weights(m, var, n2, np.sqrt(var) < 0.1, 4.685, "tukey", n_share, fac)
            out[name] = (y, m, g, w)
            rows.append({"seed": seed, "what": f"step from the truth, {name}",
                         "xi": step(y, m, g, w)})
        y, m, g, w = out["noisy"]
        mc = out["noise-free"][1]
        rows.append({"seed": seed, "what": "  map part (noise-free residuals)",
                     "xi": step(y, mc, g, w)})
        rows.append({"seed": seed, "what": "  noise part", "xi": step(y, m - mc, g, w)})
        rows.append({"seed": seed, "what": "  noise part, uniform weights",
                     "xi": step(y, m - mc, g, (w > 0).astype(float))})
        x = yn  # the noisy drive; the truth is the identity here
        for label, kw, tol in (("fixed point, Tukey 4.685", {}, (1e-6, 1e-7)),
                               ("fixed point, Tukey 20", dict(c_robust=20.0), (1e-6, 1e-7)),
                               ("fixed point, Cauchy 2.385",
                                dict(loss="cauchy", c_robust=2.3849), (1e-6, 1e-7)),
                               ("from the truth, check's tolerance", {}, (1e-4, 1e-5))):
            kw2 = dict(noise2=n2, known_std=0.1, c_robust=4.685, loss="tukey",
                       share_cell=1.0, cell_factors=True)
            kw2.update(kw)
            T, _, _, _, _ = _gauss_newton(smap, x, np.eye(4), [], max_iter=40, tol_t=tol[0],
                                          tol_r=tol[1], **kw2)
            c = (w[:, None] * y).sum(0) / w.sum()  # translation at the weighted centre
            rows.append({"seed": seed, "what": label, "xi": np.r_[
                1e3 * (T[:3, :3] @ c + T[:3, 3] - c),
                1e3 * np.degrees(Rotation.from_matrix(T[:3, :3]).as_rotvec())]})
        print(f"  seed {seed}: done", file=sys.stderr, flush=True)
    return _print_rows(rows, args.out, " [norm]")


def _bench_map(args):
    import gmmgp_app as gm
    from gmmgp_app.synth import scan_scene

    if getattr(args, "map", None):
        return gm.load_map(args.map)

    if args.cache:
        path = Path(args.cache) / f"street{args.length:g}_default"
        if path.exists():
            return gm.load_map(path)
    first, _ = scan_scene("street", density=args.density, seed=0,
                          scene_params=dict(length=args.length))
    smap = gm.build_map(first)
    if args.cache:
        smap.save(path)
    return smap


def foot(args) -> int:
    """The ``--foot`` table (see the module docstring)."""
    from gmmgp_app.check import _factors_here, _normal_matrix, _share_counts, _weights

    smap = _bench_map(args)
    params = dict(length=args.length)
    n2 = args.noise ** 2
    rows = []

    step = _one_step

    def at_foot(y, m, g):
        n2g = np.maximum((g * g).sum(1), 1e-12)
        p = y - (m / n2g)[:, None] * g
        mf, vf, gf = smap.predict(p, return_grad=True, far=False)
        return p, mf, vf, gf

    for seed in (1, 2, 3):
        yn, yc = _drive_pair(args, params, seed, smap.offset)
        mc, vc, gc = smap.predict(yc, return_grad=True, far=False)
        m, var, g = smap.predict(yn, return_grad=True, far=False)
        n_share, cell = _share_counts(yn, 1.0, return_cells=True)
        fac = _factors_here(yn, m, var, g, n2, 0.1, cell)
        p, mf, vf, gf = at_foot(yn, m, g)
        known = np.sqrt(var) < 0.1

        def W(v, kn=known, mm=m):
            return _weights(mm, v, n2, kn, 4.685, "tukey", n_share, fac)[0]

        w0 = W(var)
        base, H, pivot = step(yn, m, g, w0)
        rows.append({"seed": seed, "what": "check's weights (std at the point)", "xi": base})
        rows.append({"seed": seed, "what": "std at the noise-free point (oracle)",
                     "xi": step(yn, m, g, W(vc))[0]})
        rows.append({"seed": seed, "what": "std at the foot (one Newton projection)",
                     "xi": step(yn, m, g, W(vf))[0]})
        rows.append({"seed": seed, "what": "std at the foot, known there too",
                     "xi": step(yn, m, g, W(vf, np.sqrt(vf) < 0.1))[0]})
        rows.append({"seed": seed, "what": "min(std at point, at foot)",
                     "xi": step(yn, m, g, W(np.minimum(var, vf)))[0]})
        gn = np.linalg.norm(g, axis=1)
        rows.append({"seed": seed, "what": "residual m/|g|, gradient g/|g|",
                     "xi": step(yn, m / gn, g / gn[:, None], w0)[0]})
        # geometric distance to the zero level set: the two Newton steps' lengths
        gfn = np.maximum(np.linalg.norm(gf, axis=1), 1e-6)
        rgeo = m / gn + mf / gfn
        rows.append({"seed": seed, "what": "residual: distance to the 2-step foot",
                     "xi": step(yn, rgeo, g / gn[:, None], w0)[0]})
        rows.append({"seed": seed, "what": "residual: distance to the 2-step foot, foot std",
                     "xi": step(yn, rgeo, g / gn[:, None], W(vf))[0]})
        # a 7th parameter: a common offset of the map's distances on some faces
        ax_n = np.argmax(np.abs(g), axis=1)
        Jn, _, _ = _normal_matrix(yn, g, w0, m, pivot)
        for name, col in (("facades (x- and y-facing)", ax_n < 2), ("y-facing faces", ax_n == 1),
                          ("all faces", np.ones(len(yn), bool))):
            J7 = np.c_[Jn, col.astype(float)]
            Jw = J7 * w0[:, None]
            x7 = np.linalg.solve(Jw.T @ J7, -Jw.T @ m)
            rows.append({"seed": seed, "what": f"7th parameter: offset of the {name} (offset mm)",
                         "xi": np.r_[1e3 * x7[:3], 1e3 * np.degrees(x7[3:6])],
                         "extra": f"{1e3 * x7[6]:+.2f}"})
        # which faces carry the map's bias: the noise-free residuals' score split by the
        # gradient's dominant axis and sign, mapped through the same normal matrix
        ax = np.argmax(np.abs(gc), axis=1)
        sg = np.sign(gc[np.arange(len(gc)), ax])
        wc = _weights(mc, vc, n2, np.sqrt(vc) < 0.1, 4.685, "tukey", n_share, fac)[0]
        J, Hc, bc = _normal_matrix(yc, gc, wc, mc, pivot)
        Hinv = np.linalg.inv(Hc)
        for a, name in enumerate("xyz"):
            for sgn in (1, -1):
                sel = (ax == a) & (sg == sgn) & (wc > 0)
                if not sel.any():
                    continue
                bk = -(J[sel] * (wc[sel] * mc[sel])[:, None]).sum(0)
                xi = Hinv @ bk
                rows.append({"seed": seed,
                             "what": f"noise-free map part from faces {'+' if sgn > 0 else '-'}{name} "
                                     f"(weight share, weighted mean d mm)",
                             "xi": np.r_[1e3 * xi[:3], 1e3 * np.degrees(xi[3:])],
                             "extra": f"{wc[sel].sum() / wc.sum():.2f}, "
                                      f"{1e3 * np.average(mc[sel], weights=wc[sel]):+.2f}"})
        print(f"  seed {seed}: done", file=sys.stderr, flush=True)
    return _print_rows(rows, args.out)


def final(args) -> int:
    """The ``--final`` table (see the module docstring): the registration's last stage's
    residuals, the GP field's mean plus the surface correction (check._surface_correction:
    the blended mean minus the GP field's where the blend's variance is the smaller),
    with the GP field's gradient and variance, at the truth."""
    import gmmgp_app.check as ck
    from gmmgp_app.check import (_factors_here, _normal_matrix, _share_counts,
                                 _surface_correction, _weights)

    smap = _bench_map(args)
    params = dict(length=args.length)
    n2 = args.noise ** 2
    rows = []

    bias = {}  # the shape's squared bias at the points (check.SHAPE_BIAS), by drive

    def field(y, key):
        m, var, g = smap.predict(y, return_grad=True, far=False)
        out = {} if ck.SHAPE_BIAS else None
        corr = _surface_correction(smap, y, m, var, g, bias_out=out)
        bias[key] = None if out is None else out.get("bias2")
        return m + (0.0 if corr is None else corr), var, g, m

    def W(y, r, var, g, key):
        n_share, cell = _share_counts(y, 1.0, return_cells=True)
        fac = _factors_here(y, r, var, g, n2, 0.1, cell)
        return _weights(r, var, n2, np.sqrt(var) < 0.1, 4.685, "tukey", n_share, fac,
                        bias[key])[0]

    for seed in (1, 2, 3):
        yn, yc = _drive_pair(args, params, seed, smap.offset)
        rn, vn, gn, mgn = field(yn, "noisy")
        rc, vc, gc, mgc = field(yc, "clean")
        wn = W(yn, rn, vn, gn, "noisy")
        base, _, pivot = _one_step(yn, rn, gn, wn)
        rows.append({"seed": seed, "what": "step from the truth, noisy (last stage's field)",
                     "xi": base})
        rows.append({"seed": seed, "what": "  map part (noise-free residuals, noisy weights)",
                     "xi": _one_step(yn, rc, gn, wn)[0]})
        rows.append({"seed": seed, "what": "  noise part", "xi": _one_step(yn, rn - rc, gn, wn)[0]})
        rows.append({"seed": seed, "what": "  map part, GP field alone (no correction)",
                     "xi": _one_step(yn, mgc, gn, wn)[0]})
        wc = W(yc, rc, vc, gc, "clean")
        rows.append({"seed": seed, "what": "step from the truth, noise-free drive",
                     "xi": _one_step(yc, rc, gc, wc)[0]})
        # which faces carry the map's part: the noise-free residuals' score split by the
        # gradient's dominant axis and sign, through the normal matrix; with the noisy
        # drive's points, gradient and weights (the map part above) and with the
        # noise-free drive's own
        for label, yy, gg, ww in (("map part (noisy weights)", yn, gn, wn),
                                  ("noise-free drive", yc, gc, wc)):
            ax = np.argmax(np.abs(gg), axis=1)
            sg = np.sign(gg[np.arange(len(gg)), ax])
            J, Hc, _ = _normal_matrix(yy, gg, ww, rc, pivot)
            Hinv = np.linalg.inv(Hc)
            for a, name in enumerate("xyz"):
                for sgn in (1, -1):
                    sel = (ax == a) & (sg == sgn) & (ww > 0)
                    if not sel.any():
                        continue
                    bk = -(J[sel] * (ww[sel] * rc[sel])[:, None]).sum(0)
                    xi = Hinv @ bk
                    rows.append({"seed": seed,
                                 "what": f"{label} from faces {'+' if sgn > 0 else '-'}{name} "
                                         f"(weight share, weighted mean r mm, corrected share)",
                                 "xi": np.r_[1e3 * xi[:3], 1e3 * np.degrees(xi[3:])],
                                 "extra": f"{ww[sel].sum() / ww.sum():.2f}, "
                                          f"{1e3 * np.average(rc[sel], weights=ww[sel]):+.2f}, "
                                          f"{np.mean(rc[sel] != mgc[sel]):.2f}"})
        print(f"  seed {seed}: done", file=sys.stderr, flush=True)
    return _print_rows(rows, args.out)


if __name__ == "__main__":
    sys.exit(main())
