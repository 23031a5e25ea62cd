"""The paper's metrics, ground truth from meshes and clouds, reports and ``gmmgp eval``."""

import argparse
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy import integrate, stats

from gmmgp_app.evaluation import (EvaluationError, Reference, TriangleDistance,
                                  binned_metrics, closest_point_on_triangles, evaluate_field,
                                  folded_normal_loglik, gaussian_loglik, sample_mesh_surface,
                                  sample_queries, surface_distances)
from gmmgp_app.synth import box_sdf
from gmmgp_app.synth.scenes import _box_mesh, _icosphere

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


# --------------------------------------------------------------------------- likelihoods
def test_gaussian_loglik_matches_scipy():
    y, m, v = np.array([0.1, -0.3, 2.0]), np.array([0.0, -0.2, 1.0]), np.array([0.01, 0.5, 4.0])
    np.testing.assert_allclose(gaussian_loglik(y, m, v), stats.norm.logpdf(y, m, np.sqrt(v)))


def test_gaussian_loglik_hand_value():
    # log N(0; 0, 1) = -log(2 pi) / 2
    assert gaussian_loglik(0.0, 0.0, 1.0) == pytest.approx(-0.5 * math.log(2 * math.pi))


@pytest.mark.parametrize("m,v", [(0.0, 1.0), (0.3, 0.01), (-0.2, 0.04), (1.0, 0.25)])
def test_folded_normal_integrates_to_one(m, v):
    f = lambda a: math.exp(folded_normal_loglik(np.array([a]), m, v)[0])  # noqa: E731
    total, err = integrate.quad(f, 0.0, np.inf, limit=200)
    assert total == pytest.approx(1.0, abs=1e-7)


def test_folded_normal_matches_scipy_foldnorm():
    a = np.array([0.0, 0.05, 0.3, 1.2])
    m, s = 0.2, 0.3
    expect = stats.foldnorm.logpdf(a, m / s, scale=s)
    np.testing.assert_allclose(folded_normal_loglik(a, m, s * s), expect, rtol=1e-10)


# --------------------------------------------------------------------------- binning
def test_binned_metrics_hand_computed():
    mean = np.array([0.1, -0.1, 0.5, 0.0])
    var = np.array([1.0, 1.0, 1.0, 4.0])
    truth = np.array([0.0, 0.1, 0.2, -0.3])
    dist = np.array([0.01, 0.02, 0.15, 0.6])   # last one outside every bin
    r = binned_metrics(mean, var, truth, dist, bins=(0.0, 0.1, 0.2))
    assert r["n"] == [2, 1]
    # bin 0: errors 0.1 and -0.2 -> RMSE sqrt((0.01 + 0.04) / 2)
    assert r["rmse_sdf"][0] == pytest.approx(math.sqrt(0.025))
    # EDF: |0.1| - 0 and |-0.1| - 0.1 -> sqrt(0.01 / 2)
    assert r["rmse_edf"][0] == pytest.approx(math.sqrt(0.005))
    ll0 = -0.5 * (math.log(2 * math.pi) + 0.01)
    ll1 = -0.5 * (math.log(2 * math.pi) + 0.04)
    assert r["ll_sdf"][0] == pytest.approx(0.5 * (ll0 + ll1))
    assert r["rmse_sdf"][1] == pytest.approx(0.3)
    assert r["all"]["n"] == 3
    assert r["all"]["rmse_sdf"] == pytest.approx(math.sqrt((0.01 + 0.04 + 0.09) / 3))


def test_binned_metrics_unsigned_prediction_and_empty_bin():
    mean, var = np.array([0.1, 0.2]), np.array([0.01, 0.01])
    truth = np.array([-0.1, 0.25])
    r = binned_metrics(mean, var, truth, np.array([0.0, 0.01]), bins=(0.0, 0.05, 0.1),
                       signed_prediction=False)
    assert math.isnan(r["rmse_sdf"][0]) and math.isnan(r["ll_sdf"][0])
    assert r["rmse_edf"][0] == pytest.approx(math.sqrt((0.0 + 0.05 ** 2) / 2))
    expect = np.mean(stats.norm.logpdf(np.abs(truth), mean, 0.1))
    assert r["ll_edf"][0] == pytest.approx(expect)
    assert r["n"][1] == 0 and math.isnan(r["rmse_edf"][1])


def test_binned_metrics_unsigned_truth_gives_only_edf():
    r = binned_metrics([0.1], [0.01], [0.1], [0.0], bins=(0, 1), signed_truth=False)
    assert math.isnan(r["rmse_sdf"][0]) and r["rmse_edf"][0] == pytest.approx(0.0)


def test_binned_metrics_errors():
    with pytest.raises(EvaluationError, match="of one length"):
        binned_metrics([0.0, 1.0], [1.0], [0.0], [0.0])
    with pytest.raises(EvaluationError, match="increasing bin edges"):
        binned_metrics([0.0], [1.0], [0.0], [0.0], bins=(0.1, 0.05))


def test_evaluate_field_exact_predictor_has_zero_error():
    ref = Reference.from_sdf(lambda x: x[:, 2])
    rng = np.random.default_rng(1)
    q = rng.uniform(-0.4, 0.4, (500, 3))
    train = np.column_stack([rng.uniform(-1, 1, (2000, 2)), np.zeros(2000)])
    r = evaluate_field(lambda x: (x[:, 2], np.full(len(x), 1e-4)), ref, q, train)
    assert all(v == pytest.approx(0.0, abs=1e-12) for v in r["rmse_sdf"] if v == v)
    assert r["all"]["ll_sdf"] == pytest.approx(float(gaussian_loglik(0.0, 0.0, 1e-4)))
    assert r["test_seconds"] >= 0 and r["n_queries"] == 500
    with pytest.raises(EvaluationError, match="at least one training point"):
        evaluate_field(lambda x: (x[:, 2], x[:, 2]), ref, q, np.zeros((0, 3)))


def test_sample_queries_lie_along_normals():
    pts = np.zeros((10, 3))
    nrm = np.tile([0.0, 0.0, 1.0], (10, 1))
    q = sample_queries(pts, nrm, 1000, max_distance=0.3, tangential=0.0,
                       rng=np.random.default_rng(0))
    assert np.allclose(q[:, :2], 0.0) and np.abs(q[:, 2]).max() <= 0.3
    assert q[:, 2].min() < -0.25 and q[:, 2].max() > 0.25
    with pytest.raises(EvaluationError, match="same shape"):
        sample_queries(pts, nrm[:3], 5)


# --------------------------------------------------------------------------- geometry
def _brute_closest(p, tri, n=200):
    """Oracle: densest barycentric sampling of the triangle."""
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    keep = u + v <= 1
    u, v = u[keep], v[keep]
    s = tri[0] + u[:, None] * (tri[1] - tri[0]) + v[:, None] * (tri[2] - tri[0])
    return np.linalg.norm(s - p, axis=1).min()


def test_closest_point_on_triangles_against_brute_force():
    rng = np.random.default_rng(3)
    tri = rng.normal(size=(40, 3, 3))
    p = rng.normal(size=(40, 3)) * 2
    c, reg = closest_point_on_triangles(p, tri, return_region=True)
    d = np.linalg.norm(c - p, axis=1)
    brute = np.array([_brute_closest(p[k], tri[k]) for k in range(40)])
    assert np.all(d <= brute + 1e-12)          # never farther than any sampled point
    assert np.all(brute - d < 0.03)            # and the sampling gets close to it
    assert set(np.unique(reg)) <= set(range(7)) and len(np.unique(reg)) >= 3


def test_closed_box_mesh_matches_analytic_sdf():
    v, f = _box_mesh(np.array([0.5, -0.2, 1.0]), np.array([1.0, 0.5, 0.3]))
    ref = Reference.from_mesh(v, f)
    assert "closed" in ref.kind
    q = np.random.default_rng(0).uniform(-1.5, 2.5, (3000, 3))
    expect = box_sdf(q, np.array([0.5, -0.2, 1.0]), np.array([1.0, 0.5, 0.3]))
    np.testing.assert_allclose(ref.sdf(q), expect, atol=1e-9)
    # the open-mesh path gives the same on a closed mesh (float64 recomputation,
    # pseudo-normal signs)
    np.testing.assert_allclose(TriangleDistance(v, f)(q), expect, atol=1e-6)


def _hemisphere(r=1.0):
    v, f = _icosphere(r, 3)
    keep_face = v[f].mean(axis=1)[:, 2] > 0.0
    return v, f[keep_face]


def test_open_hemisphere_sign_from_closest_feature():
    v, f = _hemisphere()
    ref = Reference.from_mesh(v, f)
    assert "open" in ref.kind
    rng = np.random.default_rng(2)
    u = rng.normal(size=(4000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u = u[u[:, 2] > 0.3]                        # away from the open rim
    for off in (-0.2, -0.02, 0.02, 0.3):
        q = u * (1.0 + off)
        d = ref.sdf(q)
        assert np.all(np.sign(d) == np.sign(off)), off
        # an icosphere of level 3 deviates from the sphere by < 1 % of r
        np.testing.assert_allclose(d, off, atol=0.012)


def test_open_mesh_sign_at_sharp_edges_uses_pseudo_normals():
    # Two faces of a box (an open, sharply folded mesh): points just outside the
    # fold are closest to the shared edge, where a single face's normal can lie.
    v, f = _box_mesh(np.zeros(3), np.ones(3))
    nrm = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    keep = (nrm[:, 0] > 0.9) | (nrm[:, 2] > 0.9)  # the +x and +z faces
    dist = TriangleDistance(v, f[keep])
    q = np.array([[1.0 + 0.05, 0.0, 1.0 + 0.3], [1.3, 0.2, 1.05], [0.9, 0.0, 0.95]])
    d = dist(q)
    assert d[0] > 0 and d[1] > 0 and d[2] < 0
    np.testing.assert_allclose(np.abs(d), [math.hypot(0.05, 0.3), math.hypot(0.3, 0.05), 0.05],
                               atol=1e-9)


def test_triangle_distance_errors():
    with pytest.raises(EvaluationError, match="triangle mesh"):
        TriangleDistance(np.zeros((3, 3)), np.zeros((0, 3), dtype=int))
    with pytest.raises(EvaluationError, match="face indices"):
        TriangleDistance(np.zeros((3, 3)), np.array([[0, 1, 5]]))


def test_reference_from_points_signed_and_unsigned():
    g = np.linspace(-1, 1, 41)
    x, y = np.meshgrid(g, g)
    pts = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    q = np.array([[0.0, 0.0, 0.3], [0.0, 0.0, -0.2], [0.025, 0.0, 0.0]])
    un = Reference.from_points(pts)
    assert not un.signed
    np.testing.assert_allclose(un.sdf(q), [0.3, 0.2, 0.025])
    sg = Reference.from_points(pts, np.tile([0.0, 0.0, 1.0], (len(pts), 1)))
    assert sg.signed
    np.testing.assert_allclose(sg.sdf(q.tolist()), [0.3, -0.2, 0.025])
    with pytest.raises(EvaluationError, match="reference cloud is empty"):
        Reference.from_points(np.zeros((0, 3)))
    with pytest.raises(EvaluationError, match="one normal per reference point"):
        Reference.from_points(pts, np.zeros((3, 3)))


def test_reference_load_errors(tmp_path):
    with pytest.raises(EvaluationError, match="does not exist"):
        Reference.load(tmp_path / "nope.ply")
    with pytest.raises(EvaluationError, match="no surface to sample"):
        Reference.from_sdf(lambda x: x[:, 0]).sample_surface(5, np.random.default_rng(0))


def test_reference_load_mesh_file(tmp_path):
    import open3d as o3d

    v, f = _box_mesh(np.zeros(3), np.ones(3))
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(f))
    o3d.io.write_triangle_mesh(str(tmp_path / "box.ply"), m)
    ref = Reference.load(tmp_path / "box.ply")
    assert "closed" in ref.kind
    assert ref.sdf(np.array([[0.0, 0.0, 1.5]]))[0] == pytest.approx(0.5)


def test_sample_mesh_surface_is_area_weighted():
    v, f = _box_mesh(np.zeros(3), np.array([2.0, 0.5, 0.5]))
    p = sample_mesh_surface(v, f, 20000, np.random.default_rng(0))
    assert np.allclose(np.abs(box_sdf(p, np.zeros(3), np.array([2.0, 0.5, 0.5]))), 0, atol=1e-12)
    # a 4 x 1 x 1 box: the two x faces hold 2 of the 2 + 8 + 8 = 18 area units
    frac = np.mean(np.isclose(np.abs(p[:, 0]), 2.0))
    assert frac == pytest.approx(2 / 18, abs=0.01)


def test_surface_distances_of_a_shifted_sphere():
    v, f = _icosphere(1.0, 4)
    ref = Reference.from_mesh(v, f)
    shifted = v * 1.01                            # 1 cm larger
    r = surface_distances(shifted, f, ref, n_samples=5000)
    # both directions are about 1 cm (the mesh is close to a sphere)
    assert r["accuracy"] == pytest.approx(0.01, abs=0.002)
    assert r["completeness"] == pytest.approx(0.01, abs=0.002)
    assert 0.009 <= r["hausdorff"] < 0.02
    # cropping the reference to a cap keeps only the samples near the cap
    cap = v[v[:, 2] > 0.8]
    rc = surface_distances(shifted, f, ref, n_samples=2000, crop_points=cap, crop_radius=0.05)
    assert rc["n_samples"][1] <= 2000
    with pytest.raises(EvaluationError, match="No reference surface lies within"):
        surface_distances(shifted, f, ref, n_samples=100, crop_points=cap + 10.0)
    with pytest.raises(EvaluationError, match="with faces"):
        surface_distances(v, np.zeros((0, 3), dtype=int), ref)


# --------------------------------------------------------------------------- real data
def test_bunny_reference_is_open_and_signed_near_the_surface():
    path = SHARED_DATA / "stanford_bunny" / "reconstruction" / "bun_zipper_res3.ply"
    if not path.is_file():
        pytest.skip(f"bunny reference not found at {path}")
    ref = Reference.load(path)
    assert "open" in ref.kind
    v, f = ref.mesh
    rng = np.random.default_rng(0)
    p = sample_mesh_surface(v, f, 2000, rng)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    # move off the surface along the local normal of a random face's sample
    t = rng.choice(len(f), 2000)
    c = v[f[t]].mean(axis=1)
    nn = n[t] / np.linalg.norm(n[t], axis=1, keepdims=True)
    out_d, in_d = ref.sdf(c + 0.002 * nn), ref.sdf(c - 0.002 * nn)
    # the zippered bunny is oriented outwards: nearly every offset keeps its sign
    assert np.mean(out_d > 0) > 0.97 and np.mean(in_d < 0) > 0.97
    assert np.all(np.abs(ref.sdf(p)) < 1e-6)


# --------------------------------------------------------------------------- gmmgp eval
def _eval_parser():
    from gmmgp_app.commands.eval import add_eval_arguments

    p = argparse.ArgumentParser()
    add_eval_arguments(p)
    return p


@pytest.fixture(scope="module")
def tiny_run(box_scene):
    """A 'gmmgp run' folder (run/) of the small synthetic box of conftest, beside its
    scan.npz and exact mesh.ply."""
    from gmmgp_app import MappingConfig
    from gmmgp_app.pipeline import build_map

    root, scan = box_scene
    cfg = MappingConfig().replace({"prepare.subsample_rate": 0.5, "surface.voxel_size": 0.1})
    build_map(scan, cfg, method="gmmgp").save(root / "run" / "map")
    return root


@pytest.mark.slow
def test_eval_cli_writes_every_output(tiny_run):
    from gmmgp_app.commands.eval import run as cmd_eval

    out = tiny_run / "eval"
    args = _eval_parser().parse_args([
        str(tiny_run / "run"), "--reference", str(tiny_run / "mesh.ply"), "--scan",
        str(tiny_run / "scan.npz"), "--queries", "400", "--out", str(out),
        "--bins", "0,0.1,0.3", "--lambda", "30"])
    args.quiet = True
    assert cmd_eval(args) == 0
    names = {"metrics.json", "metrics.csv", "metrics.md", "rmse_sdf.png", "rmse_edf.png",
             "ll_sdf.png", "ll_edf.png", "times.png", "metrics.png"}
    assert names <= {p.name for p in out.iterdir()}
    assert not [p for p in out.iterdir() if p.name.startswith(".")]   # no temporaries left
    res = json.loads((out / "metrics.json").read_text())
    assert list(res["methods"]) == ["gmmgp", "hgmm", "gpis", "loggpis"]
    g = res["methods"]["gmmgp"]
    assert sum(g["field"]["n"]) == g["field"]["all"]["n"] <= 400
    # The accuracy bounds on this box live in the xfail test below (a known open problem).
    assert np.isfinite(g["field"]["all"]["rmse_sdf"]) and g["surface"]["chamfer"] > 0
    lg = res["methods"]["loggpis"]
    assert lg["field"]["all"]["rmse_sdf"] is None and lg["surface"] is None
    assert lg["lambda"] == 30.0
    rows = (out / "metrics.csv").read_text().splitlines()
    assert len(rows) == 1 + 4 * 3        # header + (2 bins + all) per method
    for f in names - {"metrics.json", "metrics.csv", "metrics.md"}:
        assert (out / f).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_eval_cli_errors(tiny_run, tmp_path):
    from gmmgp_app.commands.eval import run as cmd_eval
    from gmmgp_app.compare import EvalInputError
    from gmmgp_app.pipeline import MapFormatError

    def run(*extra):
        args = _eval_parser().parse_args([str(tiny_run / "run"), "--reference",
                                          str(tiny_run / "mesh.ply"), *extra])
        args.quiet = True
        return cmd_eval(args)

    with pytest.raises(EvalInputError, match="Unknown method"):
        run("--methods", "gmmgp,kigp")
    with pytest.raises(EvalInputError, match="increasing, non-negative --bins"):
        run("--bins", "0,0.2,0.1")
    with pytest.raises(EvalInputError, match="--bins as numbers"):
        run("--bins", "a,b")
    with pytest.raises(EvalInputError, match="--queries >= 10"):
        run("--queries", "3")
    with pytest.raises(EvalInputError, match="does not record its scan"):
        run()
    from gmmgp_app.synth import save_scan_npz

    save_scan_npz(tmp_path / "other.npz", np.random.default_rng(0).normal(size=(50, 3)))
    with pytest.raises(EvalInputError, match="the map was built from"):
        run("--scan", str(tmp_path / "other.npz"))
    args = _eval_parser().parse_args([str(tmp_path), "--reference", "x.ply"])
    with pytest.raises(MapFormatError, match="is not a saved map"):
        cmd_eval(args)


@pytest.mark.slow
def test_eval_cli_sparse_box_within_10cm_rmse_and_5cm_chamfer(tiny_run):
    from gmmgp_app.commands.eval import run as cmd_eval

    out = tiny_run / "eval_chamfer"
    args = _eval_parser().parse_args([
        str(tiny_run / "run"), "--reference", str(tiny_run / "mesh.ply"), "--scan",
        str(tiny_run / "scan.npz"), "--queries", "400", "--out", str(out),
        "--methods", "gmmgp"])
    args.quiet = True
    assert cmd_eval(args) == 0
    res = json.loads((out / "metrics.json").read_text())
    g = res["methods"]["gmmgp"]
    # (0.062 m and 0.019 m; were 0.17 m and 0.075 m before the HGMM tied a hit point's
    # virtual points to its component: free EM split the box's faces into one-sheet
    # components)
    assert g["field"]["all"]["rmse_sdf"] < 0.1 and g["surface"]["chamfer"] < 0.05
