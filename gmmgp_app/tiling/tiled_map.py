"""The tiled map: a SurfaceMap-like field of independently mapped, overlapping tiles,
stitched by blending weights; building, saving and loading it."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from ..config import MappingConfig
from ..types import Scan, as_up_axis
from .geometry import (TileSpec, TilingError, members, owners_summary, tile_dirname,
                       union_points, split_into_tiles, tile_owners, warn_if_not_z_up)
from .store import TileStore
from .auto import resolve_tiles
from .tasks import largest_first, map_tiles_to_store, run_tiles

__all__ = ["TiledMap", "build_tiled_map", "load_tiled_map"]

TILED_MAP_FORMAT = "gmmgp-tiled-map"
TILED_MAP_FORMAT_VERSION = 1


class _StitchSums:
    """Per-query running sums of the tiles' stitching (:meth:`TiledMap.predict`):
    ``W = sum w_t``, ``sum w_t m_t``, ``sum w_t v_t``, ``sum w_t m_t^2``, and the
    stitched mean and variance from them, in one order of operations (so that
    :meth:`TiledMap.predict` and :meth:`TiledMap.distribution` agree bit for bit)."""

    def __init__(self, K: int):
        self.W = np.zeros(K)
        self.Wm = np.zeros(K)
        self.Wv = np.zeros(K)
        self.Wm2 = np.zeros(K)

    def add(self, rows, w, m, v) -> None:
        self.W[rows] += w
        self.Wm[rows] += w * m
        self.Wv[rows] += w * v
        self.Wm2[rows] += w * m * m

    def mean_var(self):
        """(mean, var, ok): ``mean = sum w m / W``, ``var = sum w v / W + sum w m^2 / W
        - mean^2`` (written so that a single tile of weight 1 returns its variance bit
        for bit) where ``ok = W > 0``, zeros elsewhere."""
        W, ok = self.W, self.W > 0
        mean = np.zeros(len(W))
        var = np.zeros(len(W))
        mean[ok] = self.Wm[ok] / W[ok]
        var[ok] = self.Wv[ok] / W[ok] + np.maximum(self.Wm2[ok] / W[ok] - mean[ok] ** 2, 0.0)
        return mean, var, ok


def _rows_by_key(key_arr) -> list:
    """``[(key, rows)]``: the distinct rows ``key`` (tuples of ints) of an (n, 2) integer
    array in ``np.unique(key_arr, axis=0)``'s lexicographic order, each with the indices
    of the rows equal to it. Each key packed into one int64 that keeps that order (a
    1-D unique; ``np.unique(axis=0)``'s row sort took 47 of 123 s of a tiled street's
    surface, docs/speed.md 'Seventh pass, tiled')."""
    k = np.asarray(key_arr, dtype=np.int64)
    if len(k) == 0:
        return []
    lo = k.min(0)
    span = int(k[:, 1].max() - lo[1]) + 1
    packed = (k[:, 0] - lo[0]) * span + (k[:, 1] - lo[1])
    return [((int(u // span + lo[0]), int(u % span + lo[1])), np.flatnonzero(packed == u))
            for u in np.unique(packed)]


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
    up : (3,) float64, optional
        The scan's up axis (``Scan.up``; default z), saved for viewers.
    """

    def __init__(self, spec: TileSpec, tiles: dict, config: MappingConfig, method: str,
                 offset=None, tile_points: Optional[dict] = None, summary=None,
                 owners: Optional[dict] = None, up=None):
        self.spec = spec
        self.up = as_up_axis(up)
        # a dict is copied; a lazy mapping (tiles on disk, views of tiles) is kept as is
        self.tiles = dict(tiles) if isinstance(tiles, dict) else tiles
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

    def predict(self, xyz, return_grad: bool = False, far: bool = True):
        """Stitched signed distance: mean (K,), variance (K,)[, gradient (K, 3)].
        ``far=False``: each tile's GP field without its far field (SurfaceMap.predict).

        Mixture of the tiles weighted by :meth:`TileSpec.weights` (renormalised
        over the mapped tiles): ``mean = sum w_t m_t``, ``var = sum w_t (v_t +
        m_t^2) - mean^2`` (so tiles that disagree widen the variance), and the
        gradient of that mean including the weights' gradient. A query no mapped
        tile weighs is answered by the nearest mapped tile.
        """
        from ..pipeline import as_queries

        x = as_queries(xyz)
        K = len(x)
        sums = _StitchSums(K)
        gW = np.zeros((K, 2))
        gWm = np.zeros((K, 3))
        for owner, rows, w, dw in self._tile_weights(x):
            out = self.tiles[owner].predict(x[rows], return_grad=return_grad, far=far)
            m = out[0]
            sums.add(rows, w, m, out[1])
            if return_grad:
                gW[rows] += dw
                gWm[rows] += w[:, None] * out[2]
                gWm[rows, :2] += m[:, None] * dw
        mean, var, ok = sums.mean_var()
        W = sums.W
        grad = np.zeros((K, 3))
        if return_grad:
            grad[ok] = gWm[ok] / W[ok, None]
            grad[ok, :2] -= mean[ok, None] * gW[ok] / W[ok, None]
        if (~ok).any() and self.tiles:
            self._nearest_tile(x, ~ok, mean, var, grad, return_grad, far)
        return (mean, var, grad) if return_grad else (mean, var)

    def distribution(self, xyz):
        """The stitched predictive distribution at query points (what :meth:`predict`
        summarises; :meth:`SurfaceMap.distribution` of a single map): an object with
        ``mean``, ``var``, ``std`` (K,), ``logpdf(y)`` and ``half_width(level)``.

        The choice: per query, the mixture of the tiles' predictives with the
        stitching weights of :meth:`predict`, ``p(y) = sum_t w_t p_t(y) / sum_t w_t``
        (each ``p_t`` the tile's :meth:`SurfaceMap.distribution`, a Gaussian or the
        two-component mixture of eq. unseen_mixture; a tile without one, such as the
        GMR prior of compare's hgmm baseline, the Gaussian of its ``predict``). Its
        ``mean`` and ``var`` are :meth:`predict`'s, computed the same way (``sum w_t
        m_t / W`` bit for bit; ``sum w_t (v_t + m_t^2) / W - mean^2`` with ``v_t`` each
        tile's reported variance), ``std = sqrt(var)``: the mixture's variance by the
        law of total variance, with each tile's reported sigma (its central 68.27 %
        half-width) in place of its own variance. ``logpdf`` is the mixture's log
        density and ``half_width(level)`` its exact central interval about the mean
        (stages/unseen.py, :class:`StitchedPredictive`); in blend zones
        ``half_width(0.6827)`` therefore differs from ``std``. Where one tile weighs a
        query (weight 1 inside its square, or the nearest tile beyond every tile) the
        result is that tile's distribution exactly.
        """
        from ..pipeline import StitchedPredictive, as_queries

        x = as_queries(xyz)
        sums = _StitchSums(len(x))
        parts = []
        for owner, rows, w, _ in self._tile_weights(x):
            d, v = self._tile_distribution(owner, x[rows])
            sums.add(rows, w, d.mean, v)
            parts.append((rows, w, d))
        # the same operations as predict: the same mean and variance bit for bit
        mean, var, ok = sums.mean_var()
        W = sums.W
        if (~ok).any() and self.tiles:
            for key, r in self._nearest_tiles(x, ~ok):
                d, v = self._tile_distribution(key, x[r])
                mean[r], var[r] = d.mean, v
                W[r] = 1.0
                parts.append((r, np.ones(len(r)), d))
        return StitchedPredictive(mean, var, parts, W)

    def _tile_distribution(self, key, x) -> tuple:
        """(predictive, reported variance) of tile ``key`` at ``x``: its
        ``distribution`` and that one's ``var`` (what its ``predict`` returns), or for a
        tile without one the Gaussian of its ``predict``."""
        tile = self.tiles[key]
        dist = getattr(tile, "distribution", None)
        if dist is not None:
            d = dist(x)
            return d, d.var
        from ..pipeline import UnseenMixture

        m, v = tile.predict(x)[:2]
        return UnseenMixture(m, v, reported_var=v), v

    def predict_mean(self, xyz) -> np.ndarray:
        """(K,) the mean of :meth:`predict` alone, the same values bit for bit: the
        stitching weights depend on the query's position only, not on the tiles'
        variances, so the stitched mean ``sum w_t m_t / sum w_t`` needs each tile's mean
        alone (:meth:`SurfaceMap.predict_mean`)."""
        return self._stitched_mean(xyz, "predict_mean")

    def lattice_mean(self, xyz) -> np.ndarray:
        """(K,) the field the stitched surface lattice is evaluated with: each tile's
        :meth:`SurfaceMap.lattice_mean` (its own ``surface.lattice_field``: the far
        field's mean with "far", the default, its :meth:`predict_mean` with "map"),
        stitched by :meth:`predict`'s weights, as :meth:`predict_mean` stitches the
        tiles' means (the nearest tile beyond every tile). With every tile on "map" it
        is :meth:`predict_mean` bit for bit; the vertices' mean and variance are
        :meth:`predict`'s either way."""
        return self._stitched_mean(xyz, "lattice_mean")

    def _stitched_mean(self, xyz, field: str) -> np.ndarray:
        """``sum w_t f_t / sum w_t`` of each tile's method ``field`` (one order of
        operations for :meth:`predict_mean` and :meth:`lattice_mean`, the same as
        :class:`_StitchSums`' mean)."""
        from ..pipeline import as_queries

        x = as_queries(xyz)
        K = len(x)
        W = np.zeros(K)
        Wm = np.zeros(K)
        for owner, rows, w, _ in self._tile_weights(x):
            m = getattr(self.tiles[owner], field)(x[rows])
            W[rows] += w
            Wm[rows] += w * m
        mean = np.zeros(K)
        ok = W > 0
        mean[ok] = Wm[ok] / W[ok]
        if (~ok).any() and self.tiles:
            for key, r in self._nearest_tiles(x, ~ok):
                mean[r] = getattr(self.tiles[key], field)(x[r])
        return mean

    def _tile_weights(self, x) -> list:
        """``[(owner, rows, w, dw)]``, sorted by owner: the queries ``rows`` each mapped
        tile weighs, with their weights (n,) and weight gradients (n, 2); the weight of
        a mapped tile is its own square's plus those of the squares it owns."""
        parts: dict = {}
        for key_arr in self.spec.candidate_keys(x[:, :2]):
            for key, rows in _rows_by_key(key_arr):
                owner = self._owner(key)
                if owner is None:
                    continue
                w, dw = self.spec.weights(x[rows, :2], key)
                keep = w > 0
                if keep.any():
                    parts.setdefault(owner, []).append((rows[keep], w[keep], dw[keep]))
        out = []
        for owner, pieces in sorted(parts.items()):
            if len(pieces) == 1:
                rows, w, dw = pieces[0]
            else:  # one prediction per query even when several squares weigh it
                rows, inv = np.unique(np.concatenate([r for r, _, _ in pieces]),
                                      return_inverse=True)
                w = np.bincount(inv, np.concatenate([q for _, q, _ in pieces]), len(rows))
                dwc = np.concatenate([d for _, _, d in pieces])
                dw = np.column_stack([np.bincount(inv, dwc[:, a], len(rows)) for a in (0, 1)])
            out.append((owner, rows, w, dw))
        return out

    def _nearest_tiles(self, x, miss) -> list:
        """``[(key, rows)]``: the queries ``miss`` no mapped tile weighs, grouped by the
        mapped tile whose square's centre is nearest (which answers for them)."""
        keys = np.array(self.keys, dtype=np.float64)
        centres = (keys + 0.5) * self.spec.size
        rows = np.flatnonzero(miss)
        d = np.linalg.norm(x[rows, None, :2] - centres[None], axis=2)
        pick = np.argmin(d, axis=1)
        return [(tuple(int(k) for k in keys[t]), rows[pick == t]) for t in np.unique(pick)]

    def _nearest_tile(self, x, miss, mean, var, grad, return_grad, far=True):
        for key, r in self._nearest_tiles(x, miss):
            out = self.tiles[key].predict(x[r], return_grad, far=far)
            mean[r], var[r] = out[0], out[1]
            if return_grad:
                grad[r] = out[2]

    def _weighs(self, key, xyz) -> np.ndarray:
        """Where mapped tile ``key`` has a non-zero weight (its square or one it owns)."""
        return tile_weighs(self.spec, self.owners, key, xyz)

    def extract_surface(self, voxel_size: Optional[float] = None, max_std=None,
                        progress=None, reach: Optional[float] = None, seeds=None,
                        trim_to_reach: Optional[bool] = None):
        """Marching cubes on the stitched field (seamless: one field, one lattice);
        ``seeds`` (where the surface is sought) default to :meth:`stitched_seeds` (a
        viewer's tile piece passes its tile's own), ``reach`` to :meth:`surface_reach`
        of them. The lattice is evaluated with
        :meth:`lattice_mean` (each tile's ``surface.lattice_field``, stitched), the
        vertices' mean and variance with :meth:`predict`, as
        :meth:`SurfaceMap.extract_surface` does for one map; with the tiled config's
        ``surface.project_steps`` > 0 the vertices take Newton steps onto
        :meth:`predict`'s zero level (its stitched gradient). ``trim_to_reach`` overrides
        the config's ``surface.trim_to_reach`` (a viewer's piece meshes untrimmed and trims
        against every tile's seeds)."""
        import dataclasses

        from ..pipeline import mesh_field

        cfg = self.config.surface
        if trim_to_reach is not None:
            cfg = dataclasses.replace(cfg, trim_to_reach=bool(trim_to_reach))
        if seeds is None:
            seeds = self.stitched_seeds()
        if voxel_size is None:
            voxel_size = self.surface_voxel()
        return mesh_field(self.predict, seeds, cfg, voxel_size, max_std,
                          progress, self.surface_reach(seeds) if reach is None else reach,
                          predict_mean=self.lattice_mean,
                          project=lambda x: self.predict(x, return_grad=True))

    def stitched_seeds(self) -> np.ndarray:
        """Where the stitched surface is sought: every tile's seed points (with smooth
        blending, those the tile weighs), without duplicates."""
        return self._stitch_seeds([self._tile_seeds(k, t) for k, t in self.tiles.items()])

    def _tile_seeds(self, key, tile) -> np.ndarray:
        """Tile ``key``'s share of :meth:`stitched_seeds` (with smooth blending, the seeds
        it weighs)."""
        if self.spec.blend == "smooth":
            return tile.seed_points[self._weighs(key, tile.seed_points)]
        return tile.seed_points

    @staticmethod
    def _stitch_seeds(parts) -> np.ndarray:
        """:meth:`stitched_seeds` of the tiles' shares: without duplicates, sorted."""
        return np.unique(np.concatenate(parts), axis=0) if parts else np.zeros((0, 3))

    def surface_reach(self, seeds) -> Optional[float]:
        """How far from a seed the stitched surface is followed (m), whatever voxel it
        is meshed at: :func:`stages.surface.surface_reach` of the stitched ``seeds`` at
        :meth:`extent_cell`, as :meth:`SurfaceMap.surface_reach` for one map."""
        from ..pipeline import surface_reach

        return surface_reach(seeds, self.extent_cell()) if len(seeds) else None

    def extent_cell(self) -> float:
        """The cell bounding the stitched surface's extent (m, ``surface.extent_cell``):
        the configured one, or with ``"auto"`` (each tile resolved it from its own
        points) the median of the tiles' values; the surface voxel for tiles made
        before the extent cell."""
        return self._median_extent([t.config.surface for _, t in self.tiles.items()])

    def _median_extent(self, surfaces) -> float:
        """:meth:`extent_cell` from the tiles' SurfaceConfigs."""
        from ..config import is_auto

        e = self.config.surface.extent_cell
        if not is_auto(e):
            return float(e)
        cells = [s.extent_cell for s in surfaces if not is_auto(s.extent_cell)]
        if not cells:
            return self._median_voxel([s.voxel_size for s in surfaces])
        return float(np.median(cells))

    def surface_voxel(self) -> float:
        """The surface voxel of the stitched mesh (m): the configured one, or with
        ``"auto"`` (each tile resolved it from its own points) the median of the tiles'
        values: one lattice needs one voxel."""
        from ..config import is_auto

        if not is_auto(self.config.surface.voxel_size):
            return float(self.config.surface.voxel_size)
        return self._median_voxel([t.config.surface.voxel_size for _, t in self.tiles.items()])

    def _median_voxel(self, voxels) -> float:
        """:meth:`surface_voxel` from the tiles' ``surface.voxel_size`` values."""
        from ..config import is_auto

        v = self.config.surface.voxel_size
        if not is_auto(v):
            return float(v)
        voxels = [x for x in voxels if not is_auto(x)]
        if not voxels:
            raise TilingError("The tiled map has no mapped tile with a surface voxel; "
                              "pass --voxel-size explicitly.")
        return float(np.median(voxels))

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
        from .._atomic import atomic_dir
        from .._json import jsonable

        directory = Path(directory)
        keys = self.keys
        with atomic_dir(directory) as tmp:
            (tmp / "tiles").mkdir()
            for key in keys:
                dest = tmp / "tiles" / tile_dirname(key)
                if isinstance(self.tiles, TileStore):
                    self.tiles.export(key, dest)
                else:
                    self.tiles[key].save(dest)
            if self.tile_points:
                (tmp / "points").mkdir()
                for key, (pts, org) in sorted(self.tile_points.items()):
                    arrays = {"points": np.asarray(pts, dtype=np.float64)}
                    if org is not None:
                        arrays["origins"] = np.asarray(org, dtype=np.float64)
                    np.savez(tmp / "points" / f"{tile_dirname(key)}.npz", **arrays)
            meta = {
                "format": TILED_MAP_FORMAT,
                "format_version": TILED_MAP_FORMAT_VERSION,
                "spec": dataclasses.asdict(self.spec),
                "method": self.method,
                "offset": [float(v) for v in self.offset],
                "up": [float(v) for v in self.up],
                "tiles": [list(k) for k in keys],
                "owners": [[list(k), list(o)] for k, o in sorted(self.owners.items())],
                "points": sorted(list(k) for k in self.tile_points),
                "summary": jsonable(self.summary),
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
        from .update import update_tiled_map

        return update_tiled_map(self, scan, refit_hgmm=refit_hgmm, executor=executor,
                                progress=progress, new_space_fraction=new_space_fraction,
                                new_space_voxel=new_space_voxel)



def tile_weighs(spec: TileSpec, owners, key, xyz) -> np.ndarray:
    """(N,) bool: where mapped tile ``key`` (with the small tiles it ``owners``) has a
    non-zero blending weight at the points ``xyz``."""
    w = np.zeros(len(xyz))
    for k in members(owners, key):
        w += spec.weights(np.asarray(xyz)[:, :2], k)[0]
    return w > 0


def check_stitched_grid(cfg: MappingConfig, spec: TileSpec, owners, tiles) -> None:
    """Refuse, before any tile is mapped, a stitched surface grid too large to extract
    at the tiles' shared voxel: the check the region-by-region mesh makes
    (:func:`~.mesh.stream_tiled_surface`), on the seeds the tile maps will have.

    ``tiles``: one ``(key, points)`` per mapped tile, ``points`` what it trains on (an
    iterable, read once: a streamed build loads one tile at a time here). Each tile
    seeks its surface from its own points (``pipeline.surface_seeds``); with smooth
    blending the stitched surface keeps the seeds where the tile weighs, as
    :meth:`TiledMap.stitched_seeds` does.

    Raises
    ------
    GridTooLargeError
        As :func:`stages.surface.check_grid_size`.
    """
    from ..pipeline import check_grid_size, surface_seeds

    parts = []
    for key, points in tiles:
        seeds = surface_seeds(points, cfg)
        parts.append(seeds[tile_weighs(spec, owners, key, seeds)]
                     if spec.blend == "smooth" else seeds)
    seeds = TiledMap._stitch_seeds(parts)
    del parts
    if len(seeds):
        check_grid_size(seeds, cfg.surface.voxel_size)


def build_tiled_map(scan: Scan, cfg: Optional[MappingConfig] = None,
                    spec: Optional[TileSpec] = None, method: str = "gmmgp", *,
                    executor=None, progress: Optional[Callable[[int, int], None]] = None,
                    keep_points: bool = True, work_dir=None, cache_tiles: int = 4,
                    check_grid: bool = False) -> TiledMap:
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
    work_dir : path, optional
        Keep the tile maps on disk in ``work_dir/maps`` as they finish (the returned
        map loads them on demand, ``cache_tiles`` at a time), as a streamed LAS build
        does: memory then holds a few tile maps, not all of them (``gmmgp run
        --tile-size 15`` of bench_scale's 8x street, 30 tiles: peak RSS 532 -> 263 MB
        without meshing, 1268 -> 1056 MB with). Default: every tile map in memory.
    check_grid : bool
        Refuse, before any tile is mapped, a stitched surface grid too large to extract
        at the tiles' shared voxel (``gmmgp run --tile-size`` with a mesh; the check
        the region-by-region mesh makes, :func:`check_stitched_grid`).

    Returns
    -------
    TiledMap
    """
    cfg = MappingConfig() if cfg is None else cfg
    spec = TileSpec() if spec is None else spec
    warn_if_not_z_up(scan)                       # tiles are cut in x and y
    tiles = split_into_tiles(scan, spec)
    owners = tile_owners({k: len(t) for k, t in tiles.items()}, spec.min_points)
    tasks = []
    for k, t in tiles.items():
        if len(t) < spec.min_points:
            continue
        pts, org = union_points([(tiles[m].points, tiles[m].origins) for m in members(owners, k)])
        tasks.append((k, pts, org, cfg, method))
    if not tasks:
        raise TilingError(f"Expected at least one tile with {spec.min_points} points, found "
                          f"{max((len(t) for t in tiles.values()), default=0)}; use larger "
                          "tiles or lower TileSpec.min_points.")
    # the "auto" fields resolved once, from the tiles' pooled measurements: every tile
    # gets the same lengths (tiling/auto.py)
    cfg, auto = resolve_tiles(cfg, ((members(owners, t[0]), t[1], t[2]) for t in tasks),
                              spec, len(scan))
    tasks = [t[:3] + ((cfg, auto) if auto else cfg,) + t[4:] for t in tasks]
    if check_grid:
        check_stitched_grid(cfg, spec, owners, ((t[0], t[1]) for t in tasks))
    if work_dir is None:
        maps, skipped = run_tiles(executor, tasks, progress)
    else:
        maps = TileStore(Path(work_dir) / "maps", [], cache=cache_tiles)
        skipped = map_tiles_to_store(executor, largest_first(tasks, [len(t[1]) for t in tasks]),
                                     maps, progress)
    if not len(maps):
        raise TilingError(f"Expected at least one tile to map, all {len(skipped)} failed; "
                          f"first: {next(iter(skipped.values()))}")
    kept = {k: (t.points, t.origins) for k, t in tiles.items()} if keep_points else None
    return TiledMap(spec, maps, cfg, method, offset=scan.offset, tile_points=kept,
                    owners=owners, up=scan.up,
                    summary=dict(n_tiles=len(maps), n_points=len(scan),
                                 absorbed_tiles=owners_summary(owners),
                                 skipped_tiles={str(k): v for k, v in skipped.items()},
                                 auto=auto))



def load_any_map(directory, *, load_points: bool = False):
    """A single map (:class:`~gmmgp_app.pipeline.SurfaceMap`) or a :class:`TiledMap` from
    ``directory``: a map folder (``map.json`` or ``tiled.json``) or a run folder of
    ``gmmgp run`` holding one in ``map/``. ``load_points`` as in :func:`load_tiled_map`."""
    from ..pipeline import MapFormatError, load_map

    d = Path(directory)
    if not d.is_dir():
        raise MapFormatError(f"Map folder '{d}' does not exist; make one with 'gmmgp run "
                             "SCAN --out DIR' (the map is DIR/map; DIR works too).")
    if not (d / "map.json").is_file() and not (d / "tiled.json").is_file() \
            and (d / "map").is_dir():
        d = d / "map"
    if (d / "tiled.json").is_file():
        return load_tiled_map(d, load_points=load_points)
    return load_map(d)


def load_tiled_map(directory, cache_tiles: int = 4, *, load_points: bool = True) -> TiledMap:
    """Open a tiled map written by :meth:`TiledMap.save`; it predicts identically.

    The tiles stay on disk and are loaded on demand, ``cache_tiles`` at a time
    (:class:`TileStore`); tiles replaced by :meth:`TiledMap.update` are kept in
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
    missing = [tile_dirname(k) for k in keys
               if not (directory / "tiles" / tile_dirname(k) / "map.json").is_file()]
    if missing:
        raise TilingError(f"Tiled map '{directory}' is incomplete: tiles/{missing[0]} is "
                          f"missing ({len(missing)} of {len(keys)} tiles); save the tiled "
                          "map again.")
    tile_points = {}
    if load_points:
        for key in point_keys:
            path = directory / "points" / f"{tile_dirname(key)}.npz"
            if not path.is_file():
                raise TilingError(f"Tiled map '{directory}' is incomplete: points/"
                                  f"{path.name} is missing; save the tiled map again or "
                                  "load it with load_points=False.")
            with np.load(path, allow_pickle=False) as z:
                tile_points[key] = (z["points"], z["origins"] if "origins" in z.files
                                    else None)
    store = TileStore(directory / "tiles", keys, cache=cache_tiles, read_only=True)
    return TiledMap(spec, store, cfg, method, offset=offset, tile_points=tile_points,
                    summary=meta.get("summary", {}), owners=owners,
                    up=meta.get("up"))   # saved before the up axis: z
