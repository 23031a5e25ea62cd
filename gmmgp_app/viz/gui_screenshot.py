"""Render what the desktop app shows to a PNG, without a window: ``gmmgp view --screenshot``.

One frame through Open3D's ``OffscreenRenderer`` (the same Filament renderer and the
same layers, materials and camera as the window's 3D view), written once: no event
loop, no swapchain, no frame to wait for. The tests check what is drawn through this
path, and the README screenshots are made with it.

Why not the window's own frames: with Mesa's CPU Vulkan driver (llvmpipe/lavapipe,
picked by Open3D's Filament when no GPU is found) one frame costs seconds to minutes of
rasterizer CPU, and the window draws one for every change while the GUI main thread
waits in ``FilamentRenderer::BeginFrame``; every posted callback (script steps, results)
queues behind it. Measured (one 640x480 offscreen frame of a sphere of 6240 triangles,
rasterizer CPU seconds; the wall time is 2-5x that on 2 cores at load 5-9):
no vertex colours, lit 1.3 s; random vertex colours, lit 1.4 s; uniform grey 0.75
(as the app's surface and grey points), lit 28 s, unlit 5.4 s; grey +- 0.004 jitter, lit
26 s; a smooth z gradient, lit 16 s; 360 triangles 0.2 s; 19 k triangles (no colours)
3.9 s; 6240 triangles at 320x240 0.17 s, at 1280x960 1.3 s. Threads (LP_NUM_THREADS
0/1/2/4) change nothing; hidden geometry costs nothing; the slow frames run on one
rasterizer thread, in JIT-compiled shader code. But the same content is not always
equally slow: the 360-triangle, 320x240, uncoloured frame that took 0.2 s took 30 s of
rasterizer CPU (90 s wall) in a later process, so the figures above are not a clean
function of the content; the cause inside the renderer stack was not found. Hence the
tests do not wait for the window's frames at all, and the offscreen frames they render
are small (320x240) with time limits that only guard against a hang.

The cause found (2026-11-23): lit meshes without texture coordinates. Open3D's lit
material samples its placeholder texture maps at the mesh's texture coordinates; without
any, the CPU renderer's frame cost varied and sometimes ran away. A frame of the demo's
lit HGMM ellipsoids that had run 9 min spent its time (perf, both rasterizer threads) in
one JIT-compiled fragment loop of texel gathers; the same grey lit sphere as above
(640x480) cost 1.1-1.9 s of rasterizer CPU per frame (both threads) without coordinates
and 0.2 s with all-zero or planar ones in the same sessions. The app's lit meshes (ellipsoids, surfaces,
probe) now carry zero coordinates (``gui_geometry._zero_uvs``); what is drawn does not
change.

Two more observations (2 cores, load 12-14), from before that fix: the compare view at the HGMM stage (two sets
of lit ellipsoids side by side) did not finish a frame in 15 min at 1280x800 on the demo,
nor in 8 min at 320x240 on a small plane, while one set alone took 3-5 s (so the tests and
the README draw the comparison at the GP stage, unlit points); and flushing denormals
(FTZ/DAZ set in the main thread before the renderer's threads start) changed nothing
(grey lit sphere, 640x480: 9.3 vs 9.7 s of rasterizer CPU).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import numpy as np

from .gui_layers import (LAYERS, STAGE_LAYERS, layer_geometry,  # noqa: F401
                         materials, scene_view, set_lighting)
from .gui_model import STAGES, ViewerError, ViewerModel

__all__ = ["STAGE_LAYERS", "materials", "camera_pose", "SceneState", "render_png",
           "screenshot_target"]

def camera_pose(points: np.ndarray):
    """(lo, hi, centre, eye) of the default view (:func:`gui_camera.default_view`)."""
    from .gui_camera import default_view

    v = default_view(points)
    return v.lo, v.hi, v.centre, v.eye


class SceneState:
    """What the 3D view shows (stage, level, colouring) for a model, without widgets.

    Duck-types the attributes ``ViewerApp._layer_geometry`` reads, so the offscreen
    render builds exactly the layers the window builds.
    """

    MAX_DRAWN_POINTS = 300_000

    def __init__(self, model: ViewerModel, stage: str, level: int = 0,
                 colour_by_variance: bool = False, layers=(), previous=None,
                 selected_segment=None):
        self.model = model
        self.stage = stage
        self.level = level
        self.colour_by_variance = colour_by_variance
        self.layers = set(layers)
        self.previous = previous
        self.selected_segment = selected_segment
        self._std_cache: dict = {}

    def _display_points(self, pts):
        if len(pts) <= self.MAX_DRAWN_POINTS:
            return np.arange(len(pts))
        return np.sort(np.random.default_rng(0).choice(len(pts), self.MAX_DRAWN_POINTS,
                                                       replace=False))

    def _predict_std_async(self, key, results, pts):
        # Offscreen there is no later frame: predict now, at the drawn points.
        field_ = results.smap if results.smap is not None else results.prior
        self._std_cache[key] = field_.predict(pts)[1]

    def layer_geometry(self, name):
        key, build, mat, leg = layer_geometry(self, name)
        if key is not None and key[0] == "grey" and self.colour_by_variance:
            # the std arrived synchronously above: build again with it
            key, build, mat, leg = layer_geometry(self, name)
        return key, build, mat, leg


def render_png(model: ViewerModel, path, size=(1600, 1000), stage: Optional[str] = None,
               level: int = 0, layers=None, colour_by_variance: bool = False,
               previous=None, segment: Optional[int] = None) -> Path:
    """Render one stage of ``model`` to a PNG at ``path`` (no window, no event loop).

    Parameters
    ----------
    model : ViewerModel
        With its results computed up to (at least) ``stage``.
    path : str or Path
    size : (width, height) in pixels
    stage : str, optional
        Default: the last stage with a result.
    level : int
        HGMM level of the ellipsoid layer.
    layers : iterable of str, optional
        Default: the stage's preset (:data:`STAGE_LAYERS`).
    colour_by_variance : bool
    previous : StageResults, optional
        A previous run drawn beside the current one (the "compare" layer, added).
    segment : int, optional
        A check result's change segment to select (drawn red, the camera on it).

    Returns
    -------
    Path of the PNG.
    """
    import open3d as o3d
    import open3d.visualization.rendering as rendering

    r = model.results
    if stage is None:
        stage = next(s for s in reversed(STAGES) if r.has(s))
    if stage not in STAGES:
        raise ViewerError(f"Unknown stage {stage!r}; expected one of {', '.join(STAGES)}.")
    if not r.has(stage):
        raise ViewerError(f"Nothing to show for stage {stage!r} yet; the results hold "
                          f"{', '.join(s for s in STAGES if r.has(s))}.")
    layers = set(STAGE_LAYERS[stage] if layers is None else layers)
    if previous is not None:
        layers.add("compare")
    if segment is not None:
        ck = r.check
        if ck is None or not (0 <= segment < len(ck.segments)):
            n = 0 if ck is None else len(ck.segments)
            raise ViewerError(f"Expected --segment between 1 and {n} (the check's change "
                              f"segments), found {segment + 1}.")
    state = SceneState(model, stage, level, colour_by_variance, layers, previous, segment)
    w, h = size
    ren = rendering.OffscreenRenderer(int(w), int(h))
    scene = ren.scene
    scene.set_background([1.0, 1.0, 1.0, 1.0])
    scene.show_axes(False)
    scene.view.set_post_processing(False)  # as the window: tone mapping shifts colour maps
    set_lighting(scene, rendering)
    mats = materials(rendering)
    for name in LAYERS:
        if name not in layers:
            continue
        key, build, mat, _ = state.layer_geometry(name)
        if key is None:
            continue
        geom = build()
        parts = geom if isinstance(geom, dict) else {name: geom}
        for gname, g in parts.items():
            scene.add_geometry(gname, g, mats[gname if mat is None else mat])
    v = scene_view(state)  # as the window's (ViewerApp.reset_camera)
    if segment is not None:
        from .gui_camera import default_view

        sg = r.check.segments[segment]
        pts = np.vstack([sg["bbox_min"], sg["bbox_max"]])
        pad = max(float(np.linalg.norm(pts[1] - pts[0])), 0.3)
        v = default_view(np.vstack([pts - pad, pts + pad]))
    if v is not None:
        from .gui_camera import sun_direction

        ext, dist = v.extent, v.distance
        ren.setup_camera(50.0, v.centre.astype(np.float32), v.eye.astype(np.float32),
                         v.up.astype(np.float32), max(1e-3 * dist, 1e-4), dist + 4.0 * ext)
        set_lighting(scene, rendering, sun_direction(v))
    img = ren.render_to_image()
    # remove the renderables before the renderer and its materials go: left to the
    # garbage collector's order, Filament sometimes destroyed a material still in use
    # and aborted the process ("destroying MaterialInstance ... still in use by
    # Renderable", once in a full test run)
    scene.clear_geometry()
    del scene, ren
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".part" + path.suffix)
    if not o3d.io.write_image(str(tmp), img):
        raise ViewerError(f"Could not write the screenshot '{path}'; check the folder is "
                          "writable and the name ends in .png.")
    tmp.replace(path)
    return path


def screenshot_target(model: ViewerModel, path, size=(1600, 1000), stage: Optional[str] = None,
                      level: int = 0, colour_by_variance: bool = False, log=None,
                      compare: Optional[dict] = None, segment: Optional[int] = None) -> Path:
    """Compute what ``model`` still lacks (a scan: every stage; a map: the surface; a
    tiled map: every tile), then render ``stage`` (default: the last one) to ``path``.

    With ``compare`` (settings, e.g. ``{"hgmm.split_threshold": 0.03}``) the model
    is computed twice, with its settings and then with these, and the first run is
    drawn beside the second (the app's compare mode); both runs' records are logged.
    """
    from .gui_model import first_affected_stage
    from .gui_tuning import run_record

    r = model.results
    t0 = time.perf_counter()
    if r.check is not None:
        stage = stage or "scan"
        if stage != "scan":
            raise ViewerError(f"'{model.source}' is a check result: it shows the scan's "
                              f"points coloured by z (stage 'scan'), not {stage!r}.")
        if compare:
            raise ViewerError("--compare needs a scan to map twice; a check result has "
                              "nothing to re-run.")
        out = render_png(model, path, size=size, stage="scan", segment=segment)
        if log:
            log(f"wrote {out} ({time.perf_counter() - t0:.1f} s)")
        return out
    if segment is not None:
        raise ViewerError("--segment selects a change segment of a check result "
                          "('gmmgp check ... --out DIR'); this target is not one.")
    stage = stage or "surface"
    if compare and not model.can_refit:
        raise ViewerError(f"--compare re-runs the map with other settings, which needs the "
                          f"scan; '{model.source}' is a saved map: open the scan.")
    if r.tiles is not None:
        if stage in ("scan", "prepare", "gmr"):
            raise ViewerError(f"'{model.source}' is a tiled map: show 'hgmm', 'gp' or "
                              "'surface' (its tiles hold no scan rows).")
        if log:
            log(f"loading {len(r.tiles.keys)} tiles ...")
        model.results = model.load_tiles(voxel_size=r.voxel_size)
        r = model.results
    previous = None
    # with --compare, at least up to the GMR: the runs' records then hold the field's change
    needed = stage if not compare or STAGES.index(stage) >= STAGES.index("gmr") else "gmr"
    if not r.has(needed):
        if needed != "scan":
            start = "prepare" if model.can_refit else "surface"
            if STAGES.index(needed) < STAGES.index(start):
                raise ViewerError(f"'{model.source}' is a saved map: stage {needed!r} needs the "
                                  "scan; open the scan, or show 'hgmm', 'gp' or 'surface'.")
            if log:
                log(f"computing from {start} to {needed} ...")
            model.results = _compute_until(model, start, needed)
    if compare:
        previous = model.results
        cfg = previous.config.replace(compare)
        start = first_affected_stage(previous, cfg, previous.voxel_size) or "surface"
        if STAGES.index(start) <= STAGES.index(needed):
            if log:
                log(f"computing again with {compare} from {start} to {needed} ...")
            model.results = _compute_until(model, start, needed, cfg=cfg)
        if log:
            for i, (a, b) in enumerate(((None, previous), (previous, model.results))):
                log(f"run {i + 1}: {run_record(a, b).label()}")
    out = render_png(model, path, size=size, stage=stage, level=level,
                     colour_by_variance=colour_by_variance, previous=previous)
    if log:
        log(f"wrote {out} ({time.perf_counter() - t0:.1f} s)")
    return out


def _compute_until(model: ViewerModel, start: str, last: str, cfg=None):
    """Run the stages from ``start`` through ``last`` only (not the ones after it)."""
    from .gui_model import Cancelled

    got = {}

    def on_stage(name, res):
        got["name"], got["results"] = name, res

    r = model.results
    try:
        return model.compute(start, r.config if cfg is None else cfg, r.voxel_size,
                             on_stage=on_stage,
                             cancelled=lambda: got.get("name") == last)
    except Cancelled:
        return got["results"]
