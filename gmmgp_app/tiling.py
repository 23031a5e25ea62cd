"""City-scale maps: overlapping tiles, each an independent map, stitched smoothly.

A scan is cut along x and y into square tiles of edge ``size``; a tile trains on
every point within ``overlap`` of its core square (so each tile sees its
neighbours' border strips) and is mapped on its own: its own HGMM, GMR prior and
local GPs (:func:`gmmgp_app.pipeline.build_map`). Tiles are independent tasks, so
they run on any executor (:mod:`gmmgp_app.distributed`).

Why an HGMM per tile rather than shared top levels: the HGMM is fitted top-down,
and its top levels on a city are a handful of Gaussians spanning hundreds of
metres that only route rows to subtrees; fitting them needs every row in one
process (unbounded memory), and the leaves the field uses are local anyway. Per
tile, the whole fit is bounded by the tile size and the overlap gives each tile
the context across its borders.

Stitching: with ``blend="smooth"`` a query is the mixture of the tiles whose
blending region contains it, with a partition of unity of smoothstep ramps of
width ``overlap`` centred on the core borders (so the blend happens well inside
both tiles' training regions); the mean is continuous and C1 across borders.
``blend="core"`` assigns each query to the tile whose core contains it (a step).

A tile with fewer than ``TileSpec.min_points`` points (a thin strip at the edge of
the scan) is not mapped on its own: its points join the nearest mapped tile (the
*owner*, most points among equally near ones), which then also answers for the
small tile's square, weight included. No point is dropped because it fell into a
sparse tile.

Points are sorted canonically inside a tile before mapping, so a tile's map
depends on its *set* of points only, not on the order they arrived in (chunks of
a LAS file, scans added by :meth:`TiledMap.update`).
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from .config import MappingConfig
from .types import Scan

__all__ = ["TilingError", "TileSpec", "TiledMap", "build_tiled_map", "split_into_tiles",
           "tile_owners", "load_tiled_map",
           "update_gp_blocks", "spill_las_to_tiles", "build_tiled_map_from_las"]


TILED_MAP_FORMAT = "gmmgp-tiled-map"
TILED_MAP_FORMAT_VERSION = 1


class TilingError(ValueError):
    """Bad tiling parameters or input to a tiled map."""


def _tile_dirname(key) -> str:
    """``tile_I_J``: a tile's folder (saved map) or file stem (its points)."""
    return f"tile_{int(key[0])}_{int(key[1])}"


@dataclass(frozen=True)
class TileSpec:
    """How space is cut into tiles.

    Attributes
    ----------
    size : float
        Edge of a tile's core square in x and y (m).
    overlap : float
        Training margin around the core (m); also the width of the blending band
        centred on each core border. Must satisfy ``0 <= overlap <= size / 2``.
    blend : {"smooth", "core"}
        Stitching of predictions (see the module docstring).
    min_points : int
        Tiles with fewer scan points are not mapped on their own: their points and
        their square go to the nearest mapped tile (see :func:`tile_owners`).
    """

    size: float = 20.0
    overlap: float = 2.0
    blend: str = "smooth"
    min_points: int = 200

    def __post_init__(self):
        if not (self.size > 0 and math.isfinite(self.size)):
            raise TilingError(f"Expected a positive tile size, found {self.size!r}; use e.g. "
                              "20 m.")
        if not (0 <= self.overlap <= self.size / 2):
            raise TilingError(f"Expected 0 <= tile overlap <= size / 2 = {self.size / 2}, "
                              f"found {self.overlap!r}; use e.g. 2 m.")
        if self.blend not in ("smooth", "core"):
            raise TilingError(f"Expected blend 'smooth' or 'core', found {self.blend!r}.")
        if self.min_points < 10:
            raise TilingError(f"Expected min_points >= 10, found {self.min_points!r}; "
                              "the prepare stage needs at least 10 points.")

    def assign(self, xyz) -> dict:
        """Index of the points each tile trains on (core grown by ``overlap``).

        Parameters
        ----------
        xyz : (N, 3)

        Returns
        -------
        dict mapping tile key ``(i, j)`` to a sorted (n,) int64 index array.
        """
        xy = np.asarray(xyz, dtype=np.float64)[:, :2]
        lo = np.floor((xy - self.overlap) / self.size).astype(np.int64)
        hi = np.floor((xy + self.overlap) / self.size).astype(np.int64)
        out: dict = {}
        for di in (0, 1):
            for dj in (0, 1):
                key = lo + np.array([di, dj])
                ok = np.all(key <= hi, axis=1)
                idx = np.flatnonzero(ok)
                if len(idx) == 0:
                    continue
                k = key[idx]
                order = np.lexsort((k[:, 1], k[:, 0]))
                idx, k = idx[order], k[order]
                cut = np.flatnonzero(np.any(np.diff(k, axis=0) != 0, axis=1)) + 1
                for part in np.split(np.arange(len(idx)), cut):
                    kk = (int(k[part[0], 0]), int(k[part[0], 1]))
                    out.setdefault(kk, []).append(idx[part])
        return {k: np.sort(np.concatenate(v)) for k, v in sorted(out.items())}

    def weights(self, xy, key) -> tuple[np.ndarray, np.ndarray]:
        """Blending weight of tile ``key`` at (K, 2) points and its (K, 2) gradient.

        Smooth: ``w = S(u_x^-) S(u_x^+) S(u_y^-) S(u_y^+)`` with the smoothstep
        ``S(t) = 3t^2 - 2t^3`` on ``[0, 1]`` and ``u`` the distance past the band
        start over the band width; ``S(t) + S(1 - t) = 1`` makes the weights of
        neighbouring tiles sum to one. Core: the indicator of the core square.
        """
        xy = np.asarray(xy, dtype=np.float64)
        lo = np.asarray(key, dtype=np.float64) * self.size
        if self.blend == "core" or self.overlap == 0:
            inside = np.all((xy >= lo) & (xy < lo + self.size), axis=1)
            return inside.astype(np.float64), np.zeros_like(xy)
        b = self.overlap
        t_lo = (xy - (lo - b / 2)) / b
        t_hi = ((lo + self.size + b / 2) - xy) / b
        s_lo, d_lo = _smoothstep(t_lo)
        s_hi, d_hi = _smoothstep(t_hi)
        per_axis = s_lo * s_hi
        d_axis = (d_lo * s_hi - s_lo * d_hi) / b
        w = per_axis[:, 0] * per_axis[:, 1]
        grad = np.column_stack([d_axis[:, 0] * per_axis[:, 1], per_axis[:, 0] * d_axis[:, 1]])
        return w, grad

    def candidate_keys(self, xy) -> list[np.ndarray]:
        """The (K, 2) tile keys whose weight may be non-zero at each point (4 arrays)."""
        reach = self.overlap / 2 if self.blend == "smooth" else 0.0
        lo = np.floor((np.asarray(xy) - reach) / self.size).astype(np.int64)
        return [lo + np.array([di, dj]) for di in (0, 1) for dj in (0, 1)]


def _smoothstep(t):
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t), 6.0 * t * (1.0 - t)


def _canonical(points, origins):
    """Sort points (and origins) lexicographically: a tile's map depends on its set only."""
    order = np.lexsort((points[:, 2], points[:, 1], points[:, 0]))
    return points[order], (None if origins is None else origins[order])


def tile_owners(counts: dict, min_points: int) -> dict:
    """Which mapped tile takes over each tile with fewer than ``min_points`` points.

    Parameters
    ----------
    counts : dict ``{(i, j): number of points}``
    min_points : int

    Returns
    -------
    dict ``{small key: owner key}``: the owner is a tile with at least
    ``min_points`` points whose square is nearest (Euclidean distance between the
    keys, so a neighbour across an edge comes before one across a corner, whose
    data would not reach along the whole shared side), the one with the most points
    among equally near ones. Empty when no tile is big enough.
    """
    big = sorted(k for k, n in counts.items() if n >= min_points)
    owners = {}
    for k, n in sorted(counts.items()):
        if n >= min_points or not big:
            continue
        owners[k] = min(big, key=lambda b: ((b[0] - k[0]) ** 2 + (b[1] - k[1]) ** 2,
                                            -counts[b], b))
    return owners


def _owners_summary(owners: dict) -> dict:
    """``{"(i, j)": "(k, l)"}``: the owners as the JSON-friendly ``absorbed_tiles`` summary."""
    return {str(k): str(o) for k, o in owners.items()}


def _members(owners: dict, key) -> list:
    """The tile ``key`` and the small tiles it owns, sorted."""
    return [key] + sorted(k for k, o in owners.items() if o == key)


def _as_void(points: np.ndarray) -> np.ndarray:
    """Rows of an (N, 3) float64 array as one opaque value each (exact row matching)."""
    a = np.ascontiguousarray(points, dtype=np.float64)
    return a.view(np.dtype((np.void, a.dtype.itemsize * a.shape[1]))).ravel()


def _union(parts) -> tuple:
    """Point sets of several tiles as one, without the points their overlap margins
    share: ``[(points, origins or None), ...]`` -> (points, origins), canonical order.

    A point already in an earlier tile's set is dropped from a later one; repeated
    points inside one tile's set are kept (as a single tile would keep them).
    """
    keep_pts, keep_org = [parts[0][0]], [parts[0][1]]
    for pts, org in parts[1:]:
        new = ~np.isin(_as_void(pts), _as_void(np.concatenate(keep_pts)))
        keep_pts.append(pts[new])
        keep_org.append(None if org is None else org[new])
    has_org = all(o is not None for o in keep_org)
    return _canonical(np.concatenate(keep_pts),
                      np.concatenate(keep_org) if has_org else None)


def split_into_tiles(scan: Scan, spec: TileSpec) -> dict:
    """Cut a scan into the tiles of ``spec``: ``{(i, j): Scan}`` (canonical order)."""
    out = {}
    for key, idx in spec.assign(scan.points).items():
        pts, org = _canonical(scan.points[idx],
                              None if scan.origins is None else scan.origins[idx])
        out[key] = Scan(points=pts, origins=org, offset=scan.offset, source=f"tile {key}")
    return out


def _build_tile(task):
    """Executor task: map one tile (module level so that it pickles)."""
    key, points, origins, cfg, method = task
    from .pipeline import build_map

    if isinstance(points, (list, tuple)):  # spilled chunks on disk (streaming input)
        # per tile (the tile, then the small tiles it owns): its point and origin files
        parts = [(np.concatenate([np.load(f) for f in pf]),
                  np.concatenate([np.load(f) for f in of]) if of else None)
                 for pf, of in points]
        pts, org = _union(parts)
    else:
        pts, org = _canonical(np.asarray(points, dtype=np.float64), origins)
    from .stages.hgmm import HGMMError
    from .stages.prepare import PrepareError

    try:
        smap = build_map(Scan(points=pts, origins=org, source=f"tile {key}"), cfg, method)
    except (PrepareError, HGMMError) as exc:
        # too sparse for normals, or too few hit points with one for the HGMM: its
        # neighbours answer its queries (reported in ``skipped_tiles``)
        return key, f"{type(exc).__name__}: {exc}"
    return key, _map_to_bytes(smap)


def _map_to_bytes(smap) -> dict:
    """A SurfaceMap as ``{file name: bytes}`` of its saved folder (no pickle of internals:
    the GMR field holds a lock, and the saved format is what crosses machines safely)."""
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as d:
        smap.save(Path(d) / "m")
        return {p.name: p.read_bytes() for p in (Path(d) / "m").iterdir()}


def _map_from_bytes(files: dict):
    import tempfile
    from pathlib import Path

    from .pipeline import load_map

    with tempfile.TemporaryDirectory() as d:
        for name, data in files.items():
            (Path(d) / name).write_bytes(data)
        return load_map(d)


def _run_tiles(executor, tasks, progress):
    from .distributed import map_batched

    maps, skipped = {}, {}
    for k, b in map_batched(executor, _build_tile, tasks, progress=progress):
        if isinstance(b, str):
            skipped[k] = b
        else:
            maps[k] = _map_from_bytes(b)
    return maps, skipped


class TiledMap:
    """A SurfaceMap-like field made of independently mapped, overlapping tiles.

    Parameters
    ----------
    spec : TileSpec
    tiles : dict
        ``{(i, j): SurfaceMap}`` of the mapped tiles.
    config : MappingConfig
    method : str
    offset : (3,) float64
        Local-frame shift shared by all tiles (original = local + offset).
    tile_points : dict, optional
        ``{(i, j): (points, origins)}`` of every tile, small ones included (needed
        by :meth:`update`).
    owners : dict, optional
        ``{small key: mapped key}`` (:func:`tile_owners`): the mapped tile that
        trained on a small tile's points and answers for its square.
    """

    def __init__(self, spec: TileSpec, tiles: dict, config: MappingConfig, method: str,
                 offset=None, tile_points: Optional[dict] = None, summary=None,
                 owners: Optional[dict] = None):
        self.spec = spec
        self.tiles = tiles if isinstance(tiles, _TileStore) else dict(tiles)
        self.config = config
        self.method = method
        self.offset = np.zeros(3) if offset is None else np.asarray(offset, float).reshape(3)
        self.tile_points = dict(tile_points or {})
        self.summary = dict(summary or {})
        self.owners = dict(owners or {})

    def _owner(self, key):
        """The mapped tile answering for square ``key`` (itself or its owner), or None."""
        if key in self.tiles:
            return key
        owner = self.owners.get(key)
        return owner if owner is not None and owner in self.tiles else None

    @property
    def keys(self) -> list:
        return sorted(self.tiles)

    def predict(self, xyz, return_grad: bool = False):
        """Stitched signed distance: mean (K,), variance (K,)[, gradient (K, 3)].

        Mixture of the tiles weighted by :meth:`TileSpec.weights` (renormalised
        over the mapped tiles): ``mean = sum w_t m_t``, ``var = sum w_t (v_t +
        m_t^2) - mean^2`` (so tiles that disagree widen the variance), and the
        gradient of that mean including the weights' gradient. A query no mapped
        tile weighs is answered by the nearest mapped tile.
        """
        from .pipeline import _as_queries

        x = _as_queries(xyz)
        K = len(x)
        W = np.zeros(K)
        Wm = np.zeros(K)
        Wv = np.zeros(K)
        Wm2 = np.zeros(K)
        gW = np.zeros((K, 2))
        gWm = np.zeros((K, 3))
        # weight of each mapped tile per query: its own square's plus those it owns
        parts: dict = {}
        for key_arr in self.spec.candidate_keys(x[:, :2]):
            for key in map(tuple, np.unique(key_arr, axis=0).tolist()):
                owner = self._owner(key)
                if owner is None:
                    continue
                rows = np.flatnonzero(np.all(key_arr == np.array(key), axis=1))
                w, dw = self.spec.weights(x[rows, :2], key)
                keep = w > 0
                if keep.any():
                    parts.setdefault(owner, []).append((rows[keep], w[keep], dw[keep]))
        for owner, pieces in sorted(parts.items()):
            if len(pieces) == 1:
                rows, w, dw = pieces[0]
            else:  # one prediction per query even when several squares weigh it
                rows, inv = np.unique(np.concatenate([r for r, _, _ in pieces]),
                                      return_inverse=True)
                w = np.bincount(inv, np.concatenate([q for _, q, _ in pieces]), len(rows))
                dwc = np.concatenate([d for _, _, d in pieces])
                dw = np.column_stack([np.bincount(inv, dwc[:, a], len(rows)) for a in (0, 1)])
            out = self.tiles[owner].predict(x[rows], return_grad=return_grad)
            m, v = out[0], out[1]
            W[rows] += w
            Wm[rows] += w * m
            Wv[rows] += w * v
            Wm2[rows] += w * m * m
            if return_grad:
                gW[rows] += dw
                gWm[rows] += w[:, None] * out[2]
                gWm[rows, :2] += m[:, None] * dw
        mean = np.zeros(K)
        var = np.zeros(K)
        grad = np.zeros((K, 3))
        ok = W > 0
        mean[ok] = Wm[ok] / W[ok]
        # written so that a single tile of weight 1 returns its variance bit for bit
        var[ok] = Wv[ok] / W[ok] + np.maximum(Wm2[ok] / W[ok] - mean[ok] ** 2, 0.0)
        if return_grad:
            grad[ok] = gWm[ok] / W[ok, None]
            grad[ok, :2] -= mean[ok, None] * gW[ok] / W[ok, None]
        if (~ok).any() and self.tiles:
            self._nearest_tile(x, ~ok, mean, var, grad, return_grad)
        return (mean, var, grad) if return_grad else (mean, var)

    def _nearest_tile(self, x, miss, mean, var, grad, return_grad):
        keys = np.array(self.keys, dtype=np.float64)
        centres = (keys + 0.5) * self.spec.size
        rows = np.flatnonzero(miss)
        d = np.linalg.norm(x[rows, None, :2] - centres[None], axis=2)
        pick = np.argmin(d, axis=1)
        for t in np.unique(pick):
            r = rows[pick == t]
            out = self.tiles[tuple(int(k) for k in keys[t])].predict(x[r], return_grad)
            mean[r], var[r] = out[0], out[1]
            if return_grad:
                grad[r] = out[2]

    def _weighs(self, key, xyz) -> np.ndarray:
        """Where mapped tile ``key`` has a non-zero weight (its square or one it owns)."""
        w = np.zeros(len(xyz))
        for k in _members(self.owners, key):
            w += self.spec.weights(xyz[:, :2], k)[0]
        return w > 0

    def extract_surface(self, voxel_size: Optional[float] = None, max_std=None,
                        progress=None):
        """Marching cubes on the stitched field (seamless: one field, one lattice)."""
        from .stages.surface import extract_surface

        seeds = [t.seed_points[self._weighs(k, t.seed_points)]
                 if self.spec.blend == "smooth" else t.seed_points
                 for k, t in self.tiles.items()]
        seeds = np.unique(np.concatenate(seeds), axis=0) if seeds else np.zeros((0, 3))
        cfg = self.config.surface
        return extract_surface(self.predict, seeds,
                               voxel_size=cfg.voxel_size if voxel_size is None else voxel_size,
                               max_std=cfg.max_std if max_std is None else max_std,
                               progress=progress)

    # ------------------------------------------------------------ save/load
    def save(self, directory) -> Path:
        """Write the tiled map to ``directory`` (npz + json, no pickle), atomically.

        Layout: ``tiled.json`` (format tag and version, tile spec, method, offset,
        mapped tile keys, owners as ``[small, owner]`` pairs, summary, config as
        TOML); ``tiles/tile_I_J/``, one saved :class:`~gmmgp_app.pipeline.SurfaceMap`
        per mapped tile; and, when the map keeps its points, ``points/tile_I_J.npz``
        (``points`` (n, 3) and ``origins`` (n, 3) when known) for :meth:`update`.

        The folder is written under a temporary name beside ``directory`` and
        renamed when complete (an existing folder is replaced whole), so an
        interrupted save never leaves a half-written map. Tiles kept on disk (a
        streamed or loaded map) are copied file by file, not loaded.

        Returns
        -------
        Path
            ``directory``.
        """
        from ._atomic import atomic_dir
        from .pipeline import _jsonable

        directory = Path(directory)
        keys = self.keys
        with atomic_dir(directory) as tmp:
            (tmp / "tiles").mkdir()
            for key in keys:
                dest = tmp / "tiles" / _tile_dirname(key)
                if isinstance(self.tiles, _TileStore):
                    self.tiles.export(key, dest)
                else:
                    self.tiles[key].save(dest)
            if self.tile_points:
                (tmp / "points").mkdir()
                for key, (pts, org) in sorted(self.tile_points.items()):
                    arrays = {"points": np.asarray(pts, dtype=np.float64)}
                    if org is not None:
                        arrays["origins"] = np.asarray(org, dtype=np.float64)
                    np.savez(tmp / "points" / f"{_tile_dirname(key)}.npz", **arrays)
            meta = {
                "format": TILED_MAP_FORMAT,
                "format_version": TILED_MAP_FORMAT_VERSION,
                "spec": dataclasses.asdict(self.spec),
                "method": self.method,
                "offset": [float(v) for v in self.offset],
                "tiles": [list(k) for k in keys],
                "owners": [[list(k), list(o)] for k, o in sorted(self.owners.items())],
                "points": sorted(list(k) for k in self.tile_points),
                "summary": _jsonable(self.summary),
                "config_toml": self.config.to_toml(),
            }
            (tmp / "tiled.json").write_text(json.dumps(meta, indent=2))
        return directory

    # ------------------------------------------------------------ incremental
    def update(self, scan: Scan, refit_hgmm: bool = False, executor=None,
               progress: Optional[Callable[[int, int], None]] = None,
               new_space_fraction: Optional[float] = 0.25, new_space_voxel: float = 1.0
               ) -> dict:
        """Add new points; refit only what they touch.

        Tiles that are new, or all touched tiles when ``refit_hgmm``, are mapped
        again from all their points (old and new). Otherwise a touched tile keeps
        its HGMM/GMR prior and only the GP blocks whose training region contains a
        new point are refitted (:func:`update_gp_blocks`); predictions away from the
        new points are unchanged bit for bit.

        A tile whose new points mostly lie in *new space* (more than
        ``new_space_fraction`` of them in ``new_space_voxel`` cells holding no old
        point) is also mapped again: its old prior knows nothing there, nearly every
        new point would become a GP point (770 blocks refitted), which was measured
        slower and less accurate than remapping the touched tiles (1.6 s vs 1.1 s;
        median error 1.03 vs 0.84 mm; half a 36 m street added to the other half,
        out/bench/bench_scale_update.json). ``new_space_fraction=None`` never does this.

        Returns
        -------
        dict with ``rebuilt_tiles``, ``gp_updated_tiles``, ``refit_blocks``.
        """
        if not np.allclose(scan.offset, self.offset):
            raise TilingError(f"Expected the update's offset {self.offset.tolist()}, found "
                              f"{scan.offset.tolist()}; read it in the map's local frame.")
        if self.tiles and not self.tile_points:
            raise TilingError("This tiled map was built without keeping its points "
                              "(streamed input or keep_points=False), found none to update "
                              "from; rebuild it with build_tiled_map(..., keep_points=True).")
        parts = self.spec.assign(scan.points)
        old_points = dict(self.tile_points)
        new_points = {}
        for key, idx in parts.items():
            new_p = scan.points[idx]
            new_o = None if scan.origins is None else scan.origins[idx]
            old_p, old_o = self.tile_points.get(key, (np.zeros((0, 3)), None))
            all_p = np.concatenate([old_p, new_p])
            all_o = (None if (old_o is None and len(old_p)) or new_o is None
                     else np.concatenate([old_o if old_o is not None else np.zeros((0, 3)),
                                          new_o]))
            self.tile_points[key] = _canonical(all_p, all_o)
            new_points[key] = new_p
        counts = {k: len(p) for k, (p, _) in self.tile_points.items()}
        owners = tile_owners(counts, self.spec.min_points)
        # mapped tiles whose training set changed: new points in their square or in a
        # small square they own, or a change in which small squares they own
        touched = {k if counts[k] >= self.spec.min_points else owners.get(k) for k in parts}
        moved = {t for t in set(owners.values()) | set(self.owners.values())
                 if _members(owners, t) != _members(self.owners, t)}
        touched = sorted(t for t in touched | moved
                         if t is not None and counts.get(t, 0) >= self.spec.min_points)
        rebuild, report = [], dict(rebuilt_tiles=[], gp_updated_tiles=[], refit_blocks=0)
        for key in touched:
            members = _members(owners, key)
            all_p, all_o = _union([self.tile_points[k] for k in members])
            new_p = np.concatenate([new_points.get(k, np.zeros((0, 3))) for k in members])
            old_p = np.concatenate([old_points.get(k, (np.zeros((0, 3)), None))[0]
                                    for k in members])
            if (refit_hgmm or key in moved or key not in self.tiles
                    or self.tiles[key].gp is None
                    or _new_space(old_p, new_p, new_space_voxel) > (
                        np.inf if new_space_fraction is None else new_space_fraction)):
                rebuild.append((key, all_p, all_o, self.config, self.method))
            else:
                self.tiles[key], n = update_gp_blocks(self.tiles[key], all_p, all_o, new_p,
                                                      self.config, executor=executor)
                report["gp_updated_tiles"].append(key)
                report["refit_blocks"] += n
        self.owners = owners
        self.summary["absorbed_tiles"] = _owners_summary(owners)
        maps, skipped = _run_tiles(executor, rebuild, progress)
        report["skipped_tiles"] = skipped
        for key, smap in maps.items():
            self.tiles[key] = smap
            report["rebuilt_tiles"].append(key)
        return report


def _new_space(old_points, new_points, voxel: float) -> float:
    """Fraction of ``new_points`` in voxels that hold none of ``old_points``."""
    if len(new_points) == 0:
        return 0.0
    if len(old_points) == 0:
        return 1.0
    from .stages.octree import BlockGrid

    grid = BlockGrid.from_points(old_points, voxel, 0.0)
    cells = np.floor(new_points / voxel).astype(np.int64)
    return float(np.mean(grid.lookup(cells) < 0))


def _fit_blocks_at(keys, pts, nrm, prior, gcfg, executor):
    """Local GPs of the blocks ``keys`` only, on the GP points ``pts`` of their regions."""
    from .stages.gp import LocalGPField
    from .stages.octree import BlockGrid

    grid = BlockGrid(keys, gcfg.block_size, gcfg.block_overlap)
    m, v, g = prior.predict(pts, return_grad=True)
    targets = np.column_stack([-np.asarray(m), nrm - np.asarray(g)])
    sigma_p = np.sqrt(np.maximum(np.asarray(v, dtype=np.float64), 0.0))
    pi, bi = grid.cover(pts)
    rng = np.random.default_rng(0)
    items = []
    for b in range(grid.n_blocks):
        idx = pi[bi == b]
        if len(idx) > gcfg.max_block_points:
            idx = np.sort(rng.choice(idx, gcfg.max_block_points, replace=False))
        items.append((pts[idx], sigma_p[idx], targets[idx]))
    from .distributed import batch_by_cost, gp_block_seconds, map_batched
    from .stages.gp import _fit_block_batch

    hyper = (float(gcfg.length_scale), float(gcfg.value_noise), float(gcfg.gradient_noise),
             float(gcfg.jitter))
    batches = batch_by_cost(gp_block_seconds([len(it[0]) for it in items]))
    out = map_batched(executor, _fit_block_batch,
                      [([items[i] for i in bt], hyper) for bt in batches])
    blocks = [f for part in out for f in part]
    hyper_d = {k: float(getattr(gcfg, k)) for k in
               ("length_scale", "value_noise", "gradient_noise", "block_size", "block_overlap")}
    return LocalGPField(prior, grid, blocks, hyper_d, {})


def update_gp_blocks(smap, all_points, all_origins, new_points, cfg: MappingConfig,
                     executor=None):
    """Refit the GP blocks of ``smap`` whose training region holds a new point.

    The tile's prior (HGMM/GMR) is kept. The neighbourhood of the touched blocks
    is prepared again from all the tile's points (normals need neighbours), GP
    points are selected there (eq. condition1 through ``select_gp_points``) and
    each touched block is fitted on the GP points in its region; every other
    block keeps its factorisation.

    Returns
    -------
    (SurfaceMap, int)
        The updated map and the number of refitted blocks.
    """
    from .pipeline import SurfaceMap, _surface_seeds
    from .stages.gp import LocalGPField, select_gp_points
    from .stages.octree import BlockGrid
    from .stages.prepare import prepare

    gp = smap.gp
    bs, ov = gp.hyper["block_size"], gp.hyper["block_overlap"]
    half = 0.5 * (1.0 + ov) * bs
    # cells whose training region [c*bs + bs/2 - half, ...] contains a new point
    reach = int(math.ceil(half / bs - 0.5))
    base = np.unique(np.floor(new_points / bs).astype(np.int64), axis=0)
    rng_ = np.arange(-reach, reach + 1)
    offs = np.stack(np.meshgrid(rng_, rng_, rng_, indexing="ij"), -1).reshape(-1, 3)
    touched = np.unique((base[:, None, :] + offs[None]).reshape(-1, 3), axis=0)
    tgrid = BlockGrid(touched, bs, ov)
    # prepare the touched regions plus a margin for the normals' neighbourhoods
    margin = half + 2.0 * cfg.prepare.normal_radius + cfg.prepare.virtual_spacing
    # a superset through a coarse grid of cell >= margin: cells around the touched
    # blocks' centres (BlockGrid.cover with a huge overlap loops over span^3 offsets)
    coarse = margin + bs
    ck = np.unique(np.floor(tgrid.centres / coarse).astype(np.int64), axis=0)
    o1 = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), -1).reshape(-1, 3)
    ck = np.unique((ck[:, None, :] + o1[None]).reshape(-1, 3), axis=0)
    near = np.flatnonzero(BlockGrid(ck, coarse, 0.0).lookup(
        np.floor(all_points / coarse).astype(np.int64)) >= 0)
    sub = Scan(points=all_points[near],
               origins=None if all_origins is None else all_origins[near])
    data = prepare(sub, cfg)
    m = smap.prior.predict(data.points)[0]
    mask = select_gp_points(m, cfg.gp.d_m)
    pts, nrm = data.points[mask], data.normals[mask]
    keep_pts = np.zeros(len(pts), dtype=bool)
    if len(pts):
        keep_pts[tgrid.cover(pts)[0]] = True
    pts, nrm = pts[keep_pts], nrm[keep_pts]
    # old blocks outside the touched set stay as they are
    old_touched = tgrid.lookup(gp.grid.keys) >= 0
    keys = [gp.grid.keys[~old_touched]]
    blocks = [b for b, t in zip(gp.blocks, old_touched) if not t]
    n_refit = 0
    if len(pts):
        # only the touched cells that hold a GP point are fitted (as fit_local_gps would
        # create them), each on the GP points of its whole training region
        own = np.unique(np.floor(pts / bs).astype(np.int64), axis=0)
        own = own[tgrid.lookup(own) >= 0]
        new = _fit_blocks_at(own, pts, nrm, smap.prior, cfg.gp, executor)
        keys.append(new.grid.keys)
        blocks += list(new.blocks)
        n_refit = len(new.blocks)
    all_keys = np.concatenate(keys)
    grid = BlockGrid(all_keys, bs, ov)
    # BlockGrid sorts its keys: put the blocks in the same order
    order = grid.lookup(all_keys)
    sorted_blocks = [None] * len(blocks)
    for b, pos in zip(blocks, order):
        sorted_blocks[pos] = b
    field = LocalGPField(smap.prior, grid, sorted_blocks, gp.hyper,
                         dict(gp.info, n_blocks=len(sorted_blocks), updated=True))
    gpp = np.unique(np.concatenate([smap.gp_points, pts]), axis=0)
    scan_all = Scan(points=all_points)
    out = SurfaceMap(smap.method, smap.config, smap.offset, smap.prior, hgmm=smap.hgmm,
                     gp=field, gp_points=gpp, seed_points=_surface_seeds(scan_all, cfg),
                     summary=smap.summary)
    return out, n_refit


def build_tiled_map(scan: Scan, cfg: Optional[MappingConfig] = None,
                    spec: Optional[TileSpec] = None, method: str = "gmmgp", *,
                    executor=None, progress: Optional[Callable[[int, int], None]] = None,
                    keep_points: bool = True) -> TiledMap:
    """Map a large scan tile by tile (each tile one task on ``executor``).

    Parameters
    ----------
    scan : Scan
    cfg : MappingConfig, optional
    spec : TileSpec, optional
        Default ``TileSpec()`` (20 m tiles, 2 m overlap, smooth blending).
    method : str
        As :func:`gmmgp_app.pipeline.build_map`.
    executor : concurrent.futures.Executor, optional
        ``None``: serial, in this process.
    progress : callable(done, total), optional
        One count per finished tile.
    keep_points : bool
        Keep each tile's points for :meth:`TiledMap.update`.

    Returns
    -------
    TiledMap
    """
    cfg = MappingConfig() if cfg is None else cfg
    spec = TileSpec() if spec is None else spec
    tiles = split_into_tiles(scan, spec)
    owners = tile_owners({k: len(t) for k, t in tiles.items()}, spec.min_points)
    tasks = []
    for k, t in tiles.items():
        if len(t) < spec.min_points:
            continue
        pts, org = _union([(tiles[m].points, tiles[m].origins) for m in _members(owners, k)])
        tasks.append((k, pts, org, cfg, method))
    if not tasks:
        raise TilingError(f"Expected at least one tile with {spec.min_points} points, found "
                          f"{max((len(t) for t in tiles.values()), default=0)}; use larger "
                          "tiles or lower TileSpec.min_points.")
    maps, skipped = _run_tiles(executor, tasks, progress)
    if not maps:
        raise TilingError(f"Expected at least one tile to map, all {len(skipped)} failed; "
                          f"first: {next(iter(skipped.values()))}")
    kept = {k: (t.points, t.origins) for k, t in tiles.items()} if keep_points else None
    return TiledMap(spec, maps, cfg, method, offset=scan.offset, tile_points=kept,
                    owners=owners,
                    summary=dict(n_tiles=len(maps), n_points=len(scan),
                                 absorbed_tiles=_owners_summary(owners),
                                 skipped_tiles={str(k): v for k, v in skipped.items()}))


# ------------------------------------------------------------------ streaming input
class _TileStore:
    """Tile maps saved on disk, loaded on demand (a few kept in memory).

    A mapping ``{(i, j): SurfaceMap}``: memory stays bounded by ``cache`` tiles
    however long the street. Tile ``(i, j)`` lives in ``directory/tile_i_j``.

    With ``read_only`` (a map opened by :func:`load_tiled_map`) assigning a tile
    keeps it in memory instead of overwriting the folder, so that updating a
    loaded map never changes the saved one behind its ``tiled.json``; save the
    updated map explicitly.
    """

    def __init__(self, directory, keys, cache: int = 4, read_only: bool = False):
        from collections import OrderedDict
        from pathlib import Path

        self.directory = Path(directory)
        self._keys = sorted(keys)
        self._cache: "OrderedDict" = OrderedDict()
        self._size = int(cache)
        self.read_only = bool(read_only)
        self._written: dict = {}  # read-only store: tiles replaced since loading

    def _path(self, key):
        return self.directory / _tile_dirname(key)

    def __contains__(self, key):
        return key in set(self._keys)

    def __iter__(self):
        return iter(self._keys)

    def __len__(self):
        return len(self._keys)

    def get(self, key, default=None):
        return self[key] if key in self else default

    def __getitem__(self, key):
        from .pipeline import load_map

        if key in self._written:
            return self._written[key]
        if key not in self._cache:
            if key not in self:
                raise KeyError(key)
            self._cache[key] = load_map(self._path(key))
            while len(self._cache) > self._size:
                self._cache.popitem(last=False)
        self._cache.move_to_end(key)
        return self._cache[key]

    def __setitem__(self, key, smap):
        if self.read_only:
            self._written[key] = smap
        else:
            smap.save(self._path(key))
        if key not in self:
            self._keys = sorted(self._keys + [key])
        self._cache.pop(key, None)

    def items(self):
        return ((k, self[k]) for k in self._keys)

    def export(self, key, dest) -> None:
        """Write tile ``key`` as a saved map folder ``dest`` (a copy of its files when
        it is unchanged on disk: no load, bit for bit)."""
        import shutil

        if key in self._written or not self._path(key).is_dir():
            self[key].save(dest)
        else:
            shutil.copytree(self._path(key), dest)


def spill_las_to_tiles(path, spec: TileSpec, directory, chunk_size: int = 1_000_000,
                       offset=None) -> tuple[dict, np.ndarray, int]:
    """Read a LAS/LAZ file in chunks, appending each chunk's points to its tiles' files.

    Only one chunk is in memory at a time (``laspy.open(path).chunk_iterator``).
    Sensor origins are read from extra dimensions ``origin_x``, ``origin_y``,
    ``origin_z`` when the file has them.

    Parameters
    ----------
    path : str or Path
    spec : TileSpec
    directory : Path
        Where the per-tile ``.npy`` pieces go.
    chunk_size : int
        Points per chunk.
    offset : (3,) array_like, optional
        Local-frame shift (default: the header minimum rounded down to 100 m).

    Returns
    -------
    pieces : dict ``{(i, j): (list of point files, list of origin files)}``
    offset : (3,) float64
    n_points : int
    """
    from pathlib import Path

    import laspy

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    if chunk_size < 1:
        raise TilingError(f"Expected chunk_size >= 1, found {chunk_size!r}.")
    pieces: dict = {}
    n = 0
    with laspy.open(path) as reader:
        hdr = reader.header
        names = set(hdr.point_format.dimension_names)
        has_org = {"origin_x", "origin_y", "origin_z"} <= names
        off = (np.floor(np.asarray(hdr.mins, dtype=np.float64) / 100.0) * 100.0
               if offset is None else np.asarray(offset, dtype=np.float64).reshape(3))
        for c, chunk in enumerate(reader.chunk_iterator(int(chunk_size))):
            pts = np.column_stack([np.asarray(chunk.x, dtype=np.float64),
                                   np.asarray(chunk.y, dtype=np.float64),
                                   np.asarray(chunk.z, dtype=np.float64)]) - off
            org = (np.column_stack([np.asarray(chunk[f"origin_{a}"], dtype=np.float64)
                                    for a in "xyz"]) - off if has_org else None)
            n += len(pts)
            for key, idx in spec.assign(pts).items():
                stem = directory / f"t{key[0]}_{key[1]}_c{c}"
                np.save(f"{stem}_p.npy", pts[idx])
                entry = pieces.setdefault(key, ([], []))
                entry[0].append(f"{stem}_p.npy")
                if org is not None:
                    np.save(f"{stem}_o.npy", org[idx])
                    entry[1].append(f"{stem}_o.npy")
    return pieces, off, n


def build_tiled_map_from_las(path, cfg: Optional[MappingConfig] = None,
                             spec: Optional[TileSpec] = None, method: str = "gmmgp", *,
                             work_dir, executor=None, chunk_size: int = 1_000_000,
                             progress: Optional[Callable[[int, int], None]] = None,
                             cache_tiles: int = 4, offset=None) -> TiledMap:
    """Stream a LAS/LAZ file into tiles and map them, with memory bounded by a tile.

    The file is read chunk by chunk into per-tile pieces on disk
    (:func:`spill_las_to_tiles`); each tile task loads only its own pieces, and
    each finished tile map is saved under ``work_dir/maps`` and dropped from
    memory (the returned map loads tiles on demand, ``cache_tiles`` at a time).
    Peak memory is therefore that of one chunk or one tile's mapping (per
    worker), not of the whole file. ``offset`` is the local-frame shift (default:
    see :func:`spill_las_to_tiles`); tiles are aligned in the local frame.

    Returns
    -------
    TiledMap (without the points :meth:`TiledMap.update` needs; re-stream to update)
    """
    from pathlib import Path

    from .distributed import map_batched

    cfg = MappingConfig() if cfg is None else cfg
    spec = TileSpec() if spec is None else spec
    work_dir = Path(work_dir)
    pieces, off, n = spill_las_to_tiles(path, spec, work_dir / "pieces", chunk_size, offset)
    counts = {key: sum(int(np.load(f, mmap_mode="r").shape[0]) for f in pfiles)
              for key, (pfiles, _) in pieces.items()}
    owners = tile_owners(counts, spec.min_points)
    tasks = []
    for key in sorted(pieces):
        if counts[key] >= spec.min_points:
            files = [(pieces[m][0], pieces[m][1] if len(pieces[m][1]) == len(pieces[m][0])
                      else []) for m in _members(owners, key)]
            tasks.append((key, files, None, cfg, method))
    store = _TileStore(work_dir / "maps", [], cache=cache_tiles)
    skipped = {}
    # submit in waves so that at most a few finished tile maps wait in memory
    wave = 4
    done = 0
    total = len(tasks)
    for s in range(0, len(tasks), wave):
        part = map_batched(executor, _build_tile, tasks[s:s + wave])
        for key, b in part:
            if isinstance(b, str):
                skipped[key] = b
            else:
                store[key] = _map_from_bytes(b)
        done += len(part)
        if progress is not None:
            progress(done, total)
    if not len(store):
        raise TilingError(f"Expected at least one tile with {spec.min_points} points in "
                          f"'{path}', found none that could be mapped.")
    return TiledMap(spec, store, cfg, method, offset=off, owners=owners,
                    summary=dict(n_tiles=len(store), n_points=n,
                                 absorbed_tiles=_owners_summary(owners),
                                 skipped_tiles={str(k): v for k, v in skipped.items()}))


# ------------------------------------------------------------------ save/load
def load_tiled_map(directory, cache_tiles: int = 4, *, load_points: bool = True) -> TiledMap:
    """Open a tiled map written by :meth:`TiledMap.save`; it predicts identically.

    The tiles stay on disk and are loaded on demand, ``cache_tiles`` at a time
    (:class:`_TileStore`); tiles replaced by :meth:`TiledMap.update` are kept in
    memory and the saved folder is left as it was (save the updated map to keep
    them).

    Parameters
    ----------
    directory : str or Path
        The folder holding ``tiled.json``.
    cache_tiles : int
        Tile maps kept in memory at once.
    load_points : bool
        Read the saved tile points (needed by :meth:`TiledMap.update`; all of
        them are read into memory). ``False`` opens the map for prediction only.

    Returns
    -------
    TiledMap
    """
    import tomllib

    directory = Path(directory)
    meta_path = directory / "tiled.json"
    fix = "save one with TiledMap.save(DIR) or 'gmmgp run SCAN --out DIR --tile-size 20'"
    if not meta_path.is_file():
        if (directory / "map.json").is_file():
            raise TilingError(f"'{directory}' holds a single map (map.json), not a tiled map "
                              "(tiled.json); open it with gmmgp_app.pipeline.load_map.")
        what = "does not exist" if not directory.exists() else "has no tiled.json"
        raise TilingError(f"'{directory}' is not a saved tiled map ({what}); {fix}.")
    try:
        meta = json.loads(meta_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise TilingError(f"'{meta_path}' is not valid JSON ({exc}); save the tiled map "
                          "again.") from None
    if not isinstance(meta, dict) or meta.get("format") != TILED_MAP_FORMAT:
        found = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
        raise TilingError(f"'{meta_path}' is not a tiled map description (format "
                          f"{found!r}, expected {TILED_MAP_FORMAT!r}); {fix}.")
    if meta.get("format_version") != TILED_MAP_FORMAT_VERSION:
        raise TilingError(f"Tiled map format version {meta.get('format_version')} in "
                          f"'{directory}' is not supported (expected "
                          f"{TILED_MAP_FORMAT_VERSION}); rebuild the map with this version.")
    try:
        spec = TileSpec(**meta["spec"])
        cfg = MappingConfig.from_dict(tomllib.loads(meta["config_toml"]))
        keys = [(int(k[0]), int(k[1])) for k in meta["tiles"]]
        owners = {(int(k[0]), int(k[1])): (int(o[0]), int(o[1])) for k, o in meta["owners"]}
        point_keys = [(int(k[0]), int(k[1])) for k in meta["points"]]
        method, offset = meta["method"], np.asarray(meta["offset"], dtype=np.float64)
    except KeyError as exc:
        raise TilingError(f"'{meta_path}' lacks the field {exc}; save the tiled map "
                          "again.") from None
    missing = [_tile_dirname(k) for k in keys
               if not (directory / "tiles" / _tile_dirname(k) / "map.json").is_file()]
    if missing:
        raise TilingError(f"Tiled map '{directory}' is incomplete: tiles/{missing[0]} is "
                          f"missing ({len(missing)} of {len(keys)} tiles); save the tiled "
                          "map again.")
    tile_points = {}
    if load_points:
        for key in point_keys:
            path = directory / "points" / f"{_tile_dirname(key)}.npz"
            if not path.is_file():
                raise TilingError(f"Tiled map '{directory}' is incomplete: points/"
                                  f"{path.name} is missing; save the tiled map again or "
                                  "load it with load_points=False.")
            with np.load(path, allow_pickle=False) as z:
                tile_points[key] = (z["points"], z["origins"] if "origins" in z.files
                                    else None)
    store = _TileStore(directory / "tiles", keys, cache=cache_tiles, read_only=True)
    return TiledMap(spec, store, cfg, method, offset=offset, tile_points=tile_points,
                    summary=meta.get("summary", {}), owners=owners)
