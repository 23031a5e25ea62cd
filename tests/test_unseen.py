"""The unseen-geometry variance (stages/farfield.py, eqs. unseen_behind, unseen_extent,
unseen_var; issue 15): exact ground truth from slabs and half-planes."""

from __future__ import annotations

import warnings

import numpy as np
from scipy.spatial import cKDTree

import gmmgp_app as gm
from gmmgp_app.stages.farfield import behind_width, extent_width, unseen_variance
from gmmgp_app.types import Scan


def slab_sdf(x, t):
    """Signed distance to the infinite slab 0 <= x <= t (outside positive)."""
    return np.where(x < 0, -x, np.where(x > t, x - t, -np.minimum(x, t - x)))


def test_behind_width_bounds_the_error_behind_a_slab_of_any_thickness():
    # seen from x < 0, the located surface is the face x = 0: m = -x behind it
    t_min = 0.06
    x = np.linspace(0.0, 1.0, 2001)
    m = -x
    w = behind_width(m, t_min)
    for t in (t_min, 0.1, 0.2, 0.5, 5.0):
        e = slab_sdf(x, t) - m
        assert np.all(e >= -1e-12) and np.all(e <= w + 1e-12), t
    # tight: a slab of the least thickness reaches the bound beyond t_min / 2
    e = slab_sdf(x, t_min) - m
    np.testing.assert_allclose(e[x >= t_min / 2], w[x >= t_min / 2], atol=1e-12)
    # in front of the surface (m > 0) there is nothing behind
    assert np.all(behind_width(np.linspace(0, 1, 11), t_min) == 0)


def test_extent_width_is_the_distance_to_the_edge_of_a_half_plane():
    # hit points on the half-plane z = 0, x >= 0 (1 cm grid); queries beside its edge
    g = np.arange(0.0, 1.0, 0.01)
    pts = np.array([(a, b, 0.0) for a in g for b in np.arange(-1.0, 1.0, 0.01)])
    rng = np.random.default_rng(0)
    q = np.c_[rng.uniform(-1.0, 0.5, 500), rng.uniform(-0.5, 0.5, 500),
              rng.uniform(0.01, 0.5, 500)]
    m = q[:, 2]                           # the located plane z = 0, continued
    r = cKDTree(pts).query(q)[0]
    truth = np.hypot(m, np.maximum(-q[:, 0], 0.0))  # exact distance to the half-plane
    w = extent_width(m, r, 0.0)
    # m + w is the distance to the nearest hit point: exact up to the grid spacing
    assert np.all(np.abs(m + w - truth) <= 0.01)
    # over the data (x >= 0) the sampling gap explains r > |m|: no extra width
    over = q[:, 0] > 0.01
    assert np.all(extent_width(m[over], r[over], 0.01) == 0)
    assert np.all(extent_width(-m, r, 0.0) == w)       # symmetric in the sign


def test_unseen_variance_is_lambda_squared_times_the_widths():
    np.testing.assert_allclose(unseen_variance([0.3, 0.0], [0.4, 0.2], 0.25),
                               [0.0625 * 0.25, 0.0625 * 0.04], rtol=1e-15)


def _wall_map(weight, predictive="gaussian"):
    # a 0.1 m wall (0 <= x <= 0.1, |y| <= 1, 0 <= z <= 2) seen from x = -3 only
    rng = np.random.default_rng(7)
    n = 4000
    yz = rng.uniform([-1.0, 0.0], [1.0, 2.0], (n, 2))
    pts = np.c_[rng.normal(0.0, 0.002, n), yz]
    origins = np.tile([-3.0, 0.0, 1.0], (n, 1))
    cfg = gm.MappingConfig().with_overrides([f"far.unseen_weight={weight}",
                                             f"far.unseen_predictive={predictive}"])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return gm.build_map(Scan(pts, origins=origins), cfg)


def test_thin_wall_seen_from_one_side_is_not_overconfident_behind():
    # eq. unseen_var (the Gaussian; the mixture, the default: tests/test_unseen_mixture.py)
    smap = _wall_map(gm.MappingConfig().far.unseen_weight)     # the default, 0.15
    rng = np.random.default_rng(8)
    k = 400
    # behind the face, away from the wall's rim (edges >= 0.6 m away): exact slab SDF
    qb = np.c_[rng.uniform(0.1, 0.5, k), rng.uniform(-0.4, 0.4, k), rng.uniform(0.6, 1.4, k)]
    qf = np.c_[rng.uniform(-0.5, -0.01, k), rng.uniform(-0.4, 0.4, k),
               rng.uniform(0.6, 1.4, k)]
    yb, yf = slab_sdf(qb[:, 0], 0.1), slab_sdf(qf[:, 0], 0.1)
    mb, vb = smap.predict(qb)
    mf, vf = smap.predict(qf)
    zb = np.abs(yb - mb) / np.sqrt(vb)
    # the map puts the inside at m ~ -x; the truth is x - 0.1 beyond the back face
    assert np.median(mb) < -0.2 and np.median(yb - mb) > 0.3
    # default lambda = 0.15: the worst case of the interval lies at 1 / 0.15 = 6.7 sigma
    assert np.all(zb <= 6.9), np.max(zb)
    # free space in front stays tight and calibrated-ish
    zf = np.abs(yf - mf) / np.sqrt(vf)
    assert np.sqrt(np.median(vf)) < 0.01 and np.mean(zf <= 2) >= 0.9
    # lambda = 0.5: the interval is covered at 2 sigma; in front almost nothing changes
    smap.config = smap.config.with_overrides(["far.unseen_weight=0.5"])
    mb2, vb2 = smap.predict(qb)
    assert np.all(np.abs(yb - mb2) <= 2.1 * np.sqrt(vb2))
    mf2, vf2 = smap.predict(qf)
    # (about 10 % face a random gap in the scan wider than h: a wider std there)
    assert np.sqrt(np.median(vf2)) < 0.01 and np.mean(np.isclose(vf2, vf, rtol=0.05)) > 0.8
    assert np.mean(np.abs(yf - mf2) <= 2 * np.sqrt(vf2)) >= 0.9
    # without the term (the defect): tens of sigma out behind the wall
    smap.config = smap.config.with_overrides(["far.unseen_weight=0"])
    mb0, vb0 = smap.predict(qb)
    assert np.median(np.abs(yb - mb0) / np.sqrt(vb0)) > 10
