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

Modules (one job each): :mod:`.geometry` (tile squares, blending weights, owners of
small tiles, point sets), :mod:`.tiled_map` (the stitched map, build/save/load),
:mod:`.update` (adding points), :mod:`.store` (tiles on disk, loaded on demand),
:mod:`.tasks` (one tile as an executor task), :mod:`.las` (streaming a LAS/LAZ file
into tiles, with its plan).
"""

from .geometry import TileSpec, TilingError, TilingWarning, split_into_tiles, tile_owners
from .las import build_tiled_map_from_las, spill_las_to_tiles, stream_plan, stream_tiles
from .tiled_map import TiledMap, build_tiled_map, load_any_map, load_tiled_map
from .update import update_gp_blocks

__all__ = ["TilingError", "TilingWarning", "TileSpec", "TiledMap", "build_tiled_map", "split_into_tiles",
           "tile_owners", "load_tiled_map", "load_any_map", "update_gp_blocks",
           "spill_las_to_tiles", "build_tiled_map_from_las", "stream_plan", "stream_tiles"]
