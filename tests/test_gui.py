"""The desktop app: geometry builders and the model without a display, the window under Xvfb.

The window test runs the app in a subprocess (a crash in the renderer cannot take
pytest down) on its own Xvfb display, drives it with a ``--script`` and checks
the screenshots and the state the panel showed.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from gmmgp_app.config import MappingConfig
from gmmgp_app.types import Scan
from gmmgp_app.viz import gui_geometry as G
from gmmgp_app.viz.gui_model import (STAGES, Cancelled, StageResults, ViewerError,
                                     ViewerModel, first_affected_stage)
from gmmgp_app.viz.gui_screenshot import STAGE_LAYERS


def _random_gaussians(k=5, d=4, seed=0):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(k, d, d))
    cov = a @ np.transpose(a, (0, 2, 1)) + 0.1 * np.eye(d)
    return rng.normal(size=(k, d)), cov


# --------------------------------------------------------------------------- geometry
def test_ellipsoid_mesh_vertices_lie_on_the_two_sigma_surface():
    means, cov = _random_gaussians()
    cols = np.linspace(0, 1, 15).reshape(5, 3)
    m = G.ellipsoid_mesh(means, cov, cols, n_sigma=2.0, resolution=6)
    v = np.asarray(m.vertices).reshape(5, -1, 3)
    inv = np.linalg.inv(cov[:, :3, :3])
    diff = v - means[:, None, :3]
    maha2 = np.einsum("kvi,kij,kvj->kv", diff, inv, diff)
    np.testing.assert_allclose(maha2, 4.0, rtol=1e-9)
    # each ellipsoid keeps its own colour and the faces never cross ellipsoids
    np.testing.assert_allclose(np.asarray(m.vertex_colors).reshape(5, -1, 3)[:, 0], cols)
    f = np.asarray(m.triangles) // v.shape[1]
    assert np.all(f == f[:, :1])
    # lit meshes carry (zero) texture coordinates: without them CPU frames ran away
    for mesh in (m, G.triangle_mesh(v.reshape(-1, 3), np.asarray(m.triangles),
                                    np.full((v.size // 3, 3), 0.5))):
        uv = np.asarray(mesh.triangle_uvs)
        assert uv.shape == (3 * len(mesh.triangles), 2) and not uv.any()


def test_scan_colours_follow_the_up_axis():
    """Height colours by z, or along the data's up axis (y for the Stanford sets)."""
    pts = np.random.default_rng(4).normal(size=(500, 3))
    z = G.scan_colors(pts)
    assert all(np.array_equal(a, b) for a, b in zip(z, G.scan_colors(pts, (0, 0, 1))))
    y = G.scan_colors(pts, (0.0, 1.0, 0.0))
    assert all(np.array_equal(a, b) for a, b in zip(y, G.scan_colors(pts[:, [0, 2, 1]])))
    down = G.scan_colors(pts, (0.0, 0.0, -1.0))
    assert down[1] == pytest.approx(-z[2]) and down[2] == pytest.approx(-z[1])


def test_probe_marker_is_a_lit_sphere_around_the_point():
    """The probe's marker (built in gui_geometry, where the meshes drawn lit get their
    zero texture coordinates): Open3D's sphere of resolution 10 moved to the point."""
    import open3d as o3d

    xyz, r = np.array([1.0, -2.0, 0.5]), 0.03
    m = G.probe_marker(xyz, r)
    v = np.asarray(m.vertices)
    np.testing.assert_allclose(np.linalg.norm(v - xyz, axis=1), r, rtol=1e-12)
    ref = o3d.geometry.TriangleMesh.create_sphere(radius=r, resolution=10)
    np.testing.assert_array_equal(v, np.asarray(ref.vertices) + xyz)
    np.testing.assert_array_equal(np.asarray(m.triangles), np.asarray(ref.triangles))
    assert m.has_vertex_normals()
    uv = np.asarray(m.triangle_uvs)
    assert uv.shape == (3 * len(m.triangles), 2) and not uv.any()


def test_ellipsoid_wireframe_lines_join_points_on_the_surface():
    means, cov = _random_gaussians(k=3, seed=1)
    ls = G.ellipsoid_wireframe(means, cov, np.ones((3, 3)), n_sigma=1.0, resolution=5)
    p = np.asarray(ls.points).reshape(3, -1, 3)
    inv = np.linalg.inv(cov[:, :3, :3])
    diff = p - means[:, None, :3]
    np.testing.assert_allclose(np.einsum("kvi,kij,kvj->kv", diff, inv, diff), 1.0, rtol=1e-9)
    lines = np.asarray(ls.lines)
    assert len(lines) == 3 * len(G._unit_sphere(5)[2])
    assert np.all(lines[:, 0] // p.shape[1] == lines[:, 1] // p.shape[1])


def test_block_boxes_have_twelve_unit_edges_each():
    centres = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]])
    ls = G.block_boxes(centres, 0.1)
    p, lines = np.asarray(ls.points), np.asarray(ls.lines)
    assert len(lines) == 24
    np.testing.assert_allclose(np.linalg.norm(p[lines[:, 0]] - p[lines[:, 1]], axis=1), 0.2)
    np.testing.assert_allclose(p.reshape(2, 8, 3).mean(axis=1), centres, atol=1e-12)
    np.testing.assert_allclose(np.abs(p.reshape(2, 8, 3) - centres[:, None]), 0.1)


def test_colour_maps_match_matplotlib_and_saturate():
    import matplotlib

    bar = G.colorbar_rgb("viridis", width=11, height=3)
    assert bar.shape == (3, 11, 3) and bar.dtype == np.uint8
    ref = (matplotlib.colormaps["viridis"]([0.0, 1.0])[:, :3] * 255 + 0.5).astype(np.uint8)
    np.testing.assert_array_equal(bar[0, [0, -1]], ref)
    col, lo, hi = G.error_colors(np.array([0.0, 0.1, -1.0]), d_m=0.02)
    assert (lo, hi) == (0.0, pytest.approx(0.1))
    np.testing.assert_allclose(col[1], col[2])  # both saturate at 5 d_m
    col, lo, hi = G.std_colors(np.array([0.0, 0.04, 0.01]), vmax=0.2)
    np.testing.assert_allclose(col[1], G.colormap(np.array([1.0]), "viridis")[0])


# --------------------------------------------------------------------------- model
def _results(**kw):
    return StageResults(config=MappingConfig(), voxel_size=0.1, **kw)


def test_first_affected_stage_follows_the_dependency_of_each_setting():
    cfg = MappingConfig()
    mesh = object()
    old = _results(mesh=mesh)
    assert first_affected_stage(old, cfg, 0.1) is None
    assert first_affected_stage(old, cfg.replace("hgmm.split_threshold", 0.05), 0.1) == "hgmm"
    assert first_affected_stage(old, cfg.replace("gp.d_m", 0.05), 0.1) == "gp"
    assert first_affected_stage(old, cfg, 0.2) == "surface"
    assert first_affected_stage(_results(), cfg, 0.1) == "surface"  # no mesh yet
    both = cfg.replace({"hgmm.split_threshold": 0.05, "gp.d_m": 0.05})
    assert first_affected_stage(old, both, 0.2) == "hgmm"


def _plane_scan(n=1500, seed=0):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 2, size=(n, 2))
    z = 0.002 * rng.normal(size=n)
    pts = np.column_stack([xy, z])
    return Scan(pts, origins=np.tile([1.0, 1.0, 2.0], (n, 1)))


@pytest.fixture(scope="module")
def plane_model():
    cfg = MappingConfig().replace({"prepare.subsample_rate": 0.5, "gp.d_m": 0.0})
    model = ViewerModel(StageResults(config=cfg, voxel_size=0.2, scan=_plane_scan()), "plane")
    seen = []
    model.results = model.compute("prepare", cfg, 0.2, on_stage=lambda n, r: seen.append(n))
    return model, seen


def test_compute_runs_every_stage_in_order_and_reports_each(plane_model):
    model, seen = plane_model
    assert seen == list(STAGES[1:])
    r = model.results
    assert all(r.has(s) for s in STAGES)
    # d_m = 0: every hit point with a non-zero GMR error is a GP point (the oracle)
    assert len(r.gp_points) == int(np.sum(np.abs(r.gmr_error) > 0.0))
    mean, std = model.probe([1.0, 1.0, 0.3])
    assert mean == pytest.approx(0.3, abs=0.1) and std > 0


def test_changing_d_m_reuses_the_hierarchy_and_reselects_points(plane_model):
    model, _ = plane_model
    base = model.results
    d_m = float(np.quantile(np.abs(base.gmr_error), 0.5))
    cfg = base.config.replace("gp.d_m", d_m)
    seen = []
    r = model.compute(first_affected_stage(base, cfg, 0.2), cfg, 0.2, base=base,
                      on_stage=lambda n, _: seen.append(n))
    assert seen == ["gp", "surface"]
    assert r.hgmm is base.hgmm and r.gmr_error is base.gmr_error
    assert len(r.gp_points) == int(np.sum(np.abs(base.gmr_error) > d_m))
    assert len(r.gp_points) < len(base.gp_points)


def test_cancelled_run_stops_after_the_stage_in_progress(plane_model):
    model, _ = plane_model
    seen = []
    with pytest.raises(Cancelled):
        model.compute("gp", model.results.config, 0.2, on_stage=lambda n, _: seen.append(n),
                      cancelled=lambda: len(seen) > 0)
    assert seen == ["gp"]


def test_save_then_open_the_map_folder(plane_model, tmp_path):
    model, _ = plane_model
    model.save(tmp_path / "run" / "map")
    loaded = ViewerModel.open(tmp_path / "run", voxel_size=0.2)  # a 'gmmgp run' output
    assert loaded.results.hgmm.leaves.n_components == model.results.hgmm.leaves.n_components
    assert not loaded.can_refit
    q = np.array([1.0, 1.0, 0.1])
    np.testing.assert_allclose(loaded.probe(q), model.probe(q), rtol=1e-9, atol=1e-12)
    with pytest.raises(ViewerError, match="needs the scan.*saved map"):
        loaded.compute("hgmm", loaded.results.config, 0.2)
    r = loaded.compute("surface", loaded.results.config, 0.2)
    assert len(r.mesh.faces) > 0


def test_run_record_counts_and_the_fields_change_at_the_scan_points(plane_model):
    from gmmgp_app.viz.gui_tuning import field_change, run_record

    model, _ = plane_model
    base = model.results
    assert field_change(base, base) == 0.0
    first = run_record(None, base)
    assert first.field_change_rms is None
    assert (first.leaves, first.gp_points) == (base.hgmm.leaves.n_components,
                                               len(base.gp_points))
    cfg = base.config.replace("gp.d_m", float(np.quantile(np.abs(base.gmr_error), 0.5)))
    new = model.compute("gp", cfg, 0.2, base=base)
    rec = run_record(base, new)
    # oracle: both fields evaluated at every scan point (1500 < the subsample cap)
    p = base.scan.points
    ref = np.sqrt(np.mean((new.smap.predict(p)[0] - base.smap.predict(p)[0]) ** 2))
    assert rec.field_change_rms == pytest.approx(ref, rel=1e-12) and ref > 0
    assert rec.gp_points == len(new.gp_points) < first.gp_points
    assert f"GP pts {rec.gp_points}" in rec.label() and "mm rms" in rec.label()


def test_model_errors_name_the_problem_and_the_fix(tmp_path):
    with pytest.raises(ViewerError, match="does not exist; give a scan file, a map or run folder"):
        ViewerModel.open(tmp_path / "nope.ply")
    m = ViewerModel(_results(scan=_plane_scan(50)), "x")
    with pytest.raises(ViewerError, match="Cannot start a run at stage 'scan'"):
        m.compute("scan", MappingConfig(), 0.1)
    with pytest.raises(ViewerError, match="No field to probe yet"):
        m.probe([0, 0, 0])
    with pytest.raises(ViewerError, match="No map to save yet"):
        m.save(tmp_path / "map")


def test_cli_helpers_fail_in_one_line(tmp_path, monkeypatch):
    import argparse

    from gmmgp_app.viz import gui
    from gmmgp_app.viz.gui_script import load_script

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    if sys.platform.startswith("linux"):
        with pytest.raises(ViewerError, match="No display found.*xvfb-run"):
            gui.check_display()
    with pytest.raises(ViewerError, match="Expected --size like 1600x1000"):
        gui._parse_size("big")
    bad = tmp_path / "s.json"
    bad.write_text("{not json")
    with pytest.raises(ViewerError, match="Cannot read the script"):
        load_script(bad)
    bad.write_text('{"stage": "hgmm"}')
    with pytest.raises(ViewerError, match="Expected a JSON list of step objects"):
        load_script(bad)
    monkeypatch.setenv("DISPLAY", ":12345")
    p = argparse.ArgumentParser()
    gui.add_view_arguments(p)
    with pytest.raises(ViewerError, match="Expected --voxel-size between"):
        gui.open_view(p.parse_args([str(bad), "--voxel-size", "5"]), MappingConfig())


def test_compute_modules_never_import_the_gui():
    code = ("import sys, gmmgp_app as gm, gmmgp_app.pipeline, gmmgp_app.stages.gp, "
            "gmmgp_app.stages.surface, gmmgp_app.viz.gui_model, gmmgp_app.viz.gui_geometry\n"
            "bad = [m for m in sys.modules if m.startswith('open3d.visualization.gui')]\n"
            "print(bad); sys.exit(1 if bad else 0)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr


# --------------------------------------------------------------------------- the window
def _lock_owner_alive(num) -> bool:
    """Whether display :num is held by a running X server (a lock left by a killed one
    is stale: the new server replaces it)."""
    try:
        pid = int(Path(f"/tmp/.X{num}-lock").read_text().strip())
    except (OSError, ValueError):
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _start_xvfb(tmp_path):
    if not sys.platform.startswith("linux"):
        pytest.skip("the window test uses Xvfb (Linux only)")
    exe = shutil.which("Xvfb")
    if exe is None:
        pytest.skip("Xvfb is not installed (apt-get install xvfb)")
    for num in range(170, 200):
        if _lock_owner_alive(num):
            continue
        proc = subprocess.Popen([exe, f":{num}", "-screen", "0", "1600x1000x24", "-nolisten",
                                 "tcp"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        for _ in range(100):  # ready once the lock holds our server's pid
            try:
                if int(Path(f"/tmp/.X{num}-lock").read_text().strip()) == proc.pid and \
                        Path(f"/tmp/.X11-unix/X{num}").exists():
                    return proc, f":{num}"
            except (OSError, ValueError):
                pass
            if proc.poll() is not None:
                break
            time.sleep(0.1)
        _stop_xvfb(proc)
    pytest.fail("Xvfb is installed but did not start on any display :170-:199")


def _stop_xvfb(proc):
    """SIGTERM, so the server removes its lock and socket (SIGKILL left them behind)."""
    proc.terminate()
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


@pytest.fixture(scope="module")
def box_scan(tmp_path_factory):
    from gmmgp_app.synth import scan_scene
    from gmmgp_app.synth.io import save_scan_npz

    scan, _ = scan_scene("box", density=0.08)  # small: the app's runs take seconds
    return save_scan_npz(tmp_path_factory.mktemp("box") / "box.npz", scan.points, scan.origins)


def _png(path):
    from PIL import Image

    return np.asarray(Image.open(path).convert("RGB")).astype(np.int16)


def _run_quiet(cmd, env=None, timeout=300):
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
    noise = ("[Open3D", "Using 'soft'", "FEngine", "Vulkan", "Selected physical", "Backend f")
    err = "\n".join(ln for ln in r.stderr.splitlines() if not ln.startswith(noise))
    return r.returncode, err


_RENDER_STAGES = """
import json, sys
from gmmgp_app.viz.gui_model import ViewerModel, STAGES
from gmmgp_app.viz.gui_screenshot import render_png
from gmmgp_app.config import MappingConfig
out, todo = sys.argv[2], sys.argv[3:]
m = ViewerModel.open(sys.argv[1], MappingConfig().replace("gp.d_m", 0.05), voxel_size=0.2)
m.results = m.compute("prepare", m.results.config, 0.2)
pictures = {s: dict(stage=s) for s in STAGES}
pictures["hgmm_level2"] = dict(stage="hgmm", level=2)
pictures["gp_points_only"] = dict(stage="gp", layers=["gp_points"])
for name in todo:
    render_png(m, f"{out}/{name}.png", size=(320, 240), **pictures[name])
print(json.dumps({**m.results.counts(), "gp_n": len(m.results.gp_points)}))
"""


@pytest.mark.slow
def test_every_stage_is_drawn_and_differs_in_an_offscreen_render(tmp_path, box_scan):
    """What the 3D view draws, checked through one offscreen frame per stage (no window)."""
    # 320x240: on Mesa's CPU renderer a frame's cost grows with the lit triangles in view
    # and is ~7x lower at this size than at 640x480 (measured). Each frame takes seconds,
    # but now and then one rasterizer thread of llvmpipe spins on a frame for good: seen
    # twice in full-suite runs on 2026-11-23, both at hgmm_level2 (10 ellipsoids), one
    # of them 12 min at load 1 while the six frames before took 4 s (the cause inside
    # the renderer stack is not known, see viz/gui_screenshot.py). Such a process is
    # stopped after 240 s and the pictures it had not written are rendered by a fresh
    # process once; a picture that hangs in two processes fails the test.
    names = list(STAGES) + ["hgmm_level2", "gp_points_only"]
    for attempt in range(2):
        todo = [n for n in names if not (tmp_path / f"{n}.png").is_file()]
        try:
            code, err = _run_quiet([sys.executable, "-c", _RENDER_STAGES, str(box_scan),
                                    str(tmp_path), *todo], timeout=240)
            break
        except subprocess.TimeoutExpired:
            code, err = -1, f"rendering {todo} hung for 240 s (attempt {attempt + 1})"
    assert code == 0, err[-3000:]
    imgs = {n: _png(tmp_path / f"{n}.png") for n in names}
    for name, im in imgs.items():
        assert im.shape == (240, 320, 3), name
        assert im.std() > 3, f"{name}.png is blank"
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            frac = np.mean(np.any(imgs[a] != imgs[b], axis=2))
            assert frac > 0.005, f"{a}.png and {b}.png are (almost) the same"
    # GP points are drawn in red (0.85, 0.05, 0.05) on white, nothing else in that picture
    gp = imgs["gp_points_only"]
    red = (gp[..., 0] > 150) & (gp[..., 1] < 80) & (gp[..., 2] < 80)
    drawn = np.any(gp < 250, axis=2)
    assert red.sum() > 20 and red.sum() > 0.5 * drawn.sum()
    # (the surface coloured by std is not rendered here: that frame took over 3 min at
    # 320x240 on the busy machine, the grey one 4 s; see the report of issue 18)


@pytest.mark.slow
def test_view_screenshot_writes_a_png_and_exits(tmp_path, box_scan):
    """``gmmgp view SCAN --screenshot PNG``: maps the scan up to the stage, renders once."""
    xvfb, display = _start_xvfb(tmp_path)
    env = dict(os.environ, DISPLAY=display)
    env.pop("WAYLAND_DISPLAY", None)
    png = tmp_path / "shot" / "hgmm.png"
    try:
        code, err = _run_quiet([sys.executable, "-m", "gmmgp_app.viz.gui", str(box_scan),
                                "--stage", "hgmm", "--level", "1", "--size", "480x320",
                                "--screenshot", str(png)], env=env, timeout=900)
    finally:
        _stop_xvfb(xvfb)
    assert code == 0, err[-3000:]
    assert "wrote" in err and "computing from prepare to hgmm" in err
    im = _png(png)
    assert im.shape == (320, 480, 3) and im.std() > 3
    assert not list(png.parent.glob("*.part*"))  # nothing half-written left
    # without a display: the one-line error, exit code 2, no PNG
    env.pop("DISPLAY")
    png2 = tmp_path / "shot" / "none.png"
    r = subprocess.run([sys.executable, "-m", "gmmgp_app.cli", "view", str(box_scan),
                        "--screenshot", str(png2)], env=env, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2 and "No display found" in r.stderr
    assert "Traceback" not in r.stderr and not png2.exists()


@pytest.mark.slow
def test_app_steps_through_stages_and_reruns_under_xvfb(tmp_path, box_scan):
    """Open the box scan, show every stage, step HGMM levels, retune and re-run.

    Without 3D geometry (``--no-3d``): on Mesa's CPU renderer a frame of the scene
    sometimes takes minutes on a busy machine, and every step waits for the GUI main
    thread, which waits for the frame in flight. What the 3D view draws is checked
    offscreen (test above); here the controller and the panel, and which geometry the
    view would hold (``drawn``).
    """
    xvfb, display = _start_xvfb(tmp_path)
    out = tmp_path
    steps = [{"state": str(out / "s0.json")}]
    for s in STAGES:  # the HGMM stage opens on level 0
        steps += [{"stage": s}, {"state": str(out / f"stage_{s}.json")}]
    steps += [
        {"stage": "hgmm"}, {"level": 3}, {"state": str(out / "level3.json")},
        {"stage": "surface"}, {"colour_by_variance": True},
        {"probe": "center"}, {"state": str(out / "s1.json")},
        # c of the box's nodes is either ~0 or ~0.08: 0.1 stops the split at level 0
        {"threshold": 0.1}, {"d_m": 0.2}, {"run": True}, {"state": str(out / "s2.json")},
        # compare: the previous run's surface beside the new one
        {"layer": "compare", "on": True}, {"state": str(out / "cmp.json")},
        {"layer": "compare", "on": False},
        # a run superseded at once: its results must be dropped, the newer one shown
        {"d_m": 0.05, "run": True, "wait": False}, {"voxel": 0.25, "run": True},
        {"state": str(out / "s3.json")}, {"save": str(out / "saved" / "map")}, {"quit": True},
    ]
    (out / "steps.json").write_text(json.dumps(steps))
    env = dict(os.environ, DISPLAY=display)
    env.pop("WAYLAND_DISPLAY", None)
    try:
        code, err = _run_quiet([sys.executable, "-m", "gmmgp_app.viz.gui", str(box_scan),
                                "--size", "1200x800", "--voxel-size", "0.2", "--set",
                                "gp.d_m=0.05", "--no-3d", "--script", str(out / "steps.json")],
                               env=env, timeout=900)
    finally:
        _stop_xvfb(xvfb)
    assert code == 0, err[-3000:]
    s0, s1, s2, s3 = (json.loads((out / f"s{i}.json").read_text()) for i in range(4))
    assert s0["errors"] == [] and s3["errors"] == []

    # each stage shows its own layers and legend
    for s in STAGES:
        st = json.loads((out / f"stage_{s}.json").read_text())
        assert st["stage"] == s and st["layers"] == sorted(STAGE_LAYERS[s])
        assert set(st["drawn"]) >= set(STAGE_LAYERS[s]) - {"blocks", "gp_points", "segments"}
        # the colour bar (its last cell) fits the panel
        assert st["legend_bar_right"] <= st["panel_right"], (st["legend_bar_right"],
                                                             st["panel_right"])
    legends = {s: json.loads((out / f"stage_{s}.json").read_text())["legend"] for s in STAGES}
    assert legends["scan"].startswith("height") and legends["gmr"].startswith("GMR error")
    assert legends["hgmm"].startswith("complexity")

    # the panel shows the counts of the results it holds
    lv = s0["counts"]["levels"]
    assert f"leaves {s0['counts']['leaves']}" in s0["counts_label"]
    lv3 = json.loads((out / "level3.json").read_text())
    assert lv3["level_label"].startswith(f"level {min(3, lv - 1)} of {lv - 1}")
    assert "SDF" in s1["probe"] and "+-" in s1["probe"] and "|grad|" in s1["probe"]
    assert s1["legend"] == "predicted std (m)"
    assert s2["threshold"] == 0.1 and s2["counts"]["leaves"] != s0["counts"]["leaves"]
    assert s2["threshold_shown"] == pytest.approx(0.1)  # the value itself, not its log10
    assert f"leaves {s2['counts']['leaves']}" in s2["counts_label"]
    # one record per finished run: the first without a change, the re-run with one
    assert len(s0["runs"]) == 1 and s0["runs"][0]["field_change_rms"] is None
    assert len(s2["runs"]) == 2 and s2["runs"][1]["leaves"] == s2["counts"]["leaves"]
    assert s2["runs"][1]["field_change_rms"] > 0 and "run 2: c* 0.1" in s2["runs_label"]
    # the worker waited after each stage but the last (no 3D view here: drawn at once)
    assert [w[:2] for w in s2["frame_waits"]] == [["hgmm", "drawn"], ["gmr", "drawn"],
                                                  ["gp", "drawn"]]
    cmp = json.loads((out / "cmp.json").read_text())
    assert "compare" in cmp["layers"] and "compare" in cmp["drawn"]
    assert cmp["drawn"]["compare"][0] == "cmp_mesh"  # the surface stage: the previous mesh
    assert cmp["previous"]["leaves"] == s0["counts"]["leaves"] != s2["counts"]["leaves"]
    # the newer run's results are shown (whether the superseded run had a stage result
    # left to drop depends on timing: not asserted)
    assert s3["d_m"] == 0.05 and s3["generation"] == s2["generation"] + 2
    assert s3["counts"]["faces"] != s2["counts"]["faces"]
    assert (out / "saved" / "map" / "map.json").is_file()


def _until(model, start, cfg, last, base=None):
    """model.compute from ``start`` stopped after stage ``last`` (its results)."""
    got = {}

    def on_stage(n, r):
        got[n] = r
    try:
        model.compute(start, cfg, 0.2, base=base, on_stage=on_stage,
                      cancelled=lambda: last in got)
    except Cancelled:
        pass
    return got[last]


def test_threshold_refit_reuses_node_fits_and_equals_a_fresh_run():
    """After a split-threshold change the model refits only the HGMM nodes it never
    split before (its node-fit cache), with bitwise the hierarchy of a fresh model; the
    values resolved from the scan are taken again without measuring the scan."""
    from gmmgp_app.pipeline import resolve_config
    from gmmgp_app.synth import scan_scene

    scan, _ = scan_scene("box", density=0.05)  # at 0.08 both thresholds give 18 leaves
    cfg = MappingConfig()
    m = ViewerModel(StageResults(config=cfg, voxel_size=0.2, scan=scan), "box")
    m.results = _until(m, "prepare", cfg, "hgmm")
    first = m.hgmm_cache.misses
    assert first > 1 and m.hgmm_cache.hits == 0
    leaves = {}
    for t in (0.03, 0.003, 0.03):
        new_cfg = cfg.replace("hgmm.split_threshold", t)
        hits, misses = m.hgmm_cache.hits, m.hgmm_cache.misses
        r = _until(m, "hgmm", new_cfg, "hgmm", base=m.results)
        fresh = ViewerModel(StageResults(config=new_cfg, voxel_size=0.2, scan=scan), "box")
        f = _until(fresh, "prepare", new_cfg, "hgmm")
        for a, b in zip((r.hgmm.leaves.means, r.hgmm.leaves.covariances, r.hgmm.leaf_level),
                        (f.hgmm.leaves.means, f.hgmm.leaves.covariances, f.hgmm.leaf_level)):
            assert a.tobytes() == b.tobytes()
        assert m.hgmm_cache.hits > hits   # the first fit (at least) was reused
        if t == 0.03:
            assert m.hgmm_cache.misses == misses  # fewer splits: nothing to fit
        leaves[t] = r.hgmm.leaves.n_components
        # the resolved values: those of pipeline.resolve_config, in the run's summary
        run_cfg, record = resolve_config(new_cfg, scan)
        assert m._resolve(new_cfg, scan) == (run_cfg, record)
        assert r.summary["auto"]["gp.d_m"]["value"] == run_cfg.gp.d_m
    assert leaves[0.003] > leaves[0.03]


def test_lighting_switches_the_sun_on_from_the_cameras_side():
    """The app's light (window and screenshots): Open3DScene.set_lighting alone left the
    sun off (ambient only: surfaces dark grey), and its direction lit the faces turned
    away from the default camera. A stand-in scene records the calls."""
    from gmmgp_app.viz.gui_layers import set_lighting
    from gmmgp_app.viz.gui_screenshot import camera_pose

    calls = []

    class Inner:
        def set_sun_light(self, d, colour, intensity):
            calls.append(("sun", np.asarray(d, float), float(intensity)))

        def set_indirect_light_intensity(self, intensity):
            calls.append(("ambient", float(intensity)))

        def enable_sun_light(self, on):
            calls.append(("enable", on))

    class Scene:
        scene = Inner()

        def set_lighting(self, profile, d):
            calls.append(("profile", profile))

    class Rendering:
        class Open3DScene:
            class LightingProfile:
                NO_SHADOWS = "no shadows"

    from gmmgp_app.viz.gui_camera import default_view, sun_direction

    rng = np.random.default_rng(0)
    for hi in ([40, 8, 12], [3, 2, 2.5]):  # a street (viewed along x), an object (oblique)
        pts = rng.uniform([0, 0, 0], hi, size=(500, 3))
        view = default_view(pts)
        calls.clear()
        set_lighting(Scene(), Rendering, sun_direction(view))
        assert ("profile", "no shadows") in calls and ("enable", True) in calls
        sun = [c for c in calls if c[0] == "sun"][0]
        d = sun[1]
        assert sun[2] > 0 and abs(np.linalg.norm(d) - 1) < 1e-6
        ambient = [c[1] for c in calls if c[0] == "ambient"]
        assert ambient and 0 < ambient[0] < sun[2]     # the sun is the key light
        _, _, centre, eye = camera_pose(pts)
        to_eye = (eye - centre) / np.linalg.norm(eye - centre)
        assert to_eye @ -d > 0.5            # lit from the viewer's side
        assert np.array([0, -1.0, 0]) @ -d > 0 and np.array([0, 0, 1.0]) @ -d > 0  # side, ground


_RENDER_STREET = """
import sys
import numpy as np
from gmmgp_app.config import MappingConfig
from gmmgp_app.types import Scan, SurfaceMesh
from gmmgp_app.viz.gui_model import StageResults, ViewerModel
from gmmgp_app.viz.gui_screenshot import render_png

def plane(origin, u, v, normal, k=12):
    s, t = np.meshgrid(np.linspace(0, 1, k), np.linspace(0, 1, k))
    P = origin + s.reshape(-1, 1) * u + t.reshape(-1, 1) * v
    a = (np.arange(k - 1)[None, :] + k * np.arange(k - 1)[:, None]).reshape(-1)
    F = np.vstack([np.c_[a, a + 1, a + k], np.c_[a + 1, a + k + 1, a + k]])
    return P, F if np.dot(np.cross(u, v), normal) > 0 else F[:, ::-1]

X, Y, Z = np.eye(3)
L, W, H = 36.0, 16.0, 14.0
faces = {"road": plane(np.array([0, -W / 2, 0.0]), L * X, W * Y, Z),      # normals to the street
         "facade_py": plane(np.array([0, W / 2, 0.0]), L * X, H * Z, -Y),
         "facade_my": plane(np.array([0, -W / 2, 0.0]), L * X, H * Z, Y)}
scan = Scan(np.vstack([P for P, _ in faces.values()]))
for name, (P, F) in faces.items():
    mesh = SurfaceMesh(P, F.astype(np.int64), np.zeros(len(P)))
    m = ViewerModel(StageResults(MappingConfig(), 0.5, scan=scan, mesh=mesh), "street")
    render_png(m, f"{sys.argv[1]}/{name}.png", size=(240, 160), stage="surface")
"""


@pytest.mark.slow
def test_a_lit_street_is_neither_washed_out_nor_lit_from_the_wrong_side(tmp_path):
    """The road of a street (0.75 grey, as the app draws surfaces) renders mid-grey, not
    white, and the facade the sun faces (over the camera's shoulder, from -y:
    ``gui_camera.sun_direction``) is brighter than the one turned away. Before, Open3D's
    image-based light outshone the sun: road (242, 252, 255), sunlit facade 92, the
    other 236. One offscreen frame per face (the app's camera, lights and material)."""
    from gmmgp_app.viz.gui_camera import default_view, sun_direction

    xvfb, display = _start_xvfb(tmp_path)
    env = dict(os.environ, DISPLAY=display)
    env.pop("WAYLAND_DISPLAY", None)
    try:
        code, err = _run_quiet([sys.executable, "-c", _RENDER_STREET, str(tmp_path)], env=env,
                               timeout=240)
    finally:
        _stop_xvfb(xvfb)
    assert code == 0, err[-3000:]
    grey = {}
    for name in ("road", "facade_py", "facade_my"):
        im = _png(tmp_path / f"{name}.png")
        drawn = im[np.any(im < 250, axis=2)]
        assert len(drawn) > 500, f"{name}: {len(drawn)} pixels drawn"
        grey[name] = np.median(drawn, axis=0)
    # the light's geometry the pictures rely on: the sun lights the road and the facade
    # at +y (its street side faces -y), not the facade at -y
    street = np.array([[0, -8, 0], [36, 8, 14.0]])
    d = sun_direction(default_view(street))
    assert -d[2] > 0.3 and d[1] > 0.2                   # from above, from the -y side
    assert grey["road"].max() < 225, grey               # not washed out (was 255)
    assert grey["road"].min() > 120, grey               # nor dark
    assert np.ptp(grey["road"]) < 12, grey              # grey, not tinted (was 13 blue)
    assert grey["facade_py"].mean() > grey["facade_my"].mean() + 10, grey


def _street(n=4000, length=36.0, half_width=8.0, height=14.0, seed=0):
    """Points of a street along x: two facades at y = +-half_width and the road."""
    rng = np.random.default_rng(seed)
    k = n // 3
    x = rng.uniform(0, length, size=(3, k))
    left = np.column_stack([x[0], np.full(k, half_width), rng.uniform(0, height, k)])
    right = np.column_stack([x[1], np.full(k, -half_width), rng.uniform(0, height, k)])
    road = np.column_stack([x[2], rng.uniform(-half_width, half_width, k), np.zeros(k)])
    return np.vstack([left, right, road])


def test_default_view_looks_along_a_street_from_above_and_at_an_object_obliquely():
    """A street is seen along its long side from above its middle: each facade's street
    side faces the camera (the former view from -y saw the near facade from behind);
    an object keeps the oblique view; the compare copy stands across the view."""
    from gmmgp_app.viz.gui_camera import across_axis, default_view
    from gmmgp_app.viz.gui_tuning import compare_shift

    pts = _street()
    v = default_view(pts)
    assert v.along == 0 and across_axis(pts) == 1
    assert v.eye[0] < pts[:, 0].min()                 # behind the near end
    assert v.eye[2] > 14.0                            # above the facades
    assert -8.0 < v.eye[1] < 0.0                      # both facades from the street side
    fwd = (v.centre - v.eye) / v.distance
    assert fwd[0] > 0.8 and fwd[2] < -0.3 and 0 < fwd[1] < 0.15  # along x, looking down
    # the street along y: the same view turned
    vy = default_view(pts[:, [1, 0, 2]])
    assert vy.along == 1 and across_axis(pts[:, [1, 0, 2]]) == 0
    np.testing.assert_allclose(vy.eye[[1, 0, 2]], v.eye, atol=1e-9)
    sh = compare_shift(pts)
    assert sh[0] == 0 and sh[2] == 0 and sh[1] > np.ptp(pts[:, 1])  # beside, across the view
    both = np.vstack([pts, pts + sh])  # the compare layer: both framed, viewed as the street
    assert default_view(both).along is None and default_view(both, like=pts).along == 0
    vb = default_view(both, like=pts)
    assert vb.lo[1] < pts[:, 1].min() + 1 and vb.hi[1] > (pts + sh)[:, 1].max() - 1
    # a compact object (a bunny-sized blob): oblique from -y and above, as before
    blob = np.random.default_rng(1).normal(size=(2000, 3)) * [0.08, 0.06, 0.07]
    b = default_view(blob)
    assert b.along is None and across_axis(blob) == 0
    d = (b.eye - b.centre) / np.linalg.norm(b.eye - b.centre)
    np.testing.assert_allclose(d, np.array([0.25, -0.75, 0.55]) / np.linalg.norm(
        [0.25, -0.75, 0.55]), atol=1e-12)
    assert 0.2 < b.distance < 1.0  # framed at the object's size
    assert default_view(np.zeros((0, 3))).extent > 0  # nothing to frame: no crash


def test_default_view_of_y_up_data_is_the_z_up_view_turned():
    """Data whose up axis is y (the Stanford scan sets) is viewed as the same data with
    z up would be: eye, centre, up, framed box and sun turned by the same rotation;
    the bunny-sized blob is seen obliquely from above, not lying on its side."""
    from gmmgp_app.viz.gui_camera import default_view, sun_direction, up_frame

    rng = np.random.default_rng(2)
    for pts in (_street(), rng.normal(size=(2000, 3)) * [0.08, 0.06, 0.07]):
        for up in ((0.0, 1.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.0, -1.0)):
            M = up_frame(up).T                       # z-up data -> data with ``up`` up
            np.testing.assert_allclose(M @ [0.0, 0.0, 1.0], up, atol=1e-15)
            v, w = default_view(pts), default_view(pts @ M.T, up=up)
            assert w.along == v.along
            for a, b in ((w.eye, v.eye), (w.centre, v.centre), (w.up, v.up)):
                np.testing.assert_allclose(a, M @ b, atol=1e-9)
            corners = np.stack([v.lo, v.hi]) @ M.T
            np.testing.assert_allclose(w.lo, corners.min(0), atol=1e-9)
            np.testing.assert_allclose(w.hi, corners.max(0), atol=1e-9)
            np.testing.assert_allclose(sun_direction(w), M @ sun_direction(v), atol=1e-12)
    # z up given explicitly: the view as before, bit for bit
    pts = _street()
    a, b = default_view(pts), default_view(pts, up=(0, 0, 1))
    assert all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("lo", "hi", "eye",
                                                                       "centre", "up"))
    with pytest.raises(ValueError, match="up axis along x, y or z"):
        default_view(pts, up=(0.0, 0.6, 0.8))


def test_wait_for_frame_returns_when_drawn_cancelled_or_after_its_timeout():
    """The run's worker waits for the frame showing a stage; it never hangs."""
    import threading

    from gmmgp_app.viz.gui_model import wait_for_frame

    ev = threading.Event()
    threading.Timer(0.1, ev.set).start()
    t = time.monotonic()
    assert wait_for_frame(ev, timeout=10.0) == "drawn"
    assert 0.05 < time.monotonic() - t < 5.0
    ev = threading.Event()
    t = time.monotonic()
    assert wait_for_frame(ev, timeout=0.3) == "timeout"   # the frame never came
    assert 0.3 <= time.monotonic() - t < 5.0
    stop = threading.Event()
    threading.Timer(0.1, stop.set).start()
    t = time.monotonic()
    assert wait_for_frame(threading.Event(), stop.is_set, timeout=30.0) == "cancelled"
    assert time.monotonic() - t < 5.0                       # superseded: stops at once
    ev.set()
    assert wait_for_frame(ev, lambda: True, timeout=0.0) == "drawn"  # drawn beats the rest


def test_progress_reports_are_throttled_but_the_last_one_passes():
    from gmmgp_app.viz.gui_model import ProgressThrottle

    now = [0.0]
    th = ProgressThrottle(0.25, clock=lambda: now[0])
    shown = []
    for i in range(1, 101):  # 100 reports over 1 s
        now[0] = i * 0.01
        if th("surface", i / 100):
            shown.append(i)
    assert shown[0] == 1 and shown[-1] == 100 and 4 <= len(shown) <= 6
    assert th("gp", 0.5)  # each stage on its own


def test_gmr_colours_use_the_d_m_the_run_resolved():
    """With d_m "auto" the GMR error layer saturates at the d_m the run resolved from
    the scan (a TypeError comparing "auto" with a number broke the GMR stage)."""
    import dataclasses

    from gmmgp_app.config import concrete
    from gmmgp_app.viz.gui_layers import resolved_d_m
    from gmmgp_app.viz.gui_screenshot import SceneState

    cfg = MappingConfig()
    assert cfg.gp.d_m == "auto"
    r = StageResults(config=cfg, voxel_size=0.1, summary={"auto": {"gp.d_m": {"value": 0.042}}})
    assert resolved_d_m(r) == 0.042
    assert resolved_d_m(dataclasses.replace(r, summary={})) == concrete(cfg.gp).d_m
    assert resolved_d_m(dataclasses.replace(r, config=cfg.replace("gp.d_m", 0.02))) == 0.02
    pts = np.random.default_rng(0).uniform(size=(50, 3))
    data = type("Rows", (), {"points": pts})()
    r = dataclasses.replace(r, scan=Scan(pts, origins=np.zeros((50, 3))), data=data,
                            gmr_error=np.linspace(-0.1, 0.1, 50))
    key, build, _, legend = SceneState(ViewerModel(r, "x"), "gmr").layer_geometry("points")
    assert key[0] == "gmr" and legend[0] == "error" and legend[2] > 0
    assert len(build().points) == 50



def test_the_apps_first_run_builds_one_kd_tree_of_the_scan(count_scan_trees):
    """The app's run from 'prepare' shares one k-d tree of the scan between the scale
    measurement and the prepare stage, as build_map does, with the same training set."""
    import gmmgp_app as gm
    import gmmgp_app.pipeline as P
    from gmmgp_app.synth import scan_scene
    from gmmgp_app.viz.gui_model import Cancelled, StageResults, ViewerModel

    scan, _ = scan_scene("sphere", density=0.05, seed=0)
    built = count_scan_trees(scan.points)
    cfg = gm.MappingConfig()
    model = ViewerModel(StageResults(config=cfg, voxel_size=0.1, scan=scan))
    shown = []
    with pytest.raises(Cancelled):   # stopped once the prepare stage is shown
        model.compute("prepare", cfg, 0.1, on_stage=lambda st, r: shown.append(r),
                      cancelled=lambda: bool(shown))
    assert sum(built) == 1, built
    data = shown[0].data
    ref = gm.prepare(scan, P.resolve_config(cfg, scan)[0])
    for k in ("rows", "kinds", "points", "normals", "groups"):
        np.testing.assert_array_equal(getattr(data, k), getattr(ref, k))
