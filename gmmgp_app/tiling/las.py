"""LAS/LAZ streaming into tiles: the plan (can this file be streamed, in which local
frame), spilling chunks into per-tile pieces on disk, and mapping them tile by tile."""

from __future__ import annotations

from typing import Callable, Optional

import numpy as np

from ..config import MappingConfig
from .geometry import TileSpec, TilingError, members, owners_summary, tile_owners
from .store import TileStore
from .auto import resolve_tiles
from .tasks import largest_first, map_tiles_to_store, tile_points
from .tiled_map import TiledMap, check_stitched_grid

__all__ = ["spill_las_to_tiles", "build_tiled_map_from_las", "stream_plan", "stream_tiles",
           "STREAM_CHUNK_POINTS"]

#: Points per chunk when streaming a LAS/LAZ file into tiles (one chunk in memory).
STREAM_CHUNK_POINTS = 1_000_000


def stream_plan(paths, reader_kwargs: dict, no_stream: bool = False) -> tuple:
    """Whether a tiled run streams its input: ``(plan, fallback, notice)``.

    ``plan`` is None (read the scan whole) or a dict with the LAS/LAZ ``path``, the
    local ``offset`` and whether the file has ``origins`` (extra dimensions
    ``origin_x/y/z``). ``fallback`` says why a single LAS/LAZ file is read whole
    (None when it streams, or when the input is not a single LAS/LAZ file: only the
    in-memory readers know other formats and folders); ``notice`` is the one-line
    message for the user when that costs memory (else None).

    Streaming (:func:`build_tiled_map_from_las`) reads the stored coordinates as
    they are, every point of the file. So it is used only when that is exactly what
    :func:`gmmgp_app.datasets.read_scan` would return: no class filter, no pose
    file, no scan selection, and coordinates already in metres (the ``units``
    override or the file's CRS unit has a factor of 1). Anything else falls back to
    the in-memory reader instead of being re-implemented here: applying a class
    filter or a unit factor while streaming would need each chunk transformed, and
    mapping feet as metres would silently scale every length parameter of the
    config by 3.3. Options the reader refuses for a single file (``max_scans``, a
    CRS in degrees) also fall back, silently, so that the reader's own error and fix
    are what the user sees.
    """
    import warnings
    from pathlib import Path

    from ..datasets import OFFSET_THRESHOLD_M, auto_offset, parse_units, read_las_header

    if len(paths) != 1:
        return None, None, None
    path = Path(paths[0])
    if path.suffix.lower() not in (".las", ".laz") or path.is_dir():
        return None, None, None
    kw = reader_kwargs
    hdr = read_las_header(path)
    if hdr is None:
        return None, "unreadable header", None  # the in-memory reader reports it
    horiz, vert = hdr["horizontal"], hdr["vertical"]
    why, notice = None, True
    if no_stream:
        why, notice = "--no-stream", False
    elif "classes" in kw or "poses" in kw:
        why = f"{'--classes' if 'classes' in kw else '--poses'} is applied by the in-memory " \
              "reader only"
    elif "max_scans" in kw:
        return None, "--max-scans", None
    elif "units" in kw:
        if parse_units(kw["units"])[1] != 1.0:
            why = f"--units {kw['units']} scales the coordinates, which streaming does not do"
    elif horiz == "degrees":
        return None, "CRS in degrees", None
    elif any(u is not None and float(u) != 1.0 for u in (horiz, vert)):
        why = "the file's CRS unit is not the metre and streaming does not scale coordinates"
    if why is not None:
        msg = (f"{why}, so '{path}' is read whole instead of streamed into tiles (memory ~ "
               "the whole scan).") if notice else None
        return None, why, msg
    if horiz is None and hdr["crs"] and "units" not in kw:  # as the reader warns
        warnings.warn(f"Could not find a linear unit in the CRS of '{path}'; assuming "
                      "metres. Pass --units ft or --units us-ft if that is wrong.")
    # The offset the reader would choose (datasets finalize, offset="auto": a LAS holds
    # no local offset of its own), so that a streamed map and an in-memory one share
    # their local frame and hence their tile boundaries. The header's bounds stand in
    # for the points' (the same for files written by laspy, PDAL or LAStools; should a
    # header lie, the map is still consistent, only its tile grid is shifted).
    lo, hi = hdr["mins"], hdr["maxs"]
    far = max(np.abs(lo).max(), np.abs(hi).max()) > OFFSET_THRESHOLD_M
    offset = auto_offset(lo) if far else np.zeros(3)
    return {"path": path, "offset": offset, "origins": hdr["origins"]}, None, None


def stream_tiles(plan: dict, cfg, spec, method: str, work, executor, progress,
                 check_grid: bool = False):
    """:func:`build_tiled_map_from_las` of a :func:`stream_plan`, with laspy's and
    lazrs's errors on a file whose points are corrupt turned into a ScanReadError."""
    import laspy

    from ..datasets import ScanReadError

    errors = (laspy.errors.LaspyException,)
    try:
        import lazrs

        errors += (lazrs.LazrsError,)
    except ImportError:  # no LAZ backend: laspy raises a LaspyException saying so
        pass
    try:
        return build_tiled_map_from_las(plan["path"], cfg, spec, method, work_dir=work,
                                        executor=executor, chunk_size=STREAM_CHUNK_POINTS,
                                        progress=progress, offset=plan["offset"],
                                        check_grid=check_grid)
    except errors as exc:
        raise ScanReadError(f"Cannot stream '{plan['path']}' as LAS/LAZ ({type(exc).__name__}:"
                            f" {exc}); the file is corrupt or truncated, export or download it "
                            "again.") from None


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
                             cache_tiles: int = 4, offset=None,
                             tile_stats: Optional[list] = None,
                             check_grid: bool = False) -> TiledMap:
    """Stream a LAS/LAZ file into tiles and map them, with memory bounded by a tile.

    The file is read chunk by chunk into per-tile pieces on disk
    (:func:`spill_las_to_tiles`); each tile task loads only its own pieces, and
    each finished tile map is saved under ``work_dir/maps`` and dropped from
    memory (the returned map loads tiles on demand, ``cache_tiles`` at a time).
    Peak memory is therefore that of one chunk or one tile's mapping (per
    worker), not of the whole file. ``offset`` is the local-frame shift (default:
    see :func:`spill_las_to_tiles`); tiles are aligned in the local frame.

    The tiles are handed out largest first, and the workers read their pieces and
    save their maps in ``work_dir`` themselves (``executor.shared_filesystem``; the
    pieces' paths already assume it), so only file names and a few numbers cross
    between processes. ``tile_stats``: a list that receives one dict per tile
    (seconds and CPU seconds of reading, mapping and saving, the worker's process id;
    :func:`~.tasks.map_tiles_to_store`). ``check_grid``: refuse, before any tile is
    mapped, a stitched surface grid too large to extract
    (:func:`~.tiled_map.check_stitched_grid`; a second pass over the pieces, one tile in
    memory at a time).

    Returns
    -------
    TiledMap (without the points :meth:`TiledMap.update` needs; re-stream to update)
    """
    from pathlib import Path

    cfg = MappingConfig() if cfg is None else cfg
    spec = TileSpec() if spec is None else spec
    work_dir = Path(work_dir)
    pieces, off, n = spill_las_to_tiles(path, spec, work_dir / "pieces", chunk_size, offset)
    counts = {key: sum(int(np.load(f, mmap_mode="r").shape[0]) for f in pfiles)
              for key, (pfiles, _) in pieces.items()}
    owners = tile_owners(counts, spec.min_points)
    tasks, sizes = [], []
    for key in sorted(pieces):
        if counts[key] >= spec.min_points:
            mem = members(owners, key)
            files = [(pieces[m][0], pieces[m][1] if len(pieces[m][1]) == len(pieces[m][0])
                      else []) for m in mem]
            tasks.append((key, files, None, cfg, method))
            sizes.append(sum(counts[m] for m in mem))
    # the "auto" fields resolved once for all tiles (tiling/auto.py): a first pass
    # reads each tile's pieces (one tile in memory at a time)
    cfg, auto = resolve_tiles(cfg, ((members(owners, t[0]), *tile_points(t[1], None))
                                    for t in tasks), spec, n)
    tasks = [t[:3] + ((cfg, auto) if auto else cfg,) + t[4:] for t in tasks]
    if check_grid:
        check_stitched_grid(cfg, spec, owners, ((t[0], tile_points(t[1], None)[0])
                                                for t in tasks))
    store = TileStore(work_dir / "maps", [], cache=cache_tiles)
    skipped = map_tiles_to_store(executor, largest_first(tasks, sizes), store, progress,
                                 workers_write=True, stats=tile_stats)
    if not len(store):
        raise TilingError(f"Expected at least one tile with {spec.min_points} points in "
                          f"'{path}', found none that could be mapped.")
    return TiledMap(spec, store, cfg, method, offset=off, owners=owners,
                    summary=dict(n_tiles=len(store), n_points=n,
                                 absorbed_tiles=owners_summary(owners),
                                 skipped_tiles={str(k): v for k, v in skipped.items()},
                                 auto=auto))
