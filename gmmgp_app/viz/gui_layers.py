"""What the app's 3D view draws for each layer and stage, shared by the window
(:mod:`gmmgp_app.viz.gui`) and the offscreen render (:mod:`gmmgp_app.viz.gui_screenshot`).
No widgets here: the functions take the view's state (duck-typed) and return geometry."""

from __future__ import annotations

import numpy as np

from .gui_model import ViewerError

STAGE_LAYERS = {"scan": {"points", "segments"}, "prepare": {"points"},
                "hgmm": {"points", "ellipsoids"},
                "gmr": {"points"}, "gp": {"points", "gp_points", "blocks"},
                "surface": {"mesh"}}
#: "segments": a check result's change segments (boxes; the selected one red);
#: "compare": the previous run's leaves / GP points / surface beside the current ones.
LAYERS = ("points", "ellipsoids", "gp_points", "blocks", "mesh", "segments", "compare")
#: geometry names of each layer (a layer may be drawn as several geometries)
LAYER_PARTS = {"ellipsoids": ("ellipsoids_leaf", "ellipsoids_split"),
               "compare": ("compare_leaf", "compare_split", "compare_points", "compare_gp",
                           "compare_mesh")}


def layer_parts(layer) -> tuple:
    """The geometry names a layer may be drawn as."""
    return LAYER_PARTS.get(layer, (layer,))


def materials(rendering, scaling: float = 1.0) -> dict:
    """The material of each geometry name (window and offscreen renders share them)."""
    def mat(shader, **kw):
        m = rendering.MaterialRecord()
        m.shader = shader
        for k, v in kw.items():
            setattr(m, k, v)
        return m

    # Many lines (the GP blocks' 12 edges each, the split nodes' wireframes) are drawn
    # as the renderer's own 1-pixel lines ("defaultUnlit"), not as "unlitLine" wide
    # lines (a quad per segment): 1280x800 on the CPU renderer, demo scan, rasterizer
    # CPU per frame: the 58,595 GP blocks 17.3 s -> 1.3 s, the 187 split ellipsoids of
    # HGMM level 3 1.06 s -> 0.22 s (scripts/bench_scene_frames.py).
    return {
        "points": mat("defaultUnlit", point_size=2.0 * scaling),
        "gp_points": mat("defaultUnlit", point_size=5.0 * scaling),
        "ellipsoids_leaf": mat("defaultLit"),
        "ellipsoids_split": mat("defaultUnlit"),
        "blocks": mat("defaultUnlit"),
        "mesh": mat("defaultLit"),
        "probe": mat("defaultLit", base_color=[1.0, 0.1, 0.1, 1.0]),
        "segments": mat("unlitLine", line_width=2.5 * scaling),
        "compare_leaf": mat("defaultLit"),
        "compare_split": mat("defaultUnlit"),
        "compare_points": mat("defaultUnlit", point_size=2.0 * scaling),
        "compare_gp": mat("defaultUnlit", point_size=5.0 * scaling),
        "compare_mesh": mat("defaultLit"),
    }


#: Direction the sun's light travels before a scene is framed; once it is, the sun comes
#: from over the default camera's shoulder (``gui_camera.sun_direction``).
SUN_DIRECTION = (-0.3, 0.6, -0.75)
#: Sun intensity (lux, Filament's unit): the key light. A 0.75-grey face turned to it
#: renders ~160/255 from the sun alone (pixels are linear in the light: the frames are
#: drawn without post-processing; 96 at 60,000 lux, measured).
SUN_INTENSITY = 100000.0
#: Intensity of the image-based (ambient) light: a fill, about a quarter of Open3D's own
#: (~37,500, whose brightest direction, +y, lights a 0.75-grey face to 231/255 alone).
INDIRECT_INTENSITY = 10000.0


def set_lighting(open3d_scene, rendering, direction=SUN_DIRECTION) -> None:
    """Light an ``Open3DScene`` as the app does (window and offscreen frames).

    ``Open3DScene.set_lighting(NO_SHADOWS, direction)`` alone leaves the scene lit by
    the image-based (ambient) light only: the direction changed nothing in a render and
    lit surfaces came out dark grey (a 0.75-grey sphere: 118-173 of 255, the same
    pixels for opposite directions). The sun is switched on here explicitly; no
    shadow-map pass (it costs every frame on a CPU renderer and adds nothing to
    reading the map).

    The sun is the key light and the image-based light a weak fill. Open3D's image-based
    light is fixed to the world's axes and uneven (0.75-grey faces lit by it alone:
    +y 231, +z 189, -x 169, +x 106, -z 90, -y 50 of 255) and, at its own intensity,
    brighter than the sun was (at most 96): upward faces (a street's road) clipped to
    white and the sun's side of a street came out darker than the other side. Now a
    face turned to the sun is the brightest (~196 of 255: ~160 from the sun, the rest
    fill; nothing clips), the road of a street is mid-grey (~154), the facade on the
    sun's side (82) is brighter than the other (63), and faces away from the sun keep
    13-62 of fill. Medians of the drawn pixels: the demo street's surface 234 -> 149,
    the bunny's (upright) 141 -> 183."""
    d = np.asarray(direction, np.float32)
    d /= np.linalg.norm(d)
    open3d_scene.set_lighting(rendering.Open3DScene.LightingProfile.NO_SHADOWS, d)
    open3d_scene.scene.set_indirect_light_intensity(INDIRECT_INTENSITY)
    open3d_scene.scene.set_sun_light(d, np.ones(3, np.float32), SUN_INTENSITY)
    open3d_scene.scene.enable_sun_light(True)


def _hgmm_level_geometry(hgmm, level, shift=0.0, prefix="ellipsoids"):
    from . import gui_geometry as G

    lv = hgmm.levels[min(level, len(hgmm.levels) - 1)]
    col = G.complexity_colors(lv.complexity)[0]
    split = np.asarray(lv.split, bool)
    m, g = lv.mixture, {}
    means = m.means.copy()
    means[:, :3] += shift
    if (~split).any():
        g[f"{prefix}_leaf"] = G.ellipsoid_mesh(means[~split], m.covariances[~split],
                                               col[~split])
    if split.any():
        g[f"{prefix}_split"] = G.ellipsoid_wireframe(means[split], m.covariances[split],
                                                     col[split])
    return g


def resolved_d_m(results) -> float:
    """The d_m (m) a run used: the number set, or the value resolved from the scan for
    "auto" (its summary), else the urban default."""
    from ..config import concrete
    from .gui_tuning import resolved_setting

    v = resolved_setting(results, "gp.d_m")
    return v if np.isfinite(v) else float(concrete(results.config.gp).d_m)


def compare_scene_points(view):
    """The points the camera frames: the scan's, and their shifted copy when the
    previous run is drawn beside (None without a scan)."""
    r = view.model.results
    if r.scan is None or len(r.scan) == 0:
        return None
    pts = r.scan.points
    prev = getattr(view, "previous", None)
    if prev is None or "compare" not in getattr(view, "layers", ()):
        return pts
    from .gui_tuning import compare_shift

    return np.vstack([pts, pts + compare_shift(pts, up=getattr(view.model, "up", None))])


def scene_view(view):
    """The default camera (:func:`gui_camera.default_view`) of what ``view`` shows: its
    points and the compare copy framed, viewed as the scan alone (None without a scan)."""
    from .gui_camera import default_view

    pts = compare_scene_points(view)
    if pts is None:
        return None
    return default_view(pts, like=view.model.results.scan.points,
                        up=getattr(view.model, "up", None))


def _compare_geometry(view, r, stage):
    """The previous run (``view.previous``) beside the current one: its HGMM level,
    GP points or surface, shifted by :func:`gui_tuning.compare_shift`."""
    from . import gui_geometry as G
    from .gui_tuning import compare_shift

    prev = getattr(view, "previous", None)
    if prev is None or r.scan is None or len(r.scan) == 0:
        return None, None, None, None
    shift = compare_shift(r.scan.points, up=getattr(view.model, "up", None))
    sp = prev.scan.points if prev.scan is not None else np.zeros((0, 3))
    idx = view._display_points(sp)
    grey = lambda: G.point_cloud(sp[idx] + shift, np.full((len(idx), 3), 0.72))  # noqa: E731
    if stage == "hgmm" and prev.hgmm is not None:
        level = view.level
        # the nodes alone (two sets of lit ellipsoids side by side already stalled the
        # CPU renderer for minutes on the demo at 1280x800, grey points or not)
        return (("cmp_hgmm", id(prev.hgmm), level, tuple(shift)),
                lambda: _hgmm_level_geometry(prev.hgmm, level, shift, "compare"), None, None)
    if stage == "gp" and prev.gp_points is not None:
        gp = prev.gp_points + shift
        return (("cmp_gp", id(prev.gp_points), tuple(shift)),
                lambda: {"compare_points": grey(), "compare_gp": G.point_cloud(
                    gp, np.tile([0.85, 0.05, 0.05], (len(gp), 1)))}, None, None)
    if stage == "surface" and prev.mesh is not None and len(prev.mesh.faces):
        mesh = prev.mesh
        return (("cmp_mesh", id(mesh), tuple(shift)),
                lambda: {"compare_mesh": G.triangle_mesh(
                    mesh.vertices + shift, mesh.faces,
                    np.full((len(mesh.vertices), 3), 0.75))}, None, None)
    if len(sp):
        return (("cmp_scan", id(prev.scan), tuple(shift)),
                lambda: {"compare_points": grey()}, None, None)
    return None, None, None, None


def layer_geometry(view, name):
    """(key, build, material, legend) of a layer for the current state of ``view``
    (the window's ViewerApp or the offscreen SceneState: ``model``, ``stage``,
    ``level``, ``colour_by_variance``, ``_std_cache``, ``_display_points``,
    ``_predict_std_async``).

    ``key`` identifies what would be drawn, so an unchanged layer is not rebuilt;
    ``build()`` makes the geometry (or a dict name -> geometry); ``material`` None
    means "the material named like each part".
    """
    from . import gui_geometry as G

    r = view.model.results
    stage = view.stage or "scan"
    if name == "points" and r.check is not None and r.scan is not None:
        ck, pts = r.check, r.scan.points
        idx = view._display_points(pts)
        col, lo, hi = G.z_colors(ck.z[idx], ck.known[idx], ck.z_threshold)
        return (("z", id(ck)), lambda: G.point_cloud(pts[idx], col), "points", ("z", lo, hi))
    if name == "segments":
        ck = r.check
        if ck is None or not ck.segments:
            return None, None, "segments", None
        sel = getattr(view, "selected_segment", None)
        lo = np.array([s["bbox_min"] for s in ck.segments])
        hi = np.array([s["bbox_max"] for s in ck.segments])
        col = np.tile([0.1, 0.1, 0.1], (len(lo), 1))
        if sel is not None and 0 <= sel < len(lo):
            col[sel] = [0.9, 0.0, 0.0]
        pad = 0.02  # a box around the points, not through them
        return (("segments", id(ck), sel), lambda: G.aabb_boxes(lo - pad, hi + pad, col),
                "segments", None)
    if name == "compare":
        return _compare_geometry(view, r, stage)
    if name == "points":
        if stage == "prepare" and r.data is not None:
            rows, s = r.data.rows, r.data.spacing
            idx = view._display_points(rows)
            return (("rows", id(r.data)),
                    lambda: G.point_cloud(rows[idx, :3], G.row_colors(rows[idx, 3], s)[0]),
                    "points", ("d", -s, s))
        if stage == "gmr" and r.gmr_error is not None:
            col, lo, hi = G.error_colors(r.gmr_error, resolved_d_m(r))
            return (("gmr", id(r.gmr_error)), lambda: G.point_cloud(r.data.points, col),
                    "points", ("error", lo, hi))
        if r.scan is None:
            return None, None, "points", None
        pts = r.scan.points
        idx = view._display_points(pts)
        if view.colour_by_variance and (r.smap is not None or r.prior is not None):
            key = ("std", id(r))
            var = view._std_cache.get(key)
            if var is not None:
                col, lo, hi = G.std_colors(var)
                return key, lambda: G.point_cloud(pts[idx], col), "points", ("std", lo, hi)
            view._predict_std_async(key, r, pts[idx])  # grey until it arrives
        if stage in ("hgmm", "gp", "surface"):
            return (("grey", id(r.scan)),
                    lambda: G.point_cloud(pts[idx], np.full((len(idx), 3), 0.72)),
                    "points", None)
        col, lo, hi = G.scan_colors(pts[idx], getattr(view.model, "up", None))
        return (("height", id(r.scan)), lambda: G.point_cloud(pts[idx], col), "points",
                ("height", lo, hi))
    if name == "ellipsoids":
        if r.hgmm is None:
            return None, None, None, None
        level = min(view.level, len(r.hgmm.levels) - 1)
        hg = r.hgmm
        return (("ell", id(hg), level), lambda: _hgmm_level_geometry(hg, level), None,
                ("c", 0.0, None))
    if name == "gp_points":
        if r.gp_points is None or len(r.gp_points) == 0:
            return None, None, "gp_points", None
        gp = r.gp_points
        return (("gp", id(gp)),
                lambda: G.point_cloud(gp, np.tile([0.85, 0.05, 0.05], (len(gp), 1))),
                "gp_points", None)
    if name == "blocks":
        if r.gp is None:
            return None, None, "blocks", None
        grid = r.gp.grid
        return (("blocks", id(r.gp)),
                lambda: G.block_boxes(grid.centres, grid.block_size / 2), "blocks", None)
    if name == "mesh":
        if r.mesh is None or len(r.mesh.faces) == 0:
            return None, None, "mesh", None
        by_var = view.colour_by_variance
        col, lo, hi = G.std_colors(r.mesh.vertex_variance)
        if not by_var:
            col = np.full((len(r.mesh.vertices), 3), 0.75)
        mesh = r.mesh
        return (("mesh", id(mesh), by_var),
                lambda: G.triangle_mesh(mesh.vertices, mesh.faces, col), "mesh",
                ("std", lo, hi) if by_var else None)
    raise ViewerError(f"Unknown layer {name!r}; expected one of {', '.join(LAYERS)}.")
