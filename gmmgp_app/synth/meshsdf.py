"""Exact float64 signed distance from points to a closed triangle mesh.

Distance: the closest point on each candidate triangle by the standard
Voronoi-region tests (Ericson, *Real-Time Collision Detection*, 5.1.5), which
also say *which feature* (face, edge or vertex) is closest.

Sign: the angle-weighted pseudo-normal of that closest feature (Baerentzen &
Aanaes, "Signed distance computation using the angle weighted pseudonormal",
IEEE TVCG 2005): the face normal for a face, the sum of the two adjacent face
normals for an edge, the incidence-angle weighted sum of the face normals for a
vertex. For a closed, consistently oriented 2-manifold the sign of
``(p - c) . n_pseudo`` is the sign of the signed distance, exactly, with no
ray-parity or winding-number sum over all triangles. It needs a manifold mesh,
which is why :class:`MeshDistance` checks every edge on construction. Points
exactly on the surface get distance 0 (sign +).

Pruning: a uniform grid of cells over the mesh bounding box, every triangle
listed in each cell its bounding box overlaps. A query visits Chebyshev rings
of cells around (the projection onto the grid box of) the query point and
stops when no cell outside the visited block can be closer than the best
triangle found. The lower bound uses ``|p - x|^2 >= |p - q|^2 + |q - x|^2``,
which holds for ``q`` the projection of ``p`` on the (convex) grid box and any
``x`` in it.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

__all__ = ["MeshError", "MeshDistance", "mesh_signed_distance", "edge_topology"]


class MeshError(ValueError):
    """A mesh is not what the signed distance needs (closed, oriented, manifold)."""


# ---------------------------------------------------------------------------
# topology and pseudo-normals


def edge_topology(faces: np.ndarray):
    """Pair every directed half-edge of a triangle mesh with its opposite.

    Parameters
    ----------
    faces : (F, 3) int64

    Returns
    -------
    opposite_face : (F, 3) int64
        For edge ``e`` of face ``f`` (edge 0: v0->v1, 1: v1->v2, 2: v2->v0), the
        face holding the reversed half-edge, or -1 if there is none.
    n_bad : int
        Number of undirected edges not shared by exactly two faces with
        opposite orientation (0 for a closed, oriented 2-manifold).
    """
    faces = np.asarray(faces, dtype=np.int64)
    nf = len(faces)
    a = faces.reshape(-1)
    b = faces[:, [1, 2, 0]].reshape(-1)
    nv = int(faces.max()) + 1 if nf else 0
    key = a * nv + b
    rkey = b * nv + a
    order = np.argsort(key, kind="stable")
    skey = key[order]
    dup_directed = int(np.count_nonzero(skey[1:] == skey[:-1]))
    pos = np.searchsorted(skey, rkey)
    pos = np.minimum(pos, len(skey) - 1)
    found = skey[pos] == rkey
    opp = np.full(3 * nf, -1, dtype=np.int64)
    opp[found] = order[pos[found]] // 3
    n_unpaired = int(np.count_nonzero(~found))
    return opp.reshape(nf, 3), n_unpaired + dup_directed


def _pseudo_normals(v: np.ndarray, f: np.ndarray, opp: np.ndarray):
    """Face unit normals (F,3), edge pseudo-normals (F,3,3), vertex pseudo-normals (V,3)."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    n = np.cross(b - a, c - a)
    area2 = np.linalg.norm(n, axis=1)
    fn = n / area2[:, None]
    en = fn[:, None, :] + fn[opp]  # edge e of face f: this face + its neighbour
    vn = np.zeros_like(v)
    corners = (a, b, c)
    for i in range(3):
        e1 = corners[(i + 1) % 3] - corners[i]
        e2 = corners[(i + 2) % 3] - corners[i]
        cosang = np.einsum("ij,ij->i", e1, e2) / (
            np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1))
        ang = np.arccos(np.clip(cosang, -1.0, 1.0))
        np.add.at(vn, f[:, i], ang[:, None] * fn)
    return fn, en, vn


# ---------------------------------------------------------------------------
# numba kernels


@nb.njit(cache=True)
def _closest_on_triangle(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """Closest point on triangle abc to p and its feature.

    Returns (qx, qy, qz, region) with region 0 = face, 1 = edge ab, 2 = edge bc,
    3 = edge ca, 4 = vertex a, 5 = vertex b, 6 = vertex c.
    """
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        return ax, ay, az, 4
    bpx, bpy, bpz = px - bx, py - by, pz - bz
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0.0 and d4 <= d3:
        return bx, by, bz, 5
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        t = d1 / (d1 - d3)
        return ax + t * abx, ay + t * aby, az + t * abz, 1
    cpx, cpy, cpz = px - cx, py - cy, pz - cz
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0.0 and d5 <= d6:
        return cx, cy, cz, 6
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        t = d2 / (d2 - d6)
        return ax + t * acx, ay + t * acy, az + t * acz, 3
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return bx + t * (cx - bx), by + t * (cy - by), bz + t * (cz - bz), 2
    denom = 1.0 / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    return (ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w, 0)


@nb.njit(cache=True)
def _bin_triangles(v, f, lo, h, dims):
    """CSR lists of the triangles whose bounding box overlaps each grid cell."""
    nx, ny, nz = dims[0], dims[1], dims[2]
    nf = f.shape[0]
    ranges = np.empty((nf, 6), dtype=np.int64)
    counts = np.zeros(nx * ny * nz + 1, dtype=np.int64)
    for t in range(nf):
        for ax in range(3):
            mn = min(v[f[t, 0], ax], v[f[t, 1], ax], v[f[t, 2], ax])
            mx = max(v[f[t, 0], ax], v[f[t, 1], ax], v[f[t, 2], ax])
            i0 = int(math.floor((mn - lo[ax]) / h))
            i1 = int(math.floor((mx - lo[ax]) / h))
            i0 = min(max(i0, 0), dims[ax] - 1)
            i1 = min(max(i1, 0), dims[ax] - 1)
            ranges[t, 2 * ax] = i0
            ranges[t, 2 * ax + 1] = i1
        for i in range(ranges[t, 0], ranges[t, 1] + 1):
            for j in range(ranges[t, 2], ranges[t, 3] + 1):
                for k in range(ranges[t, 4], ranges[t, 5] + 1):
                    counts[(i * ny + j) * nz + k + 1] += 1
    start = np.cumsum(counts)
    fill = start[:-1].copy()
    items = np.empty(start[-1], dtype=np.int64)
    for t in range(nf):
        for i in range(ranges[t, 0], ranges[t, 1] + 1):
            for j in range(ranges[t, 2], ranges[t, 3] + 1):
                for k in range(ranges[t, 4], ranges[t, 5] + 1):
                    c = (i * ny + j) * nz + k
                    items[fill[c]] = t
                    fill[c] += 1
    return start, items


@nb.njit(cache=True)
def _visit_cell(c, start, items, v, f, sph, px, py, pz, best):
    """Test the triangles of cell c; best = [d2, tri, region, qx, qy, qz] updated in place."""
    for s in range(start[c], start[c + 1]):
        t = items[s]
        # bounding-sphere rejection before the exact test
        sx, sy, sz = px - sph[t, 0], py - sph[t, 1], pz - sph[t, 2]
        dc = math.sqrt(sx * sx + sy * sy + sz * sz) - sph[t, 3]
        if dc > 0.0 and dc * dc >= best[0]:
            continue
        a = f[t, 0]
        b = f[t, 1]
        cc = f[t, 2]
        qx, qy, qz, reg = _closest_on_triangle(
            px, py, pz, v[a, 0], v[a, 1], v[a, 2], v[b, 0], v[b, 1], v[b, 2],
            v[cc, 0], v[cc, 1], v[cc, 2])
        dx, dy, dz = px - qx, py - qy, pz - qz
        d2 = dx * dx + dy * dy + dz * dz
        if d2 < best[0]:
            best[0] = d2
            best[1] = t
            best[2] = reg
            best[3] = qx
            best[4] = qy
            best[5] = qz


@nb.njit(cache=True)
def _cell_d2(i, j, k, lo, h, px, py, pz):
    """Squared distance from p to the box of cell (i, j, k)."""
    d2 = 0.0
    x0 = lo[0] + i * h
    if px < x0:
        d2 += (x0 - px) ** 2
    elif px > x0 + h:
        d2 += (px - x0 - h) ** 2
    y0 = lo[1] + j * h
    if py < y0:
        d2 += (y0 - py) ** 2
    elif py > y0 + h:
        d2 += (py - y0 - h) ** 2
    z0 = lo[2] + k * h
    if pz < z0:
        d2 += (z0 - pz) ** 2
    elif pz > z0 + h:
        d2 += (pz - z0 - h) ** 2
    return d2


@nb.njit(cache=True)
def _try_cell(i, j, k, ny, nz, start, items, v, f, sph, lo, h, px, py, pz, best):
    c = (i * ny + j) * nz + k
    if start[c] == start[c + 1]:
        return
    if _cell_d2(i, j, k, lo, h, px, py, pz) >= best[0]:
        return
    _visit_cell(c, start, items, v, f, sph, px, py, pz, best)


@nb.njit(cache=True, parallel=True)
def _query(p, v, f, fn, en, vn, sph, start, items, lo, h, dims, out_d, out_tri, out_reg):
    nx, ny, nz = dims[0], dims[1], dims[2]
    hi0 = lo[0] + nx * h
    hi1 = lo[1] + ny * h
    hi2 = lo[2] + nz * h
    for n in nb.prange(p.shape[0]):
        px, py, pz = p[n, 0], p[n, 1], p[n, 2]
        # projection q of p onto the grid box
        qx = min(max(px, lo[0]), hi0)
        qy = min(max(py, lo[1]), hi1)
        qz = min(max(pz, lo[2]), hi2)
        dpq2 = (px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2
        ci = min(max(int(math.floor((qx - lo[0]) / h)), 0), nx - 1)
        cj = min(max(int(math.floor((qy - lo[1]) / h)), 0), ny - 1)
        ck = min(max(int(math.floor((qz - lo[2]) / h)), 0), nz - 1)
        best = np.empty(6)
        best[0] = np.inf
        best[1] = -1.0
        r = 0
        while True:
            i0, i1 = ci - r, ci + r
            j0, j1 = cj - r, cj + r
            k0, k1 = ck - r, ck + r
            for i in range(max(i0, 0), min(i1, nx - 1) + 1):
                for j in range(max(j0, 0), min(j1, ny - 1) + 1):
                    on_side = i == i0 or i == i1 or j == j0 or j == j1
                    if on_side:
                        for k in range(max(k0, 0), min(k1, nz - 1) + 1):
                            _try_cell(i, j, k, ny, nz, start, items, v, f, sph, lo, h,
                                      px, py, pz, best)
                    else:
                        if k0 >= 0:
                            _try_cell(i, j, k0, ny, nz, start, items, v, f, sph, lo, h,
                                      px, py, pz, best)
                        if k1 <= nz - 1 and k1 != k0:
                            _try_cell(i, j, k1, ny, nz, start, items, v, f, sph, lo, h,
                                      px, py, pz, best)
            # distance from q to the part of the grid outside the visited block
            gap = np.inf
            if i0 > 0:
                gap = min(gap, qx - (lo[0] + i0 * h))
            if i1 < nx - 1:
                gap = min(gap, lo[0] + (i1 + 1) * h - qx)
            if j0 > 0:
                gap = min(gap, qy - (lo[1] + j0 * h))
            if j1 < ny - 1:
                gap = min(gap, lo[1] + (j1 + 1) * h - qy)
            if k0 > 0:
                gap = min(gap, qz - (lo[2] + k0 * h))
            if k1 < nz - 1:
                gap = min(gap, lo[2] + (k1 + 1) * h - qz)
            if gap == np.inf or dpq2 + gap * gap >= best[0]:
                break
            r += 1
        t = int(best[1])
        reg = int(best[2])
        if reg == 0:
            nxn, nyn, nzn = fn[t, 0], fn[t, 1], fn[t, 2]
        elif reg <= 3:
            nxn, nyn, nzn = en[t, reg - 1, 0], en[t, reg - 1, 1], en[t, reg - 1, 2]
        else:
            vi = f[t, reg - 4]
            nxn, nyn, nzn = vn[vi, 0], vn[vi, 1], vn[vi, 2]
        dot = (px - best[3]) * nxn + (py - best[4]) * nyn + (pz - best[5]) * nzn
        d = math.sqrt(best[0])
        out_d[n] = -d if dot < 0.0 else d
        out_tri[n] = t
        out_reg[n] = reg


# ---------------------------------------------------------------------------
# public API


def triangle_arrays(vertices, faces, error=MeshError):
    """Contiguous float64 vertices (V, 3) and int64 faces (F >= 1, 3) indexing them.

    Raises ``error`` (a ValueError subclass) naming the bad shape or index range.
    """
    v = np.ascontiguousarray(np.asarray(vertices, dtype=np.float64))
    f = np.ascontiguousarray(np.asarray(faces, dtype=np.int64))
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise error(f"Expected vertices (V, 3) and faces (F, 3) with F >= 1, found "
                    f"{v.shape} and {f.shape}; pass a triangle mesh.")
    if f.min() < 0 or f.max() >= len(v):
        raise error(f"Expected face indices in [0, {len(v) - 1}], found [{f.min()}, "
                    f"{f.max()}]; the faces do not match the vertices.")
    return v, f


class MeshDistance:
    """Signed distance to a closed, outward-oriented triangle mesh (free space > 0).

    Build once (pseudo-normals and the cell grid), query many times.

    Parameters
    ----------
    vertices : (V, 3) float64
    faces : (F, 3) int64
        A closed 2-manifold with outward (counter-clockwise seen from outside)
        faces and no degenerate triangles.
    cell_size : float, optional
        Edge of the pruning grid cells in metres. Default: six times the
        square root of the mean triangle area, capped so the grid has at most
        4M cells.

    Raises
    ------
    MeshError
        If the shapes are wrong, a triangle is degenerate, or an edge is not
        shared by exactly two faces with opposite orientation.
    """

    def __init__(self, vertices, faces, cell_size: float | None = None):
        v, f = triangle_arrays(vertices, faces)
        if not np.all(np.isfinite(v)):
            raise MeshError("Expected finite vertex coordinates, found NaN or inf; "
                            "clean the mesh first.")
        area2 = np.linalg.norm(
            np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
        if np.any(area2 <= 0.0):
            raise MeshError(
                f"Expected non-degenerate triangles, found {int(np.sum(area2 <= 0))} with zero "
                "area; remove them before computing signed distances.")
        opp, n_bad = edge_topology(f)
        if n_bad:
            raise MeshError(
                f"Expected a closed oriented 2-manifold (every edge in exactly two faces with "
                f"opposite orientation), found {n_bad} bad edges; the pseudo-normal sign "
                "needs a watertight mesh.")
        self.vertices, self.faces = v, f
        self.face_normals, self.edge_normals, self.vertex_normals = _pseudo_normals(v, f, opp)
        lo = v.min(axis=0)
        ext = np.maximum(v.max(axis=0) - lo, 1e-9)
        if cell_size is None:
            # about 36 triangles of mean area per planar cell cross-section: small
            # enough to prune near the surface, large enough that far queries do not
            # spend their time walking empty cells (measured on the street and sphere)
            cell_size = 6.0 * float(np.sqrt(0.5 * area2.mean()))
            cell_size = max(cell_size, float(np.cbrt(np.prod(ext) / 4.0e6)))
        if not (cell_size > 0 and math.isfinite(cell_size)):
            raise MeshError(f"Expected cell_size > 0 m, found {cell_size!r}; pass a positive size.")
        h = float(cell_size)
        dims = np.maximum(np.ceil(ext / h).astype(np.int64), 1)
        # pad by half a cell so the box strictly contains the mesh
        self._lo = lo - 0.5 * h
        self._dims = dims + 1
        self._h = h
        self._start, self._items = _bin_triangles(v, f, self._lo, h, self._dims)
        # triangle bounding spheres (centroid, largest centroid-vertex distance), padded
        # so that rounding can never reject the true closest triangle
        cen = v[f].mean(axis=1)
        rad = np.linalg.norm(v[f] - cen[:, None, :], axis=2).max(axis=1)
        self._spheres = np.ascontiguousarray(
            np.concatenate([cen, (rad * (1 + 1e-9) + 1e-12)[:, None]], axis=1))

    def __call__(self, xyz, return_closest: bool = False):
        """Signed distance of each query point.

        Parameters
        ----------
        xyz : (K, 3) array_like
        return_closest : bool
            Also return the index of the closest triangle and its feature
            (0 face, 1-3 edge ab/bc/ca, 4-6 vertex a/b/c).

        Returns
        -------
        d : (K,) float64
            Signed distance in metres, positive outside (free space).
        tri, region : (K,) int64, only with ``return_closest``
        """
        p = np.ascontiguousarray(np.asarray(xyz, dtype=np.float64))
        if p.ndim != 2 or p.shape[1] != 3:
            raise MeshError(f"Expected query points of shape (K, 3), found {p.shape}; "
                            "pass an array of xyz rows.")
        if not np.all(np.isfinite(p)):
            raise MeshError("Expected finite query points, found NaN or inf; "
                            "drop them before querying.")
        k = len(p)
        d = np.empty(k)
        tri = np.empty(k, dtype=np.int64)
        reg = np.empty(k, dtype=np.int64)
        if k:
            _query(p, self.vertices, self.faces, self.face_normals, self.edge_normals,
                   self.vertex_normals, self._spheres, self._start, self._items, self._lo, self._h,
                   self._dims, d, tri, reg)
        return (d, tri, reg) if return_closest else d


def mesh_signed_distance(vertices, faces, xyz) -> np.ndarray:
    """Exact signed distance from points to a closed triangle mesh (free space > 0).

    One-shot convenience over :class:`MeshDistance`; build that once to query
    the same mesh repeatedly.

    Parameters
    ----------
    vertices : (V, 3) float64
    faces : (F, 3) int64
        Closed, outward-oriented 2-manifold.
    xyz : (K, 3) float64

    Returns
    -------
    (K,) float64
    """
    return MeshDistance(vertices, faces)(xyz)
