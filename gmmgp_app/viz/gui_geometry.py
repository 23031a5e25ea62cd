"""Open3D geometry for the desktop app: points, merged ellipsoids, block boxes, meshes.

Only ``open3d.geometry`` is used here (no windows), so these builders can be
tested without a display. Every builder returns one geometry per layer: the
renderer draws a single merged mesh of thousands of ellipsoids far faster than
thousands of small meshes.
"""

from __future__ import annotations

import functools

import numpy as np

from .rerun_observer import C_MAX, ERROR_SATURATION_DM, ellipsoid_params

__all__ = ["colormap", "colorbar_rgb", "point_cloud", "ellipsoid_mesh", "ellipsoid_wireframe",
           "block_boxes", "triangle_mesh", "scan_colors", "row_colors", "error_colors",
           "complexity_colors", "std_colors", "z_colors", "aabb_boxes", "probe_marker",
           "LEGENDS"]

#: Colour map and value range of each colouring: (title, colour map, lo, hi, scale note).
LEGENDS = {
    "height": ("height (m)", "turbo"),
    "d": ("signed distance d of rows (m)", "coolwarm"),
    "error": ("GMR error |m(x)| at hits (m)", "RdYlGn_r"),
    "c": ("complexity c (sqrt scale)", "plasma"),
    "std": ("predicted std (m)", "viridis"),
    "z": ("check z = d / sqrt(s^2 + noise^2)", "coolwarm"),
}


def colormap(t: np.ndarray, name: str) -> np.ndarray:
    """(N, 3) float64 RGB in [0, 1] of values ``t`` in [0, 1] on a matplotlib colour map."""
    import matplotlib

    return matplotlib.colormaps[name](np.clip(np.nan_to_num(np.asarray(t, float)), 0, 1))[:, :3]


def colorbar_rgb(name: str, width: int = 256, height: int = 14) -> np.ndarray:
    """(height, width, 3) uint8 image of a horizontal colour bar, low values on the left."""
    row = (colormap(np.linspace(0, 1, width), name) * 255 + 0.5).astype(np.uint8)
    return np.ascontiguousarray(np.broadcast_to(row[None], (height, width, 3)))


# --------------------------------------------------------------------------- colourings
def scan_colors(points: np.ndarray, up=None):
    """Height colours; returns (colours (N,3), lo, hi) with lo/hi the 2-98 % range of
    the height: z, or the coordinate along ``up`` (3,), the data's up axis."""
    u = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=np.float64)
    z = points[:, 2] if np.array_equal(u, [0.0, 0.0, 1.0]) else np.asarray(points) @ u
    lo, hi = (np.percentile(z, [2, 98]) if len(z) else (0.0, 1.0))
    hi = max(hi, lo + 1e-6)
    return colormap((z - lo) / (hi - lo), "turbo"), float(lo), float(hi)


def row_colors(d: np.ndarray, spacing: float):
    """Training rows by their distance d in [-s, s] (blue inside, red outside)."""
    return colormap(0.5 + 0.5 * d / max(spacing, 1e-12), "coolwarm"), -spacing, spacing


def error_colors(error: np.ndarray, d_m: float):
    """Hit points by |m(x)|, saturating at ERROR_SATURATION_DM * d_m (as the rerun log)."""
    hi = ERROR_SATURATION_DM * max(d_m, 1e-6)
    return colormap(np.abs(error) / hi, "RdYlGn_r"), 0.0, hi


def complexity_colors(c: np.ndarray):
    """Nodes by c on a sqrt scale from 0 to C_MAX (the isotropic 4D maximum)."""
    return colormap(np.sqrt(np.clip(c, 0, None) / C_MAX), "plasma"), 0.0, C_MAX


def std_colors(variance: np.ndarray, vmax=None):
    """Predicted standard deviation, 0 .. vmax (default: 98th percentile)."""
    std = np.sqrt(np.maximum(np.asarray(variance, float), 0))
    if vmax is None:
        vmax = float(np.quantile(std, 0.98)) if len(std) else 1.0
    vmax = max(vmax, 1e-12)
    return colormap(std / vmax, "viridis"), 0.0, vmax


def z_colors(z: np.ndarray, known: np.ndarray, z_threshold: float):
    """Check points by z on coolwarm from -2 to +2 thresholds (blue: behind the map's
    surface, red: in front); points where the map knows no surface are grey.
    Returns (colours, lo, hi)."""
    hi = 2.0 * max(float(z_threshold), 1e-6)
    col = colormap(0.5 + 0.5 * np.nan_to_num(np.asarray(z, float)) / hi, "coolwarm")
    col[~np.asarray(known, bool)] = 0.8
    return col, -hi, hi


# --------------------------------------------------------------------------- geometry
def point_cloud(points: np.ndarray, colors: np.ndarray):
    """An ``open3d.geometry.PointCloud`` with per-point colours (N, 3) in [0, 1]."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, float)))
    pc.colors = o3d.utility.Vector3dVector(np.asarray(colors, float))
    return pc


@functools.lru_cache(maxsize=4)
def _unit_sphere(resolution: int):
    """Vertices (V,3), triangles (F,3) and unique edges (E,2) of a unit sphere, built once."""
    import open3d as o3d

    s = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=resolution)
    v = np.asarray(s.vertices).copy()
    f = np.asarray(s.triangles).copy()
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    return v, f, np.unique(e, axis=0)


def _transformed_spheres(means, covariances, n_sigma, resolution):
    """Unit-sphere vertices mapped onto each Gaussian's n-sigma ellipsoid: (K, V, 3)."""
    from scipy.spatial.transform import Rotation

    centres, half, quats = ellipsoid_params(means, covariances, n_sigma)
    v, f, e = _unit_sphere(resolution)
    rot = Rotation.from_quat(quats).as_matrix() if len(quats) else np.zeros((0, 3, 3))
    # x = R diag(half) u + centre for each unit vertex u.
    verts = np.einsum("kij,kj,vj->kvi", rot, half, v) + centres[:, None, :]
    return verts, f, e


def ellipsoid_mesh(means, covariances, colors, n_sigma: float = 2.0, resolution: int = 8):
    """All ellipsoids merged into one shaded ``TriangleMesh``.

    Parameters
    ----------
    means : (K, D) with D >= 3
    covariances : (K, D, D); the xyz block sets the shape
    colors : (K, 3) in [0, 1], one per ellipsoid
    n_sigma : float
        Half-axis length in standard deviations.
    resolution : int
        Sphere tessellation (Open3D's ``create_sphere`` resolution).
    """
    import open3d as o3d

    verts, f, _ = _transformed_spheres(means, covariances, n_sigma, resolution)
    k, nv = verts.shape[:2]
    faces = (f[None] + (np.arange(k) * nv)[:, None, None]).reshape(-1, 3)
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts.reshape(-1, 3)),
                                  o3d.utility.Vector3iVector(faces.astype(np.int32)))
    m.vertex_colors = o3d.utility.Vector3dVector(np.repeat(np.asarray(colors, float), nv, 0))
    m.compute_vertex_normals()
    _zero_uvs(m)
    return m


def probe_marker(xyz, radius: float):
    """The lit sphere marking a probed point: radius ``radius`` (m) around ``xyz`` (3,)."""
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_sphere(radius=float(radius), resolution=10)
    m.translate(np.asarray(xyz, dtype=np.float64).reshape(3))
    m.compute_vertex_normals()
    _zero_uvs(m)
    return m


def _zero_uvs(mesh) -> None:
    """Give a mesh texture coordinates (all zero) before it is drawn lit.

    The lit material samples its (1x1 placeholder) texture maps at the mesh's
    texture coordinates; a mesh without any made Mesa's CPU renderer spend a varying,
    sometimes unbounded, time in the fragment shader's texture fetches: a grey lit
    sphere of 6240 triangles at 640x480 cost 1.1-1.9 s of rasterizer CPU per frame
    without coordinates and 0.2 s with zero (or planar) ones in the same sessions
    (scripts/bench_render_frames.py, UVS=none|zero|planar), and a stalled frame of lit
    ellipsoids (9 min, both rasterizer threads busy) was spent in one JIT-compiled
    loop of texel gathers. What is drawn does not change (the maps are uniform)."""
    import open3d as o3d

    mesh.triangle_uvs = o3d.utility.Vector2dVector(np.zeros((3 * len(mesh.triangles), 2)))


def ellipsoid_wireframe(means, covariances, colors, n_sigma: float = 2.0, resolution: int = 6):
    """All ellipsoids as one ``LineSet`` (the sphere's edges), one colour per ellipsoid."""
    import open3d as o3d

    verts, _, e = _transformed_spheres(means, covariances, n_sigma, resolution)
    k, nv = verts.shape[:2]
    lines = (e[None] + (np.arange(k) * nv)[:, None, None]).reshape(-1, 2)
    ls = o3d.geometry.LineSet(o3d.utility.Vector3dVector(verts.reshape(-1, 3)),
                              o3d.utility.Vector2iVector(lines.astype(np.int32)))
    ls.colors = o3d.utility.Vector3dVector(np.repeat(np.asarray(colors, float), len(e), 0))
    return ls


_BOX_CORNERS = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
_BOX_EDGES = np.array([[a, b] for a in range(8) for b in range(a + 1, 8)
                       if np.sum(_BOX_CORNERS[a] != _BOX_CORNERS[b]) == 1])


def block_boxes(centres: np.ndarray, half_edge: float, color=(0.35, 0.35, 0.35)):
    """Axis-aligned cubes (12 edges each) as one ``LineSet``."""
    import open3d as o3d

    centres = np.asarray(centres, float).reshape(-1, 3)
    pts = (centres[:, None, :] + half_edge * _BOX_CORNERS[None]).reshape(-1, 3)
    lines = (_BOX_EDGES[None] + (np.arange(len(centres)) * 8)[:, None, None]).reshape(-1, 2)
    ls = o3d.geometry.LineSet(o3d.utility.Vector3dVector(pts),
                              o3d.utility.Vector2iVector(lines.astype(np.int32)))
    ls.paint_uniform_color(color)
    return ls


def aabb_boxes(lo, hi, colors):
    """Axis-aligned boxes from corners ``lo``, ``hi`` (K, 3) as one ``LineSet``, one
    colour (K, 3) per box."""
    import open3d as o3d

    lo, hi = np.asarray(lo, float).reshape(-1, 3), np.asarray(hi, float).reshape(-1, 3)
    c, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
    pts = (c[:, None, :] + h[:, None, :] * _BOX_CORNERS[None]).reshape(-1, 3)
    lines = (_BOX_EDGES[None] + (np.arange(len(c)) * 8)[:, None, None]).reshape(-1, 2)
    ls = o3d.geometry.LineSet(o3d.utility.Vector3dVector(pts),
                              o3d.utility.Vector2iVector(lines.astype(np.int32)))
    ls.colors = o3d.utility.Vector3dVector(np.repeat(np.asarray(colors, float).reshape(-1, 3),
                                                     len(_BOX_EDGES), 0))
    return ls


def triangle_mesh(vertices, faces, colors):
    """A shaded ``TriangleMesh`` with per-vertex colours (V, 3) in [0, 1]."""
    import open3d as o3d

    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(vertices, float)),
                                  o3d.utility.Vector3iVector(np.asarray(faces, np.int32)))
    m.vertex_colors = o3d.utility.Vector3dVector(np.asarray(colors, float))
    m.compute_vertex_normals()
    _zero_uvs(m)
    return m
