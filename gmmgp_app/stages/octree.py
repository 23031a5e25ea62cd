"""Grid-aligned leaf blocks for the local GPs (paper Sec. V-B, "Octree" partition).

Space is cut into cubes of edge ``block_size`` aligned to the grid ``i * block_size``;
only *occupied* leaves (cubes holding at least one GP point) exist, kept as a
sorted table of packed integer cell coordinates (a hash of the leaves of an octree,
without the inner nodes that nothing here needs). A block trains on the points
within ``(1 + overlap) * block_size / 2`` of its centre in the L-infinity norm, and
a query is predicted by every block whose training region contains it.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from gmmgp_app.stages import _distinct

__all__ = ["OctreeError", "BlockGrid", "new_space_fraction"]

_BITS = 21
_BIAS = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1


class OctreeError(ValueError):
    """Bad input to the block partition."""


@njit(cache=True, inline="always")
def _key(c0, c1, c2):
    """One int64 per cell within +-_BIAS: 21 bits per axis, sortable."""
    return ((c0 + _BIAS) << (2 * _BITS)) | ((c1 + _BIAS) << _BITS) | (c2 + _BIAS)


@njit(cache=True, nogil=True)
def _pack(cells):
    """Keys of (n, 3) cells (all within +-_BIAS)."""
    out = np.empty(cells.shape[0], dtype=np.int64)
    for i in range(cells.shape[0]):
        out[i] = _key(cells[i, 0], cells[i, 1], cells[i, 2])
    return out


@njit(cache=True, nogil=True)
def _find(packed, c0, c1, c2):
    """Index of cell (c0, c1, c2) in the sorted packed table, -1 if absent."""
    if c0 < -_BIAS or c0 >= _BIAS or c1 < -_BIAS or c1 >= _BIAS or c2 < -_BIAS or c2 >= _BIAS:
        return -1
    k = _key(c0, c1, c2)
    j = np.searchsorted(packed, k)
    if j < packed.shape[0] and packed[j] == k:
        return j
    return -1


@njit(cache=True, nogil=True)
def _lookup(packed, cells):
    """:func:`_find` of every (n, 3) cell: the binary-search oracle that
    :func:`_hlookup` (what :meth:`BlockGrid.lookup` uses) is tested against."""
    out = np.empty(cells.shape[0], dtype=np.int64)
    for i in range(cells.shape[0]):
        out[i] = _find(packed, cells[i, 0], cells[i, 1], cells[i, 2])
    return out


@njit(cache=True, nogil=True)
def _hlookup(tk, tv, cells):
    """:func:`_hfind` of every (n, 3) cell (the indices :func:`_lookup` gives)."""
    out = np.empty(cells.shape[0], dtype=np.int64)
    for i in range(cells.shape[0]):
        out[i] = _hfind(tk, tv, cells[i, 0], cells[i, 1], cells[i, 2])
    return out


@njit(cache=True, nogil=True)
def _hash_table(packed):
    """Open-addressing table of the sorted packed keys: ``(tk, tv)`` of a power-of-two
    size at least twice the number of keys, ``tk`` the key (-1 empty; packed keys are
    non-negative), ``tv`` its index in ``packed`` (what :func:`_find` returns). Written
    here rather than shared with _distinct.py's or knn.py's tables: numba's on-disk
    cache of this file's kernels would not see a change to another file's function."""
    size = 16
    while size < 2 * packed.shape[0]:
        size *= 2
    tk = np.full(size, -1, dtype=np.int64)
    tv = np.full(size, -1, dtype=np.int64)
    mask = size - 1
    for j in range(packed.shape[0]):
        s = _hslot(packed[j], mask)
        while tk[s] != -1:
            s = (s + 1) & mask
        tk[s] = packed[j]
        tv[s] = j
    return tk, tv


@njit(cache=True, inline="always")
def _hslot(k, mask):
    """Home slot of key ``k`` (xor-shift, multiply, xor-shift: every axis's bits reach
    the low bits that ``mask`` keeps)."""
    h = k ^ (k >> np.int64(33))
    h = h * np.int64(-7046029254386353131)
    h = h ^ (h >> np.int64(29))
    return h & mask


@njit(cache=True, inline="always")
def _hfind(tk, tv, c0, c1, c2):
    """:func:`_find` through the hash table of :func:`_hash_table` (the same index,
    -1 if absent): one probe run instead of a binary search."""
    if c0 < -_BIAS or c0 >= _BIAS or c1 < -_BIAS or c1 >= _BIAS or c2 < -_BIAS or c2 >= _BIAS:
        return -1
    k = _key(c0, c1, c2)
    mask = tk.shape[0] - 1
    s = _hslot(k, mask)
    while True:
        t = tk[s]
        if t == k:
            return tv[s]
        if t == -1:
            return -1
        s = (s + 1) & mask


@njit(cache=True, parallel=True, nogil=True)
def _cover_pairs(lo, hi, nb, tk, tv):
    """(point, block) pairs for per-point cell ranges [lo, hi], sorted by block, then
    by point; ``nb`` blocks, looked up in the hash table ``(tk, tv)`` of
    :func:`_hash_table`.

    One lookup pass (the blocks found per point kept in a scratch table; points in
    parallel, each writing its own row), then a counting sort by block: no second
    search and no comparison sort.
    """
    n = lo.shape[0]
    width = 0
    for i in range(n):
        w = (hi[i, 0] - lo[i, 0] + 1) * (hi[i, 1] - lo[i, 1] + 1) * (hi[i, 2] - lo[i, 2] + 1)
        width = max(width, w)
    found = np.empty((n, max(width, 1)), dtype=np.int64)
    nfound = np.zeros(n, dtype=np.int64)
    per_block = np.zeros(nb + 1, dtype=np.int64)
    for i in prange(n):
        m = 0
        for a in range(lo[i, 0], hi[i, 0] + 1):
            for b in range(lo[i, 1], hi[i, 1] + 1):
                for c in range(lo[i, 2], hi[i, 2] + 1):
                    j = _hfind(tk, tv, a, b, c)
                    if j >= 0:
                        found[i, m] = j
                        m += 1
        nfound[i] = m
    for i in range(n):
        for t in range(nfound[i]):
            per_block[found[i, t] + 1] += 1
    for j in range(nb):
        per_block[j + 1] += per_block[j]
    count = per_block[nb]
    pts = np.empty(count, dtype=np.int64)
    blk = np.empty(count, dtype=np.int64)
    for i in range(n):                    # points ascending: stable within a block
        for t in range(nfound[i]):
            j = found[i, t]
            k = per_block[j]
            pts[k] = i
            blk[k] = j
            per_block[j] = k + 1
    return pts, blk


class BlockGrid:
    """Occupied leaf blocks and the mapping of points to the blocks that cover them.

    Parameters
    ----------
    keys : (B, 3) int64
        Integer cell coordinates of the occupied leaves (any order; stored sorted).
    block_size : float
        Leaf edge in metres.
    overlap : float
        Training region half-edge is ``(1 + overlap) * block_size / 2``.
    """

    def __init__(self, keys, block_size: float, overlap: float):
        if not (block_size > 0 and math.isfinite(block_size)):
            raise OctreeError(f"Expected a positive block_size, found {block_size}.")
        if not (overlap >= 0 and math.isfinite(overlap)):
            raise OctreeError(f"Expected overlap >= 0, found {overlap}.")
        keys = np.asarray(keys, dtype=np.int64).reshape(-1, 3)
        if len(keys) and (keys.min() < -_BIAS or keys.max() >= _BIAS):
            raise OctreeError(
                f"Expected block coordinates within +-{_BIAS} cells, found "
                f"[{keys.min()}, {keys.max()}]; shift the scan to a local frame or use "
                "larger blocks.")
        packed = _pack(keys)
        order = np.argsort(packed)
        self.keys = np.ascontiguousarray(keys[order])
        self._packed = packed[order]
        if len(np.unique(self._packed)) != len(self._packed):
            raise OctreeError("Expected distinct block keys, found duplicates.")
        self._table = None          # hash table of _packed (_table_of), built on first use
        self.block_size = float(block_size)
        self.overlap = float(overlap)

    @classmethod
    def from_points(cls, points: np.ndarray, block_size: float, overlap: float) -> "BlockGrid":
        """The leaves occupied by ``points`` (P, 3)."""
        if not (block_size > 0 and math.isfinite(block_size)):
            raise OctreeError(f"Expected a positive block_size, found {block_size}.")
        points = np.asarray(points, dtype=np.float64)
        first = _distinct.cell_first(points, block_size)    # hashed: no sort of P rows
        if first is not None:        # distinct cells in point order; __init__ sorts them
            return cls(np.floor(points[first] / block_size).astype(np.int64), block_size,
                       overlap)
        cells = np.floor(points / block_size).astype(np.int64)
        return cls(np.unique(cells, axis=0), block_size, overlap)

    @property
    def n_blocks(self) -> int:
        return len(self.keys)

    @property
    def centres(self) -> np.ndarray:
        """(B, 3) block centres."""
        return (self.keys + 0.5) * self.block_size

    @property
    def half_extent(self) -> float:
        """Half-edge of the training (and prediction) region of a block."""
        return 0.5 * (1.0 + self.overlap) * self.block_size

    def lookup(self, cells: np.ndarray) -> np.ndarray:
        """Block index of each (n, 3) integer cell, -1 where the cell is unoccupied."""
        cells = np.ascontiguousarray(np.asarray(cells, dtype=np.int64).reshape(-1, 3))
        return _hlookup(*self._table_of(), cells)

    def _table_of(self) -> tuple:
        """The hash table ``(tk, tv)`` of the sorted keys (:func:`_hash_table`), built once
        on first use and shared by :meth:`lookup` and :meth:`cover`."""
        if self._table is None:
            self._table = _hash_table(self._packed)
        return self._table

    def cover(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pairs (point, block) such that the block's region contains the point.

        Parameters
        ----------
        xyz : (n, 3) float64

        Returns
        -------
        point_index : (M,) int64
        block_index : (M,) int64
            Sorted by block, then by point.
        """
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        h = self.block_size
        half = self.half_extent
        # block i covers x when |x - (i + 0.5) h| <= half, i.e. i in [lo, hi] per axis
        lo = np.ascontiguousarray(np.ceil((xyz - half) / h - 0.5).astype(np.int64))
        hi = np.ascontiguousarray(np.floor((xyz + half) / h - 0.5).astype(np.int64))
        if len(xyz) == 0 or len(self._packed) == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        return _cover_pairs(lo, hi, len(self._packed), *self._table_of())  # by block, then point


def new_space_fraction(old_points, new_points, voxel: float) -> float:
    """Fraction of ``new_points`` in cells of edge ``voxel`` (m) holding none of
    ``old_points`` (1 when there are no old points, 0 when there are no new ones)."""
    if len(new_points) == 0:
        return 0.0
    if len(old_points) == 0:
        return 1.0
    grid = BlockGrid.from_points(old_points, voxel, 0.0)
    cells = np.floor(new_points / voxel).astype(np.int64)
    return float(np.mean(grid.lookup(cells) < 0))
