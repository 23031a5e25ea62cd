"""Simulated LiDAR scanners over the synthetic scenes (Open3D ray casting).

Open3D's ``RaycastingScene`` (Embree) works in float32. Each hit is therefore
re-intersected in float64 with the plane of the triangle Open3D reports, so a
noise-free hit lies on the mesh to about 1e-12 m instead of the ~1e-6 relative
error of a float32 ray parameter. Range noise is then added *along the ray*:
``hit = origin + (t + eps) * dir`` with ``eps ~ N(0, range_noise^2)``, and a
random fraction ``dropout`` of the returns is removed (independent Bernoulli).

Mobile mapping (:func:`simulate_mms`): a vehicle drives along +x at constant
speed carrying two rotating-mirror profile scanners (as on a Riegl VMX): each
mirror sweeps a full circle in a plane that contains the vertical and is
turned by +tilt_deg / -tilt_deg about the vertical from the cross-track
plane, so the two scan lines cross in an X seen from above and each facade is
seen both looking forward and looking back. Every return has its own origin:
the scanner's position at its firing time.

Terrestrial (:func:`simulate_static`): scanner stations fire a regular grid of
directions towards the object (or a full panorama when the station stands
inside the object's bounding sphere); the origin is the station.
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np

from ..types import Scan
from .scenes import SynthError, SyntheticScene, make_scene

__all__ = ["simulate_mms", "simulate_static", "scan_scene", "cast_rays"]

#: Largest number of rays handed to Open3D at once (bounds the float32 ray buffer).
_CHUNK = 1 << 20


def _raycaster(scene: SyntheticScene):
    import open3d as o3d

    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor(scene.vertices.astype(np.float32)),
                     o3d.core.Tensor(scene.faces.astype(np.uint32)))
    return rc


def cast_rays(scene: SyntheticScene, origins, directions, *, raycaster=None):
    """First hit of each ray on the scene mesh, refined in float64.

    Parameters
    ----------
    scene : SyntheticScene
    origins : (R, 3) float64
    directions : (R, 3) float64, unit length

    Returns
    -------
    t : (R,) float64
        Distance along the ray to the hit (inf where the ray misses).
    face : (R,) int64
        Index of the hit triangle (-1 where the ray misses).
    """
    import open3d as o3d

    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    rc = raycaster if raycaster is not None else _raycaster(scene)
    t = np.full(len(o), np.inf)
    face = np.full(len(o), -1, dtype=np.int64)
    v, f = scene.vertices, scene.faces
    for s in range(0, len(o), _CHUNK):
        rays = np.concatenate([o[s:s + _CHUNK], d[s:s + _CHUNK]], axis=1).astype(np.float32)
        ans = rc.cast_rays(o3d.core.Tensor(rays))
        t32 = ans["t_hit"].numpy()
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        hit = np.isfinite(t32)
        idx = np.nonzero(hit)[0]
        tri = f[prim[idx]]
        a = v[tri[:, 0]]
        n = np.cross(v[tri[:, 1]] - a, v[tri[:, 2]] - a)
        oo, dd = o[s + idx], d[s + idx]
        # float64 ray-plane intersection with the triangle Open3D found
        t64 = np.einsum("ij,ij->i", n, a - oo) / np.einsum("ij,ij->i", n, dd)
        # keep Open3D's value if the plane is grazed so badly the refinement is worse
        bad = ~np.isfinite(t64) | (np.abs(t64 - t32[idx]) > 1e-3 + 1e-4 * t32[idx])
        t64[bad] = t32[idx][bad]
        t[s + idx] = t64
        face[s + idx] = prim[idx]
    return t, face


def _finish(scene, origins, dirs, t, face, *, range_noise, dropout, min_range, max_range, rng,
            source):
    """Noise, dropout and range gating; returns the Scan."""
    keep = (face >= 0) & (t >= min_range) & (t <= max_range)
    keep &= rng.random(len(t)) >= dropout
    o, d, t, face = origins[keep], dirs[keep], t[keep], face[keep]
    eps = rng.normal(0.0, range_noise, len(t)) if range_noise > 0 else np.zeros(len(t))
    pts = o + (t + eps)[:, None] * d
    return Scan(points=pts, origins=o, labels=scene.face_labels[face], source=source)


def _check_common(range_noise, dropout, max_range, min_range):
    if not (np.isfinite(range_noise) and range_noise >= 0):
        raise SynthError(f"Expected range_noise >= 0 m, found {range_noise!r}; "
                         "0.008 is a typical MMS figure.")
    if not 0.0 <= dropout < 1.0:
        raise SynthError(f"Expected dropout in [0, 1), found {dropout!r}; "
                         "it is the fraction of returns removed.")
    if not 0.0 <= min_range < max_range:
        raise SynthError(f"Expected 0 <= min_range < max_range, found {min_range!r} and "
                         f"{max_range!r}; widen the range gate.")


def simulate_mms(scene: SyntheticScene, *, length: Optional[float] = None,
                 start_x: float = 0.0, lane_y: float = 1.5, speed: float = 5.0,
                 line_rate: float = 75.0, points_per_line: int = 1800,
                 mount_height: float = 2.3, mount_offset: float = 0.35,
                 tilt_deg: float = 45.0, range_noise: float = 0.008, dropout: float = 0.05,
                 min_range: float = 1.0, max_range: float = 120.0, seed: int = 0) -> Scan:
    """Simulate a mobile mapping system driving along the street axis (+x).

    Parameters
    ----------
    scene : SyntheticScene
    length : float, optional
        Driven distance in metres (default: the street's ``length`` parameter,
        or the x-extent of the scene).
    start_x, lane_y : float
        Start of the drive on the x axis and the lateral position (m) of the vehicle.
    speed : float
        m/s (5 m/s = 18 km/h, a usual urban survey speed).
    line_rate : float
        Scan lines per second per scanner (Hz).
    points_per_line : int
        Pulses per full mirror revolution (angular step 360 / points_per_line deg).
    mount_height : float
        Height of both scanner centres above the road (m).
    mount_offset : float
        Scanners sit at +-mount_offset m across the vehicle axis.
    tilt_deg : float
        Each scan plane is turned by +tilt_deg (left scanner) or -tilt_deg
        (right scanner) about the vertical from the cross-track plane.
    range_noise : float
        Standard deviation of the Gaussian range noise along the ray (m).
    dropout : float
        Fraction of returns removed at random.
    min_range, max_range : float
        Range gate in metres.
    seed : int
        Seed of the noise and dropout generator.

    Returns
    -------
    Scan
        ``points`` (N, 3), ``origins`` (N, 3) (scanner position at firing time),
        ``labels`` (N,) object class of the hit face.
    """
    _check_common(range_noise, dropout, max_range, min_range)
    if length is None:
        length = float(scene.params.get("length", scene.bounds[1, 0] - scene.bounds[0, 0]))
    for key, val in (("length", length), ("speed", speed), ("line_rate", line_rate),
                     ("points_per_line", points_per_line)):
        if not (np.isfinite(val) and val > 0):
            raise SynthError(f"Expected simulate_mms parameter '{key}' > 0, found {val!r}; "
                             "pass a positive value.")
    rng = np.random.default_rng(seed)
    # the second scanner fires half a line later: keep every pulse inside the drive
    n_lines = max(int(math.floor(length / speed * line_rate - 0.5)), 1)
    ppl = int(points_per_line)
    k = np.arange(ppl)
    phi = 2.0 * math.pi * k / ppl
    origins, dirs = [], []
    for side, phase in ((+1, 0.0), (-1, 0.5)):
        yaw = math.radians(side * tilt_deg)
        # horizontal unit vector of the scan plane (cross-track turned by yaw)
        hx, hy = -math.sin(yaw), math.cos(yaw)
        # time of every pulse: lines at line_rate, pulses evenly over the revolution;
        # the second scanner is half a line out of phase
        tl = (np.arange(n_lines)[:, None] + phase + k[None, :] / ppl) / line_rate
        dx = (np.cos(phi) * hx)[None, :].repeat(n_lines, 0)
        dy = (np.cos(phi) * hy)[None, :].repeat(n_lines, 0)
        dz = np.sin(phi)[None, :].repeat(n_lines, 0)
        d = np.stack([dx, dy, dz], axis=-1).reshape(-1, 3)
        o = np.empty_like(d)
        o[:, 0] = (start_x + speed * tl).reshape(-1)
        o[:, 1] = lane_y + side * mount_offset
        o[:, 2] = mount_height
        origins.append(o)
        dirs.append(d)
    origins = np.concatenate(origins)
    dirs = np.concatenate(dirs)
    t, face = cast_rays(scene, origins, dirs)
    return _finish(scene, origins, dirs, t, face, range_noise=range_noise, dropout=dropout,
                   min_range=min_range, max_range=max_range, rng=rng,
                   source=f"synthetic MMS scan of '{scene.name}' (seed {seed})")


def simulate_static(scene: SyntheticScene, stations, *, angular_step_deg: float = 0.1,
                    range_noise: float = 0.008, dropout: float = 0.05, min_range: float = 0.3,
                    max_range: float = 120.0, seed: int = 0) -> Scan:
    """Simulate terrestrial scanner stations around an object.

    Parameters
    ----------
    scene : SyntheticScene
    stations : (S, 3) float64
        Scanner positions; each must lie in free space (sdf > 0).
    angular_step_deg : float
        Angular spacing of the pulses (deg). Outside the scene's bounding sphere
        the station fires only into the cone that covers it; inside, a full
        panorama (azimuth 0-360, elevation -90 to +90).
    range_noise, dropout, min_range, max_range, seed
        As in :func:`simulate_mms`.

    Returns
    -------
    Scan
        Origins are the station of each point.
    """
    _check_common(range_noise, dropout, max_range, min_range)
    st = np.atleast_2d(np.asarray(stations, dtype=np.float64))
    if st.ndim != 2 or st.shape[1] != 3 or len(st) == 0:
        raise SynthError(f"Expected stations of shape (S, 3) with S >= 1, found {st.shape}; "
                         "pass one xyz row per station.")
    if not (np.isfinite(angular_step_deg) and 0.005 <= angular_step_deg <= 10):
        raise SynthError(f"Expected angular_step_deg in [0.005, 10], found "
                         f"{angular_step_deg!r}; 0.1 deg is a typical setting.")
    inside = scene.sdf(st) <= 0
    if np.any(inside):
        raise SynthError(f"Expected every station in free space, found station(s) "
                         f"{np.nonzero(inside)[0].tolist()} inside the '{scene.name}' solid; "
                         "move them outside the object.")
    rng = np.random.default_rng(seed)
    lo, hi = scene.bounds
    center = 0.5 * (lo + hi)
    radius = 0.5 * float(np.linalg.norm(hi - lo))
    step = math.radians(angular_step_deg)
    origins, dirs = [], []
    for s in st:
        to_c = center - s
        dist = float(np.linalg.norm(to_c))
        if dist > radius * 1.0001:
            # regular grid on the tangent plane covering the bounding sphere's cone
            w = to_c / dist
            u = np.cross(w, [0.0, 0.0, 1.0])
            if np.linalg.norm(u) < 1e-6:
                u = np.cross(w, [1.0, 0.0, 0.0])
            u /= np.linalg.norm(u)
            v = np.cross(w, u)
            half = math.tan(math.asin(radius / dist))
            g = np.arange(-half, half + 1e-12, math.tan(step))
            a, b = np.meshgrid(g, g, indexing="ij")
            a, b = a.reshape(-1), b.reshape(-1)
            keep = a * a + b * b <= half * half
            d = w[None] + a[keep, None] * u[None] + b[keep, None] * v[None]
        else:
            az = np.arange(0.0, 2 * math.pi, step)
            el = np.arange(-math.pi / 2 + step / 2, math.pi / 2, step)
            A, E = np.meshgrid(az, el, indexing="ij")
            d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)],
                         axis=-1).reshape(-1, 3)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        origins.append(np.broadcast_to(s, d.shape))
        dirs.append(d)
    origins = np.ascontiguousarray(np.concatenate(origins))
    dirs = np.concatenate(dirs)
    t, face = cast_rays(scene, origins, dirs)
    return _finish(scene, origins, dirs, t, face, range_noise=range_noise, dropout=dropout,
                   min_range=min_range, max_range=max_range, rng=rng,
                   source=f"synthetic static scan of '{scene.name}' (seed {seed})")


def _default_stations(scene: SyntheticScene) -> np.ndarray:
    if scene.name == "plane":
        return np.array([[0.0, 0.0, 1.6], [6.0, 4.0, 1.6], [-5.0, -6.0, 1.6]])
    lo, hi = scene.bounds
    c = 0.5 * (lo + hi)
    r = 0.5 * float(np.linalg.norm(hi - lo))
    ang = np.radians([20.0, 110.0, 200.0, 290.0])
    z = np.array([0.6, -0.3, 0.9, 0.1]) * r
    return c + np.stack([2.5 * r * np.cos(ang), 2.5 * r * np.sin(ang), z], axis=1)


def scan_scene(name: str, *, density: float = 1.0, seed: int = 0, scene_params=None,
               **kw) -> tuple:
    """Make a scene and scan it with a scanner that suits it.

    Streets get the mobile mapping system of :func:`simulate_mms` (at
    ``density=1``: 75 lines/s and 1800 pulses per line per scanner at 5 m/s,
    i.e. 6.7 cm between lines and 0.2 deg between pulses, about 1.3 million
    points on the 36 m street); the plane, sphere and box get terrestrial
    stations (:func:`simulate_static`, angular step 0.1 deg / sqrt(density),
    0.4 deg for the plane whose stations see a full panorama).

    Parameters
    ----------
    name : str
        One of :data:`~gmmgp_app.synth.SCENES`.
    density : float
        Multiplies the number of points (both angular and along-track spacing
        shrink by sqrt(density)). 0.05 gives about 65k points on the street.
    seed : int
    scene_params : dict, optional
        Passed to :func:`~gmmgp_app.synth.make_scene`.
    **kw
        Passed to the scanner (override the defaults above).

    Returns
    -------
    (Scan, SyntheticScene)
    """
    if not (np.isfinite(density) and 1e-4 <= density <= 100):
        raise SynthError(f"Expected density in [1e-4, 100], found {density!r}; "
                         "1 is the default, 0.05 a small test scan.")
    scene = make_scene(name, **(scene_params or {}))
    root = math.sqrt(density)
    if name.startswith("street"):
        opts = dict(line_rate=75.0 * root, points_per_line=int(round(1800 * root)))
        opts.update(kw)
        scan = simulate_mms(scene, seed=seed, **opts)
    else:
        step = (0.4 if name == "plane" else 0.1) / root
        opts = dict(angular_step_deg=step)
        opts.update(kw)
        stations = opts.pop("stations", _default_stations(scene))
        scan = simulate_static(scene, stations, seed=seed, **opts)
    return scan, scene
