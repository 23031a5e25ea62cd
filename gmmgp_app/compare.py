"""The paper's comparison of methods on one scan, against a reference (``gmmgp eval``).

The recipe:

1. the saved map of a run and its configuration (a tiled map of ``run
   --tile-size`` answers for gmmgp, and hgmm as its tiles' stitched priors, only:
   the other methods would be built untiled on the whole scan);
2. the scan, prepared once: its hit points are the binning axis and the query seeds;
3. queries: hit points moved along their normal by up to the last bin edge;
4. every method (the saved one is reused, the others are built on the same scan and
   configuration through :func:`gmmgp_app.pipeline.build_map`) is predicted at the
   queries and scored against the reference (:mod:`gmmgp_app.evaluation`);
5. surfaces (the run's ``mesh_*.ply`` when present, else extracted) are compared
   with the reference (Chamfer, Hausdorff);
6. ``metrics.json``, ``metrics.csv``, ``metrics.md`` and PNG figures, each written
   atomically (:func:`write_outputs`).

The command line is :mod:`gmmgp_app.commands.eval`.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from .config import METHODS

__all__ = ["run_evaluation", "EVAL_METHODS", "EvalInputError", "tiled_methods",
           "write_outputs", "load_reference", "parse_methods", "parse_bins"]

EVAL_METHODS = METHODS


class EvalInputError(ValueError):
    """Bad arguments to ``gmmgp eval`` (unknown method, missing scan, ...)."""


def parse_methods(text) -> list:
    if text is None:
        return list(EVAL_METHODS)
    names = [m.strip() for m in text.split(",") if m.strip()]
    bad = [m for m in names if m not in EVAL_METHODS]
    if bad or not names:
        raise EvalInputError(f"Unknown method(s) {bad or text!r} in --methods; expected a "
                             f"comma-separated subset of {','.join(EVAL_METHODS)}.")
    return list(dict.fromkeys(names))


def parse_bins(text):
    from .evaluation import DEFAULT_BINS

    if text is None:
        return list(DEFAULT_BINS)
    try:
        edges = [float(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise EvalInputError(f"Expected --bins as numbers like 0,0.05,0.1, found "
                             f"{text!r}.") from None
    if len(edges) < 2 or any(b <= a for a, b in zip(edges, edges[1:])) or edges[0] < 0:
        raise EvalInputError(f"Expected at least two increasing, non-negative --bins edges, "
                             f"found {text!r}; e.g. 0,0.05,0.1,0.2,0.3,0.5.")
    return edges


def load_reference(path, reader_kwargs, skip):
    """The reference of ``--reference`` (a folder of scans minus its first ``skip``)."""
    from .evaluation import Reference

    if skip:
        from .datasets import read_scan

        # a folder of scans minus the training ones: read all, keep the later scans
        full = read_scan(path, **reader_kwargs)
        return _reference_without_first(full, path, reader_kwargs, skip)
    return Reference.load(path, **reader_kwargs)


def _reference_without_first(full, path, reader_kwargs, skip):
    """Reference cloud from a folder of scans without its first ``skip`` scans.

    Scans are told apart by their sensor origin (one pose per scan)."""
    from .evaluation import Reference, oriented_normals

    if full.origins is None:
        raise EvalInputError(f"--reference-skip needs scans with poses (sensor origins); "
                             f"'{path}' has none; pass --reference-poses.")
    _, first, inv = np.unique(full.origins, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)                     # scans in reading order
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    keep = rank[inv.reshape(-1)] >= skip
    if not keep.any():
        raise EvalInputError(f"--reference-skip {skip} drops all {len(order)} scans of "
                             f"'{path}'; use a smaller value.")
    pts = full.points[keep] + full.offset
    org = full.origins[keep] + full.offset
    return Reference.from_points(pts, oriented_normals(pts, org),
                                 description=f"{path} (scans {skip}..{len(order) - 1})")


def run_evaluation(scan, smap, reference, methods, *, bins, n_queries: int = 20000,
                   seed: int = 0, lam=None, surfaces: bool = True, voxel_size=None,
                   run_dir=None, log=None, surface_samples: int = 50000) -> dict:
    """Score several methods on one scan against one reference.

    Parameters
    ----------
    scan : Scan
    smap : SurfaceMap, TiledMap or None
        A saved map to reuse for its own method (others are built). A tiled map
        answers only for the methods of :func:`tiled_methods` (its own, and hgmm as
        the stitched priors of a gmmgp map's tiles); the others are refused, since
        building them untiled on the whole scan is what tiling avoids.
    reference : Reference
        In the scan's original frame (local + offset).
    methods : list of str
    bins : bin edges (m)
    n_queries, seed : test points and their seed
    lam : float, optional
        Log-GPIS lambda.
    surfaces : bool
        Also compute Chamfer / Hausdorff of each signed method's surface.
    voxel_size : float, optional
    run_dir : Path, optional
        Folder with ``mesh_{method}.ply`` from ``gmmgp run`` (reused when present).
    log : callable, optional

    Returns
    -------
    dict (see :mod:`gmmgp_app.report`)
    """
    from .config import MappingConfig
    from .evaluation import evaluate_field, sample_queries
    from .pipeline import build_map, prepare

    log = log or (lambda *a: None)
    tiled = is_tiled(smap)
    if tiled:
        check_tiled_methods(methods, tiled_methods(smap))
    cfg = smap.config if smap is not None else MappingConfig()
    offset = scan.offset
    t0 = time.perf_counter()
    data = prepare(scan, cfg)
    prep_s = time.perf_counter() - t0
    rng = np.random.default_rng(seed)
    queries = sample_queries(data.points, data.normals, n_queries, max_distance=bins[-1],
                             tangential=bins[-1] / 10, rng=rng)
    log(f"ground truth at {n_queries} queries ({reference.kind})")
    truth = reference.sdf(queries + offset)
    results = {"reference": {"path": reference.description, "kind": reference.kind},
               "bins": [[float(a), float(b)] for a, b in zip(bins[:-1], bins[1:])],
               "n_queries": int(n_queries), "seed": int(seed),
               "n_scan_points": int(len(scan)), "n_training_points": int(len(data.points)),
               "config_toml": cfg.to_toml(), "methods": {}}
    vs = cfg.surface.voxel_size if voxel_size is None else float(voxel_size)
    known = _resolved_voxel(vs, smap)  # a tiled map's 'auto': the median of its tiles'
    vs = vs if known is None else known
    for method in methods:
        log(f"{method}: building")
        saved = {k: float(v) for k, v in (smap.summary.get("seconds", {}) if smap else {})
                 .items() if k in ("prepare", "hgmm", "gmr", "gp")}
        if tiled:
            model = _TiledModel(smap if method == smap.method else _tiled_priors(smap),
                                scan.offset)
            tiles_s = smap.summary.get("seconds", {}).get("tiles")
            train = {} if tiles_s is None or method != smap.method else {"tiles": float(tiles_s)}
        elif smap is not None and smap.method == method:
            model, train = smap, saved
        elif smap is not None and method == "hgmm" and smap.hgmm is not None:
            # the saved map's prior is the GMR of the same hierarchy: no need to refit
            model = _PriorOnly(smap)
            train = {k: v for k, v in saved.items() if k != "gp"}
        elif method == "loggpis":
            model = build_map(scan, cfg, method="loggpis", loggpis_lambda=lam)
            train = {k: float(v) for k, v in model.summary["seconds"].items()}
        else:
            model = build_map(scan, cfg, method=method)
            train = {k: float(v) for k, v in model.summary["seconds"].items()}
        signed = getattr(model, "signed", True)
        log(f"{method}: predicting")
        # the predictive distribution where the model has one (SurfaceMap.distribution)
        field = evaluate_field(model.predict, reference, queries, data.points, bins,
                               signed=signed, truth=truth,
                               distribution=getattr(model, "distribution", None)
                               if signed else None)
        entry = {"train_seconds": train, "test_seconds": field.pop("test_seconds"),
                 "signed": bool(signed), "field": field, "surface": None}
        if method == "loggpis":
            entry["lambda"] = float(model.gp.params.lam)
        if surfaces and signed and (reference.mesh is not None or reference.points is not None):
            entry["surface"] = _surface_metrics(model, method, reference, scan, vs, run_dir,
                                                surface_samples, seed, log)
        results["methods"][method] = entry
        a = field["all"]
        log(f"{method}: RMSE SDF {a['rmse_sdf']:.4f} m, EDF {a['rmse_edf']:.4f} m, "
            f"LL SDF {a['ll_sdf']:.2f}, EDF {a['ll_edf']:.2f}")
        if "cov1_sdf" in field and not np.isnan(a["cov1_sdf"]):
            log(f"{method}: coverage |y-mu|<=1 sigma / in the central 95.45 % interval "
                "(a Gaussian's 2 sigma) per bin (target 0.68/0.95): " + ", ".join(
                f"{lo:g}-{hi:g} m {c1:.2f}/{c2:.2f}" for (lo, hi), c1, c2 in zip(
                    field["bins"], field["cov1_sdf"], field["cov2_sdf"]) if c1 == c1))
    results["prepare_seconds_eval"] = prep_s
    results["tiled"] = bool(tiled)
    return results


def is_tiled(smap) -> bool:
    from .tiling import TiledMap

    return isinstance(smap, TiledMap)


def tiled_methods(tmap) -> list:
    """The evaluation methods a tiled map answers for: its own method, and ``hgmm``
    for a gmmgp map (each tile's GMR prior is the hgmm baseline of that tile's
    hierarchy, stitched like the map itself)."""
    return [tmap.method] + (["hgmm"] if tmap.method == "gmmgp" else [])


def check_tiled_methods(methods, provided) -> None:
    missing = [m for m in methods if m not in provided]
    if missing:
        raise EvalInputError(
            f"--methods {','.join(missing)} cannot be evaluated on a tiled map, which holds "
            f"{','.join(provided)} only (the others would be built untiled on the whole "
            f"scan); pass --methods {','.join(provided)}, or evaluate a run made without "
            "--tile-size.")


class _TiledModel:
    """A tiled map as :func:`run_evaluation` uses a map: ``predict``, ``distribution`` and
    ``extract_surface`` in the scan's local frame, which may differ from the map's
    (a streamed map chose its offset from the LAS header)."""

    signed = True
    seed_points = None  # the whole scan crops the reference instead

    def __init__(self, tmap, scan_offset):
        self.tmap, self.method, self.config = tmap, tmap.method, tmap.config
        self.shift = np.asarray(scan_offset, dtype=np.float64) - tmap.offset

    def predict(self, xyz, return_grad: bool = False):
        x = np.asarray(xyz, dtype=np.float64)
        # frames equal (the usual case): the queries go through bit for bit
        return self.tmap.predict(x + self.shift if np.any(self.shift) else x,
                                 return_grad=return_grad)

    def distribution(self, xyz):
        """The stitched predictive (:meth:`TiledMap.distribution`), scored by its log
        density and central intervals as a single map's :meth:`SurfaceMap.distribution`."""
        x = np.asarray(xyz, dtype=np.float64)
        return self.tmap.distribution(x + self.shift if np.any(self.shift) else x)

    def extract_surface(self, voxel_size=None):
        mesh = self.tmap.extract_surface(voxel_size=voxel_size)
        if np.any(self.shift):
            from dataclasses import replace

            mesh = replace(mesh, vertices=mesh.vertices - self.shift)
        return mesh


class _PriorTiles:
    """The tiles of a tiled gmmgp map as prior-only (:class:`_PriorOnly`) maps, loaded
    on demand through the map's own tile store (memory stays bounded by its cache)."""

    def __init__(self, tiles):
        self._tiles = tiles

    def __contains__(self, key):
        return key in self._tiles

    def __iter__(self):
        return iter(self._tiles)

    def __len__(self):
        return len(self._tiles)

    def __getitem__(self, key):
        return _PriorOnly(self._tiles[key])

    def get(self, key, default=None):
        return self[key] if key in self else default

    def items(self):
        return ((k, self[k]) for k in self)


def _tiled_priors(tmap):
    """The hgmm baseline of a tiled gmmgp map: its tiles' GMR priors, stitched by the
    same tile weights."""
    from .tiling import TiledMap

    return TiledMap(tmap.spec, _PriorTiles(tmap.tiles), tmap.config, "hgmm",
                    offset=tmap.offset, summary=tmap.summary, owners=tmap.owners, up=tmap.up)


class _PriorOnly:
    """The GMR prior of a saved gmmgp map, as the hgmm method (same hierarchy)."""

    method = "hgmm"
    signed = True

    def __init__(self, smap):
        self.smap, self.config, self.seed_points = smap, smap.config, smap.seed_points

    def predict(self, xyz, return_grad: bool = False, far: bool = True):
        """The GMR prior (``far`` is accepted for the map interface: the prior has no
        far field; TiledMap.predict passes it to every tile)."""
        return self.smap.prior.predict(np.asarray(xyz, dtype=np.float64),
                                       return_grad=return_grad)

    def predict_mean(self, xyz):
        """(K,) the prior's mean (what a stitched surface's lattice asks each tile)."""
        return self.predict(xyz)[0]

    lattice_mean = predict_mean  # the prior has no far field: its own mean on the lattice

    def extract_surface(self, voxel_size=None):
        return self.smap.prior_surface(voxel_size)


def _resolved_voxel(v, tmap):
    """A surface voxel setting ``v`` in metres: a number as it is, 'auto' of a tiled map
    ``tmap`` the median of its tiles' voxels; None when it cannot be known here."""
    if not isinstance(v, str):
        return float(v)
    return tmap.surface_voxel() if hasattr(tmap, "surface_voxel") else None


def _model_voxel(model):
    """The surface voxel the model's saved mesh was made with (a tiled map's 'auto':
    the median of its tiles'), None when it cannot be known."""
    return _resolved_voxel(model.config.surface.voxel_size, getattr(model, "tmap", None))


def _surface_metrics(model, method, reference, scan, voxel_size, run_dir, n, seed, log):
    from .evaluation import surface_distances
    from .pipeline import read_mesh_ply

    saved = Path(run_dir) / f"mesh_{method}.ply" if run_dir is not None else None
    if saved is not None and saved.is_file() \
            and _model_voxel(model) is not None and np.isclose(voxel_size, _model_voxel(model)):
        mesh = read_mesh_ply(saved)                       # original frame already
        verts, source = mesh.vertices, str(saved)
    else:
        log(f"{method}: extracting the surface at {voxel_size} m")
        mesh = model.extract_surface(voxel_size=voxel_size)
        verts, source = mesh.vertices + scan.offset, f"extracted at {voxel_size} m"
    if len(mesh.faces) == 0:
        return None
    seeds = getattr(model, "seed_points", None)
    crop = (seeds if seeds is not None and len(seeds) else scan.points) + scan.offset
    res = surface_distances(verts, mesh.faces, reference, n_samples=n, crop_points=crop,
                            crop_radius=2 * voxel_size, rng=np.random.default_rng(seed))
    res.update(mesh=source, vertices=int(len(mesh.vertices)), faces=int(len(mesh.faces)),
               voxel_size=float(voxel_size))
    return res


def write_outputs(results: dict, out) -> list:
    """metrics.json, metrics.csv, metrics.md and the figures, atomically, into ``out``."""
    from ._atomic import atomic_write_text
    from .report import markdown_table, plot_metrics, write_metrics_csv, write_metrics_json

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = [write_metrics_json(results, out / "metrics.json"),
               write_metrics_csv(results, out / "metrics.csv"),
               atomic_write_text(out / "metrics.md", markdown_table(results))]
    written += plot_metrics(results, out)
    return written
