"""``gmmgp run --tile-size`` streaming a LAS/LAZ file, and ``gmmgp eval`` of tiled runs."""

import json
import struct
from pathlib import Path

import numpy as np
import pytest
from lasfile import write_las

import gmmgp_app as gm
from gmmgp_app.cli import build_parser, main
from gmmgp_app.commands.run import plan_streaming

GEO = np.array([500000.0, 5400000.0, 100.0])  # georeferenced: the reader shifts it
LOCAL_OFFSET = np.array([500000.0, 5399000.0, 0.0])  # the reader's automatic offset
QUIET = ["-q", "--no-mesh"]
# scans without sensor origins warn once per tile: the tests check the maps instead
pytestmark = pytest.mark.filterwarnings("ignore:Scan has no sensor origins")


@pytest.fixture(scope="module")
def street():
    """A 8 m piece of the synthetic street (about 2300 points, 7 tiles of 5 m)."""
    from gmmgp_app.synth import scan_scene

    scan, _ = scan_scene("street", density=0.01, scene_params=dict(length=20.0), seed=0)
    return scan.select((scan.points[:, 0] > 0) & (scan.points[:, 0] < 8))


def _write_laz_with_origins(path, scan):
    """A LAZ of a scan georeferenced by GEO, sensor origins as extra dimensions."""
    from gmmgp_app.datasets import write_las

    return write_las(path, gm.Scan(points=scan.points, origins=scan.origins, offset=GEO))


@pytest.fixture(scope="module")
def laz(street, tmp_path_factory):
    """The street as a georeferenced LAZ (0.1 mm grid, every point of class 2)."""
    path = tmp_path_factory.mktemp("laz") / "street.laz"
    return write_las(path, street.points + GEO, scale=1e-4, offset=GEO,
                     classes=np.full(len(street), 2))


def _run(laz_path, out, *extra):
    return main(["run", str(laz_path), "--out", str(out), "--tile-size", "5", *extra])


def _queries(street):
    # off the surface, in the map's local frame (the reader's offset)
    return street.points[::5] + GEO - LOCAL_OFFSET + np.array([0.03, -0.02, 0.04])


def test_streamed_run_equals_in_memory_run(laz, street, tmp_path, capsys):
    """A single LAZ streams into tiles; the saved map, loaded after the work folder is
    gone, predicts as the --no-stream run of the same file (same quantised points)."""
    from gmmgp_app.stages.surface import read_mesh_ply
    from gmmgp_app.tiling import load_tiled_map

    assert _run(laz, tmp_path / "s", "-q", "--set", "surface.voxel_size=0.3") == 0
    assert _run(laz, tmp_path / "m", *QUIET, "--no-stream") == 0
    assert "notice" not in capsys.readouterr().err  # --no-stream is no fallback
    s = json.loads((tmp_path / "s" / "summary.json").read_text())
    m = json.loads((tmp_path / "m" / "summary.json").read_text())
    assert s["streamed"] is True and s["stream"]["origins"] is False
    assert s["stream_fallback"] is None and s["n_points"] == len(street)
    assert m["streamed"] is False and m["stream"] is None and m["stream_fallback"] == "--no-stream"
    # the work folders (streamed pieces and tiles; the read-whole run's tiles) are
    # removed and nothing is left beside the outputs
    assert sorted(p.name for p in (tmp_path / "s").iterdir()) == [
        "config.toml", "map", "mesh_gmmgp.ply", "summary.json"]
    assert sorted(p.name for p in (tmp_path / "m").iterdir()) == [
        "config.toml", "map", "summary.json"]
    a = load_tiled_map(tmp_path / "s" / "map")
    b = load_tiled_map(tmp_path / "m" / "map")
    assert a.keys == b.keys and a.owners == b.owners and len(a.keys) > 3
    np.testing.assert_array_equal(a.offset, LOCAL_OFFSET)
    np.testing.assert_array_equal(b.offset, LOCAL_OFFSET)
    assert not a.tile_points and b.tile_points  # a streamed map keeps no points
    q = _queries(street)
    (ma, va), (mb, vb) = a.predict(q), b.predict(q)
    assert np.max(np.abs(ma - mb)) < 1e-6 and np.max(np.abs(va - vb)) < 1e-6
    # and it did map the street: the mesh (extracted from the saved map) has faces
    mesh = read_mesh_ply(tmp_path / "s" / "mesh_gmmgp.ply")
    assert len(mesh.faces) > 100 and s["counts"]["surface"]["gmmgp"]["faces"] == len(mesh.faces)


def test_class_filter_falls_back_to_the_in_memory_reader(laz, street, tmp_path, capsys):
    """--classes cannot be applied while streaming: the file is read whole (one notice)
    and the filter is honoured; keeping every point gives the streamed map."""
    from gmmgp_app.tiling import build_tiled_map_from_las, load_tiled_map

    assert _run(laz, tmp_path / "c", *QUIET, "--classes", "2") == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("gmmgp run: notice: --classes is applied by "
                                               "the in-memory reader only")
    s = json.loads((tmp_path / "c" / "summary.json").read_text())
    assert s["streamed"] is False and "--classes" in s["stream_fallback"]
    assert s["scan"]["reader"] == {"classes": [2]}
    c = load_tiled_map(tmp_path / "c" / "map")
    ref = build_tiled_map_from_las(laz, c.config, c.spec, work_dir=tmp_path / "w",
                                   offset=LOCAL_OFFSET)
    q = _queries(street)
    np.testing.assert_allclose(c.predict(q)[0], ref.predict(q)[0], rtol=0, atol=1e-6)


def test_streamed_laz_uses_sensor_origins(street, tmp_path, capsys):
    """origin_x/y/z extra dimensions become the tiles' sensor origins when streaming."""
    from gmmgp_app.datasets import read_scan
    from gmmgp_app.tiling import build_tiled_map, load_tiled_map

    path = _write_laz_with_origins(tmp_path / "o.laz", street)
    assert _run(path, tmp_path / "o", *QUIET) == 0
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert s["streamed"] is True and s["stream"]["origins"] is True
    got = load_tiled_map(tmp_path / "o" / "map")
    # oracle: the in-memory tiling of the reader's points with the same origins
    pts = read_scan(path)
    org = (street.origins + GEO) - LOCAL_OFFSET  # the float64 values stored, shifted
    ref = build_tiled_map(gm.Scan(points=pts.points, origins=org, offset=pts.offset),
                          got.config, got.spec)
    q = _queries(street)
    np.testing.assert_allclose(got.predict(q)[0], ref.predict(q)[0], rtol=0, atol=1e-6)
    # the in-memory reader reads the same origins, so --no-stream maps the same
    np.testing.assert_allclose(pts.origins, org, rtol=0, atol=1e-9)
    assert _run(path, tmp_path / "o2", *QUIET, "--no-stream") == 0
    whole = load_tiled_map(tmp_path / "o2" / "map")
    np.testing.assert_allclose(whole.predict(q)[0], got.predict(q)[0], rtol=0, atol=1e-6)


def _plan(*argv):
    args = build_parser().parse_args(["run", *map(str, argv), "--out", "x",
                                      "--tile-size", "5"])
    return plan_streaming(args)


def _geokeys_feet():
    """A GeoKeyDirectory VLR: projected CRS with linear unit 9002 (international foot)."""
    import laspy

    words = [1, 1, 0, 2, 1024, 0, 1, 1, 3076, 0, 1, 9002]
    return laspy.VLR("LASF_Projection", 34735, "", struct.pack(f"<{len(words)}H", *words))


def test_stream_plan_decides_from_the_reader_options(laz, street, tmp_path, capsys):
    plan, why = _plan(laz)
    assert why is None and plan["path"] == Path(laz) and plan["origins"] is False
    np.testing.assert_array_equal(plan["offset"], LOCAL_OFFSET)
    assert _plan(laz, "--units", "m")[0] is not None  # a factor of 1 streams
    assert capsys.readouterr().err == ""
    for extra, text in [(["--classes", "2"], "--classes is applied by the in-memory reader"),
                        (["--poses", "p.txt"], "--poses is applied by the in-memory reader"),
                        (["--units", "ft"], "--units ft scales the coordinates")]:
        plan, why = _plan(laz, *extra)
        err = capsys.readouterr().err.splitlines()
        assert plan is None and text in why and len(err) == 1 and text in err[0]
    # refused by the reader for a single file: no notice, the reader's error follows
    assert _plan(laz, "--max-scans", "2") == (None, "--max-scans")
    assert _plan(laz, "--no-stream") == (None, "--no-stream")
    assert capsys.readouterr().err == ""
    # not a single LAS/LAZ file: the in-memory readers, silently
    assert _plan(laz, laz) == (None, None)
    from gmmgp_app.synth import save_scan_npz

    save_scan_npz(tmp_path / "s.npz", street.points)
    assert _plan(tmp_path / "s.npz") == (None, None)
    # a CRS in feet: streaming would map feet as metres
    feet = write_las(tmp_path / "feet.laz", street.points, vlrs=[_geokeys_feet()])
    plan, why = _plan(feet)
    assert plan is None and "CRS unit is not the metre" in capsys.readouterr().err
    # origins as extra dims: streamed, and read by the in-memory reader too (no notice)
    org = _write_laz_with_origins(tmp_path / "o.laz", street)
    assert _plan(org)[0]["origins"] is True
    assert _plan(org, "--no-stream")[0] is None
    assert capsys.readouterr().err == ""


def test_stream_errors_are_one_line(laz, tmp_path, capsys):
    data = Path(laz).read_bytes()
    bad = tmp_path / "cut.laz"
    bad.write_bytes(data[: int(len(data) * 0.6)])  # the header still fits the file
    assert _run(bad, tmp_path / "out", *QUIET) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert err[0].startswith("gmmgp run: error: Cannot stream ") and "truncated" in err[0]
    assert not (tmp_path / "out").exists()  # no empty output folder, no work folder left
    assert main(["run", str(laz), "--out", str(tmp_path / "o2"), "--no-stream"]) == 2
    err = capsys.readouterr().err
    assert "--no-stream only applies to tiled mapping, found it without --tile-size" in err


# --------------------------------------------------------------------------- gmmgp eval
def _eval(run_dir, reference, *extra):
    return main(["eval", str(run_dir), "--reference", str(reference), "--queries", "400",
                 "--bins", "0,0.1,0.3", "-q", *extra])


@pytest.fixture(scope="module")
def box(box_scene):
    """The small synthetic box of conftest (scan.npz, exact mesh.ply) and mapping options."""
    opts = ["--set", "prepare.subsample_rate=0.5", "--set", "surface.voxel_size=0.1", "-q"]
    return box_scene[0], opts


def test_eval_refuses_methods_a_tiled_map_cannot_answer(box, tmp_path, capsys):
    from gmmgp_app.compare import EvalInputError, _TiledModel, run_evaluation, tiled_methods
    from gmmgp_app.tiling import load_tiled_map

    root, opts = box
    out = tmp_path / "hgmm"
    assert main(["run", str(root / "scan.npz"), "--out", str(out), *opts, "--no-mesh",
                 "--method", "hgmm", "--tile-size", "1.2", "--tile-overlap", "0.4"]) == 0
    capsys.readouterr()
    assert _eval(out, root / "mesh.ply", "--methods", "gmmgp,hgmm") == 2
    err = capsys.readouterr().err.strip()
    assert err == ("gmmgp eval: error: --methods gmmgp cannot be evaluated on a tiled map, "
                   "which holds hgmm only (the others would be built untiled on the whole "
                   "scan); pass --methods hgmm, or evaluate a run made without --tile-size.")
    tmap = load_tiled_map(out / "map", load_points=False)
    assert tiled_methods(tmap) == ["hgmm"]
    with pytest.raises(EvalInputError, match="--methods gpis cannot be evaluated on a tiled"):
        run_evaluation(None, tmap, None, ["gpis"], bins=[0, 0.1])
    # the scan's local frame may differ from the map's: queries are shifted into it
    model = _TiledModel(tmap, tmap.offset + [1.0, -2.0, 0.5])
    q = np.random.default_rng(0).uniform(-1, 1, (50, 3))
    np.testing.assert_array_equal(model.predict(q)[0],
                                  tmap.predict(q + [1.0, -2.0, 0.5])[0])


def test_eval_of_a_tiled_run_scores_the_stitched_distribution(box, tmp_path, monkeypatch,
                                                             capsys):
    """gmmgp eval on a tiled gmmgp run scores TiledMap.distribution (log density,
    central intervals), as it scores SurfaceMap.distribution on a single map, not the
    Gaussian of predict's mean and variance."""
    import gmmgp_app.evaluation as E

    root, opts = box
    out = tmp_path / "tiled"
    assert main(["run", str(root / "scan.npz"), "--out", str(out), *opts, "--no-mesh",
                 "--tile-size", "1.2", "--tile-overlap", "0.4"]) == 0
    seen = []
    real = E.binned_metrics

    def spy(mean, var, truth, dist, bins, **kw):
        res = real(mean, var, truth, dist, bins, **kw)
        seen.append((mean, var, truth, dist, np.asarray(bins), kw, res))
        return res

    monkeypatch.setattr(E, "binned_metrics", spy)
    assert _eval(out, root / "mesh.ply", "--methods", "gmmgp", "--no-surface") == 0
    capsys.readouterr()
    (mean, var, truth, dist, bins, kw, res), = seen
    d = kw["distribution"]
    assert d is not None and type(d.parts[0]).__name__ == "StitchedPredictive"
    assert np.array_equal(np.concatenate([p.mean for p in d.parts]), mean)
    sel = (dist >= bins[0]) & (dist < bins[-1])
    ll = d.logpdf(truth)
    assert res["all"]["ll_sdf"] == pytest.approx(float(np.mean(ll[sel])), rel=1e-12)
    c2 = np.abs(truth - mean) <= d.half_width(E.TWO_SIGMA)
    assert res["all"]["cov2_sdf"] == pytest.approx(float(np.mean(c2[sel])), rel=1e-12)
    # several tiles weigh some of the queries, and the score is not the Gaussian's there
    assert sum(len(p._multi) for p in d.parts) > 10
    assert not np.allclose(ll, E.gaussian_loglik(truth, mean, var))


@pytest.mark.slow
def test_eval_of_a_tiled_run_matches_the_untiled_one(box):
    """gmmgp eval on a tiled run scores gmmgp (and hgmm, the tiles' stitched priors)
    about as well as on an untiled run of the same scan against the exact mesh."""
    root, opts = box
    res = {}
    for name, extra in [("untiled", []),
                        ("tiled", ["--tile-size", "1.2", "--tile-overlap", "0.4"])]:
        assert main(["run", str(root / "scan.npz"), "--out", str(root / name), *opts,
                     *extra]) == 0
        assert _eval(root / name, root / "mesh.ply", *(["--methods", "gmmgp,hgmm"]
                                                       if name == "untiled" else [])) == 0
        res[name] = json.loads((root / name / "eval" / "metrics.json").read_text())
    t, u = res["tiled"], res["untiled"]
    assert t["tiled"] is True and u["tiled"] is False
    assert list(t["methods"]) == ["gmmgp", "hgmm"]  # the default on a tiled map
    for method in ("gmmgp", "hgmm"):
        rt = t["methods"][method]["field"]["all"]["rmse_sdf"]
        ru = u["methods"][method]["field"]["all"]["rmse_sdf"]
        # measured 0.026 vs 0.031 m (gmmgp), 0.032 vs 0.038 m (hgmm)
        assert rt < 1.5 * ru and rt < 0.05, (method, rt, ru)
    g = t["methods"]["gmmgp"]
    assert g["surface"]["mesh"].endswith("mesh_gmmgp.ply") and g["surface"]["chamfer"] < 0.05
    assert t["methods"]["hgmm"]["surface"]["chamfer"] < 0.05
    assert "tiles" in g["train_seconds"]
