"""One set of automatic values for all the tiles of a scan.

A tiled map resolves its ``"auto"`` fields once, from the whole scan, so that every tile
(and a tile mapped again by :meth:`TiledMap.update`) has the same lengths, noises and
surface voxel, and the stitched mesh one voxel. The whole scan is never in memory in a
streamed build, so the scan is measured tile by tile: each tile samples the points whose
core square it owns (``pipeline.sample_scale``; its overlap margin
only gives neighbours) in proportion to their share of the scan, and the pooled samples
give the scan's spacing and noise (``pipeline.resolve_pooled``). The
in-memory build measures the same tiles the same way, so both give the same values.

The training budget is per tile (each tile trains on at most about the 100k points an
untiled map does): the lengths follow the spacing of the largest tile's training subset
(``pipeline.resolve_pooled``), and a scan whose tiles all hold fewer points than the
budget keeps all of them.
"""

from __future__ import annotations

from typing import Iterable

import numpy as np

from .geometry import TileSpec

__all__ = ["owned_mask", "resolve_tiles"]


def owned_mask(points: np.ndarray, spec: TileSpec, keys) -> np.ndarray:
    """(N,) bool: the points whose core square (``floor(xy / size)``) is one of ``keys``
    (a tile and the small tiles it owns, :func:`~.geometry.members`): each scan point is
    owned by exactly one mapped tile, whatever the overlap."""
    core = np.floor(np.asarray(points, dtype=np.float64)[:, :2] / spec.size).astype(np.int64)
    mine = np.zeros(len(core), dtype=bool)
    for k in keys:
        mine |= (core[:, 0] == k[0]) & (core[:, 1] == k[1])
    return mine


def resolve_tiles(cfg, parts: Iterable, spec: TileSpec, n_total: int) -> tuple:
    """``cfg`` with every ``"auto"`` field resolved once for all tiles, and the record of
    the chosen values and their reasons (``pipeline.resolve_config``'s), plus ``"tiles"``
    saying how they were measured. ``cfg`` unchanged and ``{}`` when nothing is
    ``"auto"`` (``parts`` is then not read).

    ``parts``: one ``(keys, points, origins)`` per mapped tile, ``keys`` the tile and
    the small tiles it owns (:func:`~.geometry.members`), ``points`` / ``origins`` what
    the tile trains on (an iterable, read once: a streamed build loads each tile here).
    ``n_total``: the scan's number of points (each owned by one tile). A scan too small
    or degenerate to measure gets the urban values, as an untiled map.
    """
    from ..pipeline import has_auto_fields, resolve_pooled, sample_scale

    if not has_auto_fields(cfg):
        return cfg, {}
    samples, largest, n_parts = [], np.zeros((0, 3)), 0
    for keys, pts, org in parts:
        n_parts += 1
        mine = owned_mask(pts, spec, keys)
        if mine.any() and len(pts) > 16:
            samples.append(sample_scale(pts, org, owned=mine, n_total=n_total))
        if len(pts) > len(largest):
            largest = pts
    cfg, record, budget = resolve_pooled(cfg, samples, largest, n_total)
    if "fallback" not in record:
        record["tiles"] = {
            "value": n_parts, "auto": False,
            "reason": (f"measured tile by tile: the points each of the {n_parts} tiles "
                       f"owns, pooled; lengths for the largest tile's training subset "
                       f"({len(largest)} points)")}
    return cfg, record
