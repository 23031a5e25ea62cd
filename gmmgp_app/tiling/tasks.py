"""Mapping one tile as an executor task (module level so that it pickles): the tile's
points in, its saved map as bytes out (:func:`gmmgp_app.pipeline.build_map`)."""

from __future__ import annotations

import numpy as np

from ..types import Scan
from .geometry import canonical_order, union_points



def build_tile(task):
    """Executor task: map one tile (module level so that it pickles)."""
    key, points, origins, cfg, method = task
    from ..pipeline import HGMMError, PrepareError, build_map

    if isinstance(points, (list, tuple)):  # spilled chunks on disk (streaming input)
        # per tile (the tile, then the small tiles it owns): its point and origin files
        parts = [(np.concatenate([np.load(f) for f in pf]),
                  np.concatenate([np.load(f) for f in of]) if of else None)
                 for pf, of in points]
        pts, org = union_points(parts)
    else:
        pts, org = canonical_order(np.asarray(points, dtype=np.float64), origins)
    try:
        smap = build_map(Scan(points=pts, origins=org, source=f"tile {key}"), cfg, method)
    except (PrepareError, HGMMError) as exc:
        # too sparse for normals, or too few hit points with one for the HGMM: its
        # neighbours answer its queries (reported in ``skipped_tiles``)
        return key, f"{type(exc).__name__}: {exc}"
    return key, map_to_bytes(smap)


def map_to_bytes(smap) -> dict:
    """A SurfaceMap as ``{file name: bytes}`` of its saved folder (no pickle of internals:
    the GMR field holds a lock, and the saved format is what crosses machines safely)."""
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as d:
        smap.save(Path(d) / "m")
        return {p.name: p.read_bytes() for p in (Path(d) / "m").iterdir()}


def map_from_bytes(files: dict):
    import tempfile
    from pathlib import Path

    from ..pipeline import load_map

    with tempfile.TemporaryDirectory() as d:
        for name, data in files.items():
            (Path(d) / name).write_bytes(data)
        return load_map(d)


def map_tiles_to_store(executor, tasks, store, progress=None) -> dict:
    """Map the tile ``tasks`` into ``store`` (a :class:`~.store.TileStore` on disk) as they
    finish: a sliding window of tiles, each finished map's saved files written as they
    are and dropped (at most a few maps in memory), a free worker starting the next
    tile at once. Returns the skipped tiles' reasons by key (too sparse to map)."""
    from ..distributed import imap_unordered

    skipped = {}
    for done, (_, (key, b)) in enumerate(imap_unordered(executor, build_tile, tasks,
                                                        window=4), start=1):
        if isinstance(b, str):
            skipped[key] = b
        else:
            store.put_saved(key, b)  # the worker's saved files, not loaded here
        if progress is not None:
            progress(done, len(tasks))
    return dict(sorted(skipped.items()))


def run_tiles(executor, tasks, progress):
    from ..distributed import map_batched

    maps, skipped = {}, {}
    for k, b in map_batched(executor, build_tile, tasks, progress=progress):
        if isinstance(b, str):
            skipped[k] = b
        else:
            maps[k] = map_from_bytes(b)
    return maps, skipped
