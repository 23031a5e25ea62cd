"""The paper's evaluation: RMSE and predictive log-likelihood of the SDF and EDF,
binned by the query's distance to the training points (paper Sec. V-D).

Ground truth comes from a reference mesh (exact distance; sign from the closed
mesh's pseudo-normals, or from the closest face's normal when the mesh is open),
a dense reference cloud (nearest-neighbour distance, as the paper does), or an
analytic SDF (synthetic scenes).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import numpy as np
from scipy.spatial import cKDTree

__all__ = [
    "DEFAULT_BINS", "Reference", "sample_queries", "gaussian_loglik",
    "folded_normal_loglik", "binned_metrics", "evaluate_field",
]

#: Distance-to-training-points bins (m) of the paper's figures.
DEFAULT_BINS = (0.0, 0.05, 0.1, 0.2, 0.3, 0.5)
_LOG_2PI = float(np.log(2 * np.pi))


def gaussian_loglik(y, mean, var) -> np.ndarray:
    """log N(y; mean, var) per query (the SDF's predictive log-likelihood)."""
    var = np.maximum(np.asarray(var, dtype=np.float64), 1e-300)
    return -0.5 * (_LOG_2PI + np.log(var) + (np.asarray(y) - mean) ** 2 / var)


def folded_normal_loglik(a, mean, var) -> np.ndarray:
    """log p(|d| = a) when d ~ N(mean, var): the EDF's predictive log-likelihood.

    p(a) = N(a; m, v) + N(-a; m, v) for a >= 0 (a folded normal).
    """
    a = np.abs(np.asarray(a, dtype=np.float64))
    return np.logaddexp(gaussian_loglik(a, mean, var), gaussian_loglik(-a, mean, var))


@dataclass
class Reference:
    """Ground-truth signed distance ``sdf(xyz) -> (K,)`` and its provenance."""

    sdf: Callable
    kind: str
    description: str = ""
    mesh: Optional[tuple] = None  # (vertices, faces) when from a mesh

    @classmethod
    def from_sdf(cls, fn: Callable, description: str = "analytic") -> "Reference":
        return cls(fn, "analytic", description)

    @classmethod
    def from_mesh(cls, vertices, faces, description: str = "mesh") -> "Reference":
        """Exact distance to a mesh; exact sign when it is closed, else the closest
        face's normal (reliable near the surface, not inside holes)."""
        from .synth.meshsdf import MeshDistance, MeshError

        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces, dtype=np.int64)
        try:
            return cls(MeshDistance(v, f), "mesh (closed, exact sign)", description, (v, f))
        except MeshError:
            return cls(_OpenMeshDistance(v, f), "mesh (open, sign from closest face)",
                       description, (v, f))

    @classmethod
    def from_points(cls, points, normals=None, description: str = "points") -> "Reference":
        """Nearest-neighbour distance to a dense cloud (the paper's ground truth);
        signed by the nearest point's normal when normals are given."""
        points = np.asarray(points, dtype=np.float64)
        tree = cKDTree(points)

        def sdf(xyz):
            d, i = tree.query(np.asarray(xyz, dtype=np.float64), k=1)
            if normals is None:
                return d
            s = np.sign(np.einsum("ij,ij->i", xyz - points[i], normals[i]))
            return d * np.where(s == 0, 1.0, s)

        kind = "points (nearest neighbour, signed by normals)" if normals is not None else \
            "points (nearest neighbour, unsigned)"
        return cls(sdf, kind, description)

    @classmethod
    def load(cls, path) -> "Reference":
        """A mesh file (PLY/OBJ/STL/OFF with triangles) or a point cloud file."""
        import open3d as o3d

        mesh = o3d.io.read_triangle_mesh(str(path))
        if len(mesh.triangles) > 0:
            mesh.remove_duplicated_vertices()
            mesh.remove_degenerate_triangles()
            return cls.from_mesh(np.asarray(mesh.vertices), np.asarray(mesh.triangles),
                                 str(path))
        from .datasets import read_scan

        scan = read_scan(path)
        return cls.from_points(scan.points + scan.offset, description=str(path))


class _OpenMeshDistance:
    """Unsigned distance to an open mesh, signed by the closest face's normal."""

    def __init__(self, v, f):
        import open3d as o3d

        self.v, self.f = v, f
        n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        self.fn = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        self.centre = v.mean(0)
        self.scene = o3d.t.geometry.RaycastingScene()
        # Open3D ray casting is float32: work relative to the mesh centre.
        self.scene.add_triangles((v - self.centre).astype(np.float32), f.astype(np.uint32))

    def __call__(self, xyz):
        import open3d as o3d

        q = np.asarray(xyz, dtype=np.float64) - self.centre
        ans = self.scene.compute_closest_points(o3d.core.Tensor(q.astype(np.float32)))
        tri = ans["primitive_ids"].numpy().astype(np.int64)
        # Recompute the closest point on that triangle in float64.
        c = closest_point_on_triangles(q + self.centre, self.v[self.f[tri]])
        diff = q + self.centre - c
        d = np.linalg.norm(diff, axis=1)
        s = np.sign(np.einsum("ij,ij->i", diff, self.fn[tri]))
        return d * np.where(s == 0, 1.0, s)


def closest_point_on_triangles(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Closest point of each triangle ``tri[k]`` (3, 3) to ``p[k]`` (vectorised).

    Barycentric region tests on the triangle's Voronoi regions (vertex, edge,
    face), evaluated for every query at once.
    """
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ab, ac, ap = b - a, c - a, p - a
    dot = lambda u, v: np.einsum("ij,ij->i", u, v)  # noqa: E731
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp, cp = p - b, p - c
    d3, d4 = dot(ab, bp), dot(ac, bp)
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = 1.0 / (va + vb + vc)
        v = vb * denom
        w = vc * denom
        out = a + ab * v[:, None] + ac * w[:, None]                      # face
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    # Edges and vertices, from the least to the most specific region.
    m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    out[m] = a[m] + t_ab[m, None] * ab[m]
    m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    out[m] = a[m] + t_ac[m, None] * ac[m]
    m = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
    out[m] = b[m] + t_bc[m, None] * (c[m] - b[m])
    m = (d1 <= 0) & (d2 <= 0)
    out[m] = a[m]
    m = (d3 >= 0) & (d4 <= d3)
    out[m] = b[m]
    m = (d6 >= 0) & (d5 <= d6)
    out[m] = c[m]
    return out


def sample_queries(points: np.ndarray, normals: np.ndarray, n: int, *,
                   max_distance: float = 0.5, tangential: float = 0.05,
                   rng: Optional[np.random.Generator] = None) -> np.ndarray:
    """Query points near observed surfaces: random hit points moved along their normal
    by a uniform offset in [-max_distance, max_distance] plus a small tangential jitter.

    Returns
    -------
    (n, 3) float64
    """
    rng = np.random.default_rng(0) if rng is None else rng
    i = rng.integers(0, len(points), n)
    along = rng.uniform(-max_distance, max_distance, n)
    jitter = rng.normal(scale=tangential, size=(n, 3))
    jitter -= np.einsum("ij,ij->i", jitter, normals[i])[:, None] * normals[i]
    return points[i] + along[:, None] * normals[i] + jitter


def binned_metrics(mean, var, truth, dist, bins: Sequence[float] = DEFAULT_BINS,
                   edf_mean=None, edf_var=None) -> dict:
    """RMSE and mean log-likelihood of the SDF and the EDF per distance bin.

    Parameters
    ----------
    mean, var : (K,) predicted signed distance and its variance
    truth : (K,) true signed distance
    dist : (K,) distance of each query to the nearest training point
    bins : bin edges in metres
    edf_mean, edf_var : (K,), optional
        A method that predicts the unsigned distance directly (Log-GPIS) passes it
        here; otherwise the EDF is |d| with a folded-normal likelihood.

    Returns
    -------
    dict with ``bins`` (list of [lo, hi]) and per-bin lists ``n``, ``rmse_sdf``,
    ``rmse_edf``, ``ll_sdf``, ``ll_edf`` (NaN where a bin is empty), plus the
    same over all queries under ``all``.
    """
    mean, var, truth, dist = (np.asarray(a, dtype=np.float64) for a in (mean, var, truth, dist))
    edf_pred = np.abs(mean) if edf_mean is None else np.asarray(edf_mean)
    ll_sdf = gaussian_loglik(truth, mean, var)
    ll_edf = (folded_normal_loglik(truth, mean, var) if edf_mean is None
              else gaussian_loglik(np.abs(truth), edf_mean, edf_var))
    err_sdf = (mean - truth) ** 2 if edf_mean is None else np.full(len(mean), np.nan)
    err_edf = (edf_pred - np.abs(truth)) ** 2
    if edf_mean is not None:
        ll_sdf = np.full(len(mean), np.nan)
    out = {"bins": [[float(a), float(b)] for a, b in zip(bins[:-1], bins[1:])],
           "n": [], "rmse_sdf": [], "rmse_edf": [], "ll_sdf": [], "ll_edf": []}
    for lo, hi in out["bins"]:
        sel = (dist >= lo) & (dist < hi)
        _append(out, sel, err_sdf, err_edf, ll_sdf, ll_edf)
    allsel = dist < bins[-1]
    tot = {"n": [], "rmse_sdf": [], "rmse_edf": [], "ll_sdf": [], "ll_edf": []}
    _append(tot, allsel, err_sdf, err_edf, ll_sdf, ll_edf)
    out["all"] = {k: v[0] for k, v in tot.items()}
    return out


def _append(out, sel, err_sdf, err_edf, ll_sdf, ll_edf):
    n = int(sel.sum())
    out["n"].append(n)
    nan = float("nan")
    out["rmse_sdf"].append(float(np.sqrt(np.mean(err_sdf[sel]))) if n else nan)
    out["rmse_edf"].append(float(np.sqrt(np.mean(err_edf[sel]))) if n else nan)
    out["ll_sdf"].append(float(np.mean(ll_sdf[sel])) if n else nan)
    out["ll_edf"].append(float(np.mean(ll_edf[sel])) if n else nan)


def evaluate_field(predict: Callable, reference: Reference, queries: np.ndarray,
                   train_points: np.ndarray, bins: Sequence[float] = DEFAULT_BINS) -> dict:
    """Predict at ``queries``, compare with the reference, bin by distance to training."""
    dist = cKDTree(train_points).query(queries, k=1)[0]
    truth = reference.sdf(queries)
    out = predict(queries)
    if isinstance(out, dict):  # a method predicting the EDF directly
        return binned_metrics(out["mean"], out["var"], truth, dist, bins,
                              edf_mean=out["edf_mean"], edf_var=out["edf_var"])
    mean, var = out[:2]
    return binned_metrics(mean, var, truth, dist, bins)
