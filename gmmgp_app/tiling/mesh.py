"""The stitched surface of a tiled map, meshed region by region and streamed to a PLY.

:meth:`TiledMap.extract_surface` meshes the stitched field on one lattice held whole:
its node values, cells and the whole mesh grow with the street's length (the 8x
street's mesh was the run's memory peak, ~800 MB above the tiled build). Here the
same lattice is meshed one *region* at a time: a region is the marching-cubes block
columns (``BLOCK_CELLS`` cells, :func:`stages.surface.extract_surface`'s blocks) whose
lower corner lies in one tile square. Each region runs ``extract_surface`` on the seeds
within a margin of it, with the whole map's ``dilate``, ``reach`` and voxel, and keeps
the faces whose cell lies in its block columns; the margin (``dilate + 4`` cells plus
the reach) is enough for every cell within two cells of the region's blocks to be
followed exactly as on the whole lattice (a cell is reached from a seed cell within
``dilate`` steps, each step decided by node values and the nearest seed alone), so the
region's blocks see the same node values and the same evaluated-node mask, and
marching cubes gives them the same faces and vertices. Vertices on a region's
border planes are shared with the neighbouring regions by their exact coordinates.

Faces and new vertices go to files on disk as each region finishes, and the PLY
(:func:`gmmgp_app.pipeline.write_mesh_ply`'s layout) is written from them at the end:
memory holds one region's lattice and mesh, the tiles it needs (each tile loaded once:
regions run in tile order and a tile is dropped after the last region that needs it)
and the shared border vertices of the regions not yet closed, not the street's.
"""

from __future__ import annotations

import math
import shutil
import tempfile
from pathlib import Path
from typing import Optional

import numpy as np

__all__ = ["write_tiled_surface_ply", "stream_tiled_surface", "streamed_surface_mesh"]

#: Marching-cubes block edge in cells (extract_surface's ``block_cells``, passed explicitly).
BLOCK_CELLS = 32



class _TileHolder:
    """A mapping over a tiled map's tiles that loads each tile once (not through the
    store's small cache) and drops it when told: the regions' working set."""

    def __init__(self, tiles):
        self._src = tiles
        self._held: dict = {}
        self.loads = 0
        self.peak_held = 0

    def __contains__(self, key):
        return key in self._src

    def __iter__(self):
        return iter(self._src)

    def __len__(self):
        return len(self._src)

    def __getitem__(self, key):
        if key not in self._held:
            load = getattr(self._src, "load_uncached", None)
            self._held[key] = load(key) if load is not None else self._src[key]
            self.loads += 1
            self.peak_held = max(self.peak_held, len(self._held))
        return self._held[key]

    def items(self):
        return ((k, self[k]) for k in self)

    def drop(self, keys) -> None:
        for k in keys:
            self._held.pop(k, None)


class _Inside:
    """A field evaluated only at queries whose (x, y) lie in a box; zeros elsewhere."""

    def __init__(self, lo, hi):
        self.lo, self.hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)

    def wrap(self, fn, grad: bool = False):
        """``fn`` (-> mean, var[, grad]) evaluated inside the box only."""
        def inside(x):
            x = np.asarray(x, np.float64)
            ok = np.all((x[:, :2] >= self.lo) & (x[:, :2] <= self.hi), axis=1)
            if ok.all():
                return fn(x)
            n = len(x)
            out = [np.zeros(n), np.zeros(n)] + ([np.zeros((n, 3))] if grad else [])
            if ok.any():
                for z, a in zip(out, fn(x[ok])):
                    z[ok] = a
            return tuple(out)
        return inside


def _region_index(block, size: float, span: float) -> np.ndarray:
    """Tile-square index of block columns ``block`` (int array): the square holding the
    block's lower corner (``span``: a block's edge in m)."""
    return np.floor(np.asarray(block, np.float64) * span / size).astype(np.int64)


def _first_block(r: int, size: float, span: float) -> int:
    """The smallest block index whose region is ``r`` or more."""
    b = int(math.ceil(r * size / span))
    while _region_index(b - 1, size, span) >= r:
        b -= 1
    while _region_index(b, size, span) < r:
        b += 1
    return b


def stream_tiled_surface(tmap, voxel_size: Optional[float] = None, max_std=None,
                         progress=None, stats: Optional[dict] = None):
    """Yield the stitched surface of ``tmap`` region by region: ``(new_vertices (n, 3),
    new_variances (n,), faces (f, 3) int64)`` with faces indexing every vertex yielded so
    far (the vertices of earlier pieces keep their indices). The union of the pieces is
    :meth:`TiledMap.extract_surface`'s mesh (the same faces on the same vertices, in
    another order). ``stats`` (a dict) receives ``regions``, ``tile_loads``,
    ``peak_tiles_held``, ``voxel``."""
    from ..pipeline import (check_grid_size, mesh_field, project_clamp, project_steps,
                            surface_reach)
    from .tiled_map import TiledMap

    spec = tmap.spec
    holder = _TileHolder(tmap.tiles)
    # one pass over the tiles: the stitched seeds and the tiles' voxels
    parts, surfaces = [], []
    for k in sorted(tmap.tiles):
        t = holder[k]
        parts.append(tmap._tile_seeds(k, t))
        surfaces.append(t.config.surface)
        holder.drop([k])
    seeds = tmap._stitch_seeds(parts)
    del parts
    # TiledMap.surface_voxel and extent_cell, from this pass
    map_voxel = tmap._median_voxel([s.voxel_size for s in surfaces])
    h = float(map_voxel if voxel_size is None else voxel_size)
    if len(seeds) == 0:
        return
    # the whole map's reach and dilate (TiledMap.extract_surface's, from all the seeds;
    # the grid check refuses the same lattices as the whole-lattice path)
    reach = surface_reach(seeds, tmap._median_extent(surfaces))
    dilate = check_grid_size(seeds, h)
    cfg = tmap.config.surface
    steps = project_steps(cfg)
    span = BLOCK_CELLS * h
    size = float(spec.size)
    margin = (dilate + 4) * h + reach
    # with projection a face goes to the region of its projected centroid, which moves
    # by up to steps * clamp voxels: the vertices a neighbour may share lie within a cell
    # plus twice that of a border plane
    tol = (2 * steps * project_clamp(cfg) + 1) * h / span if steps > 0 else 0.0

    # regions: the tile squares holding a block column near a seed
    sb = np.floor_divide(np.floor(seeds[:, :2] / h).astype(np.int64), BLOCK_CELLS)
    near = np.concatenate([sb + np.array([di, dj]) for di in (-1, 0, 1) for dj in (-1, 0, 1)])
    regions = sorted({(int(a), int(b)) for a, b in
                      np.unique(_region_index(near, size, span), axis=0)})
    del sb, near
    boxes = {}
    for r in regions:
        lo = np.array([_first_block(r[0], size, span), _first_block(r[1], size, span)])
        hi = np.array([_first_block(r[0] + 1, size, span), _first_block(r[1] + 1, size, span)])
        boxes[r] = (lo, hi)                               # block columns [lo, hi)
    # the mapped tiles each region's field may need, and the last region needing each
    reach_w = spec.overlap / 2 if spec.blend == "smooth" else 0.0
    last_use: dict = {}
    for t_i, r in enumerate(regions):
        lo, hi = boxes[r]
        a = np.floor((lo * span - margin - reach_w - span) / size).astype(int)
        b = np.floor((hi * span + margin + reach_w + span) / size).astype(int)
        for i in range(a[0], b[0] + 1):
            for j in range(a[1], b[1] + 1):
                o = tmap._owner((i, j))
                if o is not None:
                    last_use[o] = t_i
    view = TiledMap(spec, holder, tmap.config, tmap.method, offset=tmap.offset,
                    owners=tmap.owners, up=tmap.up)
    # regions adjacent to each region (their shared border vertices)
    order = {r: t for t, r in enumerate(regions)}
    close_at = {r: max(order.get((r[0] + di, r[1] + dj), -1)
                       for di in (-1, 0, 1) for dj in (-1, 0, 1)) for r in regions}
    shared: dict = {}          # exact border vertex -> global index
    shared_of: dict = {}       # region -> its border keys (dropped when it closes)
    n_out = 0
    bar = progress(len(regions), "surface regions") if progress else None
    for t_i, r in enumerate(regions):
        lo, hi = boxes[r]
        x0, x1 = lo * span - margin, hi * span + margin
        sel = np.all((seeds[:, :2] >= x0) & (seeds[:, :2] <= x1), axis=1)
        piece = None
        if sel.any():
            # the field at the vertices only where the region may keep faces (a kept
            # face's vertices lie in its block columns, or within the projection's
            # reach of them); elsewhere zeros, for vertices whose faces are dropped
            pad = (steps * project_clamp(cfg) + 1.0) * h
            inside = _Inside(lo * span - pad, hi * span + pad)
            piece = mesh_field(inside.wrap(view.predict), seeds[sel], cfg, h, max_std,
                               reach=reach, predict_mean=view.lattice_mean,
                               project=inside.wrap(lambda x: view.predict(
                                   x, return_grad=True), grad=True),
                               block_cells=BLOCK_CELLS, dilate=dilate,
                               # serial: the same mesh; the overlap's worker thread
                               # gained no time region by region and its per-thread
                               # allocations raised the 8x street's peak RSS from
                               # 320 to 435-445 MB (scripts/bench_scale.py, session 10)
                               overlap=False)
        bar and bar.update(1)
        holder.drop([k for k in list(holder._held) if last_use.get(k, -1) <= t_i])
        if piece is not None and len(piece.faces):
            v, f, var = piece.vertices, piece.faces, piece.vertex_variance
            # the face's cell, hence its block column and region (a face lies in a cell)
            cell = np.floor(v[f].mean(axis=1)[:, :2] / h).astype(np.int64)
            blk = np.floor_divide(cell, BLOCK_CELLS)
            keep = np.all((blk >= lo) & (blk < hi), axis=1)
            f = f[keep]
            used = np.zeros(len(v), bool)
            used[f.reshape(-1)] = True
            idx = np.flatnonzero(used)
            # vertices on the region's border planes may be shared with a neighbour
            q = v[idx, :2] / span
            border = np.any(np.abs(q - np.round(q)) < 1e-6 + tol, axis=1)
            glob = np.full(len(v), -1, np.int64)
            mine = []
            for i in idx[border]:
                key = v[i].tobytes()
                g = shared.get(key)
                if g is not None:
                    glob[i] = g
                else:
                    mine.append((i, key))
            new = np.setdiff1d(idx, idx[border][glob[idx[border]] >= 0], assume_unique=True)
            glob[new] = n_out + np.arange(len(new))
            n_out += len(new)
            keys = []
            for i, key in mine:
                shared[key] = int(glob[i])
                keys.append(key)
            shared_of[r] = keys
            out = (v[new], var[new], glob[f])
            # drop this region's mesh and working arrays before the next region's lattice
            # (bound names would hold them through it: ~30 MB on the 8x street's regions)
            del piece, v, f, var, cell, blk, keep, used, idx, q, border, glob, new, mine, keys
            yield out
            del out
        piece = None
        for q_r in [q for q in shared_of if close_at[q] <= t_i]:
            for key in shared_of.pop(q_r):
                shared.pop(key, None)
    bar and bar.close()
    if stats is not None:
        stats.update(regions=len(regions), tile_loads=holder.loads,
                     peak_tiles_held=holder.peak_held, voxel=h)


def streamed_surface_mesh(tmap, voxel_size=None, max_std=None, progress=None, stats=None):
    """The pieces of :func:`stream_tiled_surface` gathered into one SurfaceMesh (for
    comparisons; it holds the whole mesh)."""
    from ..types import SurfaceMesh

    vs, vars_, fs = [], [], []
    for v, var, f in stream_tiled_surface(tmap, voxel_size, max_std, progress, stats):
        vs.append(v)
        vars_.append(var)
        fs.append(f)
    if not vs:
        return SurfaceMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0))
    return SurfaceMesh(np.concatenate(vs), np.concatenate(fs), np.concatenate(vars_))


def chunked_quantile(chunks, q: float, bins: int = 4096) -> float:
    """``np.quantile(x, q)`` (its default, linear method; the same float bit for bit) of
    the values ``x`` that ``chunks()`` yields, a chunk at a time, without holding them:
    a pass for their count and range, a histogram pass to find the bins of the two
    order statistics the quantile interpolates, and a pass collecting those bins'
    values. NaN if a value is NaN (as np.quantile)."""
    n, lo, hi = 0, np.inf, -np.inf
    for x in chunks():
        if len(x):
            if np.isnan(x).any():
                return float("nan")
            n += len(x)
            lo, hi = min(lo, float(x.min())), max(hi, float(x.max()))
    if n == 0:
        raise ValueError("Expected at least one value for a quantile, found none.")
    # numpy's linear method (Hyndman & Fan type 7): virtual index (n - 1) q
    virtual = (n - 1) * np.float64(q)
    prev = np.floor(virtual)
    gamma = virtual - prev
    k0 = int(min(max(prev, 0), n - 1))
    k1 = int(min(max(prev + 1, 0), n - 1))
    if lo == hi:
        a = b = np.float64(lo)
    else:
        def bin_of(x):
            return np.clip(((x - lo) / (hi - lo) * bins).astype(np.int64), 0, bins - 1)

        counts = np.zeros(bins, np.int64)
        for x in chunks():
            counts += np.bincount(bin_of(x), minlength=bins)
        cum = np.cumsum(counts)
        b0, b1 = (int(np.searchsorted(cum, k, side="right")) for k in (k0, k1))
        vals = np.sort(np.concatenate([x[(bin_of(x) >= b0) & (bin_of(x) <= b1)]
                                       for x in chunks()]))
        start = int(cum[b0 - 1]) if b0 > 0 else 0
        a, b = vals[k0 - start], vals[k1 - start]
    diff = b - a
    return float(b - diff * (1 - gamma) if gamma >= 0.5 else a + diff * gamma)


def _chunks(path, width: int, n: int, chunk: int, dtype="<f8"):
    """``(start, rows (m, width))`` of a raw array file, ``chunk`` rows at a time."""
    with open(path, "rb") as f:
        for s in range(0, n, chunk):
            m = min(chunk, n - s)
            yield s, np.fromfile(f, dtype, m * width).reshape(m, width)


def write_tiled_surface_ply(tmap, path, offset=None, voxel_size=None, max_std=None,
                            progress=None, chunk: int = 1 << 16) -> dict:
    """Write the stitched surface of ``tmap`` to the binary PLY ``path``
    (:func:`gmmgp_app.pipeline.write_mesh_ply`'s layout: vertices with std colours on
    viridis, top of the scale the 98th percentile of the std, and a ``variance``
    property; triangles), meshed region by region (:func:`stream_tiled_surface`) with
    the pieces kept in files beside ``path`` until the PLY is written (atomically).

    Returns
    -------
    dict with ``vertices``, ``faces``, ``vmax`` and :func:`stream_tiled_surface`'s stats.
    """
    from .._atomic import atomic_path
    from ..pipeline import PLY_FACE, PLY_VERTEX, ply_header, variance_colors

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    off = np.zeros(3) if offset is None else np.asarray(offset, np.float64).reshape(3)
    work = Path(tempfile.mkdtemp(prefix=f".{path.name}.pieces-", dir=path.parent))
    stats: dict = {}
    try:
        nv = nf = 0
        with open(work / "v.bin", "wb") as fv, open(work / "f.bin", "wb") as ff:
            for v, var, f in stream_tiled_surface(tmap, voxel_size, max_std, progress, stats):
                np.column_stack([v, var]).astype("<f8").tofile(fv)
                if nv + len(v) >= 2 ** 31:
                    raise ValueError("Expected fewer than 2^31 mesh vertices for a PLY with "
                                     "int indices, found more; mesh at a larger voxel.")
                f.astype("<i4").tofile(ff)
                nv += len(v)
                nf += len(f)
                del v, var, f      # not held through the next region's lattice
        # read back in chunks with plain reads (a memory map's pages would count in the
        # resident set); the colour scale's percentile without holding every variance
        vmax = (float(np.sqrt(chunked_quantile(
            lambda: (d[:, 3] for _, d in _chunks(work / "v.bin", 4, nv, chunk)), 0.98)))
            if nv else None)
        with atomic_path(path) as tmp, open(tmp, "wb") as out:
            out.write(ply_header(nv, nf))
            for s, d in _chunks(work / "v.bin", 4, nv, chunk):
                rec = np.empty(len(d), PLY_VERTEX)
                rec["x"], rec["y"], rec["z"] = (d[:, :3] + off).T
                rgb = variance_colors(d[:, 3], vmax)
                rec["red"], rec["green"], rec["blue"] = rgb.T
                rec["variance"] = d[:, 3]
                out.write(rec.tobytes())
            for s, d in _chunks(work / "f.bin", 3, nf, chunk, "<i4"):
                rec = np.empty(len(d), PLY_FACE)
                rec["n"] = 3
                rec["i"] = d
                out.write(rec.tobytes())
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return dict(vertices=nv, faces=nf, vmax=vmax, **stats)
