"""Where check_scan's weights read the map's variance, and the noise part's bias.

For the drawn second drives of ``scripts/bench_check.py --synthetic-pairs N --pairs-seed
S`` (the bench's map: the first drive through the 36 m street, default configuration), at
the truth, with the registration's last-stage field (the GP field's mean plus
check._surface_correction, the GP field's gradient and variance, the shape's squared bias)
and check_scan's weights (1 m share counts, cell factors, Tukey 4.685 on z with the MAD
scale), all points of the noisy drive and of the same rays without range noise:

- the M-estimator's Newton step from the truth (the IRLS fixed point linearised: Hessian
  with Tukey's ``rho'' = (1-u^2)(1-5u^2)`` instead of the IRLS weight ``(1-u^2)^2``),
  rotation in mdeg, and its noise part (the noisy minus the noise-free residuals) and map
  part (the noise-free residuals), both with the noisy drive's points and weights;
- with the map's variance in the weights and in z read at: the noisy point (check_scan
  without origins), the noise-free point (an oracle), the point mirrored through the
  noise-free one, an independent noise draw along the same rays, the ray's foot on the
  zero level set (check._ray_foot_variance: check_scan with the scan's origins) and the
  foot along the gradient.

Prints one line per drive and a summary (median and 90th percentile of the Newton step,
mean rotation vector of the noise part, x the street's axis). docs/check.md, Session 13.

    PYTHONPATH=$PWD .venv/bin/python scripts/check_noise_bias.py --pairs 10 --pairs-seed 17
    PYTHONPATH=$PWD .venv/bin/python scripts/check_noise_bias.py --pairs 10 --pairs-seed 29 --map DIR
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

NOISE2 = 1e-4  # check_scan's noise (1 cm), squared
KNOWN_STD = 0.1
C_ROBUST = 4.685


def last_stage_field(smap, y):
    """The last stage's residual, variance, gradient and shape bias at ``y``."""
    from gmmgp_app.check import _surface_correction

    m, var, g = smap.predict(y, return_grad=True, far=False)
    out = {}
    corr = _surface_correction(smap, y, m, var, g, bias_out=out)
    return m + (0.0 if corr is None else corr), var, g, out.get("bias2")


def weights(y, r, var, g, b2, var_w):
    """check_scan's last-stage weights with the map's variance ``var_w`` in the weights and
    in z (``var`` decides which points are known and the cell factors): the IRLS weights
    and the Newton ones (``rho''`` instead of the IRLS weight)."""
    from gmmgp_app.check import _factors_here, _share_counts

    n_share, cell = _share_counts(y, 1.0, return_cells=True)
    fac = _factors_here(y, r, var, g, NOISE2, KNOWN_STD, cell)
    z = r / np.sqrt(var_w + NOISE2)
    ok = (np.sqrt(var) < KNOWN_STD) & np.isfinite(z)
    scale = 1.4826 * np.median(np.abs(z[ok]))
    u = z / (C_ROBUST * scale)
    inside = np.abs(u) < 1
    rob = np.where(inside, (1 - u * u) ** 2, 0.0)
    rob2 = np.where(inside, (1 - u * u) * (1 - 5 * u * u), 0.0)
    vm = (var_w + NOISE2) * (1.0 if fac is None else fac) - NOISE2 + (0 if b2 is None else b2)
    V = vm + NOISE2 / n_share
    return np.where(ok, rob / V, 0.0), np.where(ok, rob2 / V, 0.0)


def newton_rotation(y, r, g, w, w2, pivot):
    """Rotation vector (mdeg) of the step ``-(sum w2 J J^T)^-1 sum w r J``."""
    from gmmgp_app.check import _normal_matrix

    _, _, b = _normal_matrix(y, g, w, r, pivot)
    _, H2, _ = _normal_matrix(y, g, w2, r, pivot)
    return 1e3 * np.degrees(np.linalg.solve(H2, b)[3:])


def main(argv=None) -> int:
    import gmmgp_app as gm
    from bench_check import draw_pairs
    from gmmgp_app.check import _ray_foot_variance
    from gmmgp_app.synth import scan_scene

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--pairs", type=int, default=10)
    ap.add_argument("--pairs-seed", type=int, default=17)
    ap.add_argument("--map", default=None, help="the bench's map, saved (built if absent)")
    a = ap.parse_args(argv)
    if a.map and Path(a.map).exists():
        smap = gm.load_map(a.map)
    else:
        first, _ = scan_scene("street", density=0.1, seed=0, scene_params=dict(length=36.0))
        smap = gm.build_map(first)
        if a.map:
            smap.save(a.map)
    off = smap.offset
    rng = np.random.default_rng(5)
    acc: dict = {}
    for k, (nseed, _) in enumerate(draw_pairs(a.pairs, a.pairs_seed)):
        kw = dict(density=0.1, seed=nseed, scene_params=dict(length=36.0), lane_y=-1.5)
        noisy, _ = scan_scene("street_van", **kw)
        clean, _ = scan_scene("street_van", range_noise=0.0, **kw)
        yn, yc = noisy.points - off, clean.points - off
        rn, vn, gn, bn = last_stage_field(smap, yn)
        rc = last_stage_field(smap, yc)[0]
        u = noisy.points - noisy.origins
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        dl = yn - yc
        s = np.sign(np.einsum("ij,ij->i", dl, u))
        length = np.abs(np.einsum("ij,ij->i", dl, u))
        g2 = np.maximum((gn * gn).sum(1), 1e-12)
        at = {
            "noisy point (no origins)": vn,
            "noise-free point (oracle)": smap.predict(yc, far=False)[1],
            "mirrored point (oracle)": smap.predict(2 * yc - yn, far=False)[1],
            "independent noise (oracle)": smap.predict(
                yc + (rng.permutation(s * length) * 1.0)[:, None] * u, far=False)[1],
            "ray foot (origins)": _ray_foot_variance(smap, yn, rn, gn, u, vn),
            "foot along the gradient": smap.predict(yn - (rn / g2)[:, None] * gn,
                                                    far=False)[1],
        }
        line = []
        for name, vw in at.items():
            w, w2 = weights(yn, rn, vn, gn, bn, vw)
            pivot = (w[:, None] * yn).sum(0) / w.sum()
            tot = newton_rotation(yn, rn, gn, w, w2, pivot)
            noise = newton_rotation(yn, rn - rc, gn, w, w2, pivot)
            mp = newton_rotation(yn, rc, gn, w, w2, pivot)
            acc.setdefault(name, []).append(np.r_[tot, noise, mp])
            line.append(f"{np.linalg.norm(tot):.2f}")
        print(f"draw {k} (noise seed {nseed}): Newton step from the truth (mdeg) "
              + " / ".join(line), flush=True)
    print(f"\n--pairs-seed {a.pairs_seed}, {a.pairs} drives | Newton step median (p90) mdeg | "
          "noise part: mean rotation vector (x = street axis), sd of x | map part median |")
    print("|---|---|---|---|")
    for name, v in acc.items():
        v = np.asarray(v)
        nr = np.linalg.norm(v[:, :3], axis=1)
        print(f"| {name} | {np.median(nr):.2f} ({np.percentile(nr, 90):.2f}) | "
              f"({v[:, 3]. mean():+.2f}, {v[:, 4].mean():+.2f}, {v[:, 5].mean():+.2f}), "
              f"{v[:, 3].std():.2f} | {np.median(np.linalg.norm(v[:, 6:], axis=1)):.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
