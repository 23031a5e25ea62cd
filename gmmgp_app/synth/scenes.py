"""Synthetic scenes with exact ground truth: watertight meshes and their SDF.

Scenes
------
``plane``   a 40 m x 40 m ground slab 1 m thick whose top face is the plane z = 0.
``sphere``  an icosphere (radius 1 m, 20480 faces by default); its *mesh* is the
            ground truth (at most 2.8e-4 m inside the true sphere).
``box``     a 2 x 1.2 x 0.8 m box turned 30 degrees about z, floating above the origin.
``street``  a 36 m urban street: ground with raised sidewalks, three buildings
            on one side and one long building on the other, window and door
            recesses 0.2 m deep, balconies, a round pole and a parked car.
``street2`` a second layout: a side street, an L-shaped corner building, two
            cars and two poles, other window rhythm.
``street_van`` ``street`` with a delivery van (5.5 x 2.0 x 2.4 m, label ``van``)
            parked at the kerb of the y > 0 side, from x = 0.2 L: the scene a
            second drive sees when the first one mapped ``street`` (change
            detection, :mod:`gmmgp_app.check`).

How the streets stay a single closed 2-manifold
-----------------------------------------------
Every axis-aligned part (ground, sidewalks, buildings, balconies, car body and
wheels) is a box added to, or carved from (window recesses), a solid made of
the cells of a *non-uniform rectilinear grid* whose lines are the box faces.
The boundary between solid and empty cells, one quad per cell face,
triangulated, is then exactly the surface of the union: no T-junctions
(every quad uses grid nodes only), no overlapping or coincident faces, outward
orientation by construction. Layouts avoid cells touching only along an edge
or at a corner (checked: the mesh must pass :func:`edge_topology`). The round
pole (a 16-sided prism) is stitched in: the top quads of the ground under a
square around its foot are replaced by a triangulated annulus between that
square (with every grid node on its border) and the pole's bottom ring.

Labels (per face, hence per simulated point): see :data:`LABELS`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Callable, Optional

import numpy as np

from .meshsdf import MeshDistance, edge_topology

__all__ = [
    "SynthError",
    "SyntheticScene",
    "SCENES",
    "LABELS",
    "make_scene",
    "box_sdf",
    "sphere_sdf",
    "mesh_topology",
]

SCENES = ("plane", "sphere", "box", "street", "street2", "street_van")

#: Per-point object classes of the synthetic scenes.
LABELS = {0: "unlabelled", 1: "ground", 2: "facade", 3: "balcony", 4: "pole", 5: "car",
          6: "window", 7: "object", 8: "van"}
GROUND, FACADE, BALCONY, POLE, CAR, WINDOW, OBJECT, VAN = 1, 2, 3, 4, 5, 6, 7, 8


class SynthError(ValueError):
    """A synthetic scene or scanner was asked for with an invalid name or parameter."""


# ---------------------------------------------------------------------------
# closed-form SDFs


def box_sdf(xyz, center, half_extent, yaw_deg: float = 0.0) -> np.ndarray:
    """Exact signed distance to a solid box, turned by ``yaw_deg`` about z.

    Parameters
    ----------
    xyz : (K, 3) float64
    center : (3,) float64
    half_extent : (3,) float64
    yaw_deg : float

    Returns
    -------
    (K,) float64, positive outside.
    """
    p = np.asarray(xyz, dtype=np.float64) - np.asarray(center, dtype=np.float64)
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    # rotate into the box frame (inverse yaw)
    local = np.stack([c * p[:, 0] + s * p[:, 1], -s * p[:, 0] + c * p[:, 1], p[:, 2]], axis=1)
    q = np.abs(local) - np.asarray(half_extent, dtype=np.float64)
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    inside = np.minimum(q.max(axis=1), 0.0)
    return outside + inside


def sphere_sdf(xyz, center, radius: float) -> np.ndarray:
    """Exact signed distance to a solid ball: ``|x - c| - r``; (K, 3) -> (K,)."""
    p = np.asarray(xyz, dtype=np.float64) - np.asarray(center, dtype=np.float64)
    return np.linalg.norm(p, axis=1) - radius


# ---------------------------------------------------------------------------
# the scene type


@dataclass(frozen=True, eq=False)
class SyntheticScene:
    """A watertight, outward-oriented triangle mesh with its exact SDF.

    Attributes
    ----------
    name : str
    vertices : (V, 3) float64
    faces : (F, 3) int64
        Closed 2-manifold, counter-clockwise seen from free space.
    face_labels : (F,) int64
        Object class of each face (keys of :data:`LABELS`).
    params : dict
        The parameters the scene was made with (JSON-serialisable).
    analytic : callable or None
        Closed-form SDF of the *ideal* shape, (K, 3) -> (K,), where there is
        one (plane, box: identical to the mesh; sphere: the true sphere).
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    face_labels: np.ndarray
    params: dict = field(default_factory=dict)
    analytic: Optional[Callable] = None

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) float64: minimum and maximum corner of the mesh."""
        return np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])

    @cached_property
    def distance(self) -> MeshDistance:
        """The (cached) point-to-mesh signed distance structure."""
        return MeshDistance(self.vertices, self.faces)

    def sdf(self, xyz) -> np.ndarray:
        """Exact signed distance to the mesh surface, free space positive.

        Parameters
        ----------
        xyz : (K, 3) float64

        Returns
        -------
        (K,) float64 in metres.
        """
        return self.distance(xyz)

    def analytic_sdf(self, xyz) -> np.ndarray:
        """Closed-form SDF of the ideal shape; (K, 3) -> (K,).

        Raises
        ------
        SynthError
            For scenes without a closed form (the streets).
        """
        if self.analytic is None:
            raise SynthError(
                f"Scene '{self.name}' has no closed-form SDF; use scene.sdf(xyz), which is "
                "exact for its mesh.")
        return self.analytic(np.asarray(xyz, dtype=np.float64))

    def surface_area(self) -> float:
        v, f = self.vertices, self.faces
        return 0.5 * float(np.linalg.norm(
            np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum())


def mesh_topology(vertices, faces) -> dict:
    """Watertightness figures of a triangle mesh.

    Returns
    -------
    dict with ``n_bad_edges`` (edges not shared by exactly two oppositely
    oriented faces), ``euler`` (V - E + F), ``volume`` (signed, > 0 for an
    outward-oriented closed mesh), ``n_vertices``, ``n_edges``, ``n_faces``.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    _, n_bad = edge_topology(f)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    n_edges = len(np.unique(e, axis=0))
    n_used = len(np.unique(f))
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    volume = float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)
    return dict(n_bad_edges=n_bad, euler=n_used - n_edges + len(f), volume=volume,
                n_vertices=n_used, n_edges=n_edges, n_faces=len(f))


# ---------------------------------------------------------------------------
# primitive meshes


def _box_mesh(center, half_extent, yaw_deg=0.0):
    h = np.asarray(half_extent, dtype=np.float64)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)],
                       dtype=np.float64) * h
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    v = corners @ rot.T + np.asarray(center, dtype=np.float64)
    # vertex index = 4*ix + 2*iy + iz; quads listed counter-clockwise from outside
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    f = np.array([t for q in quads for t in ((q[0], q[1], q[2]), (q[0], q[2], q[3]))],
                 dtype=np.int64)
    return v, f


def _icosphere(radius, subdivisions, center=(0.0, 0.0, 0.0)):
    t = (1.0 + math.sqrt(5.0)) / 2.0
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                  [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]],
                 dtype=np.float64)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9],
                  [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2],
                  [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
                  [8, 6, 7], [9, 8, 1]], dtype=np.int64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdivisions):
        e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        uniq, inv = np.unique(e, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        mid = v[uniq[:, 0]] + v[uniq[:, 1]]
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        nf = len(f)
        m01, m12, m20 = (len(v) + inv[:nf], len(v) + inv[nf:2 * nf], len(v) + inv[2 * nf:])
        v = np.concatenate([v, mid])
        f = np.concatenate([
            np.stack([f[:, 0], m01, m20], 1), np.stack([f[:, 1], m12, m01], 1),
            np.stack([f[:, 2], m20, m12], 1), np.stack([m01, m12, m20], 1)])
    return v * radius + np.asarray(center, dtype=np.float64), f


# ---------------------------------------------------------------------------
# rectilinear-cell solids


class _CellSolid:
    """Union/difference of axis-aligned boxes on the grid of their face planes."""

    def __init__(self):
        self.ops = []  # (lo, hi, label); label < 0 carves and tags the empty cells
        self.extra_lines = [[], [], []]

    def add(self, lo, hi, label):
        # snap to the nanometre so that coordinates computed along different paths
        # (0.7 * L + 1.3 vs 26.5) give one grid line, not a 1e-16 m sliver of cells
        lo = np.round(np.asarray(lo, dtype=np.float64), 9)
        hi = np.round(np.asarray(hi, dtype=np.float64), 9)
        if np.any(hi <= lo):
            raise SynthError(f"Expected box hi > lo, found lo={lo.tolist()} hi={hi.tolist()}; "
                             "check the scene parameters.")
        self.ops.append((lo, hi, int(label)))

    def carve(self, lo, hi, tag):
        self.add(lo, hi, -int(tag))

    def mesh(self):
        coords = []
        for ax in range(3):
            c = np.unique(np.concatenate(
                [np.array([o[0][ax] for o in self.ops] + [o[1][ax] for o in self.ops]),
                 np.asarray(self.extra_lines[ax], dtype=np.float64)]))
            # one empty padding cell on each side so every boundary face is interior
            coords.append(np.concatenate([[c[0] - 1.0], c, [c[-1] + 1.0]]))
        shape = tuple(len(c) - 1 for c in coords)
        lab = np.zeros(shape, dtype=np.int64)
        for lo, hi, label in self.ops:
            sl = tuple(slice(np.searchsorted(coords[a], lo[a]), np.searchsorted(coords[a], hi[a]))
                       for a in range(3))
            lab[sl] = label
        solid = lab > 0
        nodes = tuple(len(c) for c in coords)
        quads, qlab, qaxis = [], [], []
        for ax in range(3):
            u, w = (ax + 1) % 3, (ax + 2) % 3
            lo_cells = np.take(lab, np.arange(shape[ax] - 1), axis=ax)
            hi_cells = np.take(lab, np.arange(1, shape[ax]), axis=ax)
            for sign, mask, own, other in (
                    (+1, (lo_cells > 0) & (hi_cells <= 0), lo_cells, hi_cells),
                    (-1, (lo_cells <= 0) & (hi_cells > 0), hi_cells, lo_cells)):
                idx = np.argwhere(mask)
                if len(idx) == 0:
                    continue
                idx[:, ax] += 1  # the face plane is the node line between the two cells
                corner = []
                for du, dw in ((0, 0), (1, 0), (1, 1), (0, 1)):
                    n = idx.copy()
                    n[:, u] += du
                    n[:, w] += dw
                    corner.append(np.ravel_multi_index(n.T, nodes))
                q = np.stack(corner, axis=1)
                if sign < 0:
                    q = q[:, ::-1]
                quads.append(q)
                own_l = own[mask]
                oth_l = other[mask]
                # faces onto a carved recess carry the recess tag (e.g. window)
                qlab.append(np.where(oth_l < 0, -oth_l, own_l))
                qaxis.append(np.full(len(q), sign * (ax + 1)))
        quads = np.concatenate(quads)
        grid = np.stack(np.meshgrid(*coords, indexing="ij"), axis=-1).reshape(-1, 3)
        return grid, quads, np.concatenate(qlab), np.concatenate(qaxis), solid


def _compact(grid, faces):
    used, inv = np.unique(faces.reshape(-1), return_inverse=True)
    return np.ascontiguousarray(grid[used]), inv.reshape(-1, 3).astype(np.int64)


# ---------------------------------------------------------------------------
# street layouts


def _facade(solid, x0, x1, side, front, depth, height, *, floor_h=3.0, bay=3.0, win_w=1.2,
            win_h=1.5, sill=0.9, recess=0.2, shop=True, balcony_every=0, balcony_depth=1.0,
            bay_offset=0.0):
    """A building block on one side of the street, with recesses and balconies.

    ``side`` is +1 (building at y > 0, front face at y = +front) or -1.
    """
    if side > 0:
        y_in = (front, front + depth)
        rec = (front, front + recess)
        bal = (front - balcony_depth, front)
    else:
        y_in = (-front - depth, -front)
        rec = (-front - recess, -front)
        bal = (-front, -front + balcony_depth)
    solid.add((x0, y_in[0], 0.0), (x1, y_in[1], height), FACADE)
    n_bays = int((x1 - x0 - 2 * bay_offset) // bay)
    margin = (x1 - x0 - n_bays * bay) / 2.0
    n_floors = int(height // floor_h)
    for b in range(n_bays):
        xc = x0 + margin + (b + 0.5) * bay
        for fl in range(n_floors):
            z = fl * floor_h
            if z + sill + win_h > height - 0.5:
                break
            if fl == 0:
                if not shop:
                    continue
                # shop window or door on the ground floor (sidewalk is 0.15 m high)
                if b % 3 == 1:
                    solid.carve((xc - 0.6, rec[0], 0.15), (xc + 0.6, rec[1], 2.4), WINDOW)
                else:
                    solid.carve((xc - 1.1, rec[0], 0.8), (xc + 1.1, rec[1], 2.6), WINDOW)
                continue
            has_balcony = balcony_every and (b + fl) % balcony_every == 0
            if has_balcony:
                # balcony slab whose top is the floor level, and a door behind it
                solid.add((xc - 1.0, bal[0], z - 0.2), (xc + 1.0, bal[1], z), BALCONY)
                solid.carve((xc - 0.5, rec[0], z), (xc + 0.5, rec[1], z + 2.2), WINDOW)
            else:
                solid.carve((xc - win_w / 2, rec[0], z + sill),
                            (xc + win_w / 2, rec[1], z + sill + win_h), WINDOW)


def _car(solid, x0, y0, length=4.4, width=1.8):
    """Car-like block: body on four wheel blocks, a narrower cabin on top."""
    x1, y1 = x0 + length, y0 + width
    solid.add((x0, y0, 0.35), (x1, y1, 1.0), CAR)
    solid.add((x0 + 1.0, y0 + 0.15, 1.0), (x1 - 0.9, y1 - 0.15, 1.5), CAR)
    for wx in (x0 + 0.5, x1 - 1.1):
        for wy in (y0 + 0.05, y1 - 0.3):
            solid.add((wx, wy, 0.0), (wx + 0.6, wy + 0.25, 0.35), CAR)


def _van(solid, x0, y0, length=5.5, width=2.0):
    """Van-like block: a tall box body on four wheel blocks (label VAN)."""
    x1, y1 = x0 + length, y0 + width
    solid.add((x0, y0, 0.4), (x1, y1, 2.4), VAN)
    for wx in (x0 + 0.6, x1 - 1.3):
        for wy in (y0 + 0.05, y1 - 0.3):
            solid.add((wx, wy, 0.0), (wx + 0.7, wy + 0.25, 0.4), VAN)


def _street_solid(layout: str, length: float):
    s = _CellSolid()
    L = length
    half_w = 15.0
    s.add((-4.0, -half_w, -1.0), (L + 4.0, half_w, 0.0), GROUND)
    # raised sidewalks (0.15 m) in front of the facades at |y| = 8
    s.add((-4.0, 5.0, 0.0), (L + 4.0, 8.0, 0.15), GROUND)
    s.add((-4.0, -8.0, 0.0), (L + 4.0, -5.0, 0.15), GROUND)
    poles = []
    if layout in ("street", "street_van"):
        third = L / 3.0
        _facade(s, 0.0, third, +1, 8.0, 6.0, 12.0, balcony_every=2)
        _facade(s, third, 2 * third, +1, 8.0, 6.0, 15.0, balcony_every=3, bay=3.0)
        _facade(s, 2 * third, L, +1, 8.0, 6.0, 9.0, balcony_every=0)
        _facade(s, 0.0, L, -1, 8.0, 6.0, 18.0, balcony_every=4, bay=3.0)
        _car(s, 0.55 * L, -4.8)
        poles.append(((0.3 * L + 0.37, -6.5), 0.15))
        if layout == "street_van":
            _van(s, 0.2 * L, 2.8)
    elif layout == "street2":
        # side street between x = 0.4 L and 0.4 L + 8 on the y > 0 side
        xs = 0.4 * L
        _facade(s, 0.0, xs, +1, 8.0, 6.0, 15.0, balcony_every=2, bay=2.7)
        # L-shaped corner building: the corner part stands forward (y = 8), the rest
        # is set back 3 m, so its footprint is an L
        xc0 = xs + 8.0
        _facade(s, xc0, xc0 + 6.0, +1, 8.0, 6.0, 12.0, balcony_every=0, bay=2.7)
        _facade(s, xc0 + 6.0, L, +1, 11.0, 3.0, 12.0, balcony_every=2, bay=2.7)
        s.add((xc0 + 6.0, 8.0, 0.0), (L, 11.0, 0.15), GROUND)  # forecourt in the setback
        _facade(s, 0.0, 0.5 * L, -1, 8.0, 6.0, 21.0, balcony_every=0, bay=3.3)
        _facade(s, 0.5 * L, L, -1, 8.0, 6.0, 12.0, balcony_every=3, bay=3.3)
        _car(s, 0.15 * L, -4.8)
        _car(s, 0.7 * L, 3.0)
        poles.append(((0.25 * L + 0.21, -6.5), 0.15))
        poles.append(((0.8 * L + 0.13, 6.5), 0.12))
    else:  # pragma: no cover - guarded by make_scene
        raise SynthError(f"Unknown street layout {layout!r}.")
    foot = 0.35  # half side of the square of ground re-triangulated around a pole foot
    poles = [((round(px, 9), round(py, 9)), r) for (px, py), r in poles]
    for (px, py), _ in poles:
        s.extra_lines[0] += [round(px - foot, 9), round(px + foot, 9)]
        s.extra_lines[1] += [round(py - foot, 9), round(py + foot, 9)]
    grid, quads, qlab, _, _ = s.mesh()
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    labels = np.concatenate([qlab, qlab])
    for (px, py), r in poles:
        grid, faces, labels = _stitch_pole(grid, faces, labels, (px, py), 0.15, r, 6.0, foot)
    v, f = _compact(grid, faces)
    return v, f, labels


def _stitch_pole(grid, faces, labels, center_xy, z0, radius, height, a, sides=16):
    """Stand a ``sides``-gon prism on the flat ground at height ``z0``.

    The upward triangles at ``z0`` inside the square of half side ``a`` around
    the foot are replaced by an annulus between the square's border (every
    mesh node on it, so no T-junction) and the prism's bottom ring, triangulated
    by an angular sweep of the two loops.
    """
    px, py = center_xy
    fv = grid[faces]
    n = np.cross(fv[:, 1] - fv[:, 0], fv[:, 2] - fv[:, 0])
    cen = fv.mean(axis=1)
    inside = ((n[:, 2] > 0) & (n[:, 0] == 0) & (n[:, 1] == 0)
              & (np.abs(fv[:, :, 2] - z0).max(axis=1) < 1e-12)
              & (np.abs(cen[:, 0] - px) < a) & (np.abs(cen[:, 1] - py) < a))
    sel = fv[inside]
    area = 0.5 * np.abs(np.cross(sel[:, 1] - sel[:, 0], sel[:, 2] - sel[:, 0])[:, 2]).sum()
    if len(sel) == 0 or abs(area - 4 * a * a) > 1e-9:
        raise SynthError(
            f"Expected flat ground (z = {z0} m) under the whole pole footprint at "
            f"({px}, {py}), found a step or an edge there; move the pole.")
    used = np.unique(faces[inside])
    pts = grid[used]
    on_border = (np.isclose(np.abs(pts[:, 0] - px), a, atol=1e-12)
                 | np.isclose(np.abs(pts[:, 1] - py), a, atol=1e-12))
    outer = used[on_border]
    ang_o = np.arctan2(grid[outer, 1] - py, grid[outer, 0] - px)
    order = np.argsort(ang_o)
    outer, ang_o = outer[order], ang_o[order]
    ang_i = -math.pi + (np.arange(sides) + 0.5) * 2 * math.pi / sides
    ring = np.stack([px + radius * np.cos(ang_i), py + radius * np.sin(ang_i),
                     np.full(sides, z0)], axis=1)
    top = ring.copy()
    top[:, 2] = z0 + height
    nb = len(grid)
    grid = np.concatenate([grid, ring, top])
    inner = nb + np.arange(sides)
    tris = []
    no, ni = len(outer), sides
    i = j = 0
    while i < no or j < ni:
        ao = ang_o[(i + 1) % no] + (2 * math.pi if i + 1 >= no else 0.0)
        ai = ang_i[(j + 1) % ni] + (2 * math.pi if j + 1 >= ni else 0.0)
        if j >= ni or (i < no and ao < ai):
            tris.append((outer[i % no], outer[(i + 1) % no], inner[j % ni]))
            i += 1
        else:
            tris.append((outer[i % no], inner[(j + 1) % ni], inner[j % ni]))
            j += 1
    ann = np.array(tris, dtype=np.int64)
    e1 = grid[ann[:, 1]] - grid[ann[:, 0]]
    e2 = grid[ann[:, 2]] - grid[ann[:, 0]]
    cz = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    poly_area = 0.5 * sides * radius**2 * math.sin(2 * math.pi / sides)
    if np.any(cz <= 0) or abs(0.5 * cz.sum() - (4 * a * a - poly_area)) > 1e-9:
        raise SynthError(
            f"Expected the pole radius ({radius} m) well inside its footprint square "
            f"(half side {a} m), found an invalid triangulation; enlarge the square.")
    top_idx = nb + sides + np.arange(sides)
    side = []
    for k in range(sides):
        k1 = (k + 1) % sides
        side += [(inner[k], inner[k1], top_idx[k1]), (inner[k], top_idx[k1], top_idx[k])]
    cap = [(top_idx[0], top_idx[k], top_idx[k + 1]) for k in range(1, sides - 1)]
    ann_label = int(np.bincount(labels[inside]).argmax())
    new_faces = np.concatenate([faces[~inside], ann, np.array(side + cap, dtype=np.int64)])
    new_labels = np.concatenate([labels[~inside], np.full(len(ann), ann_label),
                                 np.full(len(side) + len(cap), POLE)])
    return grid, new_faces, new_labels


# ---------------------------------------------------------------------------
# factory

_DEFAULTS = {
    "plane": dict(size=40.0, thickness=1.0),
    "sphere": dict(radius=1.0, subdivisions=5, center=(0.0, 0.0, 0.0)),
    "box": dict(half_extent=(1.0, 0.6, 0.4), yaw_deg=30.0, center=(0.0, 0.0, 0.0)),
    "street": dict(length=36.0),
    "street2": dict(length=36.0),
    "street_van": dict(length=36.0),
}


def make_scene(name: str, **params) -> SyntheticScene:
    """Build one of the synthetic scenes in :data:`SCENES`.

    Parameters
    ----------
    name : {"plane", "sphere", "box", "street", "street2", "street_van"}
    **params
        plane: ``size`` (m, side of the square slab, default 40), ``thickness`` (m, 1).
        sphere: ``radius`` (m, 1), ``subdivisions`` (icosphere level, 5 -> 20480 faces),
        ``center``. box: ``half_extent`` (m, (1, 0.6, 0.4)), ``yaw_deg`` (30), ``center``.
        street, street2, street_van: ``length`` (m, 36; between 20 and 200).

    Returns
    -------
    SyntheticScene

    Raises
    ------
    SynthError
        Unknown scene name, unknown parameter, or a parameter out of range.
    """
    if name not in _DEFAULTS:
        raise SynthError(f"Unknown synthetic scene {name!r}; expected one of "
                         f"{', '.join(SCENES)}.")
    unknown = sorted(set(params) - set(_DEFAULTS[name]))
    if unknown:
        raise SynthError(f"Unknown parameter(s) {unknown} for scene '{name}'; expected "
                         f"some of {sorted(_DEFAULTS[name])}.")
    p = {**_DEFAULTS[name], **params}

    def positive(key, hi=np.inf):
        val = np.asarray(p[key], dtype=np.float64)
        if not np.all(np.isfinite(val)) or np.any(val <= 0) or np.any(val > hi):
            raise SynthError(f"Expected {name} parameter '{key}' in (0, {hi}], found "
                             f"{p[key]!r}; pass a positive size in metres.")

    if name == "plane":
        positive("size")
        positive("thickness")
        half = np.array([p["size"] / 2, p["size"] / 2, p["thickness"] / 2])
        center = np.array([0.0, 0.0, -p["thickness"] / 2])
        v, f = _box_mesh(center, half)
        labels = np.full(len(f), GROUND)
        analytic = lambda x: box_sdf(x, center, half)  # noqa: E731
    elif name == "sphere":
        positive("radius")
        sub = int(p["subdivisions"])
        if not 0 <= sub <= 7:
            raise SynthError(f"Expected sphere parameter 'subdivisions' in [0, 7], found "
                             f"{p['subdivisions']!r}; 5 gives 20480 faces.")
        center = np.asarray(p["center"], dtype=np.float64).reshape(3)
        v, f = _icosphere(float(p["radius"]), sub, center)
        labels = np.full(len(f), OBJECT)
        r = float(p["radius"])
        analytic = lambda x: sphere_sdf(x, center, r)  # noqa: E731
    elif name == "box":
        positive("half_extent")
        center = np.asarray(p["center"], dtype=np.float64).reshape(3)
        half = np.asarray(p["half_extent"], dtype=np.float64).reshape(3)
        yaw = float(p["yaw_deg"])
        v, f = _box_mesh(center, half, yaw)
        labels = np.full(len(f), OBJECT)
        analytic = lambda x: box_sdf(x, center, half, yaw)  # noqa: E731
    else:
        length = float(p["length"])
        if not 20.0 <= length <= 200.0:
            raise SynthError(f"Expected {name} parameter 'length' in [20, 200] m, found "
                             f"{p['length']!r}; the layouts need at least 20 m.")
        v, f, labels = _street_solid(name, length)
        analytic = None
    topo = mesh_topology(v, f)
    if topo["n_bad_edges"] or topo["volume"] <= 0:  # pragma: no cover - construction bug
        raise SynthError(f"Scene '{name}' built a mesh that is not watertight and outward "
                         f"({topo}); this is a bug in the layout.")
    jp = {k: (list(map(float, val)) if isinstance(val, (tuple, list, np.ndarray)) else val)
          for k, val in p.items()}
    return SyntheticScene(name=name, vertices=np.ascontiguousarray(v, dtype=np.float64),
                          faces=np.ascontiguousarray(f, dtype=np.int64),
                          face_labels=np.asarray(labels, dtype=np.int64), params=jp,
                          analytic=analytic)
