"""Registration of the test street's second drive against maps built with different
HGMM seeds (tests/test_check.py's pair: 20 m street, paper's field with the fixed urban
values, far field off; second drive through ``street_van``, lane -1.5, moved by 0.5 deg
/ 5.1 cm). Prints one JSON line: rotation error (deg), translation error at the map
origin (mm), the error at the pivot along / across / height (mm), Mahalanobis^2 of the
truth in the reported covariance, the reported translation std (mm).

``--nopole`` drops the scan's points within 0.3 m of the pole's axis (x = 6.37, y =
-6.5): an oracle run showing what the pole does to the along-street estimate.
``--check-pole`` prints instead the map's distance at the noise-free second drive's pole
points by bearing, with the map's std there.

    PYTHONPATH=$PWD .venv/bin/python scripts/check_seed_sweep.py --hseed 0 --nseed 1
``--fixed-point`` runs Gauss-Newton/IRLS from the truth to 1e-6 m / 1e-7 rad instead, with
check_scan's settings and with the robust loss / cell factors / share cell varied, and
prints the displacement at the points' centre (where the estimator's own minimum lies,
whatever the start).

    PYTHONPATH=$PWD .venv/bin/python scripts/check_seed_sweep.py --hseed 0 --check-pole
    PYTHONPATH=$PWD .venv/bin/python scripts/check_seed_sweep.py --hseed 1 --fixed-point

``--far`` builds the same map with its far field on (the test's map has it off), so that
the registration's last stage fits the blended field (check._surface_correction).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

POLE = np.array([6.37, -6.5])  # synth street: 0.3 L + 0.37, L = 20 m


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hseed", type=int, default=0, help="hgmm.seed of the map")
    ap.add_argument("--nseed", type=int, default=1, help="noise seed of the second drive")
    ap.add_argument("--cache", default=None, help="directory to keep the built maps in")
    ap.add_argument("--nopole", action="store_true")
    ap.add_argument("--check-pole", action="store_true")
    ap.add_argument("--fixed-point", action="store_true")
    ap.add_argument("--far", action="store_true", help="the map with its far field on")
    ap.add_argument("--no-surface", action="store_true",
                    help="check.SURFACE_CORRECTION off: the last stage fits the GP field")
    a = ap.parse_args(argv)
    if a.no_surface:
        import gmmgp_app.check as _check

        _check.SURFACE_CORRECTION = False

    import gmmgp_app as gm
    from scipy.spatial.transform import Rotation

    from gmmgp_app.check import _rotvec_to_matrix, check_scan
    from gmmgp_app.config import MappingConfig, concrete
    from gmmgp_app.synth import scan_scene
    from gmmgp_app.types import Scan

    cache = Path(a.cache or tempfile.mkdtemp()) / \
        f"street20_hgmm{a.hseed}{'_far' if a.far else ''}"
    if cache.exists():
        smap = gm.load_map(cache)
    else:
        first, _ = scan_scene("street", density=0.1, seed=0, scene_params=dict(length=20.0))
        cfg = concrete(MappingConfig()).replace({"far.enabled": bool(a.far),
                                                 "hgmm.seed": a.hseed})
        smap = gm.build_map(first, cfg)
        smap.save(cache)
    if a.check_pole:
        second, _ = scan_scene("street_van", density=0.1, seed=a.nseed,
                               scene_params=dict(length=20.0), lane_y=-1.5, range_noise=0.0)
        m, v, _ = smap.predict(second.points - smap.offset, return_grad=True, far=False)
        r = np.linalg.norm(second.points[:, :2] - POLE, axis=1)
        pole = (r < 0.2) & (second.points[:, 2] > 0.2) & (second.points[:, 2] < 6.1)
        ang = np.degrees(np.arctan2(*(second.points[pole, :2] - POLE).T[::-1]))
        rows = []
        for lo in range(-180, 180, 30):
            s = (ang >= lo) & (ang < lo + 30)
            if s.any():
                rows.append(dict(bearing_deg=[lo, lo + 30], n=int(s.sum()),
                                 d_median_mm=round(float(np.median(m[pole][s])) * 1e3, 1),
                                 std_median_mm=round(float(np.median(np.sqrt(v[pole][s]))) * 1e3, 1)))
        print(json.dumps(dict(hseed=a.hseed, pole=rows)))
        return 0
    second, _ = scan_scene("street_van", density=0.1, seed=a.nseed,
                           scene_params=dict(length=20.0), lane_y=-1.5)
    if a.fixed_point:
        return fixed_point(smap, second.points - smap.offset, a)
    pts = second.points
    if a.nopole:
        pts = pts[np.linalg.norm(pts[:, :2] - POLE, axis=1) > 0.3]
    ax = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    T = np.eye(4)
    T[:3, :3] = _rotvec_to_matrix(np.radians(0.5) * ax)
    T[:3, 3] = (0.03, -0.035, 0.02)
    moved = (pts - T[:3, 3]) @ T[:3, :3]
    t0 = time.perf_counter()
    res = check_scan(Scan(moved), smap, align=True)
    sec = time.perf_counter() - t0
    D = T @ np.linalg.inv(res.transform)
    phi = Rotation.from_matrix(D[:3, :3]).as_rotvec()
    rho = D[:3, :3] @ res.pivot + D[:3, 3] - res.pivot
    xi = np.r_[rho, phi]
    print(json.dumps(dict(
        hseed=a.hseed, nseed=a.nseed, nopole=a.nopole, far=a.far, surface=not a.no_surface,
        rot_deg=round(float(np.degrees(np.linalg.norm(phi))), 5),
        trans_mm=round(float(np.linalg.norm(D[:3, 3])) * 1e3, 2),
        pivot_error_mm=(rho * 1e3).round(2).tolist(),
        mahal2=round(float(xi @ np.linalg.pinv(res.covariance) @ xi), 2),
        std_t_mm=(np.sqrt(np.diag(res.covariance)[:3]) * 1e3).round(2).tolist(),
        converged=res.converged, iterations=res.iterations, seconds=round(sec, 2))))
    return 0


def fixed_point(smap, x, a) -> int:
    """``--fixed-point`` (see the module docstring): ``x`` is the second drive in the
    map frame, so the truth is the identity."""
    from scipy.spatial.transform import Rotation

    from gmmgp_app.check import _gauss_newton

    base = dict(noise2=1e-4, known_std=0.1, c_robust=4.685, loss="tukey", share_cell=1.0,
                cell_factors=True)
    _, v, _ = smap.predict(x, return_grad=True, far=False)
    w = 1.0 / (v + 1e-4)
    c = (w[:, None] * x).sum(0) / w.sum()
    for label, kw in (("check's (Tukey 4.685, cell factors)", {}),
                      ("no cell factors", dict(cell_factors=False)),
                      ("Tukey 20", dict(c_robust=20.0)),
                      ("Tukey 20, no cell factors", dict(c_robust=20.0, cell_factors=False)),
                      ("share_cell 0.27", dict(share_cell=0.27))):
        k = dict(base)
        k.update(kw)
        T, it, conv, _, _ = _gauss_newton(smap, x, np.eye(4), [], max_iter=60, tol_t=1e-6,
                                          tol_r=1e-7, **k)
        rho = T[:3, :3] @ c + T[:3, 3] - c
        print(json.dumps(dict(
            hseed=a.hseed, nseed=a.nseed, what=label, iterations=it, converged=conv,
            at_centre_mm=(1e3 * rho).round(2).tolist(),
            rot_mdeg=(1e3 * np.degrees(Rotation.from_matrix(T[:3, :3]).as_rotvec())).round(2)
            .tolist())), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
