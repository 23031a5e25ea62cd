"""The on-disk tile store: tile maps saved as folders, loaded on demand (a few kept in
memory), so memory stays bounded by a few tiles however long the street."""

from __future__ import annotations

from .geometry import tile_dirname

__all__ = ["TileStore"]


class TileStore:
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
        return self.directory / tile_dirname(key)

    def __contains__(self, key):
        return key in set(self._keys)

    def __iter__(self):
        return iter(self._keys)

    def __len__(self):
        return len(self._keys)

    def get(self, key, default=None):
        return self[key] if key in self else default

    def __getitem__(self, key):
        from ..pipeline import load_map

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

    def load_uncached(self, key):
        """Tile ``key`` loaded from disk (or its replacement in memory) without entering
        it in the cache: for a caller that holds tiles itself (the streamed surface)."""
        from ..pipeline import load_map

        if key in self._written:
            return self._written[key]
        if key not in self:
            raise KeyError(key)
        return self._cache[key] if key in self._cache else load_map(self._path(key))

    def __setitem__(self, key, smap):
        if self.read_only:
            self._written[key] = smap
        else:
            smap.save(self._path(key))
        self._stored(key)

    def _stored(self, key) -> None:
        """Index tile ``key`` just stored and drop a stale loaded copy of it."""
        if key not in self:
            self._keys = sorted(self._keys + [key])
        self._cache.pop(key, None)

    def put_saved(self, key, files: dict) -> None:
        """Store tile ``key`` from the files of its saved map folder (``{relative path:
        bytes}``, :func:`gmmgp_app.tiling.tasks.map_to_bytes`): written as they are,
        atomically, instead of loaded and saved again (the same files: a map's save of its
        load is byte for byte its save). A read-only store keeps the loaded map in memory."""
        if self.read_only:
            from .tasks import map_from_bytes

            self[key] = map_from_bytes(files)
            return
        from .._atomic import atomic_dir
        from ..map_io import write_files

        with atomic_dir(self._path(key)) as tmp:
            write_files(tmp, files)
        self._stored(key)

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
