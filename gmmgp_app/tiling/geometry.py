"""Tile geometry and owners: how space is cut into tiles, which tile answers where,
and each tile's point set (canonical order; the union of a tile and the small tiles
it owns)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..types import Scan

__all__ = ["TilingError", "TilingWarning", "TileSpec", "tile_owners", "split_into_tiles",
           "warn_if_not_z_up"]


class TilingError(ValueError):
    """Bad tiling parameters or input to a tiled map."""


class TilingWarning(UserWarning):
    """A tiling that works but does not do what tiles are for (bounding each tile)."""


def warn_if_not_z_up(scan: Scan) -> None:
    """Warn (:class:`TilingWarning`, one line) when ``scan.up`` is not z: tiles are cut
    in x and y, which assumes z up. For a y-up scan (a Stanford set) they are slabs
    across the height, unbounded along z; the stitched map is still right, but a tile
    no longer bounds the points it holds (a synthetic street turned y up, running along
    z, tiled at 5 m: the largest tile held 51 % of the points, against 10 % z up)."""
    import warnings

    u = np.asarray(scan.up, dtype=np.float64)
    if abs(float(u[2])) != 1.0:
        axis = "xyz"[int(np.flatnonzero(u)[0])]
        warnings.warn(f"The scan's up axis is {axis}, but tiles are cut in x and y (they "
                      f"assume z up): here they are slabs across the height, unbounded "
                      f"along z, and a tile may hold most of the points; rotate the scan "
                      f"to z up, or map it whole (without tiles).", TilingWarning,
                      stacklevel=3)


def tile_dirname(key) -> str:
    """``tile_I_J``: a tile's folder (saved map) or file stem (its points)."""
    return f"tile_{int(key[0])}_{int(key[1])}"


@dataclass(frozen=True)
class TileSpec:
    """How space is cut into tiles.

    Attributes
    ----------
    size : float
        Edge of a tile's core square in x and y (m).
    overlap : float
        Training margin around the core (m); also the width of the blending band
        centred on each core border. Must satisfy ``0 <= overlap <= size / 2``.
    blend : {"smooth", "core"}
        Stitching of predictions (see the module docstring).
    min_points : int
        Tiles with fewer scan points are not mapped on their own: their points and
        their square go to the nearest mapped tile (see :func:`tile_owners`).
    """

    size: float = 20.0
    overlap: float = 2.0
    blend: str = "smooth"
    min_points: int = 200

    def __post_init__(self):
        if not (self.size > 0 and math.isfinite(self.size)):
            raise TilingError(f"Expected a positive tile size, found {self.size!r}; use e.g. "
                              "20 m.")
        if not (0 <= self.overlap <= self.size / 2):
            raise TilingError(f"Expected 0 <= tile overlap <= size / 2 = {self.size / 2}, "
                              f"found {self.overlap!r}; use e.g. 2 m.")
        if self.blend not in ("smooth", "core"):
            raise TilingError(f"Expected blend 'smooth' or 'core', found {self.blend!r}.")
        if self.min_points < 10:
            raise TilingError(f"Expected min_points >= 10, found {self.min_points!r}; "
                              "the prepare stage needs at least 10 points.")

    def assign(self, xyz) -> dict:
        """Index of the points each tile trains on (core grown by ``overlap``).

        Parameters
        ----------
        xyz : (N, 3)

        Returns
        -------
        dict mapping tile key ``(i, j)`` to a sorted (n,) int64 index array.
        """
        xy = np.asarray(xyz, dtype=np.float64)[:, :2]
        lo = np.floor((xy - self.overlap) / self.size).astype(np.int64)
        hi = np.floor((xy + self.overlap) / self.size).astype(np.int64)
        out: dict = {}
        for di in (0, 1):
            for dj in (0, 1):
                key = lo + np.array([di, dj])
                ok = np.all(key <= hi, axis=1)
                idx = np.flatnonzero(ok)
                if len(idx) == 0:
                    continue
                k = key[idx]
                order = np.lexsort((k[:, 1], k[:, 0]))
                idx, k = idx[order], k[order]
                cut = np.flatnonzero(np.any(np.diff(k, axis=0) != 0, axis=1)) + 1
                for part in np.split(np.arange(len(idx)), cut):
                    kk = (int(k[part[0], 0]), int(k[part[0], 1]))
                    out.setdefault(kk, []).append(idx[part])
        return {k: np.sort(np.concatenate(v)) for k, v in sorted(out.items())}

    def weights(self, xy, key) -> tuple[np.ndarray, np.ndarray]:
        """Blending weight of tile ``key`` at (K, 2) points and its (K, 2) gradient.

        Smooth: ``w = S(u_x^-) S(u_x^+) S(u_y^-) S(u_y^+)`` with the smoothstep
        ``S(t) = 3t^2 - 2t^3`` on ``[0, 1]`` and ``u`` the distance past the band
        start over the band width; ``S(t) + S(1 - t) = 1`` makes the weights of
        neighbouring tiles sum to one. Core: the indicator of the core square.
        """
        xy = np.asarray(xy, dtype=np.float64)
        lo = np.asarray(key, dtype=np.float64) * self.size
        if self.blend == "core" or self.overlap == 0:
            inside = np.all((xy >= lo) & (xy < lo + self.size), axis=1)
            return inside.astype(np.float64), np.zeros_like(xy)
        b = self.overlap
        t_lo = (xy - (lo - b / 2)) / b
        t_hi = ((lo + self.size + b / 2) - xy) / b
        s_lo, d_lo = _smoothstep(t_lo)
        s_hi, d_hi = _smoothstep(t_hi)
        per_axis = s_lo * s_hi
        d_axis = (d_lo * s_hi - s_lo * d_hi) / b
        w = per_axis[:, 0] * per_axis[:, 1]
        grad = np.column_stack([d_axis[:, 0] * per_axis[:, 1], per_axis[:, 0] * d_axis[:, 1]])
        return w, grad

    def candidate_keys(self, xy) -> list[np.ndarray]:
        """The (K, 2) tile keys whose weight may be non-zero at each point (4 arrays)."""
        reach = self.overlap / 2 if self.blend == "smooth" else 0.0
        lo = np.floor((np.asarray(xy) - reach) / self.size).astype(np.int64)
        return [lo + np.array([di, dj]) for di in (0, 1) for dj in (0, 1)]


def _smoothstep(t):
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t), 6.0 * t * (1.0 - t)


def canonical_order(points, origins):
    """Sort points (and origins) lexicographically: a tile's map depends on its set only."""
    order = np.lexsort((points[:, 2], points[:, 1], points[:, 0]))
    return points[order], (None if origins is None else origins[order])


def tile_owners(counts: dict, min_points: int) -> dict:
    """Which mapped tile takes over each tile with fewer than ``min_points`` points.

    Parameters
    ----------
    counts : dict ``{(i, j): number of points}``
    min_points : int

    Returns
    -------
    dict ``{small key: owner key}``: the owner is a tile with at least
    ``min_points`` points whose square is nearest (Euclidean distance between the
    keys, so a neighbour across an edge comes before one across a corner, whose
    data would not reach along the whole shared side), the one with the most points
    among equally near ones. Empty when no tile is big enough.
    """
    big = sorted(k for k, n in counts.items() if n >= min_points)
    owners = {}
    for k, n in sorted(counts.items()):
        if n >= min_points or not big:
            continue
        owners[k] = min(big, key=lambda b: ((b[0] - k[0]) ** 2 + (b[1] - k[1]) ** 2,
                                            -counts[b], b))
    return owners


def owners_summary(owners: dict) -> dict:
    """``{"(i, j)": "(k, l)"}``: the owners as the JSON-friendly ``absorbed_tiles`` summary."""
    return {str(k): str(o) for k, o in owners.items()}


def members(owners: dict, key) -> list:
    """The tile ``key`` and the small tiles it owns, sorted."""
    return [key] + sorted(k for k, o in owners.items() if o == key)


def _as_void(points: np.ndarray) -> np.ndarray:
    """Rows of an (N, 3) float64 array as one opaque value each (exact row matching)."""
    a = np.ascontiguousarray(points, dtype=np.float64)
    return a.view(np.dtype((np.void, a.dtype.itemsize * a.shape[1]))).ravel()


def union_points(parts) -> tuple:
    """Point sets of several tiles as one, without the points their overlap margins
    share: ``[(points, origins or None), ...]`` -> (points, origins), canonical order.

    A point already in an earlier tile's set is dropped from a later one; repeated
    points inside one tile's set are kept (as a single tile would keep them).
    """
    keep_pts, keep_org = [parts[0][0]], [parts[0][1]]
    for pts, org in parts[1:]:
        new = ~np.isin(_as_void(pts), _as_void(np.concatenate(keep_pts)))
        keep_pts.append(pts[new])
        keep_org.append(None if org is None else org[new])
    has_org = all(o is not None for o in keep_org)
    return canonical_order(np.concatenate(keep_pts),
                      np.concatenate(keep_org) if has_org else None)


def split_into_tiles(scan: Scan, spec: TileSpec) -> dict:
    """Cut a scan into the tiles of ``spec``: ``{(i, j): Scan}`` (canonical order)."""
    out = {}
    for key, idx in spec.assign(scan.points).items():
        pts, org = canonical_order(scan.points[idx],
                              None if scan.origins is None else scan.origins[idx])
        out[key] = Scan(points=pts, origins=org, offset=scan.offset, source=f"tile {key}")
    return out
