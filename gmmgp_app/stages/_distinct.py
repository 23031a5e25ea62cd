"""Occupied voxels of a point set in one pass: a hash set instead of a sort.

``np.unique`` sorts its input (O(N log N), ~0.2 s on the 1.3M keys of the street's
voxel grids, plus the (N, 3) temporaries of the keys); the auto scale
(``autoscale._voxel_for_budget``, several rounds) and the voxel subsample
(``prepare.subsample``) need only the number of occupied voxels, or the first point of
each, in no particular order. One compiled pass computes each point's voxel
``floor((p - lo) / size)`` (the same float64 operations as numpy's), packs it into one
int64 and looks it up in an open-addressing table (linear probing, Fibonacci hashing,
at least twice as many slots as points): O(N). The probing is written here, not
imported from knn.py or surface.py's tables: numba's on-disk cache of this file's
kernels would not see a change to another file's function they call.
"""

from __future__ import annotations

import math
from typing import Optional

import numba as nb
import numpy as np

__all__ = ["voxel_first", "voxel_count", "cell_first", "cell_count"]

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


@nb.njit(cache=True, inline="always")
def _table(n):
    """An empty open-addressing table for ``n`` keys (at least 2n slots, a power of
    two): (slots (-1: empty), mask, Fibonacci shift)."""
    slots = 16
    bits = 4
    while slots < 2 * n:
        slots *= 2
        bits += 1
    return np.full(slots, -1, np.int64), slots - 1, np.uint64(64 - bits)


@nb.njit(cache=True, inline="always")
def _add(table, k, mask, shift) -> bool:
    """Insert key ``k`` >= 0 (linear probing from its Fibonacci hash); True when it was
    not in the table yet."""
    j = np.int64((np.uint64(k) * _GOLDEN) >> shift) & mask
    while True:
        t = table[j]
        if t == k:
            return False
        if t == -1:
            table[j] = k
            return True
        j = (j + 1) & mask


@nb.njit(cache=True, nogil=True)
def _voxel_first(points, order, lo, size, dims, want_index):
    n = order.shape[0]
    table, mask, shift = _table(n)
    first = np.empty(n if want_index else 0, np.int64)
    count = 0
    for i in range(n):
        r = order[i]
        q0 = np.int64(np.floor((points[r, 0] - lo[0]) / size))
        q1 = np.int64(np.floor((points[r, 1] - lo[1]) / size))
        q2 = np.int64(np.floor((points[r, 2] - lo[2]) / size))
        if _add(table, (q0 * dims[1] + q1) * dims[2] + q2, mask, shift):
            if want_index:
                first[count] = i
            count += 1
    return count, first[:count]


@nb.njit(cache=True, nogil=True)
def _bounds(points):
    """Per-column minimum and maximum of (N, 3) points, N >= 1, in one pass (numpy's
    ``min(axis=0)`` on an (N, 3) array walks it with a stride: ~10x slower)."""
    lo = points[0].copy()
    hi = points[0].copy()
    for i in range(1, points.shape[0]):
        for d in range(3):
            v = points[i, d]
            if v < lo[d]:
                lo[d] = v
            elif v > hi[d]:
                hi[d] = v
    return lo, hi


def _grid(points: np.ndarray, size: float):
    """``(points, lo, dims)`` of the voxel grid, or None when it has 2^62 cells or more
    (the packed key would overflow). ``lo`` is the points' minimum, so every voxel index
    is >= 0; the largest is ``floor((max - lo) / size)`` (rounding is monotone)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    if len(points) == 0:
        return points, np.zeros(3), np.ones(3, np.int64)
    lo, hi = _bounds(points)
    dims = np.floor((hi - lo) / size).astype(np.int64) + 1
    if math.prod(float(d) for d in dims) >= 2.0 ** 62:
        return None
    return points, lo, dims


def voxel_first(points: np.ndarray, size: float,
                order: Optional[np.ndarray] = None) -> Optional[np.ndarray]:
    """Positions in ``order`` (default ``arange(N)``) of the first point of each voxel of
    edge ``size`` met in that order, increasing: the set of
    ``np.unique(floor((points[order] - points.min(0)) / size), axis=0,
    return_index=True)[1]``. None when the grid would have 2^62 cells or more."""
    g = _grid(points, size)
    if g is None:
        return None
    order = np.arange(len(points)) if order is None else np.asarray(order, dtype=np.int64)
    return _voxel_first(g[0], order, g[1], float(size), g[2], True)[1]


def voxel_count(points: np.ndarray, size: float) -> Optional[int]:
    """Number of voxels of edge ``size`` (grid anchored at ``points.min(0)``) holding a
    point; None when the grid would have 2^62 cells or more."""
    g = _grid(points, size)
    if g is None:
        return None
    order = np.arange(len(points), dtype=np.int64)
    return int(_voxel_first(g[0], order, g[1], float(size), g[2], False)[0])


@nb.njit(cache=True, nogil=True)
def _cell_first(points, size, qlo, dims, want_index):
    """:func:`_voxel_first` for cells ``floor(p / size)`` anchored at 0 (the surface
    seeds' cells), packed about ``qlo`` (the cell of the points' minimum)."""
    n = points.shape[0]
    table, mask, shift = _table(n)
    first = np.empty(n if want_index else 0, np.int64)
    count = 0
    for i in range(n):
        q0 = np.int64(np.floor(points[i, 0] / size)) - qlo[0]
        q1 = np.int64(np.floor(points[i, 1] / size)) - qlo[1]
        q2 = np.int64(np.floor(points[i, 2] / size)) - qlo[2]
        if _add(table, (q0 * dims[1] + q1) * dims[2] + q2, mask, shift):
            if want_index:
                first[count] = i
            count += 1
    return count, first[:count]


def _cells(points: np.ndarray, size: float):
    """``(points, qlo, dims)`` of the cells ``floor(p / size)``, or None when they span
    2^62 cells or more, or a coordinate is not finite (the caller's sort handles it)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    lo, hi = _bounds(points)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        return None
    qlo = np.floor(lo / size)
    dims = np.floor(hi / size) - qlo + 1          # floor is monotone: every cell within
    if math.prod(float(d) for d in dims) >= 2.0 ** 62:
        return None
    return points, qlo.astype(np.int64), dims.astype(np.int64)


def cell_first(points: np.ndarray, size: float) -> Optional[np.ndarray]:
    """Indices of the first point of each cell ``floor(p / size)`` (cells anchored at 0,
    as ``stages.surface.surface_seeds``), increasing: the set of
    ``np.unique(np.floor(points / size).astype(np.int64), axis=0, return_index=True)[1]``.
    None when the cells span 2^62 or more, or for a non-finite point: sort then."""
    if len(points) == 0:
        return np.zeros(0, np.int64)
    g = _cells(points, size)
    if g is None:
        return None
    first = _cell_first(g[0], float(size), g[1], g[2], True)[1]
    return first          # met in row order: already increasing


def cell_count(points: np.ndarray, size: float) -> Optional[int]:
    """Number of distinct cells ``floor(p / size)`` holding a point (see
    :func:`cell_first`); None where that returns None."""
    if len(points) == 0:
        return 0
    g = _cells(points, size)
    if g is None:
        return None
    return int(_cell_first(g[0], float(size), g[1], g[2], False)[0])
