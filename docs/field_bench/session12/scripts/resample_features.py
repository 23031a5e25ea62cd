#!/usr/bin/env python
"""Session 12 (field-15s) prototype: resampling estimates of the far field's own error at
each cached query, from the far field dumped by build_caches.py (no map rebuilt).

Per query, with the final robust weights u of eq. rimls (as stages/farfield._imls has
them) the sphere vote (farfield._sphere_vote) and the plane vote are repeated
* on two halves of the k neighbours, for three partitions of the ranks (interleaved,
  pairs, quads): ``half_s`` / ``half_p`` = the mean over partitions of (m_A - m_B)^2 / 4;
* leaving out each neighbour in turn (jackknife): ``jack_s`` / ``jack_p`` =
  (k - 1) / k sum_j (m_(-j) - mean_j m_(-j))^2.
The halves' and the jackknife's disagreement is the vote's noise part (the shared
curvature bias, which the sphere removes, cancels). Writes ``<stem>_resample.npz``.

    PYTHONPATH=$PWD python docs/field_bench/session12/scripts/resample_features.py CACHE [STEMS]
"""
import math
import sys
from pathlib import Path

import numba as nb
import numpy as np

from gmmgp_app.stages import farfield as F
from gmmgp_app.stages.knn import GridKNN

PARTS = np.array([[j % 2 for j in range(16)], [(j // 2) % 2 for j in range(16)],
                  [(j // 4) % 2 for j in range(16)]], dtype=np.int64)


@nb.njit(parallel=True, cache=True)
def _resample(x, d, nbr, points, normals, rho0, growth, robust_scale, iters, parts):
    K, k = d.shape
    P = parts.shape[0]
    half_s = np.zeros(K)
    half_p = np.zeros(K)
    jack_s = np.zeros(K)
    jack_p = np.zeros(K)
    for q in nb.prange(K):
        r = d[q, 0]
        rho = max(rho0, growth * r)
        rho2 = rho * rho
        w = np.empty(k)
        u = np.empty(k)
        a = np.empty(k)
        ws = 0.0
        wa = 0.0
        for j in range(k):
            w[j] = math.exp(-(d[q, j] ** 2 - r * r) / rho2)
            p = nbr[q, j]
            a[j] = ((x[q, 0] - points[p, 0]) * normals[p, 0]
                    + (x[q, 1] - points[p, 1]) * normals[p, 1]) \
                + (x[q, 2] - points[p, 2]) * normals[p, 2]
            u[j] = w[j]
            ws += w[j]
            wa += w[j] * a[j]
        m = wa / ws
        if robust_scale > 0:
            s_r2 = (robust_scale * rho) ** 2
            for _ in range(iters):
                us = 0.0
                ua = 0.0
                for j in range(k):
                    u[j] = w[j] * math.exp(-(a[j] - m) ** 2 / s_r2)
                    us += u[j]
                    ua += u[j] * a[j]
                if us > 0:
                    m = ua / us
                else:
                    for j in range(k):
                        u[j] = w[j]
                    break
        # one vote on a sub-sample: weights uu (zeros leave a neighbour out)
        uu = np.empty(k)
        hs = 0.0
        hp = 0.0
        for pi in range(P):
            ms = np.zeros(2)
            mp = np.zeros(2)
            for side in range(2):
                us = 0.0
                ua = 0.0
                for j in range(k):
                    uu[j] = u[j] if parts[pi, j] == side else 0.0
                    us += uu[j]
                    ua += uu[j] * a[j]
                mp[side] = ua / us if us > 0 else m
                dq, sq, vq, ssq, ok = F._sphere_vote(x[q], nbr[q], points, normals, uu, w, a, k)
                ms[side] = dq if ok else mp[side]
            hs += (ms[0] - ms[1]) ** 2 / 4.0
            hp += (mp[0] - mp[1]) ** 2 / 4.0
        half_s[q] = hs / P
        half_p[q] = hp / P
        js = np.empty(k)
        jp = np.empty(k)
        for l in range(k):
            us = 0.0
            ua = 0.0
            for j in range(k):
                uu[j] = u[j] if j != l else 0.0
                us += uu[j]
                ua += uu[j] * a[j]
            jp[l] = ua / us if us > 0 else m
            dq, sq, vq, ssq, ok = F._sphere_vote(x[q], nbr[q], points, normals, uu, w, a, k)
            js[l] = dq if ok else jp[l]
        jack_s[q] = (k - 1.0) / k * np.sum((js - js.mean()) ** 2)
        jack_p[q] = (k - 1.0) / k * np.sum((jp - jp.mean()) ** 2)
    return half_s, half_p, jack_s, jack_p


def features(far_npz):
    f = np.load(far_npz)
    pts, nrm, q = f["points"], f["normals"], f["q"]
    k = int(f["k"])
    knn = GridKNN(pts, k)
    d, i = knn.query(q)
    hs, hp, js, jp = _resample(q, d, i, pts, nrm, float(f["rho0"]), float(f["growth"]),
                               float(f["robust_scale"]), int(f["robust_iterations"]),
                               PARTS[:, :k])
    return dict(half_s=hs, half_p=hp, jack_s=js, jack_p=jp)


def main():
    cache = Path(sys.argv[1])
    stems = sys.argv[2].split(",") if len(sys.argv) > 2 else \
        [p.name[:-8] for p in sorted(cache.glob("*_far.npz"))]
    for s in stems:
        out = cache / f"{s}_resample.npz"
        if out.exists():
            continue
        np.savez(out, **features(cache / f"{s}_far.npz"))
        print(s, flush=True)


if __name__ == "__main__" and "--loo" not in sys.argv:
    main()


def loo_features(far_npz, cap=3.0):
    """:func:`features` for the leave-self-out vote (foot_vote.loo_case): neighbours by the
    raw hit points, votes from their leave-self-out projections (moves above ``cap``
    sigma not made). Written as ``<stem>_loo<cap>_resample.npz`` by ``--loo``."""
    from foot_vote import leave_self_out_projection
    f = np.load(far_npz)
    pts, nrm, q = f["points"], f["normals"], f["q"]
    k = int(f["k"])
    d, i = GridKNN(pts, k).query(q)
    p2 = leave_self_out_projection(pts, nrm, float(f["rho0"]), k, cap=cap * float(f["noise"]))
    hs, hp, js, jp = _resample(q, d, i, p2, nrm, float(f["rho0"]), float(f["growth"]),
                               float(f["robust_scale"]), int(f["robust_iterations"]),
                               PARTS[:, :k])
    return dict(half_s=hs, half_p=hp, jack_s=js, jack_p=jp)


if __name__ == "__main__" and "--loo" in sys.argv:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    for n in sys.argv[2].split(","):
        c = Path(sys.argv[1])
        out = c / f"{n}_seed0_far.vote-sphere_loo3_resample.npz"
        if not out.exists():
            np.savez(out, **loo_features(c / f"{n}_seed0_far.vote-sphere_far.npz"))
        print(n, flush=True)
