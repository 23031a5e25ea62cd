"""Mapping one tile as an executor task (module level so that it pickles): the tile's
points in (or the files holding them), its map out: saved by the worker straight into
the tile store's folder when the worker shares the store's filesystem, else its saved
files as bytes (:func:`gmmgp_app.pipeline.build_map`)."""

from __future__ import annotations

import os
import time

import numpy as np

from ..types import Scan
from .geometry import canonical_order, union_points


def build_tile(task):
    """Executor task: map one tile (module level so that it pickles).

    ``task`` is ``(key, points, origins, cfg, method)`` (``cfg`` a MappingConfig, or the
    ``(cfg, record)`` the scan's ``"auto"`` fields were resolved to for all tiles,
    tiling/auto.py: ``build_map(resolved=...)``) or, with a sixth element
    ``dest`` (a folder path), the same with the map saved by this process into
    ``dest`` (atomically) instead of returned: nothing but a few numbers travels back.
    ``points`` is an array or, for a streamed input, the tile's piece files (read
    here, by the worker). Returns ``(key, payload, stats)``: ``payload`` is the saved
    map's files as ``{name: bytes}``, ``None`` when saved into ``dest``, or a string
    saying why the tile could not be mapped; ``stats`` (wall and CPU seconds of
    reading, mapping and saving, the process id, numba's thread count, bytes returned)
    is what :func:`map_tiles_to_store` reports per tile.
    """
    key, points, origins, cfg, method = task[:5]
    dest = task[5] if len(task) > 5 else None
    from ..pipeline import HGMMError, PrepareError, build_map

    t0, c0, h0 = time.time(), time.process_time(), time.thread_time()
    pts, org = tile_points(points, origins)
    t1, c1 = time.time(), time.process_time()
    stats = dict(key=list(key), pid=os.getpid(), n_points=int(len(pts)), start=t0,
                 read_s=t1 - t0, read_cpu_s=c1 - c0, numba_threads=_numba_threads())
    try:
        resolved = cfg if isinstance(cfg, tuple) else None
        smap = build_map(Scan(points=pts, origins=org, source=f"tile {key}"),
                         cfg[0] if resolved else cfg, method, resolved=resolved)
    except (PrepareError, HGMMError) as exc:
        # too sparse for normals, or too few hit points with one for the HGMM: its
        # neighbours answer its queries (reported in ``skipped_tiles``)
        payload = f"{type(exc).__name__}: {exc}"
    else:
        del pts, org
        t2, c2 = time.time(), time.process_time()
        stats.update(map_s=t2 - t1, map_cpu_s=c2 - c1)
        if dest is not None:
            smap.save(dest)
            payload = None
        else:
            payload = map_to_bytes(smap)
        del smap
    t3, c3 = time.time(), time.process_time()
    # thread_cpu_s: this thread's own CPU (a parallel numba loop's chunks on other
    # threads excluded): with the loops split evenly, about the wall on free cores
    stats.update(end=t3, seconds=t3 - t0, cpu_s=c3 - c0, thread_cpu_s=time.thread_time() - h0,
                 threading_layer=_threading_layer(),
                 save_s=t3 - t0 - stats["read_s"] - stats.get("map_s", t3 - t1),
                 bytes_returned=(sum(len(b) for b in payload.values())
                                 if isinstance(payload, dict) else 0))
    return key, payload, stats


def tile_points(points, origins) -> tuple:
    """What a tile trains on, ``(points, origins)`` in canonical order, from a task's
    ``points`` and ``origins`` (:func:`build_tile`): an array, or a streamed tile's
    piece files (per tile, the tile and then the small tiles it owns: its point and
    origin files), read here."""
    if isinstance(points, (list, tuple)):  # spilled chunks on disk (streaming input)
        parts = [(np.concatenate([np.load(f) for f in pf]),
                  np.concatenate([np.load(f) for f in of]) if of else None)
                 for pf, of in points]
        return union_points(parts)
    return canonical_order(np.asarray(points, dtype=np.float64), origins)


def _threading_layer() -> str:
    import sys

    try:
        return str(sys.modules["numba"].threading_layer())
    except Exception:  # noqa: BLE001 - no numba, or no parallel kernel run yet
        return ""


def _numba_threads() -> int:
    import sys

    if "numba" not in sys.modules:
        return 0
    return int(sys.modules["numba"].get_num_threads())


def map_to_bytes(smap) -> dict:
    """A SurfaceMap as ``{relative path: bytes}`` of its saved folder (``map.json``,
    ``arrays/gp/L.npy``, ...: :func:`gmmgp_app.map_io.folder_files`; no pickle of
    internals: the GMR field holds a lock, and the saved format is what crosses machines
    safely)."""
    import tempfile
    from pathlib import Path

    from ..map_io import folder_files

    with tempfile.TemporaryDirectory() as d:
        smap.save(Path(d) / "m")
        return folder_files(Path(d) / "m")


def map_from_bytes(files: dict):
    import tempfile
    from pathlib import Path

    from ..map_io import write_files
    from ..pipeline import load_map

    with tempfile.TemporaryDirectory() as d:
        write_files(Path(d), files)
        return load_map(d)


def largest_first(tasks, sizes) -> list:
    """``tasks`` ordered by ``sizes`` (points per tile), largest first, ties in the given
    order: with tiles handed to the next free worker, the last tiles to start are the
    small ones, so the workers finish close together (longest processing time first)."""
    order = sorted(range(len(tasks)), key=lambda i: -int(sizes[i]))
    return [tasks[i] for i in order]


def map_tiles_to_store(executor, tasks, store, progress=None, *, workers_write=None,
                       stats=None) -> dict:
    """Map the tile ``tasks`` into ``store`` (a :class:`~.store.TileStore` on disk) as they
    finish: a sliding window of tiles, a free worker starting the next tile at once.

    ``workers_write``: each task's process saves its map into the store's folder itself
    (the tile's points read from its files there too, for a streamed input), so that no
    map crosses between processes; default: when the executor says it shares this
    machine's filesystem (``executor.shared_filesystem``: the serial executor and the
    local workers of :func:`gmmgp_app.distributed.open_executor`). Otherwise each
    finished map's saved files come back as bytes and are written here as they are.
    A read-only store always gets the maps back (it keeps them in memory).
    ``stats``: a list that receives one dict per tile (:func:`build_tile`'s, plus the
    seconds this process spent storing it). Returns the skipped tiles' reasons by key
    (too sparse to map)."""
    from ..distributed import imap_unordered

    if workers_write is None:
        workers_write = bool(getattr(executor, "shared_filesystem", executor is None))
    workers_write = workers_write and not store.read_only
    if workers_write:
        tasks = [tuple(t[:5]) + (str(store._path(t[0])),) for t in tasks]
    skipped = {}
    for done, (_, (key, b, st)) in enumerate(imap_unordered(executor, build_tile, tasks,
                                                            window=4), start=1):
        t0 = time.time()
        if isinstance(b, str):
            skipped[key] = b
        elif b is None:
            store._stored(key)     # saved into the store's folder by the worker
        else:
            store.put_saved(key, b)  # the worker's saved files, not loaded here
        if stats is not None:
            stats.append(dict(st, received=t0, store_s=time.time() - t0))
        if progress is not None:
            progress(done, len(tasks))
    return dict(sorted(skipped.items()))


def run_tiles(executor, tasks, progress):
    from ..distributed import map_batched

    maps, skipped = {}, {}
    for k, b, _ in map_batched(executor, build_tile, tasks, progress=progress):
        if isinstance(b, str):
            skipped[k] = b
        else:
            maps[k] = map_from_bytes(b)
    return maps, skipped
