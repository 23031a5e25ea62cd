"""Scenes the field benchmark holds out: a courtyard and small-scale piping.

``courtyard``  a walked mobile-mapping scene, laid out unlike the streets: a 6 m
               wide yard between a building pierced by two passages (1 m and 3 m
               wide) and a pair of thin (0.2 m) walls that form a 1.8 m corridor
               with a 2 m gap, square pillars, a low thin fence (1 m high, 0.1 m
               thick) and an open-top kiosk of 0.1 m walls with a door.
``pipes``      industrial piping at small scale: horizontal pipes of radius 3, 5 and
               8 cm, a vertical pipe of 4 cm, a tank of radius 30 cm, over a
               3 x 2 m floor slab; scanned by terrestrial stations 2-4 m away with
               about 5 mm point spacing.

Both are closed, outward-oriented meshes (checked with
:func:`~gmmgp_app.synth.scenes.mesh_topology`), so ``scene.sdf`` is exact.

>>> scene = make_field_scene("courtyard")
>>> round(float(scene.sdf([[5.0, 0.0, 1.0]])[0]), 2) > 0
True
"""

from __future__ import annotations

import math

import numpy as np

from .scanner import simulate_mms, simulate_static
from .scenes import (FACADE, GROUND, OBJECT, POLE, SynthError, SyntheticScene, _box_mesh,
                     _CellSolid, _compact, mesh_topology)

__all__ = ["FIELD_SCENES", "make_field_scene", "scan_field_scene"]

FIELD_SCENES = ("courtyard", "pipes")


def _courtyard():
    s = _CellSolid()
    s.add((-4.0, -12.0, -1.0), (34.0, 12.0, 0.0), GROUND)
    # north building, front at y = 3, two passages through it
    s.add((-4.0, 3.0, 0.0), (34.0, 9.0, 8.0), FACADE)
    s.carve((8.0, 3.0, 0.0), (9.0, 9.0, 3.0), 6)
    s.carve((18.0, 3.0, 0.0), (21.0, 9.0, 3.5), 6)
    # thin south walls with a 2 m gap, and a second wall making a 1.8 m corridor
    s.add((-4.0, -3.2, 0.0), (12.0, -3.0, 3.0), FACADE)
    s.add((14.0, -3.2, 0.0), (34.0, -3.0, 3.0), FACADE)
    s.add((-4.0, -5.2, 0.0), (34.0, -5.0, 2.5), FACADE)
    # square pillars
    for x in (5.0, 15.0, 28.0):
        s.add((x - 0.2, 1.3, 0.0), (x + 0.2, 1.7, 3.0), POLE)
    # low thin fence
    s.add((2.0, -2.0, 0.0), (10.0, -1.9, 1.0), OBJECT)
    # open-top kiosk with a door in its north wall
    s.add((22.0, -1.3, 0.0), (23.0, -1.2, 2.2), OBJECT)
    s.add((23.8, -1.3, 0.0), (24.5, -1.2, 2.2), OBJECT)
    s.add((22.0, -2.7, 0.0), (24.5, -2.6, 2.2), OBJECT)
    s.add((22.0, -2.7, 0.0), (22.1, -1.2, 2.2), OBJECT)
    s.add((24.4, -2.7, 0.0), (24.5, -1.2, 2.2), OBJECT)
    grid, quads, qlab, _, _ = s.mesh()
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    v, f = _compact(grid, faces)
    return v, f, np.concatenate([qlab, qlab])


def _cylinder(p0, axis, radius, length, sides):
    """Closed prism of ``sides`` sides around ``axis`` from ``p0``, outward faces."""
    a = np.asarray(axis, dtype=np.float64)
    a /= np.linalg.norm(a)
    u = np.cross(a, [0.0, 0.0, 1.0] if abs(a[2]) < 0.9 else [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(a, u)
    ang = 2 * math.pi * np.arange(sides) / sides
    ring = radius * (np.cos(ang)[:, None] * u + np.sin(ang)[:, None] * w)
    p0 = np.asarray(p0, dtype=np.float64)
    bottom, top = p0 + ring, p0 + length * a + ring
    v = np.concatenate([bottom, top, [p0, p0 + length * a]])
    cb, ct = 2 * sides, 2 * sides + 1
    f = []
    for k in range(sides):
        k1 = (k + 1) % sides
        f += [(k, k1, sides + k1), (k, sides + k1, sides + k)]
        f += [(cb, k1, k), (ct, sides + k, sides + k1)]
    f = np.array(f, dtype=np.int64)
    # orient outward: the side normal must point away from the axis
    tri = v[f[0]]
    n = np.cross(tri[1] - tri[0], tri[2] - tri[0])
    if np.dot(n, tri.mean(0) - p0 - np.dot(tri.mean(0) - p0, a) * a) < 0:
        f = f[:, ::-1]
    return v, f


def _pipes():
    parts = [(_box_mesh((0.0, 0.0, -0.05), (1.5, 1.0, 0.05)), GROUND)]
    # horizontal pipes along x (radius 3, 5, 8 cm) at different heights and depths
    for y, z, r in ((-0.5, 0.35, 0.03), (-0.2, 0.6, 0.05), (0.15, 0.3, 0.08)):
        parts.append((_cylinder((-1.3, y, z), (1, 0, 0), r, 2.2, 64), OBJECT))
    # a vertical pipe and a tank
    parts.append((_cylinder((-0.9, 0.55, 0.02), (0, 0, 1), 0.04, 1.2, 48), OBJECT))
    parts.append((_cylinder((0.8, 0.55, 0.05), (0, 0, 1), 0.30, 1.0, 96), OBJECT))
    return _join_parts(parts)


def _join_parts(parts):
    """One mesh ``(vertices, faces, face labels)`` from ``[((vertices, faces), label)]``."""
    vs, fs, ls, off = [], [], [], 0
    for (v, f), lab in parts:
        vs.append(v)
        fs.append(f + off)
        ls.append(np.full(len(f), lab))
        off += len(v)
    return np.concatenate(vs), np.concatenate(fs), np.concatenate(ls)


def make_field_scene(name: str) -> SyntheticScene:
    """Build ``courtyard`` or ``pipes`` (see the module docstring)."""
    if name == "courtyard":
        v, f, lab = _courtyard()
    elif name == "pipes":
        v, f, lab = _pipes()
    else:
        raise SynthError(f"Unknown field scene {name!r}; expected one of "
                         f"{', '.join(FIELD_SCENES)}.")
    topo = mesh_topology(v, f)
    if topo["n_bad_edges"] or topo["volume"] <= 0:  # pragma: no cover - construction bug
        raise SynthError(f"Scene '{name}' is not watertight and outward ({topo}).")
    return SyntheticScene(name=name, vertices=np.ascontiguousarray(v, dtype=np.float64),
                          faces=np.ascontiguousarray(f, dtype=np.int64),
                          face_labels=np.asarray(lab, dtype=np.int64), params={})


def scan_field_scene(name: str, *, density: float = 1.0, seed: int = 0):
    """Scan a field scene: the courtyard walked with a two-scanner MMS at 1.8 m
    (density 1: about the street's pulse rate), the pipes from three stations
    2-4 m away at 0.1 deg (about 5 mm spacing at 3 m; density scales the count).

    Returns
    -------
    (Scan, SyntheticScene)
    """
    scene = make_field_scene(name)
    root = math.sqrt(density)
    if name == "courtyard":
        scan = simulate_mms(scene, length=30.0, start_x=0.0, lane_y=0.0, mount_height=1.8,
                            speed=1.5, line_rate=25.0 * root,
                            points_per_line=int(round(1800 * root)), min_range=0.5, seed=seed)
    else:
        stations = np.array([[0.3, -3.0, 1.4], [-2.4, -1.6, 1.1], [2.6, -2.2, 1.6]])
        scan = simulate_static(scene, stations, angular_step_deg=0.1 / root,
                               range_noise=0.002, seed=seed)
    return scan, scene
