"""The paper's evaluation: RMSE and predictive log-likelihood of the SDF and EDF,
binned by the query's distance to the training points (paper Sec. V-D), plus
Chamfer and Hausdorff distances of extracted surfaces to a reference.

Ground truth comes from a reference mesh (exact distance; sign from the closed
mesh's pseudo-normals, or from the pseudo-normal of the closest feature when the
mesh is open), a dense reference cloud (nearest-neighbour distance, as the paper
does; signed by the reference normals when it has them) or an analytic SDF.

>>> ref = Reference.from_sdf(lambda x: np.linalg.norm(x, axis=1) - 1.0)
>>> q = np.array([[0.0, 0.0, 1.1]])
>>> round(float(ref.sdf(q)[0]), 3)
0.1
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np
from scipy.spatial import cKDTree

__all__ = [
    "EvaluationError", "DEFAULT_BINS", "Reference", "sample_queries", "gaussian_loglik",
    "folded_normal_loglik", "binned_metrics", "evaluate_field", "closest_point_on_triangles",
    "TriangleDistance", "sample_mesh_surface", "surface_distances",
    "surface_distance_samples", "MESH_SUFFIXES",
    "coverage", "reliability", "plot_reliability", "RELIABILITY_LEVELS",
]

#: Distance-to-training-points bins (m) of the paper's figures.
DEFAULT_BINS = (0.0, 0.05, 0.1, 0.2, 0.3, 0.5)
#: File suffixes read as triangle meshes by :meth:`Reference.load`.
MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off", ".gltf", ".glb")
_LOG_2PI = float(np.log(2 * np.pi))


class EvaluationError(ValueError):
    """Bad input to the evaluation (empty reference, mismatched shapes, ...)."""


# --------------------------------------------------------------------------- likelihoods
def gaussian_loglik(y, mean, var) -> np.ndarray:
    """Predictive log-likelihood of one test point (paper Sec. V-D, eq. LL summand).

    ``log N(y; mean, var) = -1/2 (log 2 pi + log var + (y - mean)^2 / var)``; the
    paper's LL is the mean of this over the test points.

    Parameters
    ----------
    y, mean, var : (K,) array_like
        True distance, predicted mean and predicted variance (> 0; values below
        1e-300 are clipped so a zero variance gives a finite, very low score).

    Returns
    -------
    (K,) float64
    """
    var = np.maximum(np.asarray(var, dtype=np.float64), 1e-300)
    y = np.asarray(y, dtype=np.float64)
    return -0.5 * (_LOG_2PI + np.log(var) + (y - np.asarray(mean, dtype=np.float64)) ** 2 / var)


def folded_normal_loglik(a, mean, var) -> np.ndarray:
    """log p(|d| = a) when d ~ N(mean, var): the EDF's predictive log-likelihood.

    ``p(a) = N(a; m, v) + N(-a; m, v)`` for ``a >= 0`` (a folded normal): a method
    that predicts a signed distance is scored on the EDF by the law of ``|d|``.

    Parameters
    ----------
    a : (K,) array_like
        True unsigned distance (its absolute value is taken).
    mean, var : (K,) array_like

    Returns
    -------
    (K,) float64
    """
    a = np.abs(np.asarray(a, dtype=np.float64))
    return np.logaddexp(gaussian_loglik(a, mean, var), gaussian_loglik(-a, mean, var))


# --------------------------------------------------------------------------- geometry
def closest_point_on_triangles(p: np.ndarray, tri: np.ndarray, return_region: bool = False):
    """Closest point of each triangle ``tri[k]`` (3, 3) to ``p[k]`` (vectorised).

    Barycentric region tests on the triangle's Voronoi regions (vertex, edge,
    face), evaluated for every query at once.

    Parameters
    ----------
    p : (K, 3) float64
    tri : (K, 3, 3) float64
        Vertices a, b, c of the triangle paired with each query.
    return_region : bool
        Also return the feature the closest point lies on: 0 face, 1 edge ab,
        2 edge bc, 3 edge ca, 4 vertex a, 5 vertex b, 6 vertex c.

    Returns
    -------
    (K, 3) float64 closest points[, (K,) int64 regions]
    """
    p = np.asarray(p, dtype=np.float64)
    tri = np.asarray(tri, dtype=np.float64)
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
    region = np.zeros(len(p), dtype=np.int64)
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = 1.0 / (va + vb + vc)
        v = vb * denom
        w = vc * denom
        out = a + ab * v[:, None] + ac * w[:, None]                      # face
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    # Edges and vertices, from the least to the most specific region, so the
    # vertex tests (which imply an edge test's condition) win.
    m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    out[m] = a[m] + t_ab[m, None] * ab[m]
    region[m] = 1
    m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    out[m] = a[m] + t_ac[m, None] * ac[m]
    region[m] = 3
    m = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
    out[m] = b[m] + t_bc[m, None] * (c[m] - b[m])
    region[m] = 2
    m = (d1 <= 0) & (d2 <= 0)
    out[m] = a[m]
    region[m] = 4
    m = (d3 >= 0) & (d4 <= d3)
    out[m] = b[m]
    region[m] = 5
    m = (d6 >= 0) & (d5 <= d6)
    out[m] = c[m]
    region[m] = 6
    return (out, region) if return_region else out


class TriangleDistance:
    """Distance to a triangle mesh that need not be closed, signed by pseudo-normals.

    Open3D's ray-casting scene finds the closest triangle (in float32, relative to
    the mesh centre so that large coordinates keep their precision); the closest
    point on that triangle is then recomputed in float64. The sign is that of
    ``(x - c) . n`` with ``n`` the angle-weighted pseudo-normal of the feature
    (face, edge or vertex) holding the closest point ``c`` (Baerentzen and Aanaes),
    which is exact for a closed mesh; at an open boundary only the faces present
    vote, so the sign is reliable near the surface but not inside holes.

    Parameters
    ----------
    vertices : (V, 3) float64
    faces : (F, 3) int64
    """

    def __init__(self, vertices, faces):
        import open3d as o3d

        from .synth.meshsdf import triangle_arrays

        v, f = triangle_arrays(vertices, faces, EvaluationError)
        self.v, self.f = v, f
        e1, e2 = v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]
        n = np.cross(e1, e2)
        area2 = np.linalg.norm(n, axis=1)
        self.face_normals = n / np.maximum(area2, 1e-300)[:, None]
        self.vertex_normals, self.edge_normal = _open_pseudo_normals(v, f, self.face_normals)
        self.centre = v.mean(0)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles((v - self.centre).astype(np.float32), f.astype(np.uint32))

    def __call__(self, xyz, signed: bool = True) -> np.ndarray:
        """Signed (or unsigned) distance of each (K, 3) query point, (K,) float64."""
        import open3d as o3d

        p = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        if len(p) == 0:
            return np.zeros(0)
        out = np.empty(len(p))
        for s in range(0, len(p), 500_000):
            q = p[s:s + 500_000]
            ans = self.scene.compute_closest_points(
                o3d.core.Tensor((q - self.centre).astype(np.float32)))
            tri = ans["primitive_ids"].numpy().astype(np.int64)
            c, reg = closest_point_on_triangles(q, self.v[self.f[tri]], return_region=True)
            diff = q - c
            d = np.linalg.norm(diff, axis=1)
            if not signed:
                out[s:s + len(q)] = d
                continue
            nrm = self.face_normals[tri].copy()
            on_edge = (reg >= 1) & (reg <= 3)
            if on_edge.any():
                k = reg[on_edge] - 1                     # 0 ab, 1 bc, 2 ca
                fa = self.f[tri[on_edge]]
                i0 = fa[np.arange(len(k)), k]
                i1 = fa[np.arange(len(k)), (k + 1) % 3]
                nrm[on_edge] = self.edge_normal(i0, i1)
            on_vert = reg >= 4
            if on_vert.any():
                vi = self.f[tri[on_vert], reg[on_vert] - 4]
                nrm[on_vert] = self.vertex_normals[vi]
            sgn = np.sign(np.einsum("ij,ij->i", diff, nrm))
            out[s:s + len(q)] = d * np.where(sgn == 0, 1.0, sgn)
        return out


def _open_pseudo_normals(v, f, fn):
    """Angle-weighted vertex normals and an edge-normal lookup for any mesh.

    Returns
    -------
    vertex_normals : (V, 3) float64
    edge_normal : callable(i0 (K,), i1 (K,)) -> (K, 3)
        Sum of the normals of the (one or two) faces sharing edge (i0, i1).
    """
    vn = np.zeros_like(v)
    for k in range(3):
        a, b, c = v[f[:, k]], v[f[:, (k + 1) % 3]], v[f[:, (k + 2) % 3]]
        u, w = b - a, c - a
        cosang = np.einsum("ij,ij->i", u, w) / np.maximum(
            np.linalg.norm(u, axis=1) * np.linalg.norm(w, axis=1), 1e-300)
        ang = np.arccos(np.clip(cosang, -1.0, 1.0))
        np.add.at(vn, f[:, k], ang[:, None] * fn)
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    edges.sort(axis=1)
    nv = np.int64(len(v))
    ekey = edges[:, 0] * nv + edges[:, 1]
    uniq, inv = np.unique(ekey, return_inverse=True)
    en = np.zeros((len(uniq), 3))
    np.add.at(en, inv.reshape(-1), np.concatenate([fn, fn, fn]))

    def edge_normal(i0, i1):
        lo, hi = np.minimum(i0, i1), np.maximum(i0, i1)
        pos = np.searchsorted(uniq, lo * nv + hi)
        return en[np.minimum(pos, len(uniq) - 1)]

    return vn, edge_normal


def sample_mesh_surface(vertices, faces, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` points drawn uniformly (area-weighted) on a triangle mesh, (n, 3)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]),
                                axis=1)
    if len(f) == 0 or area.sum() <= 0:
        raise EvaluationError(f"Expected a mesh with positive area to sample, found "
                              f"{len(f)} faces with total area {area.sum():g} m^2.")
    t = rng.choice(len(f), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    # uniform on a triangle: (1 - sqrt r1) a + sqrt r1 (1 - r2) b + sqrt r1 r2 c
    return ((1 - s)[:, None] * v[f[t, 0]] + (s * (1 - r2))[:, None] * v[f[t, 1]]
            + (s * r2)[:, None] * v[f[t, 2]])


# --------------------------------------------------------------------------- reference
@dataclass
class Reference:
    """Ground-truth distance ``sdf(xyz (K,3)) -> (K,)`` and its provenance.

    Attributes
    ----------
    sdf : callable
        Signed distance (free space > 0), or unsigned when ``signed`` is False.
    kind : str
        How the truth is computed (shown in reports).
    description : str
        Where it came from (a path, "analytic", ...).
    signed : bool
        False for a cloud without normals: only EDF metrics are meaningful.
    mesh : (vertices (V,3), faces (F,3)) or None
    points : (R, 3) or None
        The reference cloud, when the truth is a cloud.
    """

    sdf: Callable
    kind: str
    description: str = ""
    signed: bool = True
    mesh: Optional[tuple] = None
    points: Optional[np.ndarray] = None

    @classmethod
    def from_sdf(cls, fn: Callable, description: str = "analytic") -> "Reference":
        """An exact signed distance function (synthetic scenes)."""
        return cls(fn, "analytic", description)

    @classmethod
    def from_mesh(cls, vertices, faces, description: str = "mesh") -> "Reference":
        """Exact distance to a mesh; exact sign when it is closed (pseudo-normals of
        :class:`~gmmgp_app.synth.MeshDistance`), else the pseudo-normal of the closest
        feature (:class:`TriangleDistance`: reliable near the surface, not in holes)."""
        from .synth.meshsdf import MeshDistance, MeshError

        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces, dtype=np.int64)
        try:
            return cls(MeshDistance(v, f), "mesh (closed, exact sign)", description,
                       mesh=(v, f))
        except MeshError:
            return cls(TriangleDistance(v, f), "mesh (open, sign from closest feature)",
                       description, mesh=(v, f))

    @classmethod
    def from_points(cls, points, normals=None, description: str = "points") -> "Reference":
        """Nearest-neighbour distance to a dense cloud (the paper's ground truth),
        signed by the nearest point's normal when normals are given.

        Parameters
        ----------
        points : (R, 3)
        normals : (R, 3), optional
            Pointing into free space.
        """
        points = np.ascontiguousarray(np.asarray(points, dtype=np.float64))
        if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
            raise EvaluationError(f"Expected reference points with shape (R, 3), R >= 1, "
                                  f"found {points.shape}; the reference cloud is empty.")
        if normals is not None:
            normals = np.asarray(normals, dtype=np.float64)
            if normals.shape != points.shape:
                raise EvaluationError(f"Expected one normal per reference point "
                                      f"{points.shape}, found {normals.shape}.")
        tree = cKDTree(points)

        def sdf(xyz):
            q = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
            d, i = tree.query(q, k=1)
            if normals is None:
                return d
            s = np.sign(np.einsum("ij,ij->i", q - points[i], normals[i]))
            return d * np.where(s == 0, 1.0, s)

        kind = ("points (nearest neighbour, signed by normals)" if normals is not None
                else "points (nearest neighbour, unsigned)")
        return cls(sdf, kind, description, signed=normals is not None, points=points)

    @classmethod
    def load(cls, path, **reader_kwargs) -> "Reference":
        """A mesh file (PLY/OBJ/STL/OFF with triangles) or any scan the readers know.

        A cloud read with sensor origins gets PCA normals oriented towards them, so
        its truth is signed; without origins it is unsigned (EDF only).
        """
        path = Path(path)
        if not path.exists():
            raise EvaluationError(f"Reference '{path}' does not exist; pass a mesh "
                                  "(.ply/.obj/.stl/.off) or a dense point cloud.")
        if path.is_file() and path.suffix.lower() in MESH_SUFFIXES:
            import open3d as o3d

            mesh = o3d.io.read_triangle_mesh(str(path))
            if len(mesh.triangles) > 0:
                mesh.remove_duplicated_vertices()
                mesh.remove_degenerate_triangles()
                mesh.remove_unreferenced_vertices()
                return cls.from_mesh(np.asarray(mesh.vertices), np.asarray(mesh.triangles),
                                     str(path))
        from .datasets import read_scan

        scan = read_scan(path, **reader_kwargs)
        pts = scan.points + scan.offset
        normals = None
        if scan.origins is not None:
            normals = oriented_normals(pts, scan.origins + scan.offset)
        return cls.from_points(pts, normals, description=str(path))

    def sample_surface(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` points on the reference surface (mesh: area-weighted; cloud: a subset)."""
        if self.mesh is not None:
            return sample_mesh_surface(*self.mesh, n, rng)
        if self.points is not None:
            idx = rng.choice(len(self.points), size=min(n, len(self.points)), replace=False)
            return self.points[idx]
        raise EvaluationError(f"Reference of kind '{self.kind}' has no surface to sample; "
                              "Chamfer distances need a mesh or a point cloud reference.")


def oriented_normals(points, origins, radius: float = 0.3, max_nn: int = 30) -> np.ndarray:
    """PCA normals of a cloud (Open3D), flipped to face each point's sensor origin.

    Parameters
    ----------
    points, origins : (R, 3) float64
    radius : float
        Neighbourhood radius (m).
    max_nn : int

    Returns
    -------
    (R, 3) float64 unit normals pointing into free space.
    """
    import open3d as o3d

    c = points.mean(0)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points - c))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn))
    n = np.asarray(pc.normals, dtype=np.float64)
    flip = np.einsum("ij,ij->i", n, origins - points) < 0
    n[flip] *= -1
    return n


# --------------------------------------------------------------------------- queries
def sample_queries(points: np.ndarray, normals: np.ndarray, n: int, *,
                   max_distance: float = 0.5, tangential: float = 0.05,
                   rng: Optional[np.random.Generator] = None) -> np.ndarray:
    """Query points near observed surfaces: random hit points moved along their normal
    by a uniform offset in [-max_distance, max_distance] plus a small tangential jitter.

    Parameters
    ----------
    points, normals : (P, 3)
        Hit points and unit normals.
    n : int
        Number of queries.
    max_distance, tangential : float
        Offset range along the normal and standard deviation across it (m).
    rng : numpy.random.Generator, optional (default seed 0)

    Returns
    -------
    (n, 3) float64
    """
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0 \
            or normals.shape != points.shape:
        raise EvaluationError(f"Expected hit points and normals of the same shape (P, 3), "
                              f"P >= 1, found {points.shape} and {normals.shape}.")
    rng = np.random.default_rng(0) if rng is None else rng
    i = rng.integers(0, len(points), n)
    along = rng.uniform(-max_distance, max_distance, n)
    jitter = rng.normal(scale=tangential, size=(n, 3))
    jitter -= np.einsum("ij,ij->i", jitter, normals[i])[:, None] * normals[i]
    return points[i] + along[:, None] * normals[i] + jitter


# --------------------------------------------------------------------------- metrics
_KEYS = ("n", "rmse_sdf", "rmse_edf", "ll_sdf", "ll_edf", "cov1_sdf", "cov2_sdf",
         "cov2sig_sdf")
#: Central probability of a Gaussian's +-2 sigma interval, erf(2 / sqrt 2).
TWO_SIGMA = 0.9544997361036416
#: Central probability levels of the reliability diagram (0.1, 0.2, ..., 0.95, 0.99 would
#: also do; ten equal steps keep the diagram readable).
RELIABILITY_LEVELS = tuple(round(0.1 * k, 1) for k in range(1, 10)) + (0.95,)


def coverage(y, mean, var, k: float = 1.0) -> np.ndarray:
    """Per query: True when ``|y - mean| <= k sigma`` (calibration, issue 15).

    A calibrated Gaussian predictive distribution covers 68.3 % of the queries at
    ``k = 1`` and 95.4 % at ``k = 2``.

    Parameters
    ----------
    y, mean, var : (K,) array_like
    k : float
        Width in standard deviations.

    Returns
    -------
    (K,) bool
    """
    y, mean, var = (np.asarray(a, dtype=np.float64) for a in (y, mean, var))
    return np.abs(y - mean) <= k * np.sqrt(np.maximum(var, 0.0))


def reliability(y, mean, var, levels: Sequence[float] = RELIABILITY_LEVELS,
                distribution=None) -> dict:
    """Expected against observed coverage of central intervals.

    For each level ``p`` the interval ``mean +- z_p sigma`` with
    ``z_p = Phi^-1((1 + p) / 2)`` (Gaussian), or ``mean +- distribution.half_width(p)``
    when a predictive ``distribution`` is given (:meth:`SurfaceMap.distribution`),
    should hold a fraction ``p`` of the truths.

    Returns
    -------
    dict with ``expected`` (levels) and ``observed`` (fractions), both lists.
    """
    from scipy.stats import norm

    y, mean, var = (np.asarray(a, dtype=np.float64).reshape(-1) for a in (y, mean, var))
    err = np.abs(y - mean)
    sd = np.sqrt(np.maximum(var, 1e-300))
    obs = []
    for p in levels:
        if not len(err):
            obs.append(float("nan"))
            continue
        half = sd * norm.ppf(0.5 + 0.5 * p) if distribution is None \
            else distribution.half_width(p)
        obs.append(float(np.mean(err <= half)))
    return {"expected": [float(p) for p in levels], "observed": obs}


def plot_reliability(curves: dict, path, title: str = "") -> Path:
    """Reliability diagram (PNG): one line per name in ``curves`` ({name: reliability()})."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(4.2, 4.2))
    ax.plot([0, 1], [0, 1], color="0.6", lw=1, ls="--", label="calibrated")
    for name, c in curves.items():
        ax.plot(c["expected"], c["observed"], marker="o", ms=3, label=name)
    ax.set_xlabel("expected coverage")
    ax.set_ylabel("observed coverage")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def binned_metrics(mean, var, truth, dist, bins: Sequence[float] = DEFAULT_BINS, *,
                   signed_prediction: bool = True, signed_truth: bool = True,
                   distribution=None) -> dict:
    """RMSE and mean log-likelihood of the SDF and the EDF per distance bin.

    Parameters
    ----------
    mean, var : (K,)
        Predicted distance and its variance: signed (SDF) unless
        ``signed_prediction`` is False (Log-GPIS predicts the EDF directly).
    truth : (K,)
        True distance, signed unless ``signed_truth`` is False.
    dist : (K,)
        Distance of each query to the nearest training point (the binning axis).
    bins : increasing bin edges in metres
    signed_prediction, signed_truth : bool
        SDF metrics need both; otherwise they are NaN. The EDF of a signed
        prediction is ``|mean|`` scored by the folded normal; an unsigned
        prediction is scored by a Gaussian on ``|truth|``.
    distribution : optional
        The signed prediction's predictive distribution (:meth:`SurfaceMap.distribution`:
        ``logpdf``, ``half_width``, ``std``) when it is not the Gaussian N(mean, var):
        the log-likelihoods are its log density (the EDF's folded: ``p(t) + p(-t)``),
        the 1-sigma coverage uses its ``std`` and the 2-sigma one its central 95.45 %
        interval (a Gaussian's +-2 sigma); ``cov2sig_sdf`` is then ``|y - mean| <= 2
        std`` as it stands.

    Returns
    -------
    dict with ``bins`` (list of [lo, hi]) and per-bin lists ``n``, ``rmse_sdf``,
    ``rmse_edf``, ``ll_sdf``, ``ll_edf``, ``cov1_sdf`` and ``cov2_sdf`` (fraction of
    queries with ``|y - mean| <= 1`` and ``2`` sigma; NaN where a bin is empty), plus
    the same over all queries inside the bins under ``all``.
    """
    mean, var, truth, dist = (np.asarray(a, dtype=np.float64).reshape(-1)
                              for a in (mean, var, truth, dist))
    k = len(mean)
    if not (len(var) == len(truth) == len(dist) == k):
        raise EvaluationError(f"Expected mean, var, truth and dist of one length, found "
                              f"{k}, {len(var)}, {len(truth)} and {len(dist)}.")
    bins = np.asarray(bins, dtype=np.float64)
    if bins.ndim != 1 or len(bins) < 2 or np.any(np.diff(bins) <= 0):
        raise EvaluationError(f"Expected at least two increasing bin edges, found "
                              f"{bins.tolist()}; e.g. 0,0.05,0.1,0.2,0.3,0.5.")
    nan = np.full(k, np.nan)
    if signed_prediction:
        err_edf = (np.abs(mean) - np.abs(truth)) ** 2
        ll_edf = folded_normal_loglik(truth, mean, var)
    else:
        err_edf = (mean - np.abs(truth)) ** 2
        ll_edf = gaussian_loglik(np.abs(truth), mean, var)
    if signed_prediction and distribution is not None:
        a = np.abs(truth)
        ll_edf = np.logaddexp(distribution.logpdf(a), distribution.logpdf(-a))
    if signed_prediction and signed_truth:
        err_sdf, ll_sdf = (mean - truth) ** 2, gaussian_loglik(truth, mean, var)
        c1 = coverage(truth, mean, var, 1.0).astype(np.float64)
        c2 = coverage(truth, mean, var, 2.0).astype(np.float64)
        c2s = c2
        if distribution is not None:
            ll_sdf = distribution.logpdf(truth)
            c2 = (np.abs(truth - mean) <= distribution.half_width(TWO_SIGMA)).astype(np.float64)
    else:
        err_sdf, ll_sdf, c1, c2, c2s = nan, nan, nan, nan, nan
    per = (err_sdf, err_edf, ll_sdf, ll_edf, c1, c2, c2s)
    out = {"bins": [[float(a), float(b)] for a, b in zip(bins[:-1], bins[1:])]}
    out.update({key: [] for key in _KEYS})
    for lo, hi in out["bins"]:
        _append(out, (dist >= lo) & (dist < hi), *per)
    tot = {key: [] for key in _KEYS}
    _append(tot, (dist >= bins[0]) & (dist < bins[-1]), *per)
    out["all"] = {key: v[0] for key, v in tot.items()}
    return out


def _append(out, sel, err_sdf, err_edf, ll_sdf, ll_edf, c1, c2, c2s):
    n = int(sel.sum())
    out["n"].append(n)
    nan = float("nan")
    out["rmse_sdf"].append(float(np.sqrt(np.mean(err_sdf[sel]))) if n else nan)
    out["rmse_edf"].append(float(np.sqrt(np.mean(err_edf[sel]))) if n else nan)
    out["ll_sdf"].append(float(np.mean(ll_sdf[sel])) if n else nan)
    out["ll_edf"].append(float(np.mean(ll_edf[sel])) if n else nan)
    out["cov1_sdf"].append(float(np.mean(c1[sel])) if n else nan)
    out["cov2_sdf"].append(float(np.mean(c2[sel])) if n else nan)
    out["cov2sig_sdf"].append(float(np.mean(c2s[sel])) if n else nan)


def evaluate_field(predict: Callable, reference: Reference, queries: np.ndarray,
                   train_points: np.ndarray, bins: Sequence[float] = DEFAULT_BINS, *,
                   signed: bool = True, truth: Optional[np.ndarray] = None,
                   batch: int = 100_000, distribution: Optional[Callable] = None) -> dict:
    """Predict at ``queries``, compare with the reference, bin by distance to training.

    Parameters
    ----------
    predict : callable
        ``predict(xyz (K,3)) -> (mean (K,), var (K,))``.
    reference : Reference
    queries : (K, 3)
    train_points : (P, 3)
        The binning axis is each query's distance to the nearest of these.
    bins : bin edges (m)
    signed : bool
        False when ``predict`` returns an unsigned distance (Log-GPIS).
    truth : (K,), optional
        Precomputed ``reference.sdf(queries)`` (to share it between methods).
    batch : int
        Queries per ``predict`` call.
    distribution : callable, optional
        ``distribution(xyz) -> predictive`` (:meth:`SurfaceMap.distribution`): scored by
        its log density and central intervals (:func:`binned_metrics`); instead of
        ``predict`` then.

    Returns
    -------
    dict: :func:`binned_metrics` plus ``test_seconds`` (wall time of the
    predictions) and ``n_queries``.
    """
    queries = np.asarray(queries, dtype=np.float64)
    train_points = np.asarray(train_points, dtype=np.float64)
    if len(train_points) == 0:
        raise EvaluationError("Expected at least one training point to bin the queries by "
                              "distance, found 0.")
    dist = cKDTree(train_points).query(queries, k=1)[0]
    truth = reference.sdf(queries) if truth is None else np.asarray(truth, dtype=np.float64)
    mean, var = np.empty(len(queries)), np.empty(len(queries))
    t0 = time.perf_counter()
    parts = []
    for s in range(0, len(queries), batch):
        if distribution is not None:
            parts.append(distribution(queries[s:s + batch]))
            out = parts[-1].mean, parts[-1].var
        else:
            out = predict(queries[s:s + batch])
        mean[s:s + batch], var[s:s + batch] = out[0], out[1]
    seconds = time.perf_counter() - t0
    res = binned_metrics(mean, var, truth, dist, bins, signed_prediction=signed,
                         signed_truth=reference.signed,
                         distribution=_Batched(parts) if parts else None)
    res["test_seconds"] = seconds
    res["n_queries"] = int(len(queries))
    return res


def surface_distance_samples(vertices, faces, reference: Reference, *,
                             n_samples: int = 100_000,
                             crop_points: Optional[np.ndarray] = None,
                             crop_radius: float = 0.1,
                             rng: Optional[np.random.Generator] = None,
                             oversample: int = 4) -> tuple:
    """The two sets of distances behind :func:`surface_distances`.

    ``n_samples`` area-weighted samples of the mesh, each with its exact distance to
    the reference (``|reference.sdf|``), and samples of the reference surface, each
    with its exact distance to the mesh (point to triangles). With ``crop_points``,
    ``oversample * n_samples`` reference samples are drawn and those within
    ``crop_radius`` of a crop point kept (at most ``n_samples``), so that surfaces the
    scan never saw do not count as missing.

    Returns
    -------
    d_ab : (n_samples,) mesh -> reference (m)
    d_ba : (n,) reference -> mesh (m), n <= n_samples
    """
    rng = np.random.default_rng(0) if rng is None else rng
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0:
        raise EvaluationError("Expected a surface mesh with faces, found none; the field "
                              "may have no zero crossing near the data.")
    a = sample_mesh_surface(v, f, n_samples, rng)
    d_ab = np.abs(reference.sdf(a))  # every kind of reference gives |distance| this way
    b = reference.sample_surface(n_samples * oversample if crop_points is not None
                                 else n_samples, rng)
    if crop_points is not None:
        near = cKDTree(np.asarray(crop_points, dtype=np.float64)).query(
            b, k=1, distance_upper_bound=crop_radius)[0] < np.inf
        b = b[near][:n_samples]
        if len(b) == 0:
            raise EvaluationError(f"No reference surface lies within {crop_radius} m of the "
                                  "scan; check that the reference and the scan share a frame.")
    return d_ab, TriangleDistance(v, f)(b, signed=False)


def surface_distances(vertices, faces, reference: Reference, *, n_samples: int = 100_000,
                      crop_points: Optional[np.ndarray] = None, crop_radius: float = 0.1,
                      rng: Optional[np.random.Generator] = None) -> dict:
    """Chamfer and Hausdorff distances between a surface mesh and the reference.

    Both surfaces are sampled (area-weighted; ``n_samples`` each) and each sample's
    distance to the *other* surface is exact (point to triangles; point to the
    nearest reference point for a cloud). The reference is cropped to within
    ``crop_radius`` of ``crop_points`` (the scan) so that surfaces the scan never saw
    do not count as missing (:func:`surface_distance_samples`).

    Parameters
    ----------
    vertices, faces : the mesh (V, 3), (F, 3)
    reference : Reference with a mesh or points
    n_samples : int
    crop_points : (P, 3), optional
    crop_radius : float (m)
    rng : numpy.random.Generator, optional

    Returns
    -------
    dict: ``chamfer`` (mean of the two mean distances), ``hausdorff`` (max of the two
    maxima), ``accuracy`` (mean mesh -> reference), ``completeness`` (mean
    reference -> mesh), ``hausdorff95`` (95th percentile, symmetric max), in metres.
    """
    d_ab, d_ba = surface_distance_samples(vertices, faces, reference, n_samples=n_samples,
                                          crop_points=crop_points, crop_radius=crop_radius,
                                          rng=rng)
    return {
        "accuracy": float(d_ab.mean()),
        "completeness": float(d_ba.mean()),
        "chamfer": float(0.5 * (d_ab.mean() + d_ba.mean())),
        "hausdorff": float(max(d_ab.max(), d_ba.max())),
        "hausdorff95": float(max(np.quantile(d_ab, 0.95), np.quantile(d_ba, 0.95))),
        "n_samples": [int(len(d_ab)), int(len(d_ba))],
    }


class _Batched:
    """Predictive distributions of consecutive query batches read as one."""

    def __init__(self, parts):
        self.parts = parts
        self.sizes = np.cumsum([0] + [len(p.mean) for p in parts])

    def logpdf(self, y):
        y = np.asarray(y, dtype=np.float64).reshape(-1)
        return np.concatenate([p.logpdf(y[a:b]) for p, a, b in
                               zip(self.parts, self.sizes[:-1], self.sizes[1:])])

    def half_width(self, level):
        return np.concatenate([p.half_width(level) for p in self.parts])
