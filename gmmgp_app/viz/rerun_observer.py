"""Record every pipeline stage to rerun (a .rrd file, a spawned viewer, or a local server).

Entity paths (all logged through an explicit ``rr.RecordingStream``):

===================================  ==================================================
``world``                            the scan's up axis as the 3D views' coordinate
                                     convention (``ViewCoordinates``, static: a y-up
                                     Stanford set opens upright)
``world/scan``                       the input points, coloured by class or height
``world/prepare/hits``               subsampled hit points (d = 0), grey
``world/prepare/virtual``            virtual points coloured by d (blue -s .. red +s)
``world/hgmm/level_{k}/split``       level k nodes that were split: wireframe
                                     ellipsoids (2 sigma, xyz part) coloured by c;
                                     only on the ``level`` timeline, at ``level = k``
``world/hgmm/level_{k}/leaf``        level k nodes kept as leaves: solid, coloured by c
``world/hgmm/leaves``                the final leaves (the mixture used downstream)
``world/gmr/error``                  hit points coloured by the GMR error |m(x)|
                                     (green 0 .. red >= 5 d_m), values in ``error``
``world/gp/points``                  points selected for the GP (|m(x)| > d_m)
``world/gp/blocks``                  octree leaf blocks that carry a local GP,
                                     coloured by their number of training points
``world/surface/{method}``           marching-cubes meshes (``gmmgp``, ``hgmm``, ...)
                                     (the blueprint shows the map's mesh and the
                                     HGMM-only mesh in two tabs)
                                     coloured by the predicted std (viridis, one
                                     scale for all meshes), raw variance in
                                     ``vertex_variance``
``metrics/seconds/{stage}``          stage wall time (scalar)
``metrics/counts/{name}``            counts: scan_points, training_rows, hgmm_levels,
                                     hgmm_leaves, gp_points, gp_blocks, vertices_{method}
``metrics/gmr_rms_error_at_hits``    RMS of m(x) at the hit points (m)
``summary``                          Markdown table of seconds and counts so far
``config``                           the resolved configuration (Markdown, static)
===================================  ==================================================

Timelines: ``stage`` (scan 0, prepare 1, hgmm 2, gmr 3, gp 4, surface 5), ``level``
(HGMM levels; switch the time panel to it to step through the hierarchy) and, in
sweeps, ``sweep`` (see :mod:`gmmgp_app.sweep`). The recording is flushed after
every stage, so a run killed mid-way leaves a file holding the stages done so far.

``--serve`` and ``--spawn`` start the ``rerun`` executable bound to 127.0.0.1 (the
SDK's own ``serve_grpc`` listens on every interface and has no bind option in
rerun 0.41), then stream to it over gRPC.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ..types import as_up_axis
from .gui_camera import up_frame
from .gui_model import STAGES as STAGE_ORDER  # the stages shown, in pipeline order

__all__ = [
    "STAGE_ORDER",
    "RerunError",
    "RerunObserver",
    "default_blueprint",
    "scan_eye",
    "view_coordinates",
    "ellipsoid_params",
    "repair_recording",
    "rerun_executable",
    "screenshot",
    "start_local_server",
]

#: |m(x)| at which the GMR error colour saturates, in units of d_m.
ERROR_SATURATION_DM = 5.0
#: Largest complexity of a D-dimensional Gaussian (isotropic) is 1/D; rows are 4D.
C_MAX = 0.25


class RerunError(ValueError):
    """The rerun executable or viewer could not be started or did not answer.

    A ValueError so that the CLI reports it in one line with exit code 2.
    """


# --------------------------------------------------------------------------- colours
def _colormap(t: np.ndarray, name: str = "viridis") -> np.ndarray:
    import matplotlib

    rgba = matplotlib.colormaps[name](np.clip(np.nan_to_num(t), 0, 1))
    return (rgba[:, :3] * 255 + 0.5).astype(np.uint8)


def ellipsoid_params(means: np.ndarray, covariances: np.ndarray, n_sigma: float = 2.0):
    """Centres, half sizes and xyzw quaternions of the xyz part of Gaussians.

    The xyz marginal of a Gaussian is its leading 3x3 block; its eigenvectors are
    the ellipsoid axes and ``n_sigma * sqrt(eigenvalue)`` the half lengths.

    Parameters
    ----------
    means : (K, D) with D >= 3
    covariances : (K, D, D)
    n_sigma : float

    Returns
    -------
    centers : (K, 3)
    half_sizes : (K, 3)
    quaternions : (K, 4) as x, y, z, w
    """
    from scipy.spatial.transform import Rotation

    means = np.asarray(means, dtype=np.float64)
    cov3 = np.asarray(covariances, dtype=np.float64)[:, :3, :3]
    if len(cov3) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 4))
    evals, evecs = np.linalg.eigh(cov3)
    # Rotation.from_matrix needs a proper rotation: flip an axis where the
    # eigenbasis is left-handed (the ellipsoid is symmetric, so this is free).
    det = np.linalg.det(evecs)
    evecs[det < 0, :, 2] *= -1
    quats = Rotation.from_matrix(evecs).as_quat()  # scipy: x, y, z, w
    half = n_sigma * np.sqrt(np.maximum(evals, 0))
    return means[:, :3].copy(), half, quats


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (V, 3); rerun shades meshes only when given."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, f[:, k], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


# --------------------------------------------------------------------------- processes
def rerun_executable() -> str:
    """Path of the ``rerun`` binary that ships with the installed rerun-sdk."""
    env = os.environ.get("RERUN_CLI_PATH")
    if env:
        if not Path(env).is_file():
            raise RerunError(f"RERUN_CLI_PATH points to '{env}', which is not a file; unset it "
                             "to use the rerun executable of rerun-sdk.")
        return env
    try:
        import rerun_cli

        exe = Path(rerun_cli.__file__).parent / "rerun"
        if exe.exists():
            return str(exe)
    except ImportError:
        pass
    exe = shutil.which("rerun") or str(Path(sys.executable).parent / "rerun")
    if not Path(exe).exists():
        raise RerunError("Expected the 'rerun' executable of rerun-sdk, found none on PATH or "
                         "next to Python; reinstall rerun-sdk or set RERUN_CLI_PATH.")
    return exe


def _free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def _wait_for_port(port: int, proc: subprocess.Popen, timeout: float) -> None:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if proc.poll() is not None:
            raise RerunError(f"rerun exited with code {proc.returncode} before listening on "
                             f"127.0.0.1:{port}; run 'rerun --help' to check the install.")
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.1)
    raise RerunError(f"rerun did not listen on 127.0.0.1:{port} within {timeout:.0f} s; "
                     "the machine may be overloaded, retry or use --rrd.")


def _viewer_env() -> dict:
    """Environment for a viewer process: winit/wgpu want a private XDG_RUNTIME_DIR."""
    env = dict(os.environ)
    xdg = env.get("XDG_RUNTIME_DIR")
    if not xdg or not os.path.isdir(xdg):
        env["XDG_RUNTIME_DIR"] = tempfile.mkdtemp(prefix="gmmgp-xdg-")
    return env


def start_local_server(port: int | None = None, *, viewer: bool = False,
                       timeout: float = 20.0) -> tuple[str, subprocess.Popen]:
    """Start ``rerun`` listening for gRPC on 127.0.0.1 only.

    Parameters
    ----------
    port : int, optional
        Defaults to a free port.
    viewer : bool
        False: a headless gRPC proxy (``--serve-grpc``) that buffers the recording
        for viewers connecting later (``rerun --connect URL``); True: a native viewer.
    timeout : float
        Seconds to wait for the port to open.

    Returns
    -------
    url : str
        ``rerun+http://127.0.0.1:PORT/proxy``
    process : subprocess.Popen
        Detached from this process's session so it outlives the run; stop it with
        ``kill PID``.
    """
    port = _free_port() if port is None else int(port)
    cmd = [rerun_executable(), "--bind", "127.0.0.1", "--port", str(port)]
    cmd += ["--expect-data-soon"] if viewer else ["--serve-grpc"]
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, env=_viewer_env(),
                            start_new_session=True)
    _wait_for_port(port, proc, timeout)
    return f"rerun+http://127.0.0.1:{port}/proxy", proc


# --------------------------------------------------------------------------- observer
def _fmt(v) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


class RerunObserver:
    """Pipeline observer that logs each stage to rerun.

    Parameters
    ----------
    rrd : path, optional
        Write the recording to this file (flushed after every stage).
    spawn : bool
        Start a native viewer bound to 127.0.0.1 and stream to it.
    serve : bool
        Start a gRPC proxy bound to 127.0.0.1 that keeps the recording for viewers
        (``rerun --connect URL``); its URL and pid are printed on stderr.
    application_id : str
    config : MappingConfig, optional
        Logged as a Markdown document; its ``gp.d_m`` scales the GMR error colours.
    recording_id : str, optional
    blueprint : rerun blueprint, optional
        Defaults to :func:`default_blueprint`.
    timelines : dict, optional
        Extra sequence timelines set on everything logged (``{"sweep": 3}``);
        change them later through :attr:`extra_time`.
    """

    def __init__(self, rrd=None, *, spawn: bool = False, serve: bool = False,
                 application_id: str = "gmmgp", config=None, recording_id=None,
                 blueprint=None, timelines: dict | None = None):
        import rerun as rr

        self.rr = rr
        self.rec = rr.RecordingStream(application_id, recording_id=recording_id)
        # Only our own timelines: log_time/log_tick would add two clutter timelines.
        self.rec.set_log_time_enabled(False)
        self.rec.set_log_tick_enabled(False)
        self.blueprint = default_blueprint() if blueprint is None else blueprint
        # the default layout gets a camera on the scan once it is known (_log_scan)
        self._frame_views = blueprint is None
        self.path = Path(rrd) if rrd else None
        self.processes: list = []
        self.urls: list = []
        sinks = []
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(str(self.path)))
        for wanted, as_viewer in ((spawn, True), (serve, False)):
            if wanted:
                url, proc = start_local_server(viewer=as_viewer)
                self.processes.append(proc)
                self.urls.append(url)
                sinks.append(rr.GrpcSink(url))
                what = "viewer" if as_viewer else "server"
                print(f"rerun: {what} on {url} (127.0.0.1 only; pid {proc.pid}; "
                      f"connect with 'rerun --connect {url}')", file=sys.stderr)
        if sinks:
            self.rec.set_sinks(*sinks, default_blueprint=self.blueprint)
        self.config = config
        self.step = 0
        self.extra_time: dict = dict(timelines or {})
        self.summary: dict = {"seconds": {}, "counts": {}}
        self._styled: set = set()
        if config is not None:
            self.log_config(config)
            self.flush()

    # -------------------------------------------------------------- helpers
    def set_time(self, *, stage: int | None = None, **timelines) -> None:
        """Set the time of what is logged next: ``stage`` plus :attr:`extra_time`.

        Passing ``stage=None`` with a ``level`` logs on the ``level`` (and extra)
        timelines only, so HGMM levels do not pile up on the stage timeline.
        """
        self.rec.reset_time()
        for k, v in {**self.extra_time, **timelines}.items():
            self.rec.set_time(k, sequence=int(v))
        if stage is not None:
            self.rec.set_time("stage", sequence=int(stage))

    def log(self, path: str, archetype, static: bool = False) -> None:
        self.rec.log(path, archetype, static=static)

    def flush(self) -> None:
        """Write everything logged so far to the sinks (blocks until done)."""
        self.rec.flush()

    def close(self) -> None:
        """Flush and detach the sinks; the file gets its footer. Servers keep running."""
        self.flush()
        self.rec.disconnect()

    def log_config(self, config, auto: dict | None = None) -> None:
        """The configuration as Markdown; ``auto`` (the map summary's ``"auto"`` record)
        adds a table of the values chosen from the scan and the reason for each."""
        md = "# Resolved configuration\n\n"
        rows = {k: v for k, v in (auto or {}).items()
                if isinstance(v, dict) and "value" in v and v.get("auto", True)}
        if rows:
            md += "## Chosen from the scan\n\n| field | value | reason |\n|---|---:|---|\n"
            md += "".join(f"| {k} | {_fmt(v['value'])} | {v.get('reason', '')} |\n"
                          for k, v in rows.items())
            md += "\n"
        if isinstance((auto or {}).get("fallback"), str):
            md += f"Automatic values: {auto['fallback']}\n\n"
        md += "```toml\n" + config.to_toml() + "```\n"
        self.log("config", self.rr.TextDocument(md, media_type="text/markdown"), static=True)

    def on_config(self, config, auto: dict) -> None:
        """The configuration the run resolved (every ``"auto"`` replaced by its value):
        it replaces the one given at construction in the config panel and in the
        colour scales."""
        self.config = config
        self.log_config(config, auto)
        self.flush()

    def scalar(self, path: str, value) -> None:
        """One value on a time series; points, since most series have a few values."""
        if path not in self._styled:
            self._styled.add(path)
            name = path.rsplit("/", 1)[-1]
            self.log(path, self.rr.SeriesPoints(marker_sizes=[4.0], names=[name]), static=True)
        self.log(path, self.rr.Scalars([float(value)]))

    def count(self, name: str, value) -> None:
        self.summary["counts"][name] = int(value)
        self.scalar(f"metrics/counts/{name}", int(value))

    def _log_summary(self) -> None:
        lines = ["# Run summary", "", "| stage | seconds |", "|---|---:|"]
        lines += [f"| {k} | {v:.3f} |" for k, v in self.summary["seconds"].items()]
        lines += ["", "| count | value |", "|---|---:|"]
        lines += [f"| {k} | {v:,} |" for k, v in self.summary["counts"].items()]
        self.log("summary", self.rr.TextDocument("\n".join(lines) + "\n",
                                                 media_type="text/markdown"))

    # -------------------------------------------------------------- observer API
    def on_stage_start(self, name: str) -> None:
        pass

    def on_stage(self, name: str, payload) -> None:
        """Log one stage's result at ``stage = index``, then flush the recording."""
        self.step = STAGE_ORDER.index(name) if name in STAGE_ORDER else self.step + 1
        self.set_time(stage=self.step)
        handler = getattr(self, f"_log_{name}", None)
        if handler is not None:
            handler(payload.result, payload.extra)
            self.set_time(stage=self.step)  # handlers may have moved the time
        seconds = float(getattr(payload, "seconds", 0.0) or 0.0)
        if name != "scan":
            self.summary["seconds"][name] = seconds
            self.scalar(f"metrics/seconds/{name}", seconds)
        self._log_summary()
        self.flush()

    # -------------------------------------------------------------- stages
    def _log_scan(self, scan, extra) -> None:
        rr = self.rr
        pts = scan.points
        up = as_up_axis(getattr(scan, "up", None))
        # the views' up axis and default eye follow the scan's (y for a Stanford set)
        self.log("world", view_coordinates(up), static=True)
        if scan.labels is not None:
            self.log("world/scan", rr.Points3D(pts, class_ids=scan.labels.astype(np.uint16),
                                               radii=-1.0))
        else:
            h = pts @ up                                  # height along the up axis
            t = (h - h.min()) / max(float(np.ptp(h)), 1e-9) if len(h) else h
            self.log("world/scan", rr.Points3D(pts, colors=_colormap(t, "turbo"), radii=-1.0))
        self.count("scan_points", len(pts))
        if self._frame_views and len(pts):
            self._frame_views = False
            self.blueprint = default_blueprint(eye=scan_eye(pts, scan.origins, up=up), up=up)
            self.rec.send_blueprint(self.blueprint)

    def _log_prepare(self, data, extra) -> None:
        rr = self.rr
        hit = data.kinds == 0
        self.log("world/prepare/hits", rr.Points3D(data.rows[hit, :3], colors=[200, 200, 200],
                                                   radii=-1.0))
        v = ~hit
        t = (data.rows[v, 3] + data.spacing) / (2 * data.spacing)
        self.log("world/prepare/virtual", rr.Points3D(data.rows[v, :3],
                                                      colors=_colormap(t, "coolwarm"),
                                                      radii=-1.0))
        self.count("training_rows", len(data.rows))
        self.count("hit_points", int(hit.sum()))

    def _log_hgmm(self, hgmm, extra) -> None:
        rr = self.rr
        for k, lv in enumerate(hgmm.levels):
            # Level k lives on the 'level' timeline only; the previous level is
            # cleared there so that scrubbing shows one level at a time.
            self.set_time(level=k)
            if k > 0:
                self.log(f"world/hgmm/level_{k - 1}", rr.Clear(recursive=True))
            gm = lv.mixture
            c, h, q = ellipsoid_params(gm.means, gm.covariances)
            split = np.asarray(lv.split, dtype=bool)
            colors = _colormap(np.sqrt(np.asarray(lv.complexity) / C_MAX), "plasma")
            labels = np.array([f"L{k}#{i} c={ci:.4f} rows={n}{' split' if s else ''}"
                               for i, (ci, s, n) in enumerate(zip(lv.complexity, split,
                                                                  lv.n_rows))])
            for tag, sel, fill in (("split", split, rr.components.FillMode.MajorWireframe),
                                   ("leaf", ~split, rr.components.FillMode.Solid)):
                if sel.any():
                    self.log(f"world/hgmm/level_{k}/{tag}", rr.Ellipsoids3D(
                        centers=c[sel], half_sizes=h[sel], quaternions=q[sel],
                        colors=colors[sel], labels=labels[sel].tolist(), show_labels=False,
                        fill_mode=fill))
            self.scalar("metrics/hgmm/nodes_per_level", gm.n_components)
            self.scalar("metrics/hgmm/split_per_level", int(split.sum()))
        self.set_time(stage=self.step)
        from ..pipeline import complexity

        leaves = hgmm.leaves
        c, h, q = ellipsoid_params(leaves.means, leaves.covariances)
        cl = complexity(leaves.covariances, normalize=self._normalized_c())
        self.log("world/hgmm/leaves", rr.Ellipsoids3D(
            centers=c, half_sizes=h, quaternions=q,
            colors=_colormap(np.sqrt(cl / C_MAX), "plasma"),
            fill_mode=rr.components.FillMode.Solid))
        self.count("hgmm_levels", len(hgmm.levels))
        self.count("hgmm_leaves", leaves.n_components)

    def _normalized_c(self) -> bool:
        cfg = self.config
        return cfg is None or cfg.hgmm.complexity_metric == "correlation"

    def _d_m(self) -> float:
        d_m = self.config.gp.d_m if self.config is not None else None
        # an unresolved "auto" (no on_config yet): the paper's value for the colour scale
        return float(d_m) if isinstance(d_m, (int, float)) else 0.02

    def _log_gmr(self, m_hits, extra) -> None:
        rr = self.rr
        err = np.abs(np.asarray(extra.get("error", m_hits), dtype=np.float64))
        pts = extra["points"]
        hi = ERROR_SATURATION_DM * max(self._d_m(), 1e-6)
        self.log("world/gmr/error", rr.Points3D(pts, colors=_colormap(err / hi, "RdYlGn_r"),
                                                radii=-1.0))
        self.log("world/gmr/error", rr.AnyValues(error=err.astype(np.float32)))
        rms = float(np.sqrt(np.mean(err ** 2))) if len(err) else 0.0
        self.scalar("metrics/gmr_rms_error_at_hits", rms)
        self.count("gmr_over_d_m", int(np.count_nonzero(err > self._d_m())))

    def _log_gp(self, gp, extra) -> None:
        rr = self.rr
        pts = extra.get("points", getattr(gp, "gp_points", np.zeros((0, 3))))
        self.log("world/gp/points", rr.Points3D(pts, colors=[230, 40, 40], radii=-1.5))
        grid = getattr(gp, "grid", None)
        if grid is not None and grid.n_blocks:
            centres = grid.centres
            blocks = getattr(gp, "blocks", [])
            # fit_local_gps fits one block per occupied leaf, in grid order.
            if len(blocks) == grid.n_blocks:
                n = np.array([len(b.X) for b in blocks], dtype=np.float64)
                rgb = _colormap(n / max(n.max(), 1.0), "YlOrRd")
                # Translucent edges: the blocks frame the GP points, not hide them.
                colors = np.column_stack([rgb, np.full(len(rgb), 90, dtype=np.uint8)])
                labels = [f"{int(v)} pts" for v in n]
            else:
                colors, labels = [255, 160, 0, 90], None
            self.log("world/gp/blocks", rr.Boxes3D(
                centers=centres, half_sizes=np.full_like(centres, grid.block_size / 2),
                colors=colors, labels=labels, show_labels=False, radii=-0.75,
                fill_mode=rr.components.FillMode.MajorWireframe))
            self.count("gp_blocks", grid.n_blocks)
        self.count("gp_points", len(pts))

    def _log_surface(self, meshes, extra) -> None:
        """``meshes``: dict method -> SurfaceMesh, all on one std colour scale."""
        from ..pipeline import std_colour_max, variance_colors

        rr = self.rr
        vmax = std_colour_max(meshes.values())
        for method, mesh in meshes.items():
            self.count(f"vertices_{method}", len(mesh.vertices))
            if len(mesh.faces) == 0:
                self.log(f"world/surface/{method}", rr.Clear(recursive=False))
                continue
            self.log(f"world/surface/{method}", rr.Mesh3D(
                vertex_positions=mesh.vertices.astype(np.float32),
                triangle_indices=mesh.faces.astype(np.uint32),
                vertex_normals=_vertex_normals(mesh.vertices, mesh.faces).astype(np.float32),
                vertex_colors=variance_colors(mesh.vertex_variance, vmax)))
            self.log(f"world/surface/{method}",
                     rr.AnyValues(vertex_variance=mesh.vertex_variance.astype(np.float32)))
        if vmax is not None:
            self.scalar("metrics/surface_std_colour_max", vmax)


# --------------------------------------------------------------------------- blueprint
def view_coordinates(up=None):
    """rerun's ``ViewCoordinates`` of a right-handed frame whose up axis is ``up``
    (+-x, +-y or +-z; default z): logged at ``world``, the 3D views' eye, navigation
    and grid stand on it (``RIGHT_HAND_Y_UP`` for a Stanford set)."""
    import rerun as rr

    u = as_up_axis(up)
    axis = "XYZ"[int(np.flatnonzero(u)[0])]
    return getattr(rr.ViewCoordinates, f"RIGHT_HAND_{axis}_{'UP' if u.sum() > 0 else 'DOWN'}")


def scan_eye(points, origins=None, up=None) -> tuple:
    """A camera (position, look target) that shows a scan from its sensor's side.

    Looks at the middle of the bounding box from the side where the sensor origins
    lie on average (a street scan is seen from the street, not from behind its
    facades), from 0.6 box diagonals away and 0.25 diagonals up. ``up`` (3,),
    optional: the scan's up axis (default z); "side" and "up" are taken in the frame
    whose z is ``up`` (without origins: from that frame's -y).
    """
    R = up_frame(up)                                  # data -> a frame whose z is up
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3) @ R.T
    lo, hi = pts.min(0), pts.max(0)
    target = 0.5 * (lo + hi)
    diag = max(float(np.linalg.norm(hi - lo)), 1e-3)
    side = np.array([0.0, -1.0])
    if origins is not None and len(origins):
        v = (np.asarray(origins, dtype=np.float64).reshape(-1, 3) @ R.T).mean(0)[:2] - target[:2]
        if np.linalg.norm(v) > 1e-6 * diag:
            side = v / np.linalg.norm(v)
    position = target + np.r_[0.6 * diag * side, 0.25 * diag]
    return R.T @ position, R.T @ target


def default_blueprint(timeline: str = "stage", sweep: bool = False, eye=None, up=None):
    """One 3D view per stage group, metrics, summary and config; time on ``timeline``.

    Parameters
    ----------
    timeline : str
        Timeline the time panel opens on (``stage``, or ``sweep`` for sweeps).
    sweep : bool
        Add the sweep metrics (``sweep/**``) and the sweep table as first tabs.
    eye : (position, look target), optional
        Same camera for every 3D view, e.g. :func:`scan_eye`.
    up : (3,), optional
        The camera's up vector with ``eye`` (the scan's up axis; default z).
    """
    import rerun.blueprint as rrb

    def view3d(name, contents):
        kw = {}
        if eye is not None:
            kw["eye_controls"] = rrb.EyeControls3D(position=eye[0], look_target=eye[1],
                                                   eye_up=as_up_axis(up).tolist())
        return rrb.Spatial3DView(name=name, origin="world", contents=contents, **kw)

    side = []
    if sweep:
        side += [rrb.TimeSeriesView(name="Sweep metrics", origin="sweep/metrics"),
                 rrb.TextDocumentView(name="Sweep table", origin="sweep/table")]
    side += [
        rrb.TimeSeriesView(name="Seconds per stage", origin="metrics/seconds"),
        rrb.TimeSeriesView(name="Counts", origin="metrics/counts"),
        rrb.TextDocumentView(name="Summary", origin="summary"),
        rrb.TextDocumentView(name="Config", origin="config"),
    ]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Grid(
                view3d("Scan and training rows", ["+ world/scan", "+ world/prepare/**"]),
                view3d("HGMM leaves (time panel 'level': levels)", ["+ world/hgmm/**"]),
                view3d("GMR error |m(x)| and GP points/blocks",
                       ["+ world/gmr/**", "+ world/gp/**"]),
                rrb.Tabs(
                    view3d("Surface of the map (colour: predicted std)",
                           ["+ world/surface/**", "- world/surface/hgmm"]),
                    view3d("Surface of the HGMM prior alone", ["+ world/surface/hgmm"]),
                ),
            ),
            rrb.Vertical(
                rrb.Tabs(*side[:len(side) - 2]),
                rrb.Tabs(*side[len(side) - 2:]),
            ),
            column_shares=[3, 1],
        ),
        rrb.TimePanel(timeline=timeline, state="collapsed"),
        rrb.BlueprintPanel(state="hidden"),
        rrb.SelectionPanel(state="hidden"),
    )


# --------------------------------------------------------------------------- screenshots
def screenshot(rrd, png, *, window_size: tuple = (1600, 900), settle: float = 2.0,
               timeout: float = 120.0, timeline: str | None = None,
               sequence: int | None = None) -> Path:
    """Render a recording headless and save a PNG of the whole viewer.

    Unlike ``rerun FILE --headless --screenshot-to PNG`` (which shoots the first
    frames, before the views have received their data), this starts a headless
    viewer on 127.0.0.1, waits until it reports nothing left to load, optionally
    moves the time cursor, and then asks for the screenshot.

    Parameters
    ----------
    rrd, png : path
    window_size : (width, height) in logical points
    settle : float
        Seconds to let the views draw after loading.
    timeout : float
    timeline, sequence : optional
        Time cursor to show (defaults to the end of the blueprint's timeline).

    Returns
    -------
    Path of the PNG.
    """
    from rerun.experimental import ViewerClient

    rrd, png = Path(rrd).resolve(), Path(png).resolve()
    if not rrd.is_file():
        raise FileNotFoundError(2, "No such recording", str(rrd))
    png.parent.mkdir(parents=True, exist_ok=True)
    port = _free_port()
    cmd = [rerun_executable(), "--headless", "--window-size",
           f"{int(window_size[0])}x{int(window_size[1])}", "--bind", "127.0.0.1",
           "--port", str(port), "--hide-welcome-screen", str(rrd)]
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, env=_viewer_env())
    try:
        _wait_for_port(port, proc, timeout=min(timeout, 60.0))
        client = ViewerClient(f"rerun+http://127.0.0.1:{port}/proxy")
        t_end = time.monotonic() + timeout
        while True:
            st = client.get_state()
            if not st.loading and st.recordings and any(r.timelines for r in st.recordings):
                break
            if time.monotonic() > t_end:
                raise RerunError(f"The headless viewer did not finish loading '{rrd}' within "
                                 f"{timeout:.0f} s; raise the timeout.")
            time.sleep(0.3)
        if timeline is not None:
            if sequence is None:
                client.set_time(timeline, play_state="paused")
            else:
                client.set_time(timeline, sequence=int(sequence), play_state="paused")
        time.sleep(settle)
        client.save_screenshot(str(png))
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    if not png.is_file():
        raise RerunError(f"The headless viewer wrote no screenshot to '{png}'.")
    return png


def repair_recording(src, dst) -> Path:
    """Rewrite a recording cut short (killed run, no footer) into a complete file.

    The stages logged before the interruption load as they are in the viewer and in
    ``rerun.chunk.RrdReader(src).stream()``; ``rerun rrd verify`` wants the footer
    that only a finished run writes, which ``rerun rrd merge`` adds.
    """
    dst = Path(dst)
    res = subprocess.run([rerun_executable(), "rrd", "merge", str(src), "-o", str(dst)], check=False,
                         stdin=subprocess.DEVNULL, capture_output=True, text=True)
    if res.returncode != 0 or not dst.is_file():
        tail = (res.stderr.strip().splitlines() or ["no output"])[-1]
        raise RerunError(f"Could not repair recording '{src}' (rerun rrd merge: {tail}); "
                         "the file may hold no complete chunk.")
    return dst
