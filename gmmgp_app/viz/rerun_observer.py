"""Record every pipeline stage to rerun (a .rrd file, a spawned viewer, or a server).

Entity paths (all under an explicit ``rr.RecordingStream``):

=============================  ==================================================
``world/scan``                 the input points, coloured by height or class
``world/prepare/hits``         subsampled hit points (d = 0)
``world/prepare/virtual``      virtual points coloured by d (blue -s .. red +s)
``world/hgmm/level_{k}``       ellipsoids of level k (2 sigma, xyz part), coloured
                               by complexity c; split nodes as wireframes, leaves
                               filled; logged at ``level = k``
``world/hgmm/leaves``          the final leaves
``world/gmr/error``            hit points coloured by the GMR error |m(x)|
``world/gp/points``            points selected for the GP (|m(x)| > d_m)
``world/gp/blocks``            octree blocks that carry a local GP
``world/surface/{method}``     marching-cubes meshes coloured by std
``metrics/seconds/{stage}``    stage wall time (scalar)
``metrics/counts/{name}``      counts (leaves, GP points, vertices, ...)
``config``                     the resolved configuration (Markdown)
=============================  ==================================================

Timelines: ``stage`` (one step per stage), ``level`` (HGMM levels) and, in
sweeps, ``sweep``. The recording is flushed after every stage, so a run killed
mid-way still leaves a loadable file with the stages done so far.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

STAGE_ORDER = ("scan", "prepare", "hgmm", "gmr", "gp", "surface")


def _colormap(t: np.ndarray, name: str = "viridis") -> np.ndarray:
    import matplotlib

    rgba = matplotlib.colormaps[name](np.clip(np.nan_to_num(t), 0, 1))
    return (rgba[:, :3] * 255).astype(np.uint8)


def _normalise(v: np.ndarray, hi: Optional[float] = None) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    if len(v) == 0:
        return v
    lo = 0.0
    hi = float(np.quantile(v, 0.98)) if hi is None else hi
    return (v - lo) / max(hi - lo, 1e-12)


def ellipsoid_params(means: np.ndarray, covariances: np.ndarray, n_sigma: float = 2.0):
    """Centres, half sizes and xyzw quaternions of the xyz part of Gaussians.

    Parameters
    ----------
    means : (K, D) with D >= 3
    covariances : (K, D, D)

    Returns
    -------
    centers (K,3), half_sizes (K,3), quaternions (K,4) as x, y, z, w
    """
    from scipy.spatial.transform import Rotation

    cov3 = covariances[:, :3, :3]
    evals, evecs = np.linalg.eigh(cov3)
    # A proper rotation: flip the last axis where the eigenbasis is left-handed.
    det = np.linalg.det(evecs)
    evecs[det < 0, :, 2] *= -1
    quats = Rotation.from_matrix(evecs).as_quat()  # scipy: x, y, z, w
    half = n_sigma * np.sqrt(np.maximum(evals, 0))
    return means[:, :3].copy(), half, quats


class RerunObserver:
    """Pipeline observer that logs each stage to rerun.

    Parameters
    ----------
    rrd : path, optional
        Write the recording to this file.
    spawn : bool
        Open a viewer.
    serve : bool
        Serve the recording over gRPC bound to 127.0.0.1 only.
    application_id : str
    config : MappingConfig, optional
        Logged as a Markdown document.
    """

    def __init__(self, rrd=None, *, spawn: bool = False, serve: bool = False,
                 application_id: str = "gmmgp", config=None, recording_id=None):
        import rerun as rr

        self.rr = rr
        self.rec = rr.RecordingStream(application_id, recording_id=recording_id)
        self.blueprint = default_blueprint()
        self.path = Path(rrd) if rrd else None
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.rec.save(str(self.path), default_blueprint=self.blueprint)
        if spawn:
            self.rec.spawn(default_blueprint=self.blueprint)
        if serve:
            uri = self.rec.serve_grpc(grpc_port=9876, default_blueprint=self.blueprint)
            print(f"rerun: serving on {uri} (bound to 127.0.0.1)")
        self.step = 0
        self.extra_time: dict = {}
        if config is not None:
            self.log_config(config)

    # -------------------------------------------------------------- helpers
    def _time(self, **extra):
        for k, v in {**self.extra_time, **extra}.items():
            self.rr.set_time(k, sequence=int(v), recording=self.rec)
        self.rr.set_time("stage", sequence=self.step, recording=self.rec)

    def log(self, path, archetype, static: bool = False):
        self.rec.log(path, archetype, static=static)

    def flush(self):
        self.rec.flush()

    def log_config(self, config):
        md = "# Resolved configuration\n\n```toml\n" + config.to_toml() + "```\n"
        self.log("config", self.rr.TextDocument(md, media_type="text/markdown"), static=True)

    def scalar(self, path, value):
        self.log(path, self.rr.Scalars([float(value)]))

    # -------------------------------------------------------------- observer API
    def on_stage_start(self, name: str) -> None:
        pass

    def on_stage(self, name: str, payload) -> None:
        self.step = STAGE_ORDER.index(name) if name in STAGE_ORDER else self.step + 1
        self._time()
        handler = getattr(self, f"_log_{name}", None)
        if handler is not None:
            handler(payload.result, payload.extra)
        if payload.seconds:
            self.scalar(f"metrics/seconds/{name}", payload.seconds)
        self.flush()

    # -------------------------------------------------------------- stages
    def _log_scan(self, scan, extra):
        rr = self.rr
        pts = scan.points
        if scan.labels is not None:
            self.log("world/scan", rr.Points3D(pts, class_ids=scan.labels.astype(np.uint16),
                                               radii=-1.5))
        else:
            z = pts[:, 2]
            t = (z - z.min()) / max(np.ptp(z), 1e-9)
            self.log("world/scan", rr.Points3D(pts, colors=_colormap(t, "turbo"), radii=-1.5))
        self.scalar("metrics/counts/scan_points", len(pts))

    def _log_prepare(self, data, extra):
        rr = self.rr
        hit = data.kinds == 0
        self.log("world/prepare/hits", rr.Points3D(data.rows[hit, :3], colors=[40, 40, 40],
                                                   radii=-1.5))
        v = ~hit
        d = data.rows[v, 3]
        t = (d + data.spacing) / (2 * data.spacing)
        self.log("world/prepare/virtual", rr.Points3D(data.rows[v, :3],
                                                      colors=_colormap(t, "coolwarm"),
                                                      radii=-1.5))
        self.scalar("metrics/counts/training_rows", len(data.rows))

    def _log_hgmm(self, hgmm, extra):
        rr = self.rr
        cmax = 0.25  # c of an isotropic 4D Gaussian; c lies in [0, 0.25]
        for k, lv in enumerate(hgmm.levels):
            self._time(level=k)
            gm = lv.mixture
            c, h, q = ellipsoid_params(gm.means, gm.covariances)
            colors = _colormap(np.sqrt(lv.complexity / cmax), "plasma")
            labels = [f"L{k}#{i} c={ci:.4f}{' split' if s else ''}"
                      for i, (ci, s) in enumerate(zip(lv.complexity, lv.split))]
            fill = [rr.components.FillMode.MajorWireframe if s else rr.components.FillMode.Solid
                    for s in lv.split]
            # One archetype per fill mode: rerun takes one fill mode per entity.
            for tag, sel in (("split", lv.split), ("leaf", ~lv.split)):
                if sel.any():
                    self.log(f"world/hgmm/level_{k}/{tag}", rr.Ellipsoids3D(
                        centers=c[sel], half_sizes=h[sel], quaternions=q[sel],
                        colors=colors[sel], labels=[labels[i] for i in np.flatnonzero(sel)],
                        show_labels=False,
                        fill_mode=fill[int(np.flatnonzero(sel)[0])]))
            self.scalar("metrics/counts/hgmm_nodes_per_level", gm.n_components)
            self.scalar("metrics/counts/hgmm_split_per_level", int(lv.split.sum()))
        self._time(level=len(hgmm.levels) - 1)
        leaves = hgmm.leaves
        c, h, q = ellipsoid_params(leaves.means, leaves.covariances)
        from ..stages.hgmm import complexity

        cl = complexity(leaves.covariances)
        self.log("world/hgmm/leaves", rr.Ellipsoids3D(
            centers=c, half_sizes=h, quaternions=q, colors=_colormap(np.sqrt(cl / cmax), "plasma"),
            fill_mode=rr.components.FillMode.Solid))
        self.scalar("metrics/counts/hgmm_leaves", leaves.n_components)

    def _log_gmr(self, m_hits, extra):
        rr = self.rr
        err = np.abs(extra["error"])
        self.log("world/gmr/error", rr.Points3D(extra["points"], colors=_colormap(
            _normalise(err, 0.1), "RdYlGn_r"), radii=-2.0))
        self.scalar("metrics/gmr_rms_error_at_hits", float(np.sqrt(np.mean(err ** 2))))

    def _log_gp(self, gp, extra):
        rr = self.rr
        self.log("world/gp/points", rr.Points3D(extra["points"], colors=[230, 40, 40],
                                                radii=-2.5))
        bounds = getattr(gp, "block_bounds", None)
        if callable(bounds):
            lo, hi = bounds()
            self.log("world/gp/blocks", rr.Boxes3D(centers=(lo + hi) / 2, half_sizes=(hi - lo) / 2,
                                                   colors=[255, 160, 0]))
            self.scalar("metrics/counts/gp_blocks", len(lo))
        self.scalar("metrics/counts/gp_points", len(extra["points"]))

    def _log_surface(self, meshes, extra):
        """``meshes``: dict method -> SurfaceMesh."""
        from ..stages.surface import variance_colors

        rr = self.rr
        vmax = None
        for method, mesh in meshes.items():
            if len(mesh.faces) == 0:
                continue
            if vmax is None:
                vmax = float(np.sqrt(np.quantile(mesh.vertex_variance, 0.98)))
            self.log(f"world/surface/{method}", rr.Mesh3D(
                vertex_positions=mesh.vertices, triangle_indices=mesh.faces,
                vertex_colors=variance_colors(mesh.vertex_variance, vmax)))
            self.log(f"world/surface/{method}/variance",
                     rr.AnyValues(variance=mesh.vertex_variance.astype(np.float32)))
            self.scalar(f"metrics/counts/vertices_{method}", len(mesh.vertices))


def default_blueprint():
    """One 3D view per stage group, a metrics view and the config, time on ``stage``."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Grid(
                rrb.Spatial3DView(name="Scan and training rows", origin="world",
                                  contents=["+ world/scan", "+ world/prepare/**"]),
                rrb.Spatial3DView(name="HGMM (level slider: 'level' timeline)", origin="world",
                                  contents=["+ world/hgmm/**"]),
                rrb.Spatial3DView(name="GMR error and GP points", origin="world",
                                  contents=["+ world/gmr/**", "+ world/gp/**"]),
                rrb.Spatial3DView(name="Surfaces (colour: std)", origin="world",
                                  contents=["+ world/surface/**"]),
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(name="Metrics", origin="metrics"),
                rrb.TextDocumentView(name="Config", origin="config"),
            ),
            column_shares=[3, 1],
        ),
        rrb.TimePanel(timeline="stage"),
        collapse_panels=True,
    )
