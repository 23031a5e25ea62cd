"""What ``gmmgp view`` opens besides a scan (run folders, tiled maps, check results),
the probe's gradient and the compare layer: the model and the layers, without frames."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gmmgp_app.config import MappingConfig
from gmmgp_app.types import Scan
from gmmgp_app.viz import gui_geometry as G
from gmmgp_app.viz.gui_model import StageResults, ViewerError, ViewerModel
from gmmgp_app.viz.gui_screenshot import SceneState
from gmmgp_app.viz.gui_targets import summary_lines
from gmmgp_app.viz.gui_tuning import compare_shift

CFG = MappingConfig().replace({"prepare.subsample_rate": 0.5, "gp.d_m": 0.0})


def _plane_scan(n=1500, seed=0, offset=(0.0, 0.0, 0.0)):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 2, size=(n, 2))
    z = 0.002 * rng.normal(size=n)
    pts = np.column_stack([xy, z])
    return Scan(pts, origins=np.tile([1.0, 1.0, 2.0], (n, 1)), offset=np.asarray(offset))


@pytest.fixture(scope="module")
def plane(tmp_path_factory):
    """A mapped plane scan with a georeferenced offset, saved as a run folder."""
    from gmmgp_app.pipeline import write_mesh_ply

    scan = _plane_scan(offset=(500000.0, 5400000.0, 120.0))
    model = ViewerModel(StageResults(config=CFG, voxel_size=0.2, scan=scan), "plane")
    model.results = model.compute("prepare", CFG, 0.2)
    run = tmp_path_factory.mktemp("run")
    model.save(run / "map")
    write_mesh_ply(model.results.mesh, run / "mesh_gmmgp.ply", offset=scan.offset)
    (run / "summary.json").write_text(json.dumps({
        "method": "gmmgp", "seconds": {"total": 12.5},
        "auto": {"prepare.virtual_spacing": {"value": 0.0625, "reason": "4 x the median "
                                             "point spacing (15.6 mm)"},
                 "gp.length_scale": {"value": 0.08, "reason": "paper"}}}))
    return model, run


def test_run_folder_opens_with_the_runs_mesh_and_summary(plane):
    model, run = plane
    m = ViewerModel.open(run, voxel_size=0.2)
    r = m.results
    assert m.kind == "run" and not m.can_refit
    # the mesh the run wrote (original frame) is shown in the map's local frame
    np.testing.assert_allclose(r.mesh.vertices, model.results.mesh.vertices, atol=1e-6)
    np.testing.assert_array_equal(r.mesh.faces, model.results.mesh.faces)
    np.testing.assert_allclose(r.mesh.vertex_variance, model.results.mesh.vertex_variance)
    assert all(r.has(s) for s in ("scan", "hgmm", "gp", "surface"))
    lines = summary_lines(r.summary)
    assert lines[0] == "method gmmgp, total 12.5 s"
    assert lines[1] == "settings from the scan:"
    text = " ".join(s.strip() for s in lines)  # unwrapped
    assert "prepare.virtual_spacing = 0.0625: 4 x the median point spacing (15.6 mm)" in text
    assert "gp.length_scale = 0.08: paper" in text
    assert max(len(s) for s in lines) <= 40  # wrapped to the panel
    # a map folder alone (no mesh, no summary.json): the surface is left to compute
    m2 = ViewerModel.open(run / "map", voxel_size=0.2)
    assert m2.kind == "run"  # map/ inside a run folder: the run's mesh and summary
    assert m2.results.mesh is not None


def test_summary_lines_without_or_with_a_malformed_auto_table():
    assert summary_lines({}) == []
    assert summary_lines({"method": "hgmm"}) == ["method hgmm"]
    lines = summary_lines({"auto": {"gp.d_m": 0.03}})
    assert lines == ["settings from the scan:", "  gp.d_m = 0.03"]


def test_probe_gradient_matches_finite_differences(plane):
    model, _ = plane
    x = np.array([1.0, 1.0, 0.2])
    mean, std, grad = model.probe(x, return_grad=True)
    assert (mean, std) == model.probe(x)
    h = 1e-5
    fd = [(model.probe(x + h * e)[0] - model.probe(x - h * e)[0]) / (2 * h)
          for e in np.eye(3)]
    # the field's own gradient (the probe passes it through). With the far field
    # (issue 15) the map's gradient is the inverse-variance blend of the two fields'
    # gradients without the blend weight's own gradient: measured 4.4e-3 from finite
    # differences here (|grad| ~ 1); the paper's field alone agreed to ~5e-5
    np.testing.assert_allclose(grad, fd, rtol=1e-4, atol=1e-2)
    assert grad[2] > 0.5  # above a horizontal plane the distance grows with z


def test_compare_layer_draws_the_previous_run_beside_the_current(plane):
    model, _ = plane
    base = model.results
    new = model.compute("hgmm", base.config.replace("hgmm.split_threshold", 0.1), 0.2,
                        base=base)
    view = ViewerModel(new, "plane")
    state = SceneState(view, "hgmm", level=0, layers={"compare"}, previous=base)
    key, build, _, _ = state.layer_geometry("compare")
    assert key[0] == "cmp_hgmm" and key[1] == id(base.hgmm)
    geom = build()
    shift = compare_shift(new.scan.points)
    # the plane spans 2 m in x and y: shifted by (1 + gap) * its extent along one axis
    assert np.count_nonzero(shift) == 1 and 2.0 < np.abs(shift).max() < 2.6
    assert "compare_points" not in geom  # the nodes alone (see _compare_geometry)
    state.stage = "scan"  # other stages: the previous run's points
    pts = np.asarray(state.layer_geometry("compare")[1]()["compare_points"].points)
    np.testing.assert_allclose(pts, base.scan.points + shift)
    cur_hi = new.scan.points.max(axis=0)
    ax = int(np.flatnonzero(shift)[0])
    assert pts[:, ax].min() > cur_hi[ax]  # beside, never overlapping
    state.stage = "hgmm"
    # the previous run's level-0 nodes: each ellipsoid centred on its node's mean + shift
    lv = base.hgmm.levels[0]
    split = np.asarray(lv.split, bool)
    centres = lv.mixture.means[:, :3] + shift
    if (~split).any():
        v = np.asarray(geom["compare_leaf"].vertices).reshape((~split).sum(), -1, 3)
        np.testing.assert_allclose(v.mean(axis=1), centres[~split], atol=1e-9)
    if split.any():
        v = np.asarray(geom["compare_split"].points).reshape(split.sum(), -1, 3)
        np.testing.assert_allclose(v.mean(axis=1), centres[split], atol=1e-9)
    # surface stage: the previous mesh, shifted
    state.stage = "surface"
    key, build, _, _ = state.layer_geometry("compare")
    if base.mesh is not None and len(base.mesh.faces):
        m = build()["compare_mesh"]
        np.testing.assert_allclose(np.asarray(m.vertices), base.mesh.vertices + shift)
    # no previous run: nothing to draw
    assert SceneState(view, "hgmm", layers={"compare"}).layer_geometry("compare")[0] is None


@pytest.fixture(scope="module")
def tiled(tmp_path_factory):
    from gmmgp_app.tiling import TileSpec, build_tiled_map

    scan = _plane_scan(n=2400, seed=3)
    tmap = build_tiled_map(scan, CFG, TileSpec(size=1.0, overlap=0.3, min_points=400))
    out = tmp_path_factory.mktemp("tiled") / "map"
    tmap.save(out)
    return tmap, out


def test_tiled_map_loads_tiles_on_demand_and_stitches_their_surface(tiled):
    tmap, out = tiled
    m = ViewerModel.open(out.parent, voxel_size=0.2)  # a run folder holding map/tiled.json
    assert m.kind == "tiled" and not m.can_refit
    assert m.results.counts()["tiles_loaded"] == 0 and m.results.counts()["tiles"] == 4
    tv = m.results.tiles
    assert tv.keys_near([0.5, 0.5], 0.2) == [(0, 0)]
    assert tv.keys_near([1.0, 1.0], 0.01)[0] in [(0, 0), (0, 1), (1, 0), (1, 1)]
    assert len(tv.keys_near([1.0, 1.0], 0.01)) == 4
    r = m.load_tiles([0.5, 0.5], 0.2)
    assert list(r.tiles.pieces) == [(0, 0)]
    assert np.all(r.scan.points[:, :2] < 1.0)  # the seeds of tile (0, 0)'s square only
    m.results = r
    # the probe answers with the stitched field
    q = np.array([0.9, 1.1, 0.15])
    np.testing.assert_allclose(m.probe(q), [tmap.predict(q[None])[0][0],
                                            np.sqrt(tmap.predict(q[None])[1][0])])
    r = m.load_tiles()
    assert sorted(r.tiles.pieces) == tmap.keys
    # oracle: the pieces together are the stitched field's surface, face for face
    full = tmap.extract_surface(voxel_size=0.2)

    def centroids(mesh):
        c = mesh.vertices[mesh.faces].mean(axis=1)
        return np.unique(np.round(c, 6), axis=0)
    a, b = centroids(r.mesh), centroids(full)
    assert len(r.mesh.faces) == len(full.faces) > 100
    np.testing.assert_allclose(a, b, atol=1e-9)
    # every tile's HGMM levels are drawn side by side
    assert r.hgmm.leaves.n_components == sum(tmap.tiles[k].hgmm.leaves.n_components
                                             for k in tmap.keys)
    with pytest.raises(ViewerError, match="needs the scan"):
        m.compute("hgmm", m.results.config, 0.2)


@pytest.fixture(scope="module")
def check_dir(plane, tmp_path_factory):
    """``gmmgp check`` of the plane scan with a raised patch against the plane's map."""
    from gmmgp_app.cli import main
    from gmmgp_app.synth.io import save_scan_npz

    model, run = plane
    scan = _plane_scan(seed=7)
    pts = scan.points.copy()
    patch = np.linalg.norm(pts[:, :2] - [1.3, 0.7], axis=1) < 0.25
    pts[patch, 2] += 0.08  # 8 cm above the mapped plane: changed
    root = tmp_path_factory.mktemp("check")
    save_scan_npz(root / "second.npz", pts + model.results.scan.offset)
    assert main(["check", str(root / "second.npz"), "--map", str(run / "map"), "--out",
                 str(root / "out"), "-q"]) == 0
    return root / "out", patch


def test_a_check_keeps_the_maps_up_axis(plane, check_dir, tmp_path):
    """check.json records the map's up axis and the viewer stands the check on it: a
    check against a y-up map (a Stanford set) opens y up, a z-up one z up, a check.json
    written before the up axis was kept z up."""
    from gmmgp_app.cli import main

    out, _ = check_dir
    assert json.loads((out / "check.json").read_text())["up"] == [0.0, 0.0, 1.0]
    np.testing.assert_array_equal(ViewerModel.open(out).up, [0, 0, 1])
    y_map = _y_up_copy(plane, tmp_path)
    assert main(["check", str(out.parent / "second.npz"), "--map", str(y_map), "--out",
                 str(tmp_path / "out"), "-q"]) == 0
    summary = json.loads((tmp_path / "out" / "check.json").read_text())
    assert summary["up"] == [0.0, 1.0, 0.0]
    np.testing.assert_array_equal(ViewerModel.open(tmp_path / "out").up, [0, 1, 0])
    del summary["up"]
    (tmp_path / "out" / "check.json").write_text(json.dumps(summary))
    np.testing.assert_array_equal(ViewerModel.open(tmp_path / "out").up, [0, 0, 1])


def test_a_check_recording_stands_on_the_maps_up_axis(plane, check_dir, tmp_path):
    """The check's .rrd logs the map's up axis as the view's coordinates (y for a y-up
    map, z for a z-up one): read back from the file."""
    pytest.importorskip("rerun")
    from rerun.chunk import RrdReader

    from gmmgp_app.cli import main

    out, _ = check_dir

    def logged_up(maps, name):
        assert main(["check", str(out.parent / "second.npz"), "--map", str(maps), "--out",
                     str(tmp_path / name), "-q", "--rrd", str(tmp_path / f"{name}.rrd")]) == 0
        rows = []
        for c in RrdReader(tmp_path / f"{name}.rrd").stream().to_chunks():
            if c.entity_path == "/world":
                rb = c.to_record_batch()
                rows += [rb.column(n).to_pylist() for n in rb.schema.names
                         if n.endswith("ViewCoordinates:xyz")]
        assert len(rows) == 1, rows
        return rows[0][0][0].index(1)             # rerun's ViewDir.Up = 1

    assert logged_up(_y_up_copy(plane, tmp_path), "y") == 1
    assert logged_up(plane[1] / "map", "z") == 2


def _y_up_copy(plane, tmp_path):
    """A copy of the plane's map saved as if its scan had been y up."""
    import shutil

    _, run = plane
    y_map = tmp_path / "map"
    shutil.copytree(run / "map", y_map)
    meta = json.loads((y_map / "map.json").read_text())
    meta["up"] = [0.0, 1.0, 0.0]
    (y_map / "map.json").write_text(json.dumps(meta))
    return y_map


def test_check_result_opens_coloured_by_z_with_its_segments(check_dir):
    out, patch = check_dir
    m = ViewerModel.open(out)
    r, ck = m.results, m.results.check
    assert m.kind == "check" and not m.can_refit
    summary = json.loads((out / "check.json").read_text())
    assert len(ck.segments) == summary["n_segments"] >= 1
    assert int(ck.changed.sum()) == r.counts()["changed"] > 0
    assert ck.changed[patch].mean() > 0.8 and ck.changed[~patch].mean() < 0.01
    # the largest segment sits on the patch, in the view's local frame
    sg = ck.segments[0]
    np.testing.assert_allclose(sg["centroid"][:2], np.mean(r.scan.points[patch, :2], axis=0),
                               atol=0.05)
    c = sg["centroid"]  # the view's local frame (check.json's minus the view's offset)
    np.testing.assert_allclose(c + r.scan.offset, summary["segments"][0]["centroid"])
    assert ck.segment_label(0) == (f"#1: {sg['size']} pts at ({c[0]:.1f}, {c[1]:.1f}, "
                                   f"{c[2]:.1f}), +{sg['mean_distance_m']:.2f} m")
    assert 0.05 < sg["mean_distance_m"] < 0.11  # the patch is 8 cm above the map
    # points coloured by z (red: in front of the map), unknown grey; segments as boxes
    state = SceneState(m, "scan", layers={"points", "segments"})
    key, build, _, legend = state.layer_geometry("points")
    assert key[0] == "z" and legend[0] == "z" and legend[2] == 2 * ck.z_threshold
    col = np.asarray(build().colors)
    red = col[:, 0] - col[:, 2]
    assert np.mean(red[patch & ck.known] > 0.3) > 0.8
    np.testing.assert_allclose(col[~ck.known], 0.8)
    key, build, _, _ = state.layer_geometry("segments")
    boxes = build()
    assert len(np.asarray(boxes.lines)) == 12 * len(ck.segments)
    assert not np.any(np.all(np.asarray(boxes.colors) == [0.9, 0.0, 0.0], axis=1))
    state.selected_segment = 0
    key2, build2, _, _ = state.layer_geometry("segments")
    assert key2 != key
    sel = np.asarray(build2().colors)[:12]
    np.testing.assert_allclose(sel, np.tile([0.9, 0.0, 0.0], (12, 1)))


def test_z_colours_and_boxes():
    col, lo, hi = G.z_colors(np.array([-9.0, 0.0, 6.0, 1.0]), np.array([1, 1, 1, 0], bool), 3.0)
    assert (lo, hi) == (-6.0, 6.0)
    np.testing.assert_allclose(col[0], G.colormap(np.array([0.0]), "coolwarm")[0])
    np.testing.assert_allclose(col[2], G.colormap(np.array([1.0]), "coolwarm")[0])
    np.testing.assert_allclose(col[3], 0.8)
    ls = G.aabb_boxes([[0, 0, 0]], [[1, 2, 3]], [[1, 0, 0]])
    p = np.asarray(ls.points)
    np.testing.assert_allclose(p.min(axis=0), [0, 0, 0])
    np.testing.assert_allclose(p.max(axis=0), [1, 2, 3])
    assert len(np.asarray(ls.lines)) == 12


def test_open_errors_name_the_fix(tmp_path):
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "summary.json").write_text("{truncated")
    (tmp_path / "bad" / "map").mkdir()
    with pytest.raises(ViewerError, match="Cannot read .*summary.json.*run 'gmmgp run' again"):
        ViewerModel.open(tmp_path / "bad")
    m = ViewerModel(StageResults(config=MappingConfig(), voxel_size=0.1,
                                 scan=_plane_scan(50)), "x")
    with pytest.raises(ViewerError, match="is not a tiled map"):
        m.load_tiles()


def test_a_folder_of_scans_opens_as_a_scan_and_any_other_folder_names_both(tmp_path):
    """A folder the project did not write (no map.json, summary.json, tiled.json or
    check.json) is read as a folder of scans, as 'gmmgp run' reads it; a folder that
    is neither ends in one error naming both."""
    from gmmgp_app.datasets import read_scan
    from gmmgp_app.synth import save_scan_npz

    scans = tmp_path / "scans"
    scans.mkdir()
    for i in range(2):
        s = _plane_scan(200, seed=i)
        save_scan_npz(scans / f"scan{i}.npz", s.points, s.origins)
    m = ViewerModel.open(scans)
    assert m.kind == "scan"
    np.testing.assert_array_equal(m.results.scan.points, read_scan(scans).points)
    (tmp_path / "empty").mkdir()
    with pytest.raises(ViewerError, match=r"is no map, run or check folder .* and no "
                                          r"folder of scans: .*contains no scan files"):
        ViewerModel.open(tmp_path / "empty")


# --------------------------------------------------------------------------- frames
_RENDER_TARGETS = """
import sys
from gmmgp_app.viz.gui_model import ViewerModel
from gmmgp_app.viz.gui_screenshot import render_png, screenshot_target
check, tiled, scan, out = sys.argv[1:5]
S = (320, 240)
screenshot_target(ViewerModel.open(check), f"{out}/check.png", size=S)
screenshot_target(ViewerModel.open(check), f"{out}/check_seg.png", size=S, segment=0)
screenshot_target(ViewerModel.open(tiled, voxel_size=0.2), f"{out}/tiled.png", size=S)
from gmmgp_app.config import MappingConfig
cfg = MappingConfig().replace({"prepare.subsample_rate": 0.5, "gp.d_m": 0.0})
m = ViewerModel.open(scan, cfg, voxel_size=0.2)
# the GP stage (unlit points): frames of lit ellipsoids side by side stalled the CPU
# renderer for over 8 min here (a plane, 320x240, load 14); see the report of issue 18
screenshot_target(m, f"{out}/compare.png", size=S, stage="gp",
                  compare={"gp.d_m": 0.004}, log=print)
render_png(m, f"{out}/gp.png", size=S, stage="gp")  # the second run alone
"""


@pytest.mark.slow
def test_results_render_offscreen(check_dir, tiled, tmp_path):
    """Check result (z colours, a selected segment), tiled map surface and the compare
    view, each through one offscreen frame (as ``gmmgp view --screenshot``)."""
    import subprocess
    import sys

    from PIL import Image

    from gmmgp_app.synth.io import save_scan_npz

    scan = _plane_scan()
    save_scan_npz(tmp_path / "plane.npz", scan.points, scan.origins)
    r = subprocess.run([sys.executable, "-c", _RENDER_TARGETS, str(check_dir[0]),
                        str(tiled[1]), str(tmp_path / "plane.npz"), str(tmp_path)],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    im = {n: np.asarray(Image.open(tmp_path / f"{n}.png").convert("RGB")).astype(int)
          for n in ("check", "check_seg", "tiled", "gp", "compare")}
    for n, a in im.items():
        assert a.shape == (240, 320, 3) and a.std() > 3, n
    # the check picture: points coloured by z (red in front of the map, blue behind)
    c = im["check"]
    assert np.sum((c[..., 0] > 150) & (c[..., 2] < 120)) > 20
    # the selected segment is framed red; the compare picture holds a second copy
    s = im["check_seg"]
    assert np.sum((s[..., 0] > 200) & (s[..., 1] < 60) & (s[..., 2] < 60)) > 50
    assert np.mean(np.any(im["compare"] != im["gp"], axis=2)) > 0.02
    # both copies hold GP points (red): the previous run's beside the current one's
    cmp_red = (im["compare"][..., 0] > 150) & (im["compare"][..., 1] < 80)
    assert cmp_red.sum() > 20
    assert "run 1: c* 0.01, d_m 0" in r.stdout and "run 2: c* 0.01, d_m 0.004" in r.stdout
    assert "mm rms" in r.stdout  # the field's change against the first run


@pytest.mark.slow
def test_app_opens_a_check_result_and_a_tiled_map_under_xvfb(check_dir, tiled, tmp_path):
    """The window (without 3D geometry, as the window test of test_gui.py) on a check
    result (segments listed, one selected) and a tiled map (tiles loaded around the
    view, then all)."""
    import os
    import subprocess
    import sys

    from test_gui import _run_quiet, _start_xvfb, _stop_xvfb

    out = tmp_path
    ck_steps = [{"state": str(out / "c0.json")}, {"segment": 1},
                {"state": str(out / "c1.json")}, {"segment": 0},
                {"state": str(out / "c2.json")}, {"quit": True}]
    tl_steps = [{"state": str(out / "t0.json")}, {"load_tiles": "view"},
                {"state": str(out / "tv.json")}, {"load_tiles": "all"},
                {"state": str(out / "t1.json")}, {"probe": [0.9, 1.1, 0.15]},
                {"state": str(out / "t2.json")}, {"quit": True}]
    (out / "ck.json").write_text(json.dumps(ck_steps))
    (out / "tl.json").write_text(json.dumps(tl_steps))
    xvfb, display = _start_xvfb(tmp_path)
    env = dict(os.environ, DISPLAY=display)
    env.pop("WAYLAND_DISPLAY", None)
    try:
        runs = [_run_quiet([sys.executable, "-m", "gmmgp_app.viz.gui", str(target),
                            "--size", "1200x800", "--voxel-size", "0.2", "--no-3d",
                            "--script", str(script)], env=env, timeout=900)
                for target, script in ((check_dir[0], out / "ck.json"),
                                       (tiled[1], out / "tl.json"))]
    finally:
        _stop_xvfb(xvfb)
    for code, err in runs:
        assert code == 0, err[-3000:]
    c0, c1, c2 = (json.loads((out / f"c{i}.json").read_text()) for i in range(3))
    assert c0["kind"] == "check" and c0["stage"] == "scan" and c0["errors"] == []
    assert c0["legend"].startswith("check z") and c0["drawn"]["points"][0] == "z"
    n = c0["counts"]["segments"]
    assert c0["segment_items"] == n + 1 and f"{n} segments" in c0["segments_label"]
    assert c0["selected_segment"] is None and c1["selected_segment"] == 0
    assert c1["drawn"]["segments"] != c0["drawn"]["segments"]  # the selected one red
    assert c2["selected_segment"] is None
    t0, t1, t2 = (json.loads((out / f"t{i}.json").read_text()) for i in range(3))
    assert t0["kind"] == "tiled" and t0["errors"] == [] and t2["errors"] == []
    tiles = len(tiled[0].keys)
    # opened around the map's centre: the tiles within one tile size of it
    assert 0 < t0["counts"]["tiles_loaded"] <= tiles
    tv = json.loads((out / "tv.json").read_text())  # around the camera's centre of view
    assert tv["errors"] == [] and tv["counts"]["tiles_loaded"] >= t0["counts"]["tiles_loaded"]
    assert t1["counts"]["tiles_loaded"] == tiles and f"{tiles} of {tiles} tiles" in \
        t1["tiles_label"]
    assert t1["counts"]["faces"] > 0 and t1["stage"] == "surface"
    mean = tiled[0].predict(np.array([[0.9, 1.1, 0.15]]))[0][0]
    assert f"SDF {mean:+.4f}" in t2["probe"] and "|grad|" in t2["probe"]


def test_screenshot_options_fail_in_one_line(tmp_path, monkeypatch):
    import argparse

    from gmmgp_app.config import ConfigError
    from gmmgp_app.viz import gui

    assert gui._parse_compare(["hgmm.split_threshold=0.03", "gp.d_m=0.01"]) == {
        "hgmm.split_threshold": 0.03, "gp.d_m": 0.01}
    with pytest.raises(ViewerError, match="Expected --compare like hgmm.split_threshold=0.03"):
        gui._parse_compare(["x"])
    with pytest.raises(ConfigError, match="Unknown config field 'hgmm.nope'"):
        gui._parse_compare(["hgmm.nope=1"])
    monkeypatch.setenv("DISPLAY", ":12345")
    p = argparse.ArgumentParser()
    gui.add_view_arguments(p)
    scan = tmp_path / "s.npz"
    with pytest.raises(ViewerError, match="--compare and --segment apply to --screenshot"):
        gui.open_view(p.parse_args([str(scan), "--segment", "1"]), MappingConfig())
    with pytest.raises(ViewerError, match="Expected --segment >= 1"):
        gui.open_view(p.parse_args([str(scan), "--segment", "0", "--screenshot", "x.png"]),
                      MappingConfig())


def test_screenshot_refuses_what_a_target_cannot_show(check_dir, tiled, tmp_path):
    from gmmgp_app.viz.gui_screenshot import screenshot_target

    m = ViewerModel.open(check_dir[0])
    n = len(m.results.check.segments)
    with pytest.raises(ViewerError, match=f"Expected --segment between 1 and {n}"):
        screenshot_target(m, tmp_path / "a.png", segment=n)
    with pytest.raises(ViewerError, match="is a check result: it shows the scan's points"):
        screenshot_target(m, tmp_path / "a.png", stage="hgmm")
    with pytest.raises(ViewerError, match="--compare needs a scan to map twice"):
        screenshot_target(m, tmp_path / "a.png", compare={"gp.d_m": 0.01})
    t = ViewerModel.open(tiled[1])
    with pytest.raises(ViewerError, match="is a tiled map: show 'hgmm', 'gp' or 'surface'"):
        screenshot_target(t, tmp_path / "a.png", stage="scan")
    with pytest.raises(ViewerError, match="--segment selects a change segment of a check"):
        screenshot_target(t, tmp_path / "a.png", segment=0)
    assert not list(tmp_path.iterdir())  # nothing written


def test_compare_screenshot_records_the_resolved_d_m_with_default_settings(tmp_path,
                                                                             monkeypatch):
    """``gmmgp view SCAN --compare hgmm.split_threshold=0.03 --screenshot PNG`` with the
    default settings (d_m 'auto', no --set): both run records name the d_m the runs used,
    the value resolved from the scan (it printed "d_m nan": a run stopped at the GP stage
    handed out results without the resolved values). The frame itself is not rendered
    here (test_results_render_offscreen renders the compare view)."""
    import re

    from gmmgp_app.config import is_auto
    from gmmgp_app.pipeline import resolve_config
    from gmmgp_app.viz import gui_screenshot as S

    drawn = {}

    def fake_render(model, path, **kw):
        drawn.update(kw, results=model.results)
        return path
    monkeypatch.setattr(S, "render_png", fake_render)
    scan = _plane_scan()
    cfg = MappingConfig()
    assert is_auto(cfg.gp.d_m)
    m = ViewerModel(StageResults(config=cfg, voxel_size=0.2, scan=scan), "plane")
    lines = []
    S.screenshot_target(m, tmp_path / "cmp.png", stage="gp",
                        compare={"hgmm.split_threshold": 0.03}, log=lines.append)
    runs = [ln for ln in lines if ln.startswith("run ")]
    assert len(runs) == 2, lines
    d_m = resolve_config(cfg, scan)[0].gp.d_m
    assert d_m > 0
    for ln in runs:
        got = re.search(r"d_m ([^,]+),", ln).group(1)
        assert got == f"{d_m:.3g}", ln
    assert "c* 0.03" in runs[1] and "leaves" in runs[1] and "GP pts" in runs[1]
    # the results drawn (and the previous run beside them) carry the resolved record
    assert drawn["stage"] == "gp" and drawn["previous"] is not None
    for r in (drawn["results"], drawn["previous"]):
        assert r.summary["auto"]["gp.d_m"]["value"] == d_m
        assert r.gp_points is not None and r.mesh is None  # stopped after the GP stage


def _stanford_set(folder, n=3000, seed=5):
    """A one-scan Stanford ``.conf`` set: a bunny-sized sphere (radius 5 cm) in a PLY."""
    import open3d as o3d

    folder.mkdir()
    d = np.random.default_rng(seed).normal(size=(n, 3))
    pts = 0.05 * d / np.linalg.norm(d, axis=1, keepdims=True)
    o3d.io.write_point_cloud(str(folder / "s0.ply"),
                             o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)))
    (folder / "set.conf").write_text("bmesh s0.ply 0 0 0 0 0 0 1\n")
    return folder / "set.conf"


@pytest.mark.filterwarnings("ignore:Scan has no sensor origins")  # a sphere / a plane
def test_a_saved_map_keeps_its_scans_up_axis_for_the_viewer(tmp_path):
    """A map made from a Stanford scan set (y up) opens y up in the app, as its scan
    does: the map (map.json "up"), the run folder and the tiled map keep the scan's up
    axis; a map saved without one (older versions) opens z up."""
    from gmmgp_app.cli import main
    from gmmgp_app.datasets import read_scan
    from gmmgp_app.pipeline import load_map

    conf = _stanford_set(tmp_path / "set")
    np.testing.assert_array_equal(read_scan(conf).up, [0, 1, 0])
    np.testing.assert_array_equal(read_scan(conf.parent).up, [0, 1, 0])
    out = tmp_path / "out"
    assert main(["run", str(conf), "--out", str(out), "--no-mesh", "--quiet",
                 "--set", "hgmm.max_levels=2"]) == 0
    np.testing.assert_array_equal(load_map(out / "map").up, [0, 1, 0])
    for target in (out, out / "map"):
        np.testing.assert_array_equal(ViewerModel.open(target).up, [0, 1, 0])
    # a map saved before the up axis was kept: z, as those maps always opened
    meta = json.loads((out / "map" / "map.json").read_text())
    assert meta.pop("up") == [0.0, 1.0, 0.0]
    (out / "map" / "map.json").write_text(json.dumps(meta))
    np.testing.assert_array_equal(ViewerModel.open(out / "map").up, [0, 0, 1])
    # a scan that is not a Stanford set: z
    np.testing.assert_array_equal(read_scan(conf.parent / "s0.ply").up, [0, 0, 1])


def test_a_tiled_map_keeps_its_scans_up_axis(tmp_path):
    from gmmgp_app.tiling import TileSpec, build_tiled_map, load_tiled_map

    scan = _plane_scan(n=1200)
    y_up = Scan(scan.points, origins=scan.origins, up=(0.0, 1.0, 0.0))
    from gmmgp_app.tiling import TilingWarning

    with pytest.warns(TilingWarning, match="up axis is y"):   # tiles cut in x and y
        tmap = build_tiled_map(y_up, CFG, TileSpec(size=5.0, overlap=0.5, min_points=50))
    np.testing.assert_array_equal(tmap.up, [0, 1, 0])
    tmap.save(tmp_path / "tiled")
    np.testing.assert_array_equal(load_tiled_map(tmp_path / "tiled").up, [0, 1, 0])
    np.testing.assert_array_equal(ViewerModel.open(tmp_path / "tiled").up, [0, 1, 0])
    meta = json.loads((tmp_path / "tiled" / "tiled.json").read_text())
    del meta["up"]
    (tmp_path / "tiled" / "tiled.json").write_text(json.dumps(meta))
    np.testing.assert_array_equal(load_tiled_map(tmp_path / "tiled").up, [0, 0, 1])


def test_the_compare_copy_stands_beside_y_up_data_not_above_it():
    """The compare layer shifts the previous run across the view in the horizontal
    plane of the data's up axis: for y-up data never along y (that stacked the copy
    above or below the scan)."""
    rng = np.random.default_rng(3)
    # a y-up street: long along x, its height along y, its width along z
    street = rng.uniform([0, 0, -4], [40, 12, 4], size=(3000, 3))
    sh = compare_shift(street, up=(0.0, 1.0, 0.0))
    assert sh[0] == 0 and sh[1] == 0 and sh[2] > np.ptp(street[:, 2])   # across: z
    # the same street z up: across is y, as before
    z_up = street[:, [0, 2, 1]]
    np.testing.assert_array_equal(compare_shift(z_up), compare_shift(z_up, up=(0, 0, 1)))
    assert np.flatnonzero(compare_shift(z_up)).tolist() == [1]
    # a y-up object longer in x than deep in z: across is z, never y
    obj = rng.normal(size=(2000, 3)) * [0.08, 0.03, 0.03]
    assert np.flatnonzero(compare_shift(obj, up=(0.0, 1.0, 0.0))).tolist() == [2]
