"""Rerun recordings: every stage logged, read back with rerun's own reader.

Ground truth is the pipeline's own result objects (counts, levels, meshes) and
an independent reconstruction of the ellipsoids' covariance.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

rr = pytest.importorskip("rerun")
from rerun.chunk import RrdReader

import gmmgp_app as gm
from gmmgp_app.pipeline import StagePayload
from gmmgp_app.viz import rerun_observer as ro

COARSE = {"surface.voxel_size": 0.2}


# --------------------------------------------------------------------------- helpers
def _chunks(path):
    return RrdReader(path).stream().to_chunks()


def _entities(chunks) -> set:
    return {c.entity_path for c in chunks}


def _column(chunks, entity, suffix):
    """Rows of the component column ending with ``suffix`` logged to ``entity``."""
    out = []
    for c in chunks:
        if c.entity_path != entity:
            continue
        rb = c.to_record_batch()
        for name in rb.schema.names:
            if name.endswith(suffix):
                out += [(rb.column("stage")[i].as_py() if "stage" in rb.schema.names else None,
                         rb.column(name)[i].as_py()) for i in range(rb.num_rows)]
    return out


def _timelines(chunks, entity) -> set:
    return {t for c in chunks if c.entity_path == entity for t in c.timeline_names}


def _verify(path) -> subprocess.CompletedProcess:
    return subprocess.run([ro.rerun_executable(), "rrd", "verify", str(path)], check=False,
                          capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A ~3k point box scan (npz + reference mesh) and its config."""
    from gmmgp_app.synth import scan_scene
    from gmmgp_app.synth.io import save_mesh_ply, save_scan_npz

    d = tmp_path_factory.mktemp("tiny")
    scan, scene = scan_scene("box", density=0.02, seed=1)
    save_scan_npz(d / "scan.npz", scan.points, scan.origins, scan.labels)
    save_mesh_ply(d / "mesh.ply", scene)
    return {"dir": d, "scan": scan, "npz": d / "scan.npz", "mesh": d / "mesh.ply",
            "cfg": gm.MappingConfig().replace(COARSE)}


@pytest.fixture(scope="module")
def recorded(tiny):
    """One full recording (all six stages) of the tiny scan."""
    path = tiny["dir"] / "run.rrd"
    cfg = tiny["cfg"]
    obs = ro.RerunObserver(path, config=cfg)
    smap = gm.build_map(tiny["scan"], cfg, observer=obs)
    mesh = smap.extract_surface()
    obs.on_stage("surface", StagePayload({"gmmgp": mesh}, 0.5))
    obs.close()
    return {"path": path, "smap": smap, "mesh": mesh, "chunks": _chunks(path)}


# --------------------------------------------------------------------------- geometry
def test_ellipsoid_params_reconstruct_the_xyz_covariance():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(5, 4, 4))
    cov = a @ a.transpose(0, 2, 1) + 0.1 * np.eye(4)
    means = rng.normal(size=(5, 4))
    from scipy.spatial.transform import Rotation

    c, h, q = ro.ellipsoid_params(means, cov, n_sigma=2.0)
    R = Rotation.from_quat(q).as_matrix()
    rebuilt = R @ np.einsum("ki,ij->kij", (h / 2) ** 2, np.eye(3)) @ R.transpose(0, 2, 1)
    np.testing.assert_allclose(rebuilt, cov[:, :3, :3], rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(c, means[:, :3])
    np.testing.assert_allclose(np.linalg.det(R), 1.0)


def test_vertex_normals_of_a_flat_square_point_up():
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    np.testing.assert_allclose(ro._vertex_normals(v, f), np.tile([0, 0, 1.0], (4, 1)))


def test_scan_eye_looks_from_the_sensor_side():
    """A facade at y = 10 scanned from y = 0: the camera stands on the street side,
    above, and looks at the middle of the scan."""
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(0, 20, 500), np.full(500, 10.0), rng.uniform(0, 8, 500)]
    org = np.c_[rng.uniform(0, 20, 500), np.zeros(500), np.full(500, 2.0)]
    pos, target = ro.scan_eye(pts, org)
    np.testing.assert_allclose(target, [10.0, 10.0, 4.0], atol=0.2)
    assert pos[1] < target[1] - 5 and pos[2] > target[2] and abs(pos[0] - target[0]) < 0.5
    pos2, _ = ro.scan_eye(pts, org + [0.0, 20.0, 0.0])  # scanned from behind
    assert pos2[1] > target[1] + 5
    pos3, _ = ro.scan_eye(pts)  # no origins: from -y
    assert pos3[1] < target[1]
    import rerun.blueprint as rrb

    assert isinstance(ro.default_blueprint(eye=(pos, target)), rrb.Blueprint)


# --------------------------------------------------------------------------- recording
def test_recording_passes_rerun_rrd_verify(recorded):
    res = _verify(recorded["path"])
    assert res.returncode == 0, res.stdout + res.stderr


def test_every_stage_has_its_entity_paths(recorded):
    ents = _entities(recorded["chunks"])
    smap = recorded["smap"]
    want = {"/config", "/summary", "/world/scan", "/world/prepare/hits",
            "/world/prepare/virtual", "/world/hgmm/leaves", "/world/gmr/error",
            "/world/gp/points", "/world/gp/blocks", "/world/surface/gmmgp",
            "/metrics/counts/scan_points", "/metrics/counts/gp_points",
            "/metrics/counts/hgmm_leaves", "/metrics/gmr_rms_error_at_hits"}
    want |= {f"/metrics/seconds/{s}" for s in ("prepare", "hgmm", "gmr", "gp", "surface")}
    for k, lv in enumerate(smap.hgmm.levels):
        if lv.split.any():
            want.add(f"/world/hgmm/level_{k}/split")
        if (~lv.split).any():
            want.add(f"/world/hgmm/level_{k}/leaf")
    assert want <= ents, sorted(want - ents)


def test_timelines_stage_and_level(recorded):
    ch = recorded["chunks"]
    stage_of = {e: s for e, s in [("/world/scan", 0), ("/world/prepare/hits", 1),
                                  ("/world/hgmm/leaves", 2), ("/world/gmr/error", 3),
                                  ("/world/gp/points", 4), ("/world/surface/gmmgp", 5)]}
    for ent, step in stage_of.items():
        assert _timelines(ch, ent) == {"stage"}, ent
        stages = {s for s, _ in _column(ch, ent, "")}
        assert stages == {step}, (ent, stages)
    # HGMM levels are on the 'level' timeline only, level k at k.
    for c in ch:
        if c.entity_path.startswith("/world/hgmm/level_"):
            assert c.timeline_names == ["level"]
            k = int(c.entity_path.split("level_")[1].split("/")[0])
            levels = c.to_record_batch().column("level").to_pylist()
            assert set(levels) <= {k, k + 1}  # data at k, its Clear at k + 1
    assert _timelines(ch, "/config") == set()  # static


def test_counts_read_back_match_the_pipeline(recorded):
    ch, smap, mesh = recorded["chunks"], recorded["smap"], recorded["mesh"]

    def scalar(name):
        vals = _column(ch, f"/metrics/counts/{name}", "Scalars:scalars")
        assert len(vals) == 1, (name, vals)
        return vals[0][1][0]

    assert scalar("scan_points") == len(recorded_scan_points(smap, ch))
    assert scalar("gp_points") == len(smap.gp_points)
    assert scalar("hgmm_leaves") == smap.hgmm.leaves.n_components
    assert scalar("hgmm_levels") == len(smap.hgmm.levels)
    assert scalar("gp_blocks") == smap.gp.grid.n_blocks
    assert scalar("vertices_gmmgp") == len(mesh.vertices)
    # Instance counts of the logged geometry.
    centers = _column(ch, "/world/hgmm/leaves", "Ellipsoids3D:centers")
    assert len(centers[0][1]) == smap.hgmm.leaves.n_components
    for k, lv in enumerate(smap.hgmm.levels):
        if lv.split.any():
            got = _column(ch, f"/world/hgmm/level_{k}/split", "Ellipsoids3D:centers")
            assert len(got[0][1]) == int(lv.split.sum())
    gp_pts = _column(ch, "/world/gp/points", "Points3D:positions")
    np.testing.assert_allclose(np.array(gp_pts[0][1]), smap.gp_points, atol=1e-4)
    verts = _column(ch, "/world/surface/gmmgp", "Mesh3D:vertex_positions")
    assert len(verts[0][1]) == len(mesh.vertices)
    var = _column(ch, "/world/surface/gmmgp", "vertex_variance")
    np.testing.assert_allclose(np.ravel(var[0][1]), mesh.vertex_variance, rtol=1e-6)


def test_config_panel_shows_the_resolved_values_and_their_reasons(recorded):
    """The panel shows the configuration the map used ('auto' replaced by the values
    chosen from the scan), each chosen value with its reason (issue 15)."""
    smap = recorded["smap"]
    docs = _column(recorded["chunks"], "/config", "TextDocument:text")
    text = docs[-1][1]
    text = text[0] if isinstance(text, list) else text
    auto = {k: v for k, v in smap.summary["auto"].items()
            if isinstance(v, dict) and "value" in v and v.get("auto")}
    assert auto, "the tiny config leaves some fields 'auto'"
    assert '"auto"' not in text.split("```toml", 1)[1]
    for key, v in auto.items():
        assert f"| {key}" in text and v["reason"] in text
    assert f"d_m = {smap.config.gp.d_m!r}" in text or str(smap.config.gp.d_m) in text


def recorded_scan_points(smap, ch):
    return _column(ch, "/world/scan", "Points3D:positions")[0][1]


def test_gmr_error_colours_follow_the_error(recorded):
    ch = recorded["chunks"]
    err = np.ravel(_column(ch, "/world/gmr/error", "error")[0][1])
    cols = np.array(_column(ch, "/world/gmr/error", "Points3D:colors")[0][1], dtype=np.uint32)
    red = (cols >> 24) & 0xFF
    green = (cols >> 16) & 0xFF
    small, large = err < 0.005, err > 0.1  # 0.1 m = 5 d_m: saturated red
    if small.any() and large.any():
        assert np.mean(green[small]) > np.mean(green[large])
        assert np.mean(red[large]) > np.mean(red[small])


# --------------------------------------------------------------------------- killed run
@pytest.mark.slow
def test_killed_run_keeps_the_stages_logged_so_far(tiny, tmp_path):
    script = tmp_path / "killme.py"
    rrd = tmp_path / "killed.rrd"
    script.write_text(
        "import sys, time\n"
        "import gmmgp_app as gm\n"
        "from gmmgp_app.datasets import read_scan\n"
        "from gmmgp_app.viz.rerun_observer import RerunObserver\n"
        "cfg = gm.MappingConfig()\n"
        "obs = RerunObserver(sys.argv[2], config=cfg)\n"
        "class Stop:\n"
        "    def on_stage(self, name, payload):\n"
        "        obs.on_stage(name, payload)\n"
        "        if name == 'hgmm':\n"
        "            print('LOGGED hgmm', flush=True)\n"
        "            time.sleep(300)\n"
        "gm.build_map(read_scan(sys.argv[1]), cfg, observer=Stop())\n")
    proc = subprocess.Popen([sys.executable, str(script), str(tiny["npz"]), str(rrd)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert line.strip() == "LOGGED hgmm", proc.stderr.read() if proc.poll() else line
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(30)
    assert proc.returncode == -signal.SIGKILL
    with pytest.warns(Warning, match="no footer"):
        ents = _entities(_chunks(rrd))
    assert {"/world/scan", "/world/prepare/virtual", "/world/hgmm/leaves",
            "/metrics/seconds/hgmm", "/config"} <= ents
    assert not any(e.startswith(("/world/gmr", "/world/gp")) for e in ents)
    # The footer is missing until repaired; the repaired file verifies.
    assert _verify(rrd).returncode != 0
    fixed = ro.repair_recording(rrd, tmp_path / "fixed.rrd")
    res = _verify(fixed)
    assert res.returncode == 0, res.stderr
    assert {"/world/hgmm/leaves"} <= _entities(_chunks(fixed))


# --------------------------------------------------------------------------- CLI run
def test_cli_run_writes_a_recording(tiny, tmp_path):
    from gmmgp_app.cli import main

    rrd = tmp_path / "cli.rrd"
    code = main(["-q", "run", str(tiny["npz"]), "--out", str(tmp_path / "out"), "--rrd",
                 str(rrd), "--no-mesh"])
    assert code == 0
    ents = _entities(_chunks(rrd))
    assert {"/world/scan", "/world/hgmm/leaves", "/world/gp/points", "/config"} <= ents
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    n = _column(_chunks(rrd), "/metrics/counts/gp_points", "Scalars:scalars")[0][1][0]
    assert n == summary["counts"]["gmr"]["gp_points"]


# --------------------------------------------------------------------------- serve / spawn
def test_local_server_listens_on_loopback_only_and_receives_data():
    psutil = pytest.importorskip("psutil")
    url, proc = ro.start_local_server()
    try:
        port = int(url.rsplit(":", 1)[1].split("/")[0])
        conns = [c for c in psutil.Process(proc.pid).net_connections(kind="inet")
                 if c.status == psutil.CONN_LISTEN]
        assert conns, "the server listens on nothing"
        assert {c.laddr.ip for c in conns} == {"127.0.0.1"}
        assert {c.laddr.port for c in conns} == {port}
        rec = rr.RecordingStream("gmmgp_test")
        rec.connect_grpc(url)
        rec.log("p", rr.Points3D([[0, 0, 0]]))
        rec.flush(timeout_sec=10)
        rec.disconnect()
        assert proc.poll() is None
    finally:
        proc.kill()
        proc.wait(10)


def test_observer_serve_streams_to_the_server(tmp_path):
    obs = ro.RerunObserver(tmp_path / "s.rrd", serve=True, config=gm.MappingConfig())
    try:
        assert obs.urls and obs.urls[0].startswith("rerun+http://127.0.0.1:")
        obs.close()
        assert "/config" in _entities(_chunks(tmp_path / "s.rrd"))
    finally:
        for p in obs.processes:
            p.kill()
            p.wait(10)


def test_bad_rerun_executable_is_reported(monkeypatch, tmp_path):
    monkeypatch.setenv("RERUN_CLI_PATH", str(tmp_path / "nope"))
    with pytest.raises(ro.RerunError, match="RERUN_CLI_PATH points to .* not a file"):
        ro.start_local_server()


def test_repair_of_a_missing_file_is_reported(tmp_path):
    with pytest.raises(ro.RerunError, match="Could not repair recording"):
        ro.repair_recording(tmp_path / "missing.rrd", tmp_path / "out.rrd")


# --------------------------------------------------------------------------- screenshots
def _not_blank(png: Path) -> None:
    from PIL import Image

    img = np.asarray(Image.open(png).convert("RGB"), dtype=np.float64)
    h, w, _ = img.shape
    assert h >= 400 and w >= 600
    # The four 3D views fill the left three quarters above the time panel: they must
    # show more than a background and a grid (many distinct colours, real contrast).
    views = img[int(0.06 * h):int(0.9 * h), :int(0.74 * w)]
    q = (views // 8).astype(np.int64)
    n_colours = len(np.unique(q[..., 0] * 1024 + q[..., 1] * 32 + q[..., 2]))
    assert n_colours > 200, n_colours
    assert views.std() > 15, views.std()


def _skip_without_renderer(res: subprocess.CompletedProcess) -> None:
    text = res.stderr + res.stdout
    if "No graphics adapter" in text or "adapter" in text and res.returncode != 0:
        pytest.skip("no Vulkan/GL adapter for the headless viewer (install "
                    "mesa-vulkan-drivers for a CPU renderer)")


@pytest.mark.slow
def test_headless_cli_screenshot_is_not_blank(recorded, tmp_path):
    png = tmp_path / "shot.png"
    # --window-size: without it the harness starts from an unbounded size and wgpu
    # refuses the view textures ("main target label is invalid"). --bind/--port 0:
    # the viewer's own gRPC server stays on loopback and on a free port.
    cmd = [ro.rerun_executable(), str(recorded["path"]), "--headless", "--window-size",
           "1280x720", "--bind", "127.0.0.1", "--port", "0", "--screenshot-to", str(png)]
    # The CLI shoots the first painted frames, racing the loading of the views: on a
    # loaded machine a frame may still be empty, so allow a few attempts
    # (ro.screenshot waits for the data instead).
    failures = []
    for _ in range(3):
        res = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=180,
                             env=ro._viewer_env())
        _skip_without_renderer(res)
        assert res.returncode == 0, res.stderr[-2000:]
        assert "Validation Error" not in res.stderr
        try:
            _not_blank(png)
            return
        except AssertionError as exc:
            failures.append(str(exc))
    pytest.fail(f"every headless CLI screenshot was blank: {failures}")


@pytest.mark.slow
def test_screenshot_helper_waits_for_the_data(recorded, tmp_path):
    try:
        png = ro.screenshot(recorded["path"], tmp_path / "full.png", window_size=(1280, 720),
                            settle=1.0)
    except ro.RerunError as exc:
        pytest.skip(f"headless viewer unavailable: {exc}")
    _not_blank(png)


# --------------------------------------------------------------------------- sweep
def test_parse_values_validates_every_value():
    from gmmgp_app.config import ConfigError
    from gmmgp_app.sweep import SweepError, parse_values

    assert parse_values("hgmm.split_threshold", "0.005, 0.01,0.02") == [0.005, 0.01, 0.02]
    assert parse_values("hgmm.n_children", "4,8") == [4, 8]
    with pytest.raises(SweepError, match="Expected --values as a comma separated list"):
        parse_values("hgmm.split_threshold", " , ")
    with pytest.raises(ConfigError, match="nosuch"):
        parse_values("hgmm.nosuch", "1,2")
    with pytest.raises(ConfigError, match="split_threshold"):
        parse_values("hgmm.split_threshold", "0.01,abc")


def test_run_sweep_rejects_no_values(tiny):
    from gmmgp_app.sweep import SweepError, run_sweep

    with pytest.raises(SweepError, match="at least one value"):
        run_sweep(tiny["scan"], "gp.d_m", [])


@pytest.mark.slow
def test_sweep_records_one_step_per_value(tiny, tmp_path):
    import argparse

    from gmmgp_app.evaluation import Reference
    from gmmgp_app.commands.sweep import add_sweep_arguments
    from gmmgp_app.commands.sweep import run as cmd_sweep

    p = argparse.ArgumentParser()
    add_sweep_arguments(p)
    rrd = tmp_path / "sweep.rrd"
    # d_m = 0 trains on every hit point, 1 m on none (no GP stage at all).
    args = p.parse_args([str(tiny["npz"]), "--param", "gp.d_m", "--values", "0.0,0.02,1.0",
                         "--rrd", str(rrd), "--reference", str(tiny["mesh"]),
                         "--set", "surface.voxel_size=0.2"])
    args.quiet = True
    assert cmd_sweep(args) == 0
    table = json.loads((tmp_path / "sweep.json").read_text())
    rows = table["rows"]
    assert [r["value"] for r in rows] == [0.0, 0.02, 1.0]
    assert rows[0]["gp_points"] > rows[1]["gp_points"] > rows[2]["gp_points"] == 0
    assert all(np.isfinite(r["rmse_sdf"]) and r["surface_rmse"] >= 0 for r in rows)
    # GMR alone (no GP) at d_m = 1 m: its surface RMSE against the reference mesh,
    # recomputed independently from the mesh of a map built without the sweep.
    ref = Reference.load(tiny["mesh"])
    cfg = gm.MappingConfig().replace({**COARSE, "gp.d_m": 1.0})
    mesh = gm.build_map(tiny["scan"], cfg).extract_surface()
    assert rows[2]["vertices"] == len(mesh.vertices)
    np.testing.assert_allclose(rows[2]["surface_rmse"],
                               np.sqrt(np.mean(ref.sdf(mesh.vertices + tiny["scan"].offset) ** 2)), rtol=1e-9)

    assert _verify(rrd).returncode == 0
    ch = _chunks(rrd)
    gp = _column(ch, "/sweep/metrics/gp_points", "Scalars:scalars")
    assert [v[0] for _, v in gp] == [r["gp_points"] for r in rows]
    assert _timelines(ch, "/sweep/metrics/gp_points") == {"sweep"}
    assert {"sweep", "stage"} <= _timelines(ch, "/world/hgmm/leaves")
    sweeps = [c.to_record_batch().column("sweep").to_pylist() for c in ch
              if c.entity_path == "/world/hgmm/leaves"]
    assert sorted(s for x in sweeps for s in x) == [0, 1, 2]
    # The GP of the last value is absent: its step clears the previous one.
    clears = [c for c in ch if c.entity_path == "/world" and "sweep" in c.timeline_names]
    assert sorted(s for c in clears for s in c.to_record_batch().column("sweep").to_pylist()) \
        == [0, 1, 2]


# --------------------------------------------------------------------------- up axis
def _logged_up_axis(path) -> int:
    """The axis (0, 1, 2) the ViewCoordinates logged at /world name Up (rerun's ViewDir.Up
    = 1), read back from the file."""
    rows = [v for _, v in _column(_chunks(path), "/world", "ViewCoordinates:xyz")]
    assert len(rows) == 1, rows
    dirs = rows[0][0]
    return dirs.index(1)


@pytest.mark.parametrize("up, axis", [(None, 2), ((0.0, 1.0, 0.0), 1)])
def test_recording_stands_the_views_on_the_scans_up_axis(tmp_path, up, axis):
    """A y-up scan (a Stanford set) is recorded with y as the views' up axis, z-up data
    with z: the .rrd opens upright."""
    rng = np.random.default_rng(2)
    scan = gm.Scan(points=rng.normal(size=(200, 3)), up=up)
    path = tmp_path / "up.rrd"
    obs = ro.RerunObserver(path)
    obs.on_stage("scan", StagePayload(scan, 0.0))
    obs.close()
    assert _logged_up_axis(path) == axis


def test_view_coordinates_of_every_up_axis_are_right_handed_with_that_axis_up():
    for axis in range(3):
        for sign in (1.0, -1.0):
            up = np.zeros(3)
            up[axis] = sign
            dirs = [d.value for d in ro.view_coordinates(up).coordinates]
            # ViewDir: Up 1, Down 2, Right 3, Left 4, Forward 5, Back 6
            assert dirs[axis] == (1 if sign > 0 else 2)


def test_scan_eye_of_a_y_up_object_looks_from_above_along_y():
    """A y-up bunny-like blob: the camera is raised along +y, not +z."""
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(500, 3)) * [0.05, 0.08, 0.04]
    pos, target = ro.scan_eye(pts, up=(0.0, 1.0, 0.0))
    pos_z, target_z = ro.scan_eye(pts)
    assert pos[1] > target[1] + 0.01
    np.testing.assert_allclose(target, target_z)
    assert pos_z[2] > target_z[2] + 0.01           # z-up data: raised along z, as before
