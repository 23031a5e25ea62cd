"""build_map end to end on scenes with exact SDF: the GP must improve on its HGMM prior."""

import json

import numpy as np
import pytest

import gmmgp_app as gm
from gmmgp_app.evaluation import Reference, evaluate_field, sample_queries
from gmmgp_app.synth import scan_scene


@pytest.fixture(scope="module")
def sphere():
    scan, scene = scan_scene("sphere", density=0.1, seed=0)
    return scan, scene


def _near_surface_metrics(smap, scan, scene, cfg, n=4000):
    data = gm.prepare(scan, cfg)
    q = sample_queries(data.points, data.normals, n, max_distance=0.1,
                       rng=np.random.default_rng(3))
    ref = Reference.from_sdf(scene.sdf)
    return evaluate_field(smap.predict, ref, q, data.points, bins=(0.0, 0.1))


def test_gmmgp_beats_its_hgmm_prior_on_a_sphere(sphere):
    scan, scene = sphere
    cfg = gm.MappingConfig()
    hg = gm.build_map(scan, cfg, method="hgmm")
    gp = gm.build_map(scan, cfg, method="gmmgp")
    a = _near_surface_metrics(hg, scan, scene, cfg)
    b = _near_surface_metrics(gp, scan, scene, cfg)
    assert b["all"]["rmse_sdf"] < a["all"]["rmse_sdf"]
    assert b["all"]["ll_sdf"] > a["all"]["ll_sdf"]
    assert len(gp.gp_points) > 0 and len(hg.gp_points) == 0


@pytest.mark.slow
def test_gmmgp_beats_its_hgmm_prior_on_the_street():
    scan, scene = scan_scene("street", density=0.05, seed=1)
    cfg = gm.MappingConfig()
    hg = gm.build_map(scan, cfg, method="hgmm")
    gp = gm.build_map(scan, cfg, method="gmmgp")
    a = _near_surface_metrics(hg, scan, scene, cfg)
    b = _near_surface_metrics(gp, scan, scene, cfg)
    assert b["all"]["rmse_sdf"] < a["all"]["rmse_sdf"]
    assert b["all"]["ll_sdf"] > a["all"]["ll_sdf"]


def test_save_load_predicts_identically(sphere, tmp_path):
    scan, _ = sphere
    smap = gm.build_map(scan, gm.MappingConfig().replace("hgmm.max_levels", 3))
    q = np.random.default_rng(0).uniform(-1.3, 1.3, size=(500, 3))
    m0, v0, g0 = smap.predict(q, return_grad=True)
    smap.save(tmp_path / "map")
    back = gm.load_map(tmp_path / "map")
    m1, v1, g1 = back.predict(q, return_grad=True)
    np.testing.assert_array_equal(m0, m1)
    np.testing.assert_array_equal(v0, v1)
    np.testing.assert_array_equal(g0, g1)
    assert back.method == "gmmgp" and back.hgmm.leaves.n_components == \
        smap.hgmm.leaves.n_components
    np.testing.assert_array_equal(back.gp_points, smap.gp_points)
    meta = json.loads((tmp_path / "map" / "map.json").read_text())
    assert meta["summary"]["counts"]["hgmm"]["leaves"] == smap.hgmm.leaves.n_components
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_observer_sees_every_stage_in_order(sphere):
    scan, _ = sphere
    seen = []

    class Recorder:
        def on_stage(self, name, payload):
            seen.append((name, payload.seconds >= 0))

    gm.build_map(scan, gm.MappingConfig(), observer=Recorder())
    assert [s for s, _ in seen] == ["scan", "prepare", "hgmm", "gmr", "gp", "far"]
    assert all(ok for _, ok in seen)


def test_predict_rejects_bad_queries(sphere):
    scan, _ = sphere
    smap = gm.build_map(scan, gm.MappingConfig(), method="hgmm")
    with pytest.raises(ValueError, match=r"Expected query points with shape \(K, 3\)"):
        smap.predict(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="Expected finite query coordinates, found 1 rows"):
        smap.predict(np.array([[0.0, 0.0, np.nan], [0.0, 0.0, 1.0]]))
    with pytest.raises(ValueError, match="Unknown method 'nope'"):
        gm.build_map(scan, gm.MappingConfig(), method="nope")


def test_load_map_errors(tmp_path):
    from gmmgp_app.pipeline import MapFormatError

    with pytest.raises(MapFormatError, match="is not a saved map"):
        gm.load_map(tmp_path)


def test_load_map_names_a_tiled_map(tmp_path):
    from gmmgp_app.pipeline import MapFormatError

    (tmp_path / "tiled.json").write_text("{}")
    with pytest.raises(MapFormatError, match="holds a tiled map .*load_tiled_map"):
        gm.load_map(tmp_path)
