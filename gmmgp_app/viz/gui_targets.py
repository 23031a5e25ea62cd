"""What ``gmmgp view`` opens besides a scan and a map, without any GUI: run folders,
tiled maps and check results.

* a **run folder** (``gmmgp run SCAN --out DIR``): the map (``DIR/map``), the meshes
  the run wrote (``DIR/mesh_<method>.ply``, shown instead of being recomputed) and
  the run's ``summary.json``;
* a **tiled map** (``tiled.json``, or a run folder made with ``--tile-size``):
  :class:`TiledView` loads tiles on demand (those around a point of the view, or
  all of them) through :class:`gmmgp_app.tiling.TiledMap`; each loaded tile
  contributes its surface seeds, HGMM, GP points and a surface piece meshed from
  the *stitched* field (``TiledMap.predict``) on the global marching-cubes lattice,
  its faces cut at the tile's core square, so neighbouring pieces meet without seam
  or overlap;
* a **check result** (``gmmgp check ... --out OUT``: ``OUT/check.json`` and
  ``OUT/points.ply``, or ``OUT/aligned.ply`` when aligned): :class:`CheckView`, the
  points with their z, known and changed flags and the change segments.

Everything here returns :class:`gmmgp_app.viz.gui_model.StageResults` pieces; the
window and the offscreen render draw them.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from ..types import GaussianMixture, HGMMLevel, HierarchicalGMM, Scan, SurfaceMesh

__all__ = ["CheckView", "TiledView", "is_result_folder", "read_check", "read_run_mesh",
           "read_summary", "summary_lines", "is_check_folder", "tiled_map_dir"]


class TargetError(ValueError):
    """A folder that looks like a result but cannot be read."""


# --------------------------------------------------------------------------- run folders
def read_summary(folder) -> dict:
    """``summary.json`` of a run folder (``{}`` when there is none)."""
    p = Path(folder) / "summary.json"
    if not p.is_file():
        return {}
    try:
        return json.loads(p.read_text())
    except json.JSONDecodeError as e:
        raise TargetError(f"Cannot read '{p}' ({e}); the run may have been interrupted: "
                          "run 'gmmgp run' again.") from None


def read_run_mesh(folder, method: str, offset) -> Optional[SurfaceMesh]:
    """The surface a run wrote (``mesh_<method>.ply``) in the map's local frame, or None."""
    from ..pipeline import read_mesh_ply

    p = Path(folder) / f"mesh_{method}.ply"
    if not p.is_file():
        return None
    m = read_mesh_ply(p)
    return SurfaceMesh(m.vertices - np.asarray(offset, float).reshape(1, 3), m.faces,
                       m.vertex_variance)


def summary_lines(summary: dict, width: int = 40) -> list:
    """Lines of the panel's summary: method, counts, total time, and the table of
    settings resolved automatically from the scan (``summary["auto"]``: name ->
    {value, reason}) when the run recorded one."""
    lines = []
    if not summary:
        return lines
    head = []
    if "method" in summary:
        head.append(f"method {summary['method']}")
    if summary.get("tiled"):
        head.append(f"{summary.get('n_tiles', '?')} tiles")
    sec = summary.get("seconds", {})
    if isinstance(sec, dict) and isinstance(sec.get("total"), (int, float)):
        head.append(f"total {sec['total']:.1f} s")
    if head:
        lines.append(", ".join(head))
    auto = summary.get("auto")
    if isinstance(auto, dict) and auto:
        lines.append("settings from the scan:")
        for name, item in auto.items():
            if isinstance(item, dict):
                v, why = item.get("value"), item.get("reason", "")
            else:
                v, why = item, ""
            val = f"{v:.4g}" if isinstance(v, float) else str(v)
            text = f"  {name} = {val}" + (f": {why}" if why else "")
            while len(text) > width:  # wrap: the panel is narrow
                cut = text.rfind(" ", 0, width)
                cut = width if cut <= 4 else cut
                lines.append(text[:cut])
                text = "    " + text[cut:].lstrip()
            lines.append(text)
    return lines


# --------------------------------------------------------------------------- tiled maps
def tiled_map_dir(path) -> Optional[Path]:
    """The folder holding ``tiled.json`` (``path`` or ``path/map``), or None."""
    p = Path(path)
    for d in (p, p / "map"):
        if (d / "tiled.json").is_file():
            return d
    return None


@dataclass(frozen=True)
class TilePiece:
    """What one loaded tile contributes to the view (local frame)."""

    key: tuple
    seeds: np.ndarray
    gp_points: np.ndarray
    hgmm: Optional[HierarchicalGMM]
    mesh: Optional[SurfaceMesh]


class TiledView:
    """Tiles of a :class:`~gmmgp_app.tiling.TiledMap` loaded on demand for the view.

    Parameters
    ----------
    tmap : TiledMap
        Opened with :func:`~gmmgp_app.tiling.load_tiled_map` (tiles stay on disk).
    """

    def __init__(self, tmap):
        self.tmap = tmap
        self.pieces: dict = {}  # key -> TilePiece, in load order
        self._reach = None  # the stitched surface's reach (m), found at the first load
        self._trim_tree = None  # every tile's seeds, with surface.trim_to_reach

    @property
    def keys(self) -> list:
        return self.tmap.keys

    @property
    def size(self) -> float:
        return float(self.tmap.spec.size)

    def _members(self, key) -> list:
        """Squares tile ``key`` answers for: its own and those of small tiles it owns."""
        return [key] + sorted(k for k, o in self.tmap.owners.items() if o == key)

    def _in_squares(self, xy, key) -> np.ndarray:
        sq = np.floor(np.asarray(xy, float) / self.size).astype(np.int64)
        keep = np.zeros(len(sq), bool)
        for k in self._members(key):
            keep |= np.all(sq == np.asarray(k, np.int64), axis=1)
        return keep

    def centre(self) -> np.ndarray:
        """(2,) centre of the mapped squares (x, y)."""
        k = np.asarray(self.keys, float)
        return (k.mean(axis=0) + 0.5) * self.size

    def keys_near(self, xy, radius: float) -> list:
        """Mapped tiles whose square comes within ``radius`` of ``xy``, nearest first."""
        xy = np.asarray(xy, float).reshape(2)
        out = []
        for key in self.keys:
            lo = np.asarray(key, float) * self.size
            d = float(np.linalg.norm(np.clip(xy, lo, lo + self.size) - xy))
            if d <= radius:
                out.append((d, key))
        return [k for _, k in sorted(out)]

    def load(self, keys, voxel_size: float, mesh: bool = True,
             progress: Optional[Callable[[int, int], None]] = None) -> list:
        """Load the tiles ``keys`` not loaded yet; returns the keys loaded now.

        Each tile's surface piece is meshed from the stitched field at the seeds of the
        tile's own squares and keeps the faces whose centroid lies in them.
        """
        if self._reach is None and mesh:
            # the stitched surface's reach (TiledMap.extract_surface), the same for
            # every piece so that the pieces are that surface face for face
            stitched = self.tmap.stitched_seeds()
            self._reach = self.tmap.surface_reach(stitched)
            # with surface.trim_to_reach the stitched surface keeps the faces within the
            # reach of any tile's seed: a piece, followed from its own seeds, is trimmed
            # against all of them
            if self.tmap.config.surface.trim_to_reach:
                from scipy.spatial import cKDTree
                self._trim_tree = cKDTree(stitched)
        todo = [tuple(k) for k in keys if tuple(k) not in self.pieces]
        for i, key in enumerate(todo):
            t = self.tmap.tiles[key]
            seeds = np.asarray(t.seed_points, float)
            seeds = seeds[self._in_squares(seeds[:, :2], key)]
            m = None
            if mesh and len(seeds):
                full = self.tmap.extract_surface(voxel_size, reach=self._reach, seeds=seeds,
                                                 trim_to_reach=False)
                m = _crop_faces(full, lambda c, k=key: self._keeps(c, k))
            gp = np.asarray(t.gp_points, float)
            self.pieces[key] = TilePiece(key, seeds, gp[self._in_squares(gp[:, :2], key)]
                                         if len(gp) else gp.reshape(0, 3), t.hgmm, m)
            if progress is not None:
                progress(i + 1, len(todo))
        return todo

    def _keeps(self, c: np.ndarray, key) -> np.ndarray:
        """(n,) True for the face centroids ``c`` that tile ``key``'s piece keeps: in its
        squares and, with the trim, within the reach of a seed."""
        keep = self._in_squares(c[:, :2], key)
        if self._trim_tree is not None:
            from ..pipeline import centroids_within_reach

            keep &= centroids_within_reach(c, self._trim_tree, self._reach)
        return keep

    def merged(self) -> dict:
        """The loaded tiles as StageResults fields: scan (seeds), hgmm, gp_points, mesh."""
        pieces = list(self.pieces.values())
        seeds = np.concatenate([p.seeds for p in pieces]) if pieces else np.zeros((0, 3))
        gp = np.concatenate([p.gp_points for p in pieces]) if pieces else np.zeros((0, 3))
        meshes = [p.mesh for p in pieces if p.mesh is not None]
        hg = [p.hgmm for p in pieces if p.hgmm is not None]
        return {"scan": Scan(seeds, offset=self.tmap.offset,
                             source=f"{len(pieces)} of {len(self.keys)} tiles (surface seeds)"),
                "hgmm": merge_hierarchies(hg) if hg else None,
                "gp_points": gp,
                "mesh": merge_meshes(meshes) if meshes else None}


def _crop_faces(mesh: SurfaceMesh, keep_centroid) -> SurfaceMesh:
    """The faces whose centroid passes ``keep_centroid`` (vertices re-indexed)."""
    if len(mesh.faces) == 0:
        return mesh
    c = mesh.vertices[mesh.faces].mean(axis=1)
    faces = mesh.faces[keep_centroid(c)]
    used, inv = np.unique(faces, return_inverse=True)
    return SurfaceMesh(mesh.vertices[used], inv.reshape(-1, 3).astype(np.int64),
                       mesh.vertex_variance[used])


def merge_meshes(meshes) -> SurfaceMesh:
    """One mesh of several (faces re-indexed)."""
    off = np.cumsum([0] + [len(m.vertices) for m in meshes])[:-1]
    return SurfaceMesh(np.concatenate([m.vertices for m in meshes]),
                       np.concatenate([m.faces + o for m, o in zip(meshes, off)]),
                       np.concatenate([m.vertex_variance for m in meshes]))


def merge_hierarchies(hs) -> HierarchicalGMM:
    """The tiles' hierarchies side by side, level by level (for drawing: each tile's
    weights stay its own, parents are re-indexed)."""
    n_levels = max(len(h.levels) for h in hs)
    levels = []
    prev_counts = [0] * len(hs)
    for lv in range(n_levels):
        parts, counts, base_prev = [], [], 0
        for i, h in enumerate(hs):
            if lv < len(h.levels):
                L = h.levels[lv]
                parent = np.where(L.parent >= 0, L.parent + base_prev, -1)
                parts.append((L, parent))
                counts.append(L.mixture.n_components)
            else:
                counts.append(0)
            base_prev += prev_counts[i]
        prev_counts = counts
        levels.append(HGMMLevel(
            GaussianMixture(np.concatenate([p[0].mixture.weights for p in parts]),
                            np.concatenate([p[0].mixture.means for p in parts]),
                            np.concatenate([p[0].mixture.covariances for p in parts])),
            np.concatenate([p[1] for p in parts]),
            np.concatenate([p[0].complexity for p in parts]),
            np.concatenate([p[0].split for p in parts]),
            np.concatenate([p[0].n_rows for p in parts])))
    leaves = GaussianMixture(np.concatenate([h.leaves.weights for h in hs]),
                             np.concatenate([h.leaves.means for h in hs]),
                             np.concatenate([h.leaves.covariances for h in hs]))
    return HierarchicalGMM(tuple(levels), leaves,
                           np.concatenate([h.leaf_level for h in hs]))


# --------------------------------------------------------------------------- check results
def is_result_folder(path) -> bool:
    """Whether folder ``path`` is something the project wrote: a ``gmmgp check``
    result, a tiled map, a saved map or a run folder (its ``map/`` or ``summary.json``).
    Any other folder is opened as a folder of scans."""
    p = Path(path)
    return (is_check_folder(p) or tiled_map_dir(p) is not None
            or any((d / "map.json").is_file() for d in (p, p / "map"))
            or (p / "summary.json").is_file())


def is_check_folder(path) -> bool:
    p = Path(path)
    return (p / "check.json").is_file() and (p / "points.ply").is_file()


@dataclass(frozen=True)
class CheckView:
    """A ``gmmgp check`` result: per point z, known, changed, segment; the segments.

    Attributes
    ----------
    z, distance, std : (N,) float64
    known, changed : (N,) bool
    segment : (N,) int64
        Index into ``segments`` (-1: none).
    segments : tuple of dict
        ``size``, ``centroid``, ``bbox_min``, ``bbox_max`` (local frame: the view's
        offset subtracted) and ``mean_distance_m``, largest first.
    z_threshold : float
        |z| above which a known point counts as changed.
    summary : dict
        ``check.json``.
    """

    z: np.ndarray
    distance: np.ndarray
    std: np.ndarray
    known: np.ndarray
    changed: np.ndarray
    segment: np.ndarray
    segments: tuple
    z_threshold: float
    summary: dict = field(repr=False, default_factory=dict)

    def segment_label(self, i: int) -> str:
        s = self.segments[i]
        c = s["centroid"]
        return (f"#{i + 1}: {s['size']} pts at ({c[0]:.1f}, {c[1]:.1f}, {c[2]:.1f}), "
                f"{'+' if s['mean_distance_m'] >= 0 else ''}{s['mean_distance_m']:.2f} m")


def read_check(folder) -> tuple:
    """(Scan, CheckView) of a ``gmmgp check`` output folder.

    The points are read from ``aligned.ply`` when the check aligned the scan (the
    map's frame, where the segments are), else from ``points.ply``; a local offset
    (the rounded median) is subtracted from both points and segments. The scan stands
    on the map's up axis (check.json "up"; a check written before it was kept: z).
    """
    import open3d as o3d

    folder = Path(folder)
    summary = json.loads((folder / "check.json").read_text())
    ply = folder / ("aligned.ply" if (folder / "aligned.ply").is_file() else "points.ply")
    pc = o3d.t.io.read_point_cloud(str(ply))
    if "positions" not in pc.point or len(pc.point["positions"]) == 0:
        raise TargetError(f"'{ply}' holds no points; run 'gmmgp check' again.")
    pos = pc.point["positions"].numpy().astype(np.float64)
    need = ("distance", "std", "z_score", "known", "changed", "segment")
    missing = [n for n in need if n not in pc.point]
    if missing:
        raise TargetError(f"'{ply}' lacks the fields {', '.join(missing)}; it was not "
                          "written by 'gmmgp check' (or by an older version): run it again.")
    f = {n: pc.point[n].numpy().reshape(-1).astype(np.float64) for n in need}
    finite = np.all(np.isfinite(pos), axis=1)
    offset = np.round(np.median(pos[finite], axis=0)) if finite.any() else np.zeros(3)
    keep = finite
    segs = []
    for s in summary.get("segments", []):
        segs.append({"size": int(s["size"]), "mean_distance_m": float(s["mean_distance_m"]),
                     **{k: np.asarray(s[k], float) - offset
                        for k in ("centroid", "bbox_min", "bbox_max")}})
    seg = f["segment"][keep].astype(np.int64)
    view = CheckView(z=f["z_score"][keep], distance=f["distance"][keep], std=f["std"][keep],
                     known=f["known"][keep] > 0.5, changed=f["changed"][keep] > 0.5,
                     segment=seg, segments=tuple(segs),
                     z_threshold=float(summary.get("z_threshold", 3.0)), summary=summary)
    scan = Scan(pos[keep] - offset, offset=offset, source=str(ply), up=summary.get("up"))
    return scan, view
