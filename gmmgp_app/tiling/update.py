"""The incremental update of a tiled map: new points refit only what they touch.

A touched tile keeps its HGMM/GMR prior and refits the GP blocks whose training
region holds a new point (:func:`gmmgp_app.pipeline.update_map`, the pipeline's
update recipe); a tile that is new, changes owners or whose new points are mostly
in new space is mapped again.
"""

from __future__ import annotations

from typing import Callable, Optional

import numpy as np

from ..config import MappingConfig
from ..types import Scan
from .geometry import (TilingError, canonical_order, members, owners_summary, tile_owners,
                       union_points)
from .tasks import run_tiles

__all__ = ["update_tiled_map", "update_gp_blocks"]


def update_tiled_map(tmap, scan: Scan, refit_hgmm: bool = False, executor=None,
                     progress: Optional[Callable[[int, int], None]] = None,
                     new_space_fraction: Optional[float] = 0.25,
                     new_space_voxel: float = 1.0) -> dict:
    """:meth:`TiledMap.update` (see there): add ``scan``'s points to ``tmap`` in place."""
    from ..pipeline import new_space_fraction as _new_space

    if not np.allclose(scan.offset, tmap.offset):
        raise TilingError(f"Expected the update's offset {tmap.offset.tolist()}, found "
                          f"{scan.offset.tolist()}; read it in the map's local frame.")
    if tmap.tiles and not tmap.tile_points:
        raise TilingError("This tiled map was built without keeping its points "
                          "(streamed input or keep_points=False), found none to update "
                          "from; rebuild it with build_tiled_map(..., keep_points=True).")
    parts = tmap.spec.assign(scan.points)
    old_points = dict(tmap.tile_points)
    new_points = {}
    for key, idx in parts.items():
        new_p = scan.points[idx]
        new_o = None if scan.origins is None else scan.origins[idx]
        old_p, old_o = tmap.tile_points.get(key, (np.zeros((0, 3)), None))
        all_p = np.concatenate([old_p, new_p])
        all_o = (None if (old_o is None and len(old_p)) or new_o is None
                 else np.concatenate([old_o if old_o is not None else np.zeros((0, 3)),
                                      new_o]))
        tmap.tile_points[key] = canonical_order(all_p, all_o)
        new_points[key] = new_p
    counts = {k: len(p) for k, (p, _) in tmap.tile_points.items()}
    owners = tile_owners(counts, tmap.spec.min_points)
    # mapped tiles whose training set changed: new points in their square or in a
    # small square they own, or a change in which small squares they own
    touched = {k if counts[k] >= tmap.spec.min_points else owners.get(k) for k in parts}
    moved = {t for t in set(owners.values()) | set(tmap.owners.values())
             if members(owners, t) != members(tmap.owners, t)}
    touched = sorted(t for t in touched | moved
                     if t is not None and counts.get(t, 0) >= tmap.spec.min_points)
    rebuild, report = [], dict(rebuilt_tiles=[], gp_updated_tiles=[], refit_blocks=0)
    for key in touched:
        group = members(owners, key)
        all_p, all_o = union_points([tmap.tile_points[k] for k in group])
        new_p = np.concatenate([new_points.get(k, np.zeros((0, 3))) for k in group])
        old_p = np.concatenate([old_points.get(k, (np.zeros((0, 3)), None))[0]
                                for k in group])
        if (refit_hgmm or key in moved or key not in tmap.tiles
                or tmap.tiles[key].gp is None
                or _new_space(old_p, new_p, new_space_voxel) > (
                    np.inf if new_space_fraction is None else new_space_fraction)):
            rebuild.append((key, all_p, all_o, tile_config(tmap), tmap.method))
        else:
            tmap.tiles[key], n = update_gp_blocks(tmap.tiles[key], all_p, all_o, new_p,
                                                  tmap.config, executor=executor)
            report["gp_updated_tiles"].append(key)
            report["refit_blocks"] += n
    tmap.owners = owners
    tmap.summary["absorbed_tiles"] = owners_summary(owners)
    maps, skipped = run_tiles(executor, rebuild, progress)
    report["skipped_tiles"] = skipped
    for key, smap in maps.items():
        tmap.tiles[key] = smap
        report["rebuilt_tiles"].append(key)
    return report


def tile_config(tmap):
    """What a tile of ``tmap`` is mapped again with (:func:`~.tasks.build_tile`): the
    map's configuration and the record of the ``"auto"`` fields it resolved once for all
    tiles (tiling/auto.py: the tile gets the lengths the others were made with, and the
    fields the scan chose stay free for the GP's marginal likelihood), or the
    configuration alone (a map saved before: the tile resolves its own)."""
    auto = tmap.summary.get("auto")
    return (tmap.config, auto) if isinstance(auto, dict) and auto else tmap.config


def update_gp_blocks(smap, all_points, all_origins, new_points, cfg: MappingConfig,
                     executor=None):
    """Refit the GP blocks of a tile's map whose training region holds a new point
    (:func:`gmmgp_app.pipeline.update_map`). Returns (SurfaceMap, blocks refitted)."""
    from ..pipeline import update_map

    return update_map(smap, all_points, all_origins, new_points, cfg, executor=executor)
