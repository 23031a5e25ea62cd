"""Exact k nearest neighbours on a hashed uniform grid, compiled (the far field's query).

The far field (stages/farfield.py) asks the ``k`` nearest hit points of every field
query; on a surface lattice those are millions of queries within a few centimetres of
the data. A k-d tree answers each from the root; here the points are bucketed in cubic
cells of about the k-th neighbour distance, and a query scans the cells of growing cube
shells around its own cell, keeping the ``k`` best by insertion, until the k-th best
distance is within the distance to the outside of the scanned box (so nothing outside
can be nearer: the result is exact). Queries whose search would need more than
``max_ring`` shells (far from the data) are answered by the k-d tree instead.

Many queries close together (a surface lattice, a mesh's vertices) share their candidates:
:meth:`GridKNN.query` groups them by cubes of ``group`` cells, finds the exact k-th
neighbour distance ``D`` of each cube's centre ``c``, and gathers once the points within
``D + |q - c|_max`` of the cube, which by the triangle inequality hold every member's k
nearest (``d_k(q) <= D + |q - c|``); each member then scans that list sorted by the
distance to ``c``, stopping once ``|p - c| - |q - c|`` exceeds its k-th best. The
neighbours and distances are the same (same formula, ascending); a cube whose centre is
beyond ``max_ring`` shells or whose list would exceed ``max_candidates`` is answered
query by query.

Distances are computed as ``sqrt(dx^2 + dy^2 + dz^2)`` (the k-d tree's formula), in
ascending order; ties between equidistant points may be ordered differently from the
k-d tree (no effect on the far field, whose sums are order-independent up to round-off).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from ._distinct import _bounds

__all__ = ["GridKNN"]


class GridKNN:
    """k nearest neighbours of queries among fixed ``points`` (exact).

    Parameters
    ----------
    points : (P, 3) float64
    k : int
        Neighbours per query (at most P).
    tree : scipy.spatial.cKDTree of ``points``, optional
        For the queries beyond ``max_ring`` shells (built when needed if not given).
    cell : float, optional
        Grid cell edge (m); default the median k-th neighbour distance of a sample of
        the points (so one shell of cells usually holds the answer).
    max_ring : int
        Shells scanned before a query is handed to the k-d tree.
    group : float
        Edge of the cubes grouping queries that share a candidate list, in cells (0:
        every query on its own).
    max_candidates : int
        Longest shared candidate list; a group needing more is answered query by query.
    """

    def __init__(self, points, k: int, tree=None, cell: float | None = None,
                 max_ring: int = 3, group: float = 0.75, max_candidates: int = 2048):
        p = np.ascontiguousarray(np.asarray(points, dtype=np.float64))
        if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
            raise ValueError(f"Expected points with shape (P, 3), P >= 1, found {p.shape}.")
        self.points = p
        self.k = int(min(max(k, 1), len(p)))
        self._tree = tree
        self.max_ring = int(max_ring)
        self.group, self.max_candidates = float(group), int(max_candidates)
        if cell is None:
            cell = self._default_cell()
        self.cell = float(cell)
        c = np.floor(p / self.cell).astype(np.int64)
        self.lo = c.min(0)
        dims = c.max(0) - self.lo + 1
        if float(np.prod(dims.astype(np.float64))) >= 2.0 ** 62:
            # too many cells to key in an int64: one giant cell per axis span instead
            self.cell = float(np.max(np.ptp(p, axis=0))) + 1.0
            c = np.floor(p / self.cell).astype(np.int64)
            self.lo = c.min(0)
            dims = c.max(0) - self.lo + 1
        self.dims = dims.astype(np.int64)
        (self.order, self.sorted_points, self.table_keys, self.table_start,
         self.table_end) = _cell_table(p, c, self.lo, self.dims)
        self._kept = None
        self._columns = None

    @property
    def columns(self) -> tuple:
        """The occupied columns of cells (cells with the same first two coordinates):
        an open-addressing table from the column's key ``a * dims[1] + b`` (box
        coordinates) to the run of its points in the cell order (``start``, ``end``),
        and each point's third cell coordinate ``zc`` (ascending within a column: the
        points are sorted by cell key). The cells ``c0..c1`` of one column are one
        stretch of points, in the order cell by cell."""
        if getattr(self, "_columns", None) is None:    # (a GridKNN pickled before it)
            c = np.floor(self.sorted_points / self.cell).astype(np.int64) - self.lo
            key2 = c[:, 0] * self.dims[1] + c[:, 1]
            starts = np.flatnonzero(np.r_[True, key2[1:] != key2[:-1]])
            ends = np.r_[starts[1:], len(key2)]
            size = 1 << int(np.ceil(np.log2(2 * len(starts) + 2)))
            self._columns = _build_table(key2[starts], starts.astype(np.int64),
                                         ends.astype(np.int64), size) + \
                (np.ascontiguousarray(c[:, 2]),)
        return self._columns

    def _default_cell(self) -> float:
        p = self.points
        sample = p[np.random.default_rng(0).permutation(len(p))[:2000]]
        d = self.tree.query(sample, k=self.k)[0].reshape(len(sample), -1)[:, -1]
        cell = float(np.median(d))
        if not (cell > 0 and math.isfinite(cell)):
            ext = float(np.max(np.ptp(p, axis=0))) if len(p) > 1 else 1.0
            cell = max(ext, 1e-3)
        return cell

    @property
    def tree(self):
        if self._tree is None:
            from scipy.spatial import cKDTree

            self._tree = cKDTree(self.points)
        return self._tree

    def query(self, x):
        """(K, k) distances (ascending) and (K, k) point indices of the queries ``x``."""
        x = np.ascontiguousarray(np.asarray(x, dtype=np.float64).reshape(-1, 3))
        if self.group > 0 and len(x) >= 64:
            d, i, done = self._query_groups(x)
            rest = np.flatnonzero(~done)
            if len(rest):
                d[rest], i[rest] = self._query_far(x[rest])
            return d, i
        return self._query_each(x)

    def _query_groups(self, x):
        """:func:`_knn_groups`: the queries grouped by cubes of ``group`` cells (sorted
        by cube); (distances, indices, done)."""
        g = self.group * self.cell
        c = np.floor(x / g).astype(np.int64)
        lo, hi = _bounds(c)            # (c.min(0), c.max(0)) in one pass
        c -= lo
        dims = hi - lo + 1
        if float(np.prod(dims.astype(np.float64))) >= 2.0 ** 62:
            return (np.empty((len(x), self.k)), np.empty((len(x), self.k), np.int64),
                    np.zeros(len(x), np.bool_))
        key = (c[:, 0] * dims[1] + c[:, 1]) * dims[2] + c[:, 2]
        qorder = np.argsort(key, kind="stable")
        ks = key[qorder]
        gptr = np.r_[np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]]), len(ks)].astype(np.int64)
        d = np.empty((len(x), self.k))
        i = np.empty((len(x), self.k), np.int64)
        done = np.zeros(len(x), np.bool_)
        G = len(gptr) - 1
        kept = getattr(self, "_kept", None)    # (a GridKNN pickled before the lists)
        if kept is not None and kept.params != self._list_params():
            kept = None       # a copy with another k, group, ...: its lists are not these
        if kept is None:
            none = np.zeros(0, np.int64)
            _knn_groups(x, qorder, gptr, g, self.k, self.cell, self.lo, self.dims,
                        self.table_keys, self.table_start, self.table_end,
                        self.sorted_points, self.order, self.max_ring, self.max_candidates,
                        *self.columns, d, i, done, np.full(G, -1, np.int64), none, np.zeros(0, np.int32),
                        np.full(G, -1, np.int64), np.zeros((0, 0), np.int32), none)
            return d, i, done
        with kept.lock:
            # each group's cube (the kernel's floor(x / g) of its first member)
            cube = np.floor(x[qorder[gptr[:-1]]] / g)
            gkey = _KeptLists.cube_keys(cube)
            have = kept.find(gkey)
            # the lists to keep: at most ROWS per call (the buffer's bound: scattered
            # queries make a group each)
            miss = np.flatnonzero((have < 0) & (gkey >= 0))[:_KeptLists.ROWS] \
                if kept.open else np.zeros(0, np.int64)
            row = np.full(G, -1, np.int64)
            row[miss] = np.arange(len(miss))
            out = np.empty((len(miss), _KeptLists.LONGEST), np.int32)
            out_n = np.empty(len(miss), np.int64)
            _knn_groups(x, qorder, gptr, g, self.k, self.cell, self.lo, self.dims,
                        self.table_keys, self.table_start, self.table_end,
                        self.sorted_points, self.order, self.max_ring, self.max_candidates,
                        *self.columns, d, i, done, have, kept.starts, kept.pool, row, out, out_n)
            kept.add(gkey[miss], out, out_n)
        return d, i, done

    def keep_lists(self, on: bool = True, max_entries: int = 1 << 25) -> None:
        """Keep each query group's candidate list (``on``) for later queries in the same
        cube, or drop the kept lists (off, the default state). A list is a function of
        its cube alone (the cube's centre, its k-th neighbour distance, the points), so
        a member scanning a kept list finds the same neighbours in the same order as
        with a list found afresh: the answers are the same bit for bit, only cheaper
        when a cube is queried again (a surface's vertices after its lattice: the
        vertex pass's k-NN without finding the lists costs about half). At most
        ``max_entries`` candidates are kept (4 bytes each; the street's lattice keeps
        ~5M); beyond, lists are found afresh again."""
        self._kept = _KeptLists(max_entries, self._list_params()) if on else None

    def _list_params(self) -> tuple:
        """What a group's candidate list depends on besides its cube and the points."""
        return (self.k, self.group, self.cell, self.max_ring, self.max_candidates)

    def _query_far(self, x):
        """:meth:`_query_each`'s answers for queries a group could not answer (mostly far
        from the data, where the k-d tree answers most of them): the k-d tree first for
        all, then the grid only for the queries whose k-th neighbour distance is within
        the distance ``out`` from the query to the outside of its ``max_ring`` box
        (:func:`_ring_outside`). The grid's search succeeds exactly when the k-th
        nearest distance is within ``out`` (its k-th best is never nearer than the true
        one, and the true k nearest lie in the box when they are within ``out``), so a
        query beyond ``out`` (with a margin for round-off) is one the grid would hand
        to the k-d tree: the same answers as :meth:`_query_each`, without the grid's
        failing searches (KITTI's lattice: 96 % of these queries)."""
        dt, it = self.tree.query(x, k=self.k, workers=-1)
        d = np.asarray(dt, dtype=np.float64).reshape(len(x), self.k)
        i = np.asarray(it).reshape(len(x), self.k).astype(np.int64, copy=False)
        out = _ring_outside(x, self.cell, self.max_ring)
        # not (d_k > out): NaN distances (none found) go to the grid as before
        maybe = np.flatnonzero(~(d[:, -1] > out * (1.0 + 1e-9) + 1e-12 * self.cell))
        if len(maybe):
            xm = np.ascontiguousarray(x[maybe])
            dg, ig, done = _knn_grid(xm, self.k, self.cell, self.lo, self.dims,
                                     self.table_keys, self.table_start, self.table_end,
                                     self.sorted_points, self.order, self.max_ring,
                                     *self.columns)
            ok = maybe[done]
            d[ok], i[ok] = dg[done], ig[done]
        return d, i

    def _query_each(self, x):
        """Query by query (:func:`_knn_grid`, the k-d tree beyond ``max_ring`` shells)."""
        d, i, done = _knn_grid(x, self.k, self.cell, self.lo, self.dims, self.table_keys,
                               self.table_start, self.table_end, self.sorted_points,
                               self.order, self.max_ring, *self.columns)
        rest = np.flatnonzero(~done)
        if len(rest):
            dr, ir = self.tree.query(x[rest], k=self.k, workers=-1)
            d[rest] = np.asarray(dr).reshape(len(rest), self.k)
            i[rest] = np.asarray(ir).reshape(len(rest), self.k)
        return d, i


class _KeptLists:
    """Candidate lists of query groups by cube (:meth:`GridKNN.keep_lists`): an
    open-addressing table from the cube's key to a list number, the lists one after
    another in ``pool`` (int32 point rows) from ``starts``. ``lock``: one query at a
    time uses it."""

    #: The longest list kept (the street's lattice: 72 on average, at most 191).
    LONGEST = 256
    #: Lists kept per query call at most (the buffer: ROWS x LONGEST int32, 8 MiB).
    ROWS = 8192
    #: Cube coordinates kept: |b| < 2^20 on each axis (21 bits each in the key).
    _HALF = 1 << 20

    def __init__(self, max_entries: int, params: tuple):
        import threading

        self.params = params
        self.lock = threading.Lock()
        self.max_entries = int(max_entries)
        self.keys = np.full(1 << 12, -1, np.int64)
        self.ids = np.zeros(1 << 12, np.int64)
        self.count = 0
        self.pool = np.empty(1 << 16, np.int32)
        self.starts = np.zeros(1 << 10, np.int64)    # starts[n]: end of the n lists
        self.open = True                              # False once max_entries is reached

    @classmethod
    def cube_keys(cls, cube: np.ndarray) -> np.ndarray:
        """(G,) int64 keys of integer-valued cube coordinates (G, 3) float; -1 for a cube
        too far out to key (its list is not kept)."""
        h = cls._HALF
        ok = np.all(np.abs(cube) < h, axis=1)
        b = np.where(ok[:, None], cube, 0).astype(np.int64) + h
        return np.where(ok, (b[:, 0] << 42) | (b[:, 1] << 21) | b[:, 2], -1)

    def find(self, gkey: np.ndarray) -> np.ndarray:
        """(G,) the list number of each key (-1: none kept)."""
        return _kept_find(self.keys, self.ids, gkey)

    def add(self, gkey, out, out_n) -> None:
        """Keep the lists ``out[r, :out_n[r]]`` (``out_n`` -1: none) of the cubes
        ``gkey``."""
        ok = np.flatnonzero(out_n >= 0)
        if len(ok) == 0:
            return
        n_lists = self.count
        used = int(self.starts[n_lists])
        lens = out_n[ok]
        need = used + int(lens.sum())
        if need > self.max_entries:
            self.open = False
            return
        if need > len(self.pool):
            self.pool = np.concatenate([self.pool[:used],
                                        np.empty(max(need, 2 * len(self.pool)) - used,
                                                 np.int32)])
        if n_lists + len(ok) + 1 > len(self.starts):
            grown = np.zeros(max(n_lists + len(ok) + 1, 2 * len(self.starts)), np.int64)
            grown[:n_lists + 1] = self.starts[:n_lists + 1]
            self.starts = grown
        _kept_append(self.pool, self.starts, n_lists, out, ok, lens)
        if 2 * (n_lists + len(ok)) > len(self.keys):
            size = len(self.keys)
            while 2 * (n_lists + len(ok)) > size:
                size *= 2
            keys, ids = np.full(size, -1, np.int64), np.zeros(size, np.int64)
            _kept_insert(keys, ids, self.keys[self.keys >= 0], self.ids[self.keys >= 0])
            self.keys, self.ids = keys, ids
        _kept_insert(self.keys, self.ids, gkey[ok], np.arange(n_lists, n_lists + len(ok)))
        self.count = n_lists + len(ok)


@nb.njit(cache=True, nogil=True)
def _kept_find(tk, tv, keys):
    mask = len(tk) - 1
    out = np.full(len(keys), -1, np.int64)
    for g in range(len(keys)):
        key = keys[g]
        if key < 0:
            continue
        s = _hash(key, mask)
        while tk[s] != -1:
            if tk[s] == key:
                out[g] = tv[s]
                break
            s = (s + 1) & mask
    return out


@nb.njit(cache=True, nogil=True)
def _kept_insert(tk, tv, keys, ids):
    mask = len(tk) - 1
    for g in range(len(keys)):
        s = _hash(keys[g], mask)
        while tk[s] != -1 and tk[s] != keys[g]:
            s = (s + 1) & mask
        tk[s] = keys[g]
        tv[s] = ids[g]


@nb.njit(cache=True, nogil=True)
def _kept_append(pool, starts, n_lists, out, rows, lens):
    pos = starts[n_lists]
    for m in range(len(rows)):
        r = rows[m]
        for u in range(lens[m]):
            pool[pos + u] = out[r, u]
        pos += lens[m]
        starts[n_lists + m + 1] = pos


@nb.njit(cache=True, inline="always")
def _hash(key, mask):
    h = (key * 0x9E3779B97F4A7C15) & 0x7FFFFFFFFFFFFFFF
    return (h >> 17) & mask


@nb.njit(cache=True, inline="always")
def _slot(tk, key, mask):
    """The table slot of cell ``key`` (linear probing), or -1 when the cell is empty."""
    s = _hash(key, mask)
    while tk[s] != -1 and tk[s] != key:
        s = (s + 1) & mask
    return s if tk[s] != -1 else -1


@nb.njit(cache=True, inline="always")
def _cell_slot(tk, mask, dims, a, b, c):
    """The table slot of the cell at box coordinates (a, b, c), or -1 when it is empty."""
    return _slot(tk, (a * dims[1] + b) * dims[2] + c, mask)


@nb.njit(cache=True, inline="always")
def _sq_dist(x, q, pts, j):
    """Squared distance between query ``x[q]`` and point ``pts[j]``."""
    d0 = x[q, 0] - pts[j, 0]
    d1 = x[q, 1] - pts[j, 1]
    d2 = x[q, 2] - pts[j, 2]
    return d0 * d0 + d1 * d1 + d2 * d2


def _cell_table(p, c, lo, dims):
    """The points ``p`` bucketed by their cells ``c`` (int64 cell coordinates, keyed in
    the box of ``dims`` cells from ``lo``): (order, the points in that order, and the
    open-addressing table of each occupied cell's run: keys, starts, ends)."""
    key = ((c[:, 0] - lo[0]) * dims[1] + (c[:, 1] - lo[1])) * dims[2] + (c[:, 2] - lo[2])
    order = np.argsort(key, kind="stable").astype(np.int64)
    ks = key[order]
    starts = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
    ends = np.r_[starts[1:], len(ks)]
    size = 1 << int(np.ceil(np.log2(2 * len(starts) + 2)))
    tk, ts, te = _build_table(ks[starts], starts.astype(np.int64), ends.astype(np.int64),
                              size)
    return order, np.ascontiguousarray(p[order]), tk, ts, te


@nb.njit(cache=True, nogil=True)
def _build_table(ukeys, starts, ends, size):
    """Open-addressing hash table (linear probing) of the occupied cells' point runs."""
    mask = size - 1
    tk = np.full(size, -1, np.int64)
    ts = np.zeros(size, np.int64)
    te = np.zeros(size, np.int64)
    for n in range(len(ukeys)):
        s = _hash(ukeys[n], mask)
        while tk[s] != -1:
            s = (s + 1) & mask
        tk[s] = ukeys[n]
        ts[s] = starts[n]
        te[s] = ends[n]
    return tk, ts, te


@nb.njit(cache=True, inline="always")
def _insert(bd, bi, cnt, k, dd, j):
    """Insert squared distance ``dd`` of point ``j`` into the ascending best lists
    ``bd``, ``bi`` holding ``cnt`` of at most ``k`` (the caller checked that it enters);
    returns the new count."""
    m = cnt if cnt < k else k - 1
    while m > 0 and bd[m - 1] > dd:
        bd[m] = bd[m - 1]
        bi[m] = bi[m - 1]
        m -= 1
    bd[m] = dd
    bi[m] = j
    return cnt + 1 if cnt < k else cnt


def _ring_outside(x, cell: float, max_ring: int) -> np.ndarray:
    """(K,) the distance from each query to the outside of the box of cells
    ``[c - max_ring, c + max_ring]`` around its cell ``c`` (:func:`_shell_knn_cols`'s
    ``out`` after its last shell)."""
    c = np.floor(x / cell)
    return np.minimum(x - (c - max_ring) * cell, (c + max_ring + 1) * cell - x).min(axis=1)


@nb.njit(cache=True, inline="always")
def _shell_knn_cols(p0, p1, p2, k, cell, lo, dims, tk, ts, te, pts, max_ring, bd, bi, colk,
                    col0, col1, zc):
    """The k nearest points of ``(p0, p1, p2)``: cube shells of cells around its own,
    the k best kept sorted by insertion in ``bd`` (squared distances) and ``bi`` (point
    rows), cells wholly farther than the k-th best skipped; stop when the k-th best is no
    farther than the outside of the scanned box. False when ``max_ring`` shells were not
    enough (``bd``, ``bi`` then incomplete). The rows of cells that a shell crosses whole
    are read through their column (:attr:`GridKNN.columns`: one look-up and a binary
    search instead of one look-up per cell): the same cells in the same order as cell by
    cell, each skipped or not by the same test at the same moment (tests/test_knn.py
    checks it against the cell-by-cell search)."""
    mask = len(tk) - 1
    cmask = len(colk) - 1
    slack = (1e-9 * cell) ** 2
    bd[:] = np.inf
    bi[:] = -1
    cnt = 0
    c0 = int(math.floor(p0 / cell))
    c1 = int(math.floor(p1 / cell))
    c2 = int(math.floor(p2 / cell))
    for r in range(max_ring + 1):
        for a in range(c0 - r, c0 + r + 1):
            qa = a - lo[0]
            if qa < 0 or qa >= dims[0]:
                continue
            g0 = max(a * cell - p0, p0 - (a + 1) * cell, 0.0)
            for b in range(c1 - r, c1 + r + 1):
                qb = b - lo[1]
                if qb < 0 or qb >= dims[1]:
                    continue
                g1 = max(b * cell - p1, p1 - (b + 1) * cell, 0.0)
                edge_ab = a == c0 - r or a == c0 + r or b == c1 - r or b == c1 + r
                if edge_ab:
                    # the whole row c2 - r .. c2 + r: the column's points in cell order
                    s = _slot(colk, qa * dims[1] + qb, cmask)
                    if s < 0:
                        continue
                    z0 = c2 - r - lo[2]
                    z1 = c2 + r - lo[2]
                    j = col0[s]
                    j1 = col1[s]
                    while j < j1:
                        m = (j + j1) >> 1
                        if zc[m] < z0:
                            j = m + 1
                        else:
                            j1 = m
                    end = col1[s]
                    while j < end and zc[j] <= z1:
                        qc = zc[j]
                        c = qc + lo[2]
                        if cnt == k:
                            g2 = max(c * cell - p2, p2 - (c + 1) * cell, 0.0)
                            gg = g0 * g0 + g1 * g1 + g2 * g2
                            if gg > bd[k - 1] * (1.0 + 1e-9) + slack:
                                while j < end and zc[j] == qc:
                                    j += 1       # the cell skipped, as cell by cell
                                continue
                        while j < end and zc[j] == qc:
                            d0 = p0 - pts[j, 0]
                            d1 = p1 - pts[j, 1]
                            d2 = p2 - pts[j, 2]
                            dd = d0 * d0 + d1 * d1 + d2 * d2
                            if cnt < k or dd < bd[k - 1]:
                                cnt = _insert(bd, bi, cnt, k, dd, j)
                            j += 1
                    continue
                for c in (c2 - r, c2 + r):
                    qc = c - lo[2]
                    if qc < 0 or qc >= dims[2]:
                        continue
                    if cnt == k:
                        g2 = max(c * cell - p2, p2 - (c + 1) * cell, 0.0)
                        gg = g0 * g0 + g1 * g1 + g2 * g2
                        if gg > bd[k - 1] * (1.0 + 1e-9) + slack:
                            continue
                    s = _cell_slot(tk, mask, dims, qa, qb, qc)
                    if s < 0:
                        continue
                    for j in range(ts[s], te[s]):
                        d0 = p0 - pts[j, 0]
                        d1 = p1 - pts[j, 1]
                        d2 = p2 - pts[j, 2]
                        dd = d0 * d0 + d1 * d1 + d2 * d2
                        if cnt < k or dd < bd[k - 1]:
                            cnt = _insert(bd, bi, cnt, k, dd, j)
        out = math.inf
        for ax in range(3):
            pa = p0 if ax == 0 else (p1 if ax == 1 else p2)
            ca = c0 if ax == 0 else (c1 if ax == 1 else c2)
            out = min(out, pa - (ca - r) * cell, (ca + r + 1) * cell - pa)
        if cnt == k and bd[k - 1] <= out * out:
            return True
    return False


@nb.njit(cache=True, parallel=True, nogil=True)
def _knn_grid(x, k, cell, lo, dims, tk, ts, te, pts, order, max_ring, colk, col0, col1, zc):
    """Per query: :func:`_shell_knn_cols` around it; ``done`` False where ``max_ring``
    shells were not enough."""
    K = x.shape[0]
    dist = np.empty((K, k))
    idx = np.empty((K, k), np.int64)
    done = np.zeros(K, np.bool_)
    chunk = 512
    for t in nb.prange((K + chunk - 1) // chunk):
        bd = np.empty(k)                 # one scratch pair per chunk of queries
        bi = np.empty(k, np.int64)
        for q in range(t * chunk, min(K, (t + 1) * chunk)):
            if _shell_knn_cols(x[q, 0], x[q, 1], x[q, 2], k, cell, lo, dims, tk, ts, te,
                               pts, max_ring, bd, bi, colk, col0, col1, zc):
                for m in range(k):
                    dist[q, m] = math.sqrt(bd[m])
                    idx[q, m] = order[bi[m]]
                done[q] = True
    return dist, idx, done


@nb.njit(cache=True, parallel=True, nogil=True)
def _knn_groups(x, qorder, gptr, gcell, k, cell, lo, dims, tk, ts, te, pts, order, max_ring,
                cap, colk, col0, col1, zc, dist, idx, done, have, pool_start, pool, row, out,
                out_n):
    """Per group of queries (``qorder[gptr[g]:gptr[g + 1]]``, all in one cube of edge
    ``gcell``): the exact k-th neighbour distance ``D`` of the cube's centre ``c`` (cube
    shells of cells, as :func:`_knn_grid`), the points within ``R = D + gcell sqrt(3)/2``
    of the cube (every member's k nearest: ``d_k(q) <= D + |q - c|``) sorted by their
    distance to ``c`` (their coordinates copied in that order), then per member the k
    best by insertion, the scan stopping once ``|p - c| - |q - c|`` is beyond its k-th
    best. Groups whose centre needs more than
    ``max_ring`` shells, or more than ``cap`` candidates, are left (``done`` False).

    Candidate lists kept from earlier queries (:meth:`GridKNN.keep_lists`): a group with
    ``have[g] >= 0`` scans the kept list ``pool[pool_start[have[g]]:pool_start[have[g] +
    1]]`` (the points' rows in the order of their distance to the cube's centre, as the
    group once found them: the same scan, so the same neighbours in the same order);
    the others find theirs, and a group with ``row[g] >= 0`` writes it to
    ``out[row[g]]`` with its length to ``out_n[row[g]]`` (-1: none, or longer than
    ``out``'s rows) for the caller to keep."""
    G = len(gptr) - 1
    mask = len(tk) - 1
    half = gcell * math.sqrt(3.0) / 2
    # groups in runs of ``chunk``, each run with its own scratch (allocated once per run,
    # not per group as before)
    chunk = 64
    for t in nb.prange((G + chunk - 1) // chunk):
        bd = np.empty(k)
        bi = np.empty(k, np.int64)
        cand = np.empty(cap, np.int64)
        cd = np.empty(cap)
        cs = np.empty(cap, np.int64)
        cdist = np.empty(cap)
        px = np.empty(cap)
        py = np.empty(cap)
        pz = np.empty(cap)
        for g in range(t * chunk, min(G, (t + 1) * chunk)):
            q0 = qorder[gptr[g]]
            b0 = math.floor(x[q0, 0] / gcell)
            b1 = math.floor(x[q0, 1] / gcell)
            b2 = math.floor(x[q0, 2] / gcell)
            cx = (b0 + 0.5) * gcell
            cy = (b1 + 0.5) * gcell
            cz = (b2 + 0.5) * gcell
            if have[g] >= 0:
                n = _kept_candidates(cx, cy, cz, pool, pool_start[have[g]],
                                     pool_start[have[g] + 1], pts, cs, cdist, px, py, pz)
            else:
                n = _group_candidates(b0, b1, b2, cx, cy, cz, gcell, half, k, cell, lo,
                                      dims, tk, ts, te, pts, max_ring, cap, mask, bd, bi,
                                      cand, cd, cs, cdist, px, py, pz, colk, col0, col1, zc)
                if row[g] >= 0:
                    r = row[g]
                    if 0 <= n <= out.shape[1]:
                        for u in range(n):
                            out[r, u] = np.int32(cs[u])
                        out_n[r] = n
                    else:
                        out_n[r] = -1
            if n < 0:
                continue
            _group_members(g, x, qorder, gptr, cx, cy, cz, gcell, k, order, n, cs, cdist,
                           px, py, pz, bd, bi, dist, idx, done)


#: Candidate lists up to this long are sorted by insertion (:func:`_group_candidates`).
_SHORT_LIST = 128


@nb.njit(cache=True, nogil=True)
def _insertion_order(cand, cd, n, rows, sq):
    """``cand[:n]`` and their keys ``cd[:n]`` sorted ascending by insertion into ``rows``
    and ``sq`` (``cand``, ``cd`` unchanged). True when the keys are all distinct: then
    that is the one ascending order, the one ``np.argsort(cd[:n])`` gives; False on a
    tie (or a NaN), where np.argsort's order among equal keys is its own."""
    for u in range(n):
        v = cd[u]
        m = u
        while m > 0 and sq[m - 1] > v:
            sq[m] = sq[m - 1]
            rows[m] = rows[m - 1]
            m -= 1
        sq[m] = v
        rows[m] = cand[u]
    for u in range(1, n):
        if not sq[u] > sq[u - 1]:
            return False
    return n == 0 or sq[0] == sq[0]


@nb.njit(cache=True, nogil=True)
def _group_candidates(b0, b1, b2, cx, cy, cz, gcell, half, k, cell, lo, dims, tk, ts, te,
                      pts, max_ring, cap, mask, bd, bi, cand, cd, cs, cdist, px, py, pz,
                      colk, col0, col1, zc):
    """The candidates of the group in cube ``(b0, b1, b2)`` (centre ``c``) in the order
    of their distance to ``c``: rows to ``cs``, those distances to ``cdist``,
    coordinates to ``px``, ``py``, ``pz``; returns their count, -1 when the centre needs
    more than ``max_ring`` shells or the list more than ``cap`` points.

    The cells within ``R`` of the cube are read column by column (:attr:`GridKNN.columns`:
    one table look-up per column and a binary search for its first cell, instead of one
    look-up per cell, most of them empty where the data are sparse): the points in the
    same order as cell by cell (a column's cells are consecutive in the cell order), so
    the same list."""
    # 1. the centre's k-th neighbour distance
    if not _shell_knn_cols(cx, cy, cz, k, cell, lo, dims, tk, ts, te, pts, max_ring, bd, bi,
                           colk, col0, col1, zc):
        return -1
    # 2. the candidates: points within R of the cube (margins cover round-off)
    R = (math.sqrt(bd[k - 1]) + half) * (1.0 + 1e-9) + 1e-12 * gcell
    R2 = R * R
    lx = b0 * gcell
    ly = b1 * gcell
    lz = b2 * gcell
    hx = lx + gcell
    hy = ly + gcell
    hz = lz + gcell
    n = 0
    cmask = len(colk) - 1
    z0 = max(int(math.floor((lz - R) / cell)) - lo[2], 0)
    z1 = min(int(math.floor((hz + R) / cell)) - lo[2], dims[2] - 1)
    for a in range(int(math.floor((lx - R) / cell)), int(math.floor((hx + R) / cell)) + 1):
        qa = a - lo[0]
        if qa < 0 or qa >= dims[0] or z0 > z1:
            continue
        for b in range(int(math.floor((ly - R) / cell)),
                       int(math.floor((hy + R) / cell)) + 1):
            qb = b - lo[1]
            if qb < 0 or qb >= dims[1]:
                continue
            s = _slot(colk, qa * dims[1] + qb, cmask)
            if s < 0:
                continue
            # the column's first point in a cell >= z0 (its points ascend in zc)
            j0 = col0[s]
            j1 = col1[s]
            while j0 < j1:
                m = (j0 + j1) >> 1
                if zc[m] < z0:
                    j0 = m + 1
                else:
                    j1 = m
            for j in range(j0, col1[s]):
                if zc[j] > z1:
                    break
                g0 = max(lx - pts[j, 0], pts[j, 0] - hx, 0.0)
                g1 = max(ly - pts[j, 1], pts[j, 1] - hy, 0.0)
                g2 = max(lz - pts[j, 2], pts[j, 2] - hz, 0.0)
                if g0 * g0 + g1 * g1 + g2 * g2 <= R2:
                    if n == cap:
                        return -1
                    e0 = cx - pts[j, 0]
                    e1 = cy - pts[j, 1]
                    e2 = cz - pts[j, 2]
                    cand[n] = j
                    cd[n] = e0 * e0 + e1 * e1 + e2 * e2
                    n += 1
    # 3. in the order of the distance to the centre. A short list: insertion sort (into
    # cs, cdist); when its distances are all distinct (checked) that is the one
    # ascending order, np.argsort's too; a tie (or a NaN) sorts by np.argsort, whose
    # order among equal distances is its own
    if n <= _SHORT_LIST and _insertion_order(cand, cd, n, cs, cdist):
        for u in range(n):
            j = cs[u]
            cdist[u] = math.sqrt(cdist[u])
            px[u] = pts[j, 0]
            py[u] = pts[j, 1]
            pz[u] = pts[j, 2]
        return n
    o = np.argsort(cd[:n])
    # their coordinates in that order, one array per axis: the members' scans read
    # them in sequence (a gather through ``cs`` per candidate was a fifth slower)
    for u in range(n):
        cs[u] = cand[o[u]]
        cdist[u] = math.sqrt(cd[o[u]])
        px[u] = pts[cs[u], 0]
        py[u] = pts[cs[u], 1]
        pz[u] = pts[cs[u], 2]
    return n


@nb.njit(cache=True, inline="always")
def _kept_candidates(cx, cy, cz, pool, s0, s1, pts, cs, cdist, px, py, pz):
    """A kept candidate list ``pool[s0:s1]`` laid out as :func:`_group_candidates` lays
    out its own (the distances to the centre by the same arithmetic: the same values);
    returns its length."""
    n = s1 - s0
    for u in range(n):
        j = pool[s0 + u]
        e0 = cx - pts[j, 0]
        e1 = cy - pts[j, 1]
        e2 = cz - pts[j, 2]
        cs[u] = j
        cdist[u] = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
        px[u] = pts[j, 0]
        py[u] = pts[j, 1]
        pz[u] = pts[j, 2]
    return n


@nb.njit(cache=True, inline="always")
def _group_members(g, x, qorder, gptr, cx, cy, cz, gcell, k, order, n, cs, cdist, px, py,
                   pz, bd, bi, dist, idx, done):
    """Each member's k best among the group's ``n`` candidates (by insertion, in the
    candidates' order, stopping once ``|p - c| - |q - c|`` is beyond its k-th best)."""
    for t in range(gptr[g], gptr[g + 1]):
        q = qorder[t]
        x0 = x[q, 0]
        x1 = x[q, 1]
        x2 = x[q, 2]
        bd[:] = np.inf
        cnt = 0
        e0 = x[q, 0] - cx
        e1 = x[q, 1] - cy
        e2 = x[q, 2] - cz
        dq = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2) * (1.0 + 1e-9) + 1e-12 * gcell
        lim = math.inf
        for u in range(n):
            if cnt == k and cdist[u] - dq > lim:
                break              # this and every later candidate: beyond the k-th
            d0 = x0 - px[u]            # _sq_dist's arithmetic
            d1 = x1 - py[u]
            d2 = x2 - pz[u]
            dd = d0 * d0 + d1 * d1 + d2 * d2
            if cnt < k or dd < bd[k - 1]:
                cnt = _insert(bd, bi, cnt, k, dd, cs[u])
                if cnt == k:
                    lim = math.sqrt(bd[k - 1]) * (1.0 + 1e-9) + 1e-12 * gcell
        for m in range(k):
            dist[q, m] = math.sqrt(bd[m])
            idx[q, m] = order[bi[m]]
        done[q] = True


def ball_lists(points, centres, radius: float):
    """Indices of the ``points`` within ``radius`` of each centre, as CSR ``(ptr, idx)``
    (``idx[ptr[c]:ptr[c+1]]`` for centre c, in grid order, not sorted): what
    ``cKDTree.query_ball_point`` returns as lists, without the Python lists.

    The points are bucketed in cells of edge ``radius``; a centre scans the 27 cells
    around its own. Two compiled passes over the centres (count, then fill)."""
    p = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    x = np.ascontiguousarray(np.asarray(centres, dtype=np.float64).reshape(-1, 3))
    r = float(radius)
    if len(p) == 0 or len(x) == 0 or not r > 0:
        return np.zeros(len(x) + 1, np.int64), np.zeros(0, np.int64)
    cell = r
    c = np.floor(p / cell).astype(np.int64)
    lo = c.min(0) - 1
    dims = (c.max(0) + 1 - lo + 1).astype(np.int64)
    if float(np.prod(dims.astype(np.float64))) >= 2.0 ** 62:
        raise ValueError("ball_lists: the points span too many cells of the radius")
    order, sp, tk, ts, te = _cell_table(p, c, lo, dims)
    counts = _ball_pass(x, r, cell, lo, dims, tk, ts, te, sp, order,
                        np.zeros(len(x) + 1, np.int64), np.zeros(0, np.int64), False)
    ptr = np.zeros(len(x) + 1, np.int64)
    np.cumsum(counts[:-1], out=ptr[1:])
    idx = np.empty(ptr[-1], np.int64)
    _ball_pass(x, r, cell, lo, dims, tk, ts, te, sp, order, ptr, idx, True)
    return ptr, idx


@nb.njit(cache=True, parallel=True, nogil=True)
def _ball_pass(x, r, cell, lo, dims, tk, ts, te, pts, order, ptr, idx, fill):
    """Count (``fill`` False: counts per centre) or write (at ``ptr``) the points within
    ``r`` of each centre; centres in parallel (each writes its own count and run)."""
    K = x.shape[0]
    counts = np.zeros(K + 1, np.int64)
    mask = len(tk) - 1
    r2 = r * r
    for q in nb.prange(K):
        c0 = int(math.floor(x[q, 0] / cell)) - lo[0]
        c1 = int(math.floor(x[q, 1] / cell)) - lo[1]
        c2 = int(math.floor(x[q, 2] / cell)) - lo[2]
        n = 0
        at = ptr[q]
        for a in range(c0 - 1, c0 + 2):
            if a < 0 or a >= dims[0]:
                continue
            for b in range(c1 - 1, c1 + 2):
                if b < 0 or b >= dims[1]:
                    continue
                for c in range(c2 - 1, c2 + 2):
                    if c < 0 or c >= dims[2]:
                        continue
                    s = _cell_slot(tk, mask, dims, a, b, c)
                    if s < 0:
                        continue
                    for j in range(ts[s], te[s]):
                        if _sq_dist(x, q, pts, j) <= r2:
                            if fill:
                                idx[at + n] = order[j]
                            n += 1
        counts[q] = n
    return counts


