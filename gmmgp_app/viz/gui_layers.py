"""What the app's 3D view draws for each layer and stage, shared by the window
(:mod:`gmmgp_app.viz.gui`) and the offscreen render (:mod:`gmmgp_app.viz.gui_screenshot`).
No widgets here: the functions take the view's state (duck-typed) and return geometry."""

from __future__ import annotations

import numpy as np

from .gui_model import ViewerError

STAGE_LAYERS = {"scan": {"points"}, "prepare": {"points"}, "hgmm": {"points", "ellipsoids"},
                "gmr": {"points"}, "gp": {"points", "gp_points", "blocks"},
                "surface": {"mesh"}}
LAYERS = ("points", "ellipsoids", "gp_points", "blocks", "mesh")


def materials(rendering, scaling: float = 1.0) -> dict:
    """The material of each geometry name (window and offscreen renders share them)."""
    def mat(shader, **kw):
        m = rendering.MaterialRecord()
        m.shader = shader
        for k, v in kw.items():
            setattr(m, k, v)
        return m

    return {
        "points": mat("defaultUnlit", point_size=2.0 * scaling),
        "gp_points": mat("defaultUnlit", point_size=5.0 * scaling),
        "ellipsoids_leaf": mat("defaultLit"),
        "ellipsoids_split": mat("unlitLine", line_width=1.5 * scaling),
        "blocks": mat("unlitLine", line_width=1.0 * scaling),
        "mesh": mat("defaultLit"),
        "probe": mat("defaultLit", base_color=[1.0, 0.1, 0.1, 1.0]),
    }


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
    if name == "points":
        if stage == "prepare" and r.data is not None:
            rows, s = r.data.rows, r.data.spacing
            idx = view._display_points(rows)
            return (("rows", id(r.data)),
                    lambda: G.point_cloud(rows[idx, :3], G.row_colors(rows[idx, 3], s)[0]),
                    "points", ("d", -s, s))
        if stage == "gmr" and r.gmr_error is not None:
            col, lo, hi = G.error_colors(r.gmr_error, r.config.gp.d_m)
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
        col, lo, hi = G.scan_colors(pts[idx])
        return (("height", id(r.scan)), lambda: G.point_cloud(pts[idx], col), "points",
                ("height", lo, hi))
    if name == "ellipsoids":
        if r.hgmm is None:
            return None, None, None, None
        level = min(view.level, len(r.hgmm.levels) - 1)
        lv = r.hgmm.levels[level]

        def build():
            col = G.complexity_colors(lv.complexity)[0]
            split = np.asarray(lv.split, bool)
            m, g = lv.mixture, {}
            if (~split).any():
                g["ellipsoids_leaf"] = G.ellipsoid_mesh(
                    m.means[~split], m.covariances[~split], col[~split])
            if split.any():
                g["ellipsoids_split"] = G.ellipsoid_wireframe(
                    m.means[split], m.covariances[split], col[split])
            return g
        return ("ell", id(r.hgmm), level), build, None, ("c", 0.0, None)
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
