"""Random scenes for fitting the field's variance model, apart from the benchmark's.

The benchmark (``scripts/bench_accuracy.py``) scores the field on fixed layouts
(``street``, ``street2``, ``sphere``, ``courtyard``, ``pipes`` and the real bunny).
Coefficients fitted on some of those scenes are tuned to them; the scenes here are
drawn at random from a seed so that a fit made on them leaves every benchmark scene
held out (issue 15, docs/field.md "Session 7").

``yard``     a walked or driven mobile-mapping scene: a ground slab, rows of buildings
             of random fronts, depths and heights on both sides of the lane (some with
             a passage carved through), random thin walls, square pillars and low
             boxes (cars, benches); scanned by :func:`~.scanner.simulate_mms`.
``objects``  a terrestrial scene at a random scale: a floor slab with random spheres,
             horizontal and vertical cylinders and turned boxes that do not touch;
             scanned from three stations 2-4 scene units away by
             :func:`~.scanner.simulate_static`.

Every scene is a union of closed, outward-oriented meshes that do not intersect
(checked with :func:`~.scenes.mesh_topology`), so ``scene.sdf`` is exact.

>>> scene = make_training_scene("objects", seed=3)
>>> scene.name
'train_objects_3'
"""

from __future__ import annotations

import math

import numpy as np

from .field_scenes import _cylinder, _join_parts
from .scanner import simulate_mms, simulate_static
from .scenes import (FACADE, GROUND, OBJECT, POLE, SynthError, SyntheticScene, _box_mesh,
                     _CellSolid, _compact, _icosphere, mesh_topology)

__all__ = ["TRAINING_KINDS", "make_training_scene", "scan_training_scene"]

TRAINING_KINDS = ("yard", "objects")


def _yard(rng):
    s = _CellSolid()
    s.add((-4.0, -14.0, -1.0), (34.0, 14.0, 0.0), GROUND)
    for side in (+1, -1):
        x = -4.0
        while x < 34.0:
            w = float(rng.uniform(4.0, 12.0))
            x1 = min(x + w, 34.0)
            front = float(rng.uniform(3.0, 8.0))
            depth = float(rng.uniform(2.0, 5.0))
            height = float(rng.uniform(2.5, 14.0))
            lo = (x, front if side > 0 else -front - depth, 0.0)
            hi = (x1, front + depth if side > 0 else -front, height)
            s.add(lo, hi, FACADE)
            if x1 - x > 5.0 and rng.random() < 0.4:  # a passage through the building
                px = float(rng.uniform(x + 1.0, x1 - 3.5))
                s.carve((px, lo[1], 0.0), (px + float(rng.uniform(1.0, 2.5)), hi[1],
                                           min(3.0, 0.8 * height)), 6)
            x = x1
    # random thin walls, pillars and low boxes in the lane's sides (|y| 1.5-2.8 m)
    for _ in range(int(rng.integers(2, 6))):
        kind = rng.integers(0, 3)
        x0 = float(rng.uniform(-2.0, 30.0))
        y0 = float(rng.uniform(1.5, 2.6)) * (1 if rng.random() < 0.5 else -1)
        if kind == 0:  # thin wall along x
            t = float(rng.uniform(0.1, 0.3))
            s.add((x0, y0, 0.0), (x0 + float(rng.uniform(1.0, 6.0)), y0 + t,
                                  float(rng.uniform(0.8, 3.0))), OBJECT)
        elif kind == 1:  # square pillar
            a = float(rng.uniform(0.15, 0.3))
            s.add((x0 - a, y0 - a, 0.0), (x0 + a, y0 + a, float(rng.uniform(1.5, 4.0))), POLE)
        else:  # low box (a car, a bench)
            y1 = y0 + float(rng.uniform(0.4, 1.0)) * np.sign(y0)
            s.add((x0, min(y0, y1), 0.0), (x0 + float(rng.uniform(1.0, 4.5)), max(y0, y1),
                                           float(rng.uniform(0.4, 1.6))), OBJECT)
    grid, quads, qlab, _, _ = s.mesh()
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    v, f = _compact(grid, faces)
    return v, f, np.concatenate([qlab, qlab])


def _objects(rng):
    parts = [(_box_mesh((0.0, 0.0, -0.05), (1.6, 1.2, 0.05)), GROUND)]
    placed = []  # (centre, bounding radius)
    n_objects = int(rng.integers(4, 8))
    for _ in range(200):
        if len(placed) >= n_objects:
            break
        kind = int(rng.integers(0, 4))
        c = np.array([rng.uniform(-1.2, 1.2), rng.uniform(-0.8, 0.9), 0.0])
        if kind == 0:  # sphere
            r = float(rng.uniform(0.05, 0.45))
            c[2] = r + float(rng.uniform(0.02, 0.4))
            bound = r
            mesh = _icosphere(r, 4, c)
        elif kind == 1:  # horizontal cylinder along a random direction in the xy plane
            r = float(rng.uniform(0.02, 0.12))
            L = float(rng.uniform(0.6, 1.8))
            a = rng.uniform(0, math.pi)
            ax = np.array([math.cos(a), math.sin(a), 0.0])
            c[2] = r + float(rng.uniform(0.05, 0.6))
            bound = math.hypot(r, L / 2)
            mesh = _cylinder(c - 0.5 * L * ax, ax, r, L, 64)
        elif kind == 2:  # vertical cylinder
            r = float(rng.uniform(0.03, 0.35))
            L = float(rng.uniform(0.3, 1.2))
            c[2] = 0.02 + L / 2
            bound = math.hypot(r, L / 2)
            mesh = _cylinder(c - [0.0, 0.0, L / 2], (0, 0, 1), r, L, 96)
        else:  # box turned about z
            h = rng.uniform([0.05, 0.05, 0.05], [0.35, 0.35, 0.4])
            c[2] = h[2] + float(rng.uniform(0.02, 0.3))
            bound = float(np.linalg.norm(h))
            mesh = _box_mesh(c, h, float(rng.uniform(0, 90)))
        if any(np.linalg.norm(c - pc) < bound + pb + 0.03 for pc, pb in placed):
            continue
        placed.append((c, bound))
        parts.append((mesh, OBJECT))
    return _join_parts(parts)


def make_training_scene(kind: str, seed: int) -> SyntheticScene:
    """A random ``yard`` or ``objects`` scene (module docstring) drawn from ``seed``."""
    if kind not in TRAINING_KINDS:
        raise SynthError(f"Unknown training scene kind {kind!r}; expected one of "
                         f"{', '.join(TRAINING_KINDS)}.")
    rng = np.random.default_rng([7919, int(seed), TRAINING_KINDS.index(kind)])
    for _ in range(50):  # random boxes may meet along an edge only: draw again
        v, f, lab = _yard(rng) if kind == "yard" else _objects(rng)
        topo = mesh_topology(v, f)
        if topo["n_bad_edges"] == 0 and topo["volume"] > 0:
            return SyntheticScene(name=f"train_{kind}_{seed}",
                                  vertices=np.ascontiguousarray(v, dtype=np.float64),
                                  faces=np.ascontiguousarray(f, dtype=np.int64),
                                  face_labels=np.asarray(lab, dtype=np.int64),
                                  params=dict(kind=kind, seed=int(seed)))
    raise SynthError(f"No closed {kind} layout in 50 draws from seed {seed}; try another seed.")


def scan_training_scene(kind: str, seed: int, *, density: float = 0.3,
                        range_noise: float | None = None):
    """Scan a training scene with a random scanner set-up drawn from ``seed``.

    ``yard``: the two-scanner mobile mapping system driven or walked along the lane
    (speed 1.5-5 m/s, mount 1.8-2.3 m, range noise 5-12 mm); ``objects``: three
    stations 2-4 m away at 0.1 deg / sqrt(density), range noise 2-8 mm; the scene
    and its scan are then scaled by a random factor 0.2-1.5 (the noise with it).
    ``range_noise`` (m, before that scaling) replaces the random draw, every other
    draw unchanged, so that one layout can be scanned at several noise levels (with
    ``density``: several spacings; docs/field.md, "Session 8").

    Returns
    -------
    (Scan, SyntheticScene, scale)
        ``scale``: the scene's length unit (1 for yards), for query bands and bins.
    """
    scene = make_training_scene(kind, seed)
    rng = np.random.default_rng([104729, int(seed), TRAINING_KINDS.index(kind)])
    root = math.sqrt(density)
    if kind == "yard":
        speed = float(rng.uniform(1.5, 5.0))
        scan = simulate_mms(scene, length=30.0, start_x=0.0,
                            lane_y=float(rng.uniform(-0.8, 0.8)),
                            mount_height=float(rng.uniform(1.8, 2.3)), speed=speed,
                            line_rate=(25.0 if speed < 3 else 75.0) * root,
                            points_per_line=int(round(1800 * root)), min_range=0.5,
                            range_noise=_noise(rng.uniform(0.005, 0.012), range_noise),
                            seed=int(seed))
        return scan, scene, 1.0
    ang = rng.uniform(0, 2 * math.pi) + np.array([0.0, 2.1, 4.2]) + rng.uniform(-0.4, 0.4, 3)
    dist = rng.uniform(2.0, 4.0, 3)
    st = np.stack([dist * np.cos(ang), dist * np.sin(ang), rng.uniform(0.8, 1.8, 3)], axis=1)
    scan = simulate_static(scene, st, angular_step_deg=0.1 / root,
                           range_noise=_noise(rng.uniform(0.002, 0.008), range_noise),
                           seed=int(seed))
    k = float(np.exp(rng.uniform(math.log(0.2), math.log(1.5))))
    scene = SyntheticScene(name=scene.name, vertices=scene.vertices * k, faces=scene.faces,
                           face_labels=scene.face_labels, params={**scene.params, "scale": k})
    scan = type(scan)(points=scan.points * k, origins=scan.origins * k, labels=scan.labels,
                      source=scan.source + f", scaled x{k:.3f}")
    return scan, scene, k


def _noise(drawn, given):
    """The range noise: ``given`` when not None (checked positive), else the draw."""
    if given is None:
        return float(drawn)
    if not (given > 0 and math.isfinite(given)):
        raise SynthError(f"Expected a positive finite range noise, found {given!r}.")
    return float(given)
