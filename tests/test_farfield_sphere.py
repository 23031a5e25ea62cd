"""The far field's sphere vote (eq. sphere_vote in stages/farfield.py, ``far.vote``)
against exact ground truth: a sphere of known radius, a plane, degenerate
neighbourhoods, and the load path of maps saved before the option."""

import json
import shutil
import warnings

import numpy as np
import pytest

from gmmgp_app.stages.farfield import FarField, FarFieldError


def _unit(v):
    return v / np.linalg.norm(v, axis=1)[:, None]


def _sphere_scan(rng, n=3000, radius=1.0, noise=0.002):
    v = _unit(rng.normal(size=(n, 3)))
    return v * (radius + rng.normal(0.0, noise, n))[:, None], v


def test_sphere_vote_recovers_the_distance_to_a_sphere():
    """1 m sphere, 3000 points (spacing ~65 mm), 2 mm noise along the exact normals;
    queries 0.1-0.5 m inside and outside. The tangent planes' vote is biased by the
    curvature (3.8 / 7.4 mm RMSE inside / outside when written); the sphere fitted to
    the same neighbours recovers the distance to within the noise (0.6 / 0.5 mm)."""
    rng = np.random.default_rng(1)
    p, n = _sphere_scan(rng)
    h = np.sqrt(4 * np.pi / len(p))
    q = _unit(rng.normal(size=(3000, 3)))
    t = rng.choice([-1.0, 1.0], 3000) * rng.uniform(0.1, 0.5, 3000)
    q = q * (1.0 + t)[:, None]
    y = np.linalg.norm(q, axis=1) - 1.0
    err = {}
    for vote in ("plane", "sphere"):
        c = FarField(p, n, h, 0.002, k=16, robust_scale=1.0, vote=vote).components(q)
        err[vote] = c["mean"] - y
    for side in (t < 0, t > 0):
        rp = np.sqrt(np.mean(err["plane"][side] ** 2))
        rs = np.sqrt(np.mean(err["sphere"][side] ** 2))
        assert rs < 0.25 * rp
        assert rs < 1.5e-3
    assert np.abs(err["sphere"]).max() < 5e-3


def test_sphere_vote_on_a_plane_is_the_plane_vote():
    """A plane scan (2000 points, 3 mm noise): with the exact normals the fitted
    curvature is exactly 0 and the sphere vote is the plane vote to rounding; with
    normals 1.1 degrees off (rms) the shrunk curvature moves the mean by at most 2 mm
    (0.9 mm when written) at queries up to 0.5 m away, and not away from the truth."""
    rng = np.random.default_rng(2)
    pts = np.c_[rng.uniform(-1, 1, (2000, 2)), rng.normal(0.0, 0.003, 2000)]
    q = np.c_[rng.uniform(-0.5, 0.5, (2000, 2)), rng.uniform(-0.5, 0.5, 2000)]
    nrm = np.tile([0.0, 0.0, 1.0], (2000, 1))
    noisy = _unit(nrm + rng.normal(0.0, 0.02, nrm.shape))
    for normals, bound in ((nrm, 1e-12), (noisy, 2e-3)):
        a = FarField(pts, normals, 0.04, 0.003, robust_scale=1.0).components(q)
        b = FarField(pts, normals, 0.04, 0.003, robust_scale=1.0,
                     vote="sphere").components(q)
        assert np.abs(a["mean"] - b["mean"]).max() <= bound
        ra = np.sqrt(np.mean((a["mean"] - q[:, 2]) ** 2))
        rb = np.sqrt(np.mean((b["mean"] - q[:, 2]) ** 2))
        assert rb <= 1.05 * ra
        # the variance and its ingredients are the plane vote's
        np.testing.assert_array_equal(a["var"], b["var"])
        np.testing.assert_array_equal(a["spread2"], b["spread2"])


def test_degenerate_neighbourhoods_keep_the_plane():
    """Fewer than four neighbours, or neighbours that all sit at one point, give no
    sphere: the sphere vote returns the plane vote exactly."""
    rng = np.random.default_rng(3)
    q = rng.normal(size=(200, 3))
    cases = [(np.array([[0.0, 0, 0], [0.1, 0, 0], [0, 0.1, 0.01]]),
              _unit(np.array([[0.0, 0.1, 1], [0.1, 0, 1], [0, 0, 1]]))),
             (np.zeros((20, 3)), _unit(rng.normal(size=(20, 3)) + [0, 0, 3]))]
    for p, n in cases:
        a = FarField(p, n, 0.05, 0.003, robust_scale=1.0).components(q)
        b = FarField(p, n, 0.05, 0.003, robust_scale=1.0, vote="sphere").components(q)
        np.testing.assert_array_equal(a["mean"], b["mean"])
        assert np.all(b["delta"] == 0)


def test_sphere_vote_reach_guard_near_the_centre():
    """Inside a small sphere (radius 0.2 m) beyond half its radius from the surface the
    sphere's distance is not used (the plane vote stands); nearer the surface it is."""
    rng = np.random.default_rng(4)
    p, n = _sphere_scan(rng, 2000, 0.2, 0.0)
    h = np.sqrt(4 * np.pi * 0.04 / len(p))
    dirs = _unit(rng.normal(size=(300, 3)))
    a = FarField(p, n, h, 0.001, vote="plane")
    b = FarField(p, n, h, 0.001, vote="sphere")
    deep = dirs * 0.05  # 0.15 m inside: beyond R / 2
    np.testing.assert_array_equal(a.components(deep)["mean"], b.components(deep)["mean"])
    near = dirs * 0.15  # 0.05 m inside: the sphere's distance, -0.05 m
    np.testing.assert_allclose(b.components(near)["mean"], -0.05, atol=1e-6)


def test_vote_must_be_named():
    with pytest.raises(FarFieldError, match="far.vote"):
        FarField(np.zeros((4, 3)), np.tile([0.0, 0, 1], (4, 1)), 0.1, 0.01, vote="quadric")


def _small_map(vote):
    import gmmgp_app as gm
    from gmmgp_app.types import Scan

    rng = np.random.default_rng(5)
    v = _unit(rng.normal(size=(4000, 3)))
    v = v[v[:, 2] > -0.3]
    scan = Scan(v * (1.0 + rng.normal(0.0, 0.002, len(v)))[:, None],
                origins=v * 3.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return gm.build_map(scan, gm.MappingConfig().with_overrides([f"far.vote={vote}"]))


def test_old_map_without_vote_loads_as_plane_bit_for_bit(tmp_path):
    """A map saved before far.vote (no vote in map.json's config nor in its far-field
    parameters) loads with the plane vote and the coefficients it was saved with, and
    predicts exactly as the plane-vote map it was; a sphere-vote map saves its vote and
    reloads to the same prediction."""
    import gmmgp_app as gm

    rng = np.random.default_rng(6)
    q = _unit(rng.normal(size=(500, 3))) * rng.uniform(0.8, 1.4, 500)[:, None]
    plane = _small_map("plane")
    m, v = plane.predict(q)
    plane.save(tmp_path / "p")
    meta = json.loads((tmp_path / "p" / "map.json").read_text())
    assert meta["far_params"]["vote"] == "plane"
    del meta["far_params"]["vote"]
    toml = meta["config_toml"]
    assert 'vote = "plane"' in toml
    meta["config_toml"] = "\n".join(l for l in toml.splitlines() if not l.startswith("vote ="))
    shutil.copytree(tmp_path / "p", tmp_path / "old")  # the arrays, whatever their format
    (tmp_path / "old" / "map.json").write_text(json.dumps(meta))
    old = gm.load_map(tmp_path / "old")
    assert old.config.far.vote == "plane" and old.far.vote == "plane"
    assert old.variance_coef == plane.resolved_variance_coef()
    lm, lv = old.predict(q)
    np.testing.assert_array_equal(lm, m)
    np.testing.assert_array_equal(lv, v)

    sphere = _small_map("sphere")
    sm, sv = sphere.predict(q)
    assert np.abs(sm - m).max() > 1e-5  # the vote changes the mean
    sphere.save(tmp_path / "s")
    meta = json.loads((tmp_path / "s" / "map.json").read_text())
    assert meta["far_params"]["vote"] == "sphere"
    loaded = gm.load_map(tmp_path / "s")
    assert loaded.config.far.vote == "sphere"
    lm, lv = loaded.predict(q)
    np.testing.assert_array_equal(lm, sm)
    np.testing.assert_array_equal(lv, sv)
