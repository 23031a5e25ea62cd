"""build_map(): the mapping recipe, one line per stage.

    scan ──prepare──> TrainingSet ──fit_hgmm──> HierarchicalGMM ──GMRField──> prior m(x), sigma_p(x)
         ──select |m(x)| > d_m──> GP points ──fit_local_gps──> LocalGPField ──> SurfaceMap

Each stage reports to an observer (``observer.on_stage(name, payload)``) as soon
as it finishes; the rerun logger and the GUI are such observers.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np

from ._atomic import atomic_dir
from .config import MappingConfig
from .types import GaussianMixture, HGMMLevel, HierarchicalGMM, Scan, SurfaceMesh

__all__ = ["build_map", "SurfaceMap", "load_map", "NullObserver", "FanoutObserver", "METHODS", "MapFormatError"]

METHODS = ("gmmgp", "hgmm", "gpis")
MAP_FORMAT_VERSION = 1


class MapFormatError(ValueError):
    """A saved map folder is missing, incomplete or from an incompatible version."""


class FanoutObserver:
    """Forward stage events to several observers (``None`` entries are skipped)."""

    def __init__(self, *observers):
        self.observers = [o for o in observers if o is not None]

    def on_stage_start(self, name: str) -> None:
        for o in self.observers:
            start = getattr(o, "on_stage_start", None)
            if start is not None:
                start(name)

    def on_stage(self, name: str, payload: Any) -> None:
        for o in self.observers:
            o.on_stage(name, payload)


class NullObserver:
    """Observer that ignores every stage (the default; costs nothing)."""

    def on_stage(self, name: str, payload: Any) -> None:  # noqa: D401
        pass


@dataclass(frozen=True)
class StagePayload:
    """What a stage hands to observers besides its result object.

    Attributes
    ----------
    result : object
        The stage's typed result (TrainingSet, HierarchicalGMM, ...).
    seconds : float
        Wall time of the stage.
    extra : dict
        Arrays or counts an observer may want (e.g. GMR error at the hit points).
    """

    result: Any
    seconds: float
    extra: dict = field(default_factory=dict)


# --------------------------------------------------------------------------- the map
class SurfaceMap:
    """A probabilistic signed distance field of a scene.

    Coordinates are in the scan's local frame (``Scan.points``); add ``offset``
    to return to the original (e.g. georeferenced) frame.

    Attributes
    ----------
    method : str
        "gmmgp" (HGMM prior + local GPs), "hgmm" (GMR alone) or "gpis".
    hgmm : HierarchicalGMM or None
        The fitted hierarchy (None for gpis).
    gp_points : (P, 3) float64
        Points the GP was trained on (empty for "hgmm").
    offset : (3,) float64
    config : MappingConfig
    summary : dict
        Timings (s) and counts per stage.
    """

    def __init__(self, method, config, offset, prior, hgmm=None, gp=None,
                 gp_points=None, gp_normals=None, seed_points=None, summary=None, far=None):
        self.method = method
        self.far = far
        self.config = config
        self.offset = np.asarray(offset, dtype=np.float64).reshape(3)
        self.prior = prior
        self.hgmm = hgmm
        self.gp = gp
        self.gp_points = np.zeros((0, 3)) if gp_points is None else gp_points
        self.gp_normals = np.zeros((0, 3)) if gp_normals is None else gp_normals
        self.seed_points = np.zeros((0, 3)) if seed_points is None else seed_points
        self.summary = dict(summary or {})

    # ------------------------------------------------------------------ predict
    def predict(self, xyz, return_grad: bool = False):
        """Signed distance mean and variance at query points.

        Parameters
        ----------
        xyz : (K, 3) array_like
            Query points in the local frame.
        return_grad : bool
            Also return the gradient of the mean.

        Returns
        -------
        mean : (K,) float64
            Signed distance, free space positive.
        var : (K,) float64
            Predictive variance (m^2).
        grad : (K, 3) float64, only if ``return_grad``
        """
        xyz = _as_queries(xyz)
        field_ = self.gp if self.gp is not None else self.prior
        if self.far is None:
            return field_.predict(xyz, return_grad=return_grad)
        from .stages.farfield import BlendedField

        return BlendedField(field_, self.far, self.config.far.calibrated,
                            self.config.far.gp_growth).predict(xyz, return_grad=return_grad)

    def extract_surface(self, voxel_size: Optional[float] = None, max_std=None,
                        progress=None) -> SurfaceMesh:
        """Marching-cubes surface of the zero level set, vertices carrying variance."""
        from .stages.surface import extract_surface

        cfg = self.config.surface
        return extract_surface(
            self.predict,
            self.seed_points,
            voxel_size=cfg.voxel_size if voxel_size is None else voxel_size,
            max_std=cfg.max_std if max_std is None else max_std,
            progress=progress,
        )

    # ------------------------------------------------------------------ save/load
    def save(self, directory) -> Path:
        """Write the map to ``directory`` (npz + json, no pickle), atomically.

        The folder is written under a temporary name beside the target and renamed
        when complete, so an interrupted save never leaves a half-written map.
        """
        directory = Path(directory)
        with atomic_dir(directory) as tmp:
            arrays = {"offset": self.offset, "gp_points": self.gp_points,
                      "gp_normals": self.gp_normals, "seed_points": self.seed_points}
            if self.hgmm is not None:
                arrays.update(_hgmm_to_arrays(self.hgmm))
            if self.gp is not None:
                arrays.update({f"gp/{k}": v for k, v in self.gp.to_arrays().items()})
            if self.far is not None:
                arrays.update({"far/points": self.far.points, "far/normals": self.far.normals})
            np.savez_compressed(tmp / "arrays.npz", **arrays)
            meta = {
                "format_version": MAP_FORMAT_VERSION,
                "method": self.method,
                "prior": type(self.prior).__name__,
                "prior_params": getattr(self.prior, "params", lambda: {})(),
                "far_params": None if self.far is None else self.far.params(),
                "config_toml": self.config.to_toml(),
                "summary": _jsonable(self.summary),
            }
            (tmp / "map.json").write_text(json.dumps(meta, indent=2))
        return directory


def load_map(directory) -> SurfaceMap:
    """Load a map written by :meth:`SurfaceMap.save`; it predicts identically."""
    import tomllib

    from .stages.gmr import GMRField
    from .stages.gp import ConstantPrior, LocalGPField

    directory = Path(directory)
    meta_path, arr_path = directory / "map.json", directory / "arrays.npz"
    if (directory / "tiled.json").is_file():
        raise MapFormatError(
            f"'{directory}' holds a tiled map (tiled.json), not a single map; open it with "
            "gmmgp_app.tiling.load_tiled_map ('gmmgp eval' reads tiled runs, 'gmmgp view' "
            "does not yet: map without --tile-size to view)."
        )
    if not meta_path.is_file() or not arr_path.is_file():
        raise MapFormatError(
            f"'{directory}' is not a saved map (expected map.json and arrays.npz); "
            "create one with 'gmmgp run SCAN --out DIR'."
        )
    meta = json.loads(meta_path.read_text())
    if meta.get("format_version") != MAP_FORMAT_VERSION:
        raise MapFormatError(
            f"Map format version {meta.get('format_version')} in '{directory}' is not "
            f"supported (expected {MAP_FORMAT_VERSION}); rebuild the map with this version."
        )
    cfg = MappingConfig.from_dict(tomllib.loads(meta["config_toml"]))
    with np.load(arr_path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    hgmm = _hgmm_from_arrays(arrays) if "hgmm/leaves/weights" in arrays else None
    if meta["prior"] == "GMRField":
        prior = GMRField.from_config(hgmm.leaves, cfg.gmr)
    else:
        prior = ConstantPrior(**meta["prior_params"])
    gp_arrays = {k[3:]: v for k, v in arrays.items() if k.startswith("gp/")}
    gp = LocalGPField.from_arrays(gp_arrays, prior, cfg.gp) if gp_arrays else None
    far = None
    if meta.get("far_params") is not None and "far/points" in arrays:
        from .stages.farfield import FarField

        fp = dict(meta["far_params"])
        far = FarField(arrays["far/points"], arrays["far/normals"], fp.pop("rho0"),
                       fp.pop("noise"), **fp)
    smap = SurfaceMap(meta["method"], cfg, arrays["offset"], prior, hgmm=hgmm, gp=gp,
                      gp_points=arrays["gp_points"], gp_normals=arrays["gp_normals"],
                      seed_points=arrays["seed_points"], summary=meta.get("summary", {}),
                      far=far)
    return smap


# --------------------------------------------------------------------------- recipe
def build_map(scan: Scan, cfg: Optional[MappingConfig] = None, method: str = "gmmgp",
              observer=None, *, stop_after: Optional[str] = None, executor=None,
              progress=None) -> SurfaceMap:
    """Map a scan into a probabilistic signed distance field.

    Parameters
    ----------
    scan : Scan
    cfg : MappingConfig, optional
        Defaults to ``MappingConfig()`` (the paper's settings).
    method : {"gmmgp", "hgmm", "gpis"}
        gmmgp: HGMM prior refined by local GPs (the paper's method);
        hgmm: Gaussian mixture regression alone; gpis: stationary GP with a
        constant prior on all points (baseline).
    observer : object with ``on_stage(name, payload)``, optional
        Receives a :class:`StagePayload` after each stage.
    stop_after : {"prepare", "hgmm", "gmr"}, optional
        Return early (used by ``gmmgp run --stage``); the map then has no GP.
    executor : concurrent.futures.Executor, optional
        Fits the GP blocks as batched tasks (see :mod:`gmmgp_app.distributed`);
        the result equals the serial one.
    progress : callable(done, total), optional
        Called as GP block tasks finish.

    Returns
    -------
    SurfaceMap
    """
    from .stages.gmr import GMRField
    from .stages.gp import ConstantPrior, fit_local_gps, select_gp_points
    from .stages.hgmm import fit_hgmm
    from .stages.prepare import prepare

    cfg = MappingConfig() if cfg is None else cfg
    if method not in METHODS:
        raise ValueError(f"Unknown method {method!r}; expected one of {', '.join(METHODS)}.")
    observer = observer or NullObserver()
    summary: dict = {"method": method, "n_scan_points": len(scan), "seconds": {}, "counts": {}}
    cfg, summary["auto"] = resolve_config(cfg, scan)
    stage = _StageRunner(observer, summary)
    observer.on_stage("scan", StagePayload(scan, 0.0))

    data = stage("prepare", lambda: prepare(scan, cfg),
                 counts=lambda d: {"hit_points": len(d.points), "rows": len(d.rows),
                                   "dropped_virtual": d.n_dropped_virtual})
    hgmm, gp, gp_mask = None, None, np.zeros(len(data.points), dtype=bool)
    if method == "gpis":
        prior = ConstantPrior(**_gpis_prior_kwargs(cfg))
        gp_mask[:] = True
    else:
        if stop_after == "prepare":
            return _early_map(method, cfg, scan, data, None, summary)
        hgmm = stage("hgmm", lambda: fit_hgmm(data, cfg.hgmm),
                     counts=lambda h: {"levels": len(h.levels),
                                       "leaves": h.leaves.n_components})
        if stop_after == "hgmm":
            return _early_map(method, cfg, scan, data, hgmm, summary)
        prior = GMRField.from_config(hgmm.leaves, cfg.gmr)
        m_hits = stage("gmr", lambda: prior.predict(data.points)[0],
                       extra=lambda m: {"points": data.points, "error": m})
        gp_mask = select_gp_points(m_hits, cfg.gp.d_m) if method == "gmmgp" else gp_mask
        summary["counts"]["gmr"] = {"rms_error_at_hits": float(np.sqrt(np.mean(m_hits ** 2))),
                                    "gp_points": int(gp_mask.sum())}
        if stop_after == "gmr" or method == "hgmm":
            return SurfaceMap(method, cfg, scan.offset, prior, hgmm=hgmm,
                              seed_points=surface_seeds(scan, cfg), summary=summary)
    pts, nrm = data.points[gp_mask], data.normals[gp_mask]
    if len(pts):
        gp = stage("gp", lambda: fit_local_gps(pts, nrm, prior, cfg.gp, executor=executor,
                                               progress=progress),
                   counts=lambda g: {k: v for k, v in g.info.items()
                                     if isinstance(v, (int, float))},
                   extra=lambda g: {"points": pts, "normals": nrm})
    far = None
    if method == "gmmgp" and cfg.far.enabled:
        far = stage("far", lambda: far_field(data, cfg))
    return SurfaceMap(method, cfg, scan.offset, prior, hgmm=hgmm, gp=gp, gp_points=pts,
                      gp_normals=nrm, seed_points=surface_seeds(scan, cfg), summary=summary,
                      far=far)


def far_field(data, cfg: MappingConfig):
    """The far field of the training hit points (stages/farfield.py)."""
    from .config import concrete
    from .stages.farfield import FarField

    f, g = concrete(cfg.far), concrete(cfg.gp)
    return FarField(data.points, data.normals, f.kernel_floor,
                    max(g.value_noise, 1e-30) ** 0.5, k=f.neighbours, growth=f.kernel_growth,
                    spread_weight=f.spread_weight, beta=f.growth)


class _StageRunner:
    """Times a stage, records its counts, and tells the observer."""

    def __init__(self, observer, summary):
        self.observer, self.summary = observer, summary

    def __call__(self, name, fn, counts=None, extra=None):
        start = getattr(self.observer, "on_stage_start", None)
        if start is not None:
            start(name)
        t0 = time.perf_counter()
        result = fn()
        seconds = time.perf_counter() - t0
        self.summary["seconds"][name] = seconds
        if counts is not None:
            self.summary["counts"][name] = counts(result)
        self.observer.on_stage(name, StagePayload(result, seconds,
                                                  extra(result) if extra else {}))
        return result


def _early_map(method, cfg, scan, data, hgmm, summary):
    from .stages.gp import ConstantPrior

    return SurfaceMap(method, cfg, scan.offset, ConstantPrior(**_gpis_prior_kwargs(cfg)),
                      hgmm=hgmm, seed_points=surface_seeds(scan, cfg), summary=summary)


def resolve_config(cfg: MappingConfig, scan: Scan) -> tuple:
    """``cfg`` with every ``"auto"`` field computed from ``scan`` (stages/autoscale.py),
    and the record of the chosen values and their reasons (empty when nothing was auto).
    """
    from .config import concrete
    from .stages.autoscale import AutoScaleError
    from .stages.autoscale import resolve_config as _resolve
    from .stages.prepare import MIN_POINTS

    pts = scan.points
    if len(pts) < MIN_POINTS or not np.isfinite(pts).all():
        return cfg, {}          # prepare raises the one-line error for such scans
    try:
        return _resolve(cfg, pts, scan.origins)
    except AutoScaleError as exc:
        # too few or coincident points to measure: the urban values, and prepare
        # gives its own one-line error if the scan cannot be mapped at all
        return concrete(cfg), {"fallback": f"urban values ({exc})"}


def surface_seeds(scan: Scan, cfg: MappingConfig) -> np.ndarray:
    """One scan point per cell of half the surface voxel: where the surface is sought.

    All hit points (not only the training subsample) so that marching cubes covers
    every observed surface; thinned so that dense scans do not bloat the map.
    """
    from .config import concrete

    cell = concrete(cfg.surface).voxel_size / 2
    keys = np.floor(scan.points / cell).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return scan.points[np.sort(first)]


def _gpis_prior_kwargs(cfg: MappingConfig) -> dict:
    # The paper's GPIS setup: a constant prior distance of 0.2 m.
    return {"distance": 0.2, "variance": 0.2 ** 2}


def _as_queries(xyz) -> np.ndarray:
    q = np.asarray(xyz, dtype=np.float64)
    if q.ndim == 1 and q.shape[0] == 3:
        q = q[None, :]
    if q.ndim != 2 or q.shape[1] != 3:
        raise ValueError(f"Expected query points with shape (K, 3), found {q.shape}.")
    if not np.all(np.isfinite(q)):
        raise ValueError(
            f"Expected finite query coordinates, found {int((~np.isfinite(q)).any(1).sum())} "
            "rows with NaN or inf; drop them before predicting."
        )
    return q


# --------------------------------------------------------------------------- (de)serialise
def _hgmm_to_arrays(h: HierarchicalGMM) -> dict:
    out = {"hgmm/n_levels": np.array(len(h.levels)), "hgmm/leaf_level": h.leaf_level}
    for name, gm in [("leaves", h.leaves)]:
        out.update({f"hgmm/{name}/weights": gm.weights, f"hgmm/{name}/means": gm.means,
                    f"hgmm/{name}/covariances": gm.covariances})
    for i, lv in enumerate(h.levels):
        p = f"hgmm/level{i}/"
        out.update({p + "weights": lv.mixture.weights, p + "means": lv.mixture.means,
                    p + "covariances": lv.mixture.covariances, p + "parent": lv.parent,
                    p + "complexity": lv.complexity, p + "split": lv.split,
                    p + "n_rows": lv.n_rows})
    return out


def _hgmm_from_arrays(a: dict) -> HierarchicalGMM:
    levels = []
    for i in range(int(a["hgmm/n_levels"])):
        p = f"hgmm/level{i}/"
        levels.append(HGMMLevel(
            GaussianMixture(a[p + "weights"], a[p + "means"], a[p + "covariances"]),
            a[p + "parent"], a[p + "complexity"], a[p + "split"], a[p + "n_rows"]))
    leaves = GaussianMixture(a["hgmm/leaves/weights"], a["hgmm/leaves/means"],
                             a["hgmm/leaves/covariances"])
    return HierarchicalGMM(tuple(levels), leaves, a["hgmm/leaf_level"], {})


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return obj


_surface_seeds = surface_seeds  # former private name, still used by tiling and the GUI model
