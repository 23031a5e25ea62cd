"""The model of the desktop app: stage results and partial re-runs, without any GUI.

The app (:mod:`gmmgp_app.viz.gui`) keeps one :class:`ViewerModel`. Its
:meth:`ViewerModel.compute` runs the pipeline from a given stage on, in a worker
thread, reusing the results of the stages before it; it never touches a widget
and reports each finished stage through a callback, so the controller can hand
the result to the main thread (and drop it if a newer run has started).

The stages themselves are run by :func:`gmmgp_app.pipeline.run_stages` on the
pipeline's recipe (the same code as ``build_map``); this model only keeps their
results. Which stages a setting invalidates (:func:`first_affected_stage`)::

    hgmm (or gmr) settings -> hgmm, gmr, gp, surface
    gp settings, e.g. d_m  -> gp, surface
    surface voxel size     -> surface
"""

from __future__ import annotations

import dataclasses
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from . import STAGES   # the stages the app shows (in the light package: the CLI's parser)
from ..config import MappingConfig
from ..types import HierarchicalGMM, Scan, SurfaceMesh, TrainingSet

__all__ = ["STAGES", "STAGE_LABELS", "ViewerError", "StageResults",
           "ViewerModel", "first_affected_stage", "wait_for_frame", "FRAME_WAIT_S",
           "ProgressThrottle"]

STAGE_LABELS = {"scan": "Scan", "prepare": "Prepared rows", "hgmm": "HGMM",
                "gmr": "GMR error", "gp": "GP points", "surface": "Surface"}
#: The pipeline stages behind each shown stage (gmmgp recipe, then the map and its mesh).
_PIPELINE_STAGES = {"prepare": ("prepare",), "hgmm": ("hgmm",), "gmr": ("gmr",),
                    "gp": ("select", "far", "gp_hyper", "gp", "map"),
                    "surface": ("surface",)}


class ViewerError(ValueError):
    """The viewer cannot open its target or cannot do what was asked."""


class Cancelled(Exception):
    """A computation was abandoned because a newer one superseded it."""


@dataclass(frozen=True)
class StageResults:
    """Everything the app shows; replaced as a whole, never mutated (thread safety).

    Attributes
    ----------
    config : MappingConfig
        The settings these results were computed with.
    voxel_size : float
        Marching-cubes voxel of ``mesh`` (m).
    scan : Scan or None
        Input points (for a loaded map: the map's surface seed points).
    data : TrainingSet or None
    hgmm : HierarchicalGMM or None
    prior : object or None
        The GMR field (``predict(xyz) -> mean, var``).
    gmr_error : (H,) float64 or None
        m(x) at the hit points ``data.points`` (the GMR's error there, true SDF is 0).
    gp_points : (P, 3) float64 or None
    gp : LocalGPField or None
    smap : SurfaceMap or None
        The map of these results (predicts the SDF, saves).
    mesh : SurfaceMesh or None
    seconds : dict
        Wall time per stage.
    tiles : TiledView or None
        A tiled map's tiles loaded so far (:mod:`.gui_targets`); ``smap`` is the
        TiledMap and the fields above hold the loaded tiles merged.
    check : CheckView or None
        A ``gmmgp check`` result: ``scan`` holds its points.
    summary : dict
        The run's summary (``summary.json`` of a run folder, or the pipeline's
        summary of the app's last run); ``summary["auto"]`` when present lists
        settings resolved from the scan (name -> {value, reason}).
    """

    config: MappingConfig
    voxel_size: float
    scan: Optional[Scan] = None
    data: Optional[TrainingSet] = None
    hgmm: Optional[HierarchicalGMM] = None
    prior: object = None
    gmr_error: Optional[np.ndarray] = None
    gp_points: Optional[np.ndarray] = None
    gp: object = None
    smap: object = None
    mesh: Optional[SurfaceMesh] = None
    seconds: dict = field(default_factory=dict)
    tiles: object = None
    check: object = None
    summary: dict = field(default_factory=dict)

    def has(self, stage: str) -> bool:
        """Whether ``stage`` has a result to show."""
        return {"scan": self.scan is not None, "prepare": self.data is not None,
                "hgmm": self.hgmm is not None, "gmr": self.gmr_error is not None,
                "gp": self.gp_points is not None, "surface": self.mesh is not None}[stage]

    def counts(self) -> dict:
        """Counts shown in the panel (and written by the app's ``state`` script step)."""
        c = {}
        if self.scan is not None:
            c["scan_points"] = len(self.scan)
        if self.data is not None:
            c["training_rows"] = len(self.data.rows)
        if self.hgmm is not None:
            c["levels"] = len(self.hgmm.levels)
            c["leaves"] = int(self.hgmm.leaves.n_components)
        if self.gmr_error is not None:
            c["gmr_rms_error"] = float(np.sqrt(np.mean(self.gmr_error ** 2)))
        if self.gp_points is not None:
            c["gp_points"] = len(self.gp_points)
        if self.gp is not None:
            c["gp_blocks"] = int(self.gp.grid.n_blocks)
        if self.mesh is not None:
            c["vertices"] = len(self.mesh.vertices)
            c["faces"] = len(self.mesh.faces)
        if self.tiles is not None:
            c["tiles_loaded"] = len(self.tiles.pieces)
            c["tiles"] = len(self.tiles.keys)
        if self.check is not None:
            c["changed"] = int(self.check.changed.sum())
            c["segments"] = len(self.check.segments)
        return c


def first_affected_stage(old: StageResults, cfg: MappingConfig, voxel_size: float) -> Optional[str]:
    """First stage whose result the new settings change, or None if nothing changed.

    Parameters
    ----------
    old : StageResults
        What is shown now.
    cfg : MappingConfig
        The requested settings.
    voxel_size : float
        The requested surface voxel (m).
    """
    if old.config.hgmm != cfg.hgmm or old.config.gmr != cfg.gmr:
        return "hgmm"
    if old.config.gp != cfg.gp:
        return "gp"
    if old.mesh is None or abs(old.voxel_size - voxel_size) > 1e-12 \
            or old.config.surface != cfg.surface:
        return "surface"
    return None


class ViewerModel:
    """Holds the current results and computes new ones (no GUI).

    Parameters
    ----------
    results : StageResults
    source : str
        What was opened (shown in the title).
    """

    def __init__(self, results: StageResults, source: str = ""):
        self.results = results
        self.source = source
        #: "scan", "map", "run", "tiled" or "check": what was opened
        self.kind = "scan" if results.smap is None else "map"
        self.mesh_file: Optional[str] = None
        #: HGMM node fits kept between runs (pipeline.HGMMFitCache): after a split-
        #: threshold change only the nodes never split before are fitted
        self.hgmm_cache = None
        self._cache_lock = threading.Lock()
        self._resolved = None   # (scan, what the resolution depends on, cfg, record)
        #: (3,) the data's up axis (``Scan.up``, or the one a map was saved with): the
        #: default view's up, the scan's height colours and the compare copy's side
        self.up = np.array([0.0, 0.0, 1.0]) if results.scan is None else results.scan.up

    # ------------------------------------------------------------------ opening
    @classmethod
    def open(cls, target, cfg: Optional[MappingConfig] = None,
             voxel_size: float = 0.1) -> "ViewerModel":
        """Open a scan file, a saved map folder, a ``gmmgp run`` output folder (single
        or tiled map), a tiled map folder, a ``gmmgp check`` output folder or a folder
        of scans (what ``read_scan`` reads: a Stanford set, a KITTI sequence, ...).

        A scan opens with no results beyond the scan itself; call :meth:`compute`
        from "prepare". A map opens with its hierarchy, GP and field, and a run
        folder also with the mesh the run wrote (else only the surface is left to
        compute). A tiled map opens with no tile loaded (:meth:`load_tiles`). A
        check result opens with its points, their z and the change segments.
        """
        from . import gui_targets as T

        path = Path(target)
        if not path.exists():
            raise ViewerError(f"'{path}' does not exist; give a scan file, a map or run "
                              "folder ('gmmgp run SCAN --out DIR') or a check folder "
                              "('gmmgp check ... --out DIR').")
        if path.is_dir() and T.is_result_folder(path):
            try:
                return cls._open_folder(path, voxel_size)
            except T.TargetError as e:
                raise ViewerError(str(e)) from None
        from ..datasets import read_scan

        if path.is_dir():
            from ..datasets import ScanReadError

            try:
                scan = read_scan(path)
            except ScanReadError as e:
                raise ViewerError(
                    f"'{path}' is no map, run or check folder (no map.json, summary.json, "
                    f"tiled.json or check.json in it) and no folder of scans: {e}") from None
        else:
            scan = read_scan(path)
        cfg = MappingConfig() if cfg is None else cfg
        m = cls(StageResults(config=cfg, voxel_size=voxel_size, scan=scan),
                source=str(path))
        m.kind = "scan"
        return m

    @classmethod
    def _open_folder(cls, path: Path, voxel_size: float) -> "ViewerModel":
        from ..pipeline import load_map
        from ..tiling import load_tiled_map
        from . import gui_targets as T

        if T.is_check_folder(path):
            scan, check = T.read_check(path)
            cfg = MappingConfig()
            res = StageResults(config=cfg, voxel_size=voxel_size, scan=scan, check=check,
                               summary=check.summary)
            m = cls(res, source=str(path))
            m.kind = "check"
            return m
        run_dir = path.parent if path.name == "map" else path
        summary = T.read_summary(run_dir)
        tdir = T.tiled_map_dir(path)
        if tdir is not None:
            tmap = load_tiled_map(tdir, cache_tiles=9, load_points=False)  # a 3x3 neighbourhood
            summary = summary or dict(tmap.summary)
            res = StageResults(config=tmap.config, voxel_size=voxel_size,
                               smap=tmap, tiles=T.TiledView(tmap), summary=summary)
            m = cls(res, source=str(tdir))
            m.kind = "tiled"
            m.up = tmap.up                 # no scan in a tiled view's results
            return m
        mapdir = path / "map" if (path / "map" / "map.json").is_file() else path
        smap = load_map(mapdir)
        gp_pts = smap.gp_points if smap.gp is not None else None
        mesh = T.read_run_mesh(run_dir, smap.method, smap.offset)
        res = StageResults(config=smap.config, voxel_size=voxel_size,
                           scan=Scan(smap.seed_points, offset=smap.offset,
                                     source=f"{mapdir} (surface seeds)", up=smap.up),
                           hgmm=smap.hgmm, prior=smap.prior, gp_points=gp_pts,
                           gp=smap.gp, smap=smap, mesh=mesh,
                           summary=summary or dict(smap.summary))
        m = cls(res, source=str(mapdir))
        m.kind = "run" if mesh is not None or summary else "map"
        m.mesh_file = str(run_dir / f"mesh_{smap.method}.ply") if mesh is not None else None
        return m

    # ------------------------------------------------------------------ tiled maps
    def load_tiles(self, xy=None, radius: Optional[float] = None, voxel_size=None,
                   progress=None) -> StageResults:
        """Load the tiles of a tiled map within ``radius`` of ``xy`` (default: all),
        and return the results with every loaded tile merged (not assigned: the caller
        swaps them in, so a worker thread can call this).

        Parameters
        ----------
        xy : (2,) local-frame x, y, optional
        radius : float, optional (m)
        voxel_size : float, optional
            Marching-cubes voxel of the tiles' surface pieces (default: the results').
        progress : callable(done, total), optional
        """
        r = self.results
        tv = r.tiles
        if tv is None:
            raise ViewerError(f"'{self.source}' is not a tiled map; tiles load only in a "
                              "map written with 'gmmgp run SCAN --out DIR --tile-size S'.")
        keys = tv.keys if xy is None or radius is None else tv.keys_near(xy, radius)
        tv.load(keys, r.voxel_size if voxel_size is None else voxel_size, progress=progress)
        merged = tv.merged()
        return dataclasses.replace(r, **merged, prior=None, gp=None)

    @property
    def can_refit(self) -> bool:
        """Whether the HGMM and GP can be re-fitted (needs the scan, not a loaded map)."""
        r = self.results
        if r.tiles is not None or r.check is not None:
            return False
        return r.data is not None or (r.smap is None and r.scan is not None)

    # ------------------------------------------------------------------ compute
    def compute(self, start: str, cfg: MappingConfig, voxel_size: float,
                base: Optional[StageResults] = None,
                on_stage: Optional[Callable[[str, StageResults], None]] = None,
                cancelled: Callable[[], bool] = lambda: False,
                progress: Optional[Callable[[str, float], None]] = None) -> StageResults:
        """Recompute the stages from ``start`` on; safe to call from a worker thread.

        Parameters
        ----------
        start : {"prepare", "hgmm", "gmr", "gp", "surface"}
        cfg : MappingConfig
        voxel_size : float
            Marching-cubes voxel (m).
        base : StageResults, optional
            Results to reuse for the stages before ``start`` (default: current).
        on_stage : callable(name, StageResults), optional
            Called after each stage with the results so far.
        cancelled : callable() -> bool
            Polled between stages; when True the run stops with :class:`Cancelled`.
        progress : callable(stage, fraction), optional
            Fraction of the marching-cubes blocks done (surface stage).

        Returns
        -------
        StageResults
        """
        from ..pipeline import RunContext, auto_fields, run_stages, scan_tree

        r = self.results if base is None else base
        if start not in STAGES[1:]:
            raise ViewerError(f"Cannot start a run at stage {start!r}; expected one of "
                              f"{', '.join(STAGES[1:])}.")
        if STAGES.index(start) < STAGES.index("surface") and not self.can_refit:
            raise ViewerError(
                f"Re-running from '{start}' needs the scan, but '{self.source}' is a saved "
                "map; open the scan with 'gmmgp view SCAN' to tune the threshold and d_m.")
        if r.smap is None and start == "surface" and r.prior is None:
            start = "prepare"
        order = STAGES[STAGES.index(start):]
        seconds = dict(r.seconds)
        # Drop everything downstream of start so a failure never shows stale results.
        keep = {"prepare": ("data",), "hgmm": ("hgmm", "prior"), "gmr": ("gmr_error",),
                "gp": ("gp_points", "gp", "smap"), "surface": ("mesh",)}
        clear = {k: None for s in order for k in keep[s]}
        if start == "surface":
            clear.pop("smap", None)
        r = dataclasses.replace(r, config=cfg, voxel_size=voxel_size, **clear)
        # the pipeline's state from the results kept (None = not computed)
        state = {k: v for k, v in (("scan", r.scan), ("data", r.data), ("hgmm", r.hgmm),
                                   ("prior", r.prior), ("gmr_error", r.gmr_error),
                                   ("smap", r.smap)) if v is not None}
        shown = {stages[-1]: name for name, stages in _PIPELINE_STAGES.items()}
        fields = {"prepare": ("data",), "hgmm": ("hgmm",), "gmr": ("prior", "gmr_error"),
                  "gp": ("gp_points", "gp", "smap"), "surface": ("mesh",)}
        summary = {"seconds": {}, "counts": {}}
        t0 = [time.perf_counter()]

        def after(name, st):
            nonlocal r
            if name in shown:
                stage = shown[name]
                seconds[stage] = time.perf_counter() - t0[0]
                r = dataclasses.replace(r, seconds=dict(seconds),
                                        **{k: st.get(k) for k in fields[stage]})
                if on_stage is not None:
                    on_stage(stage, r)
                t0[0] = time.perf_counter()
            if cancelled():
                raise Cancelled(name)

        bar = _ProgressBar(progress) if progress is not None else None
        names = [p for s in order for p in _PIPELINE_STAGES[s]]
        # "auto" fields resolved from the scan exactly as build_map does, with one k-d
        # tree of the scan for its measurement and the prepare stage
        if r.scan is not None and "prepare" in names:
            state["tree"] = scan_tree(r.scan)
        run_cfg, record = ((cfg, {}) if r.scan is None
                           else self._resolve(cfg, r.scan, state.get("tree")))
        if cancelled():
            raise Cancelled(start)
        if record:
            summary["auto"] = record  # the values chosen from the scan, as build_map keeps them
            # ... and every result of this run carries them from its first stage on: a
            # run stopped early (the caller's ``cancelled``, e.g. a screenshot up to the
            # GP stage) hands out the on_stage results, which must say which d_m was used
            r = dataclasses.replace(r, summary={**r.summary, "auto": record})
        # one run at a time uses the node cache (a superseded run may still be fitting)
        own = "hgmm" in names and self._cache_lock.acquire(blocking=False)
        try:
            if own and self.hgmm_cache is None:
                from ..pipeline import HGMMFitCache

                self.hgmm_cache = HGMMFitCache()
            ctx = RunContext(run_cfg, "gmmgp", voxel_size=voxel_size, surface_progress=bar,
                             auto_fields=auto_fields(record),
                             hgmm_cache=self.hgmm_cache if own else None)
            run_stages(names, state, ctx, summary=summary, on_stage=after)
        finally:
            if own:
                self._cache_lock.release()
        # keep what the pipeline reported beyond timings (e.g. "auto": settings
        # resolved from the scan), over what the previous results held
        extra = {k: v for k, v in summary.items() if k not in ("seconds", "counts")}
        return dataclasses.replace(r, summary={**r.summary, **extra}) if extra else r

    def _resolve(self, cfg: MappingConfig, scan: Scan, tree=None) -> tuple:
        """``pipeline.resolve_config(cfg, scan)``, measured once per scan while the
        same fields are "auto": the resolution reads the scan, which fields are
        "auto" and a hand-set training subset (autoscale.resolve_config), not the
        other values, so after a threshold or d_m edit the fields the resolution set
        before are set again instead of measuring the scan again (0.4 s on the demo)."""
        from ..config import is_auto
        from ..pipeline import resolve_config

        autos = tuple(k for k, *_ in MappingConfig.describe() if "." in k and is_auto(
            getattr(getattr(cfg, k.partition(".")[0]), k.partition(".")[2])))
        p = cfg.prepare
        dep = (autos, None if is_auto(p.subsample_rate) else float(p.subsample_rate),
               p.subsample_voxel)
        got = self._resolved
        if got is not None and got[0] is scan and got[1] == dep:
            return (cfg.replace(got[2]) if got[2] else cfg), dict(got[3])
        run_cfg, record = resolve_config(cfg, scan, tree=tree)
        # the fields the resolution set (the "auto" ones, and a training voxel it chose)
        updates = {}
        for k, *_ in MappingConfig.describe():
            sec, _, name = k.partition(".")
            if name:
                a, b = getattr(getattr(cfg, sec), name), getattr(getattr(run_cfg, sec), name)
                if type(a) is not type(b) or a != b:
                    updates[k] = b
        self._resolved = (scan, dep, updates, dict(record))
        return run_cfg, record

    # ------------------------------------------------------------------ queries
    def probe(self, xyz, return_grad: bool = False):
        """SDF mean and standard deviation at one point (m)[, and the mean's gradient].

        Uses the final field (GP over GMR, or a tiled map's stitched field) when there
        is one, else the GMR prior.

        Returns
        -------
        (mean, std) or, with ``return_grad``, (mean, std, grad (3,) ndarray)
        """
        r = self.results
        field_ = r.smap if r.smap is not None else r.prior
        if field_ is None:
            raise ViewerError("No field to probe yet (the HGMM has not been fitted); "
                              "wait for the run to reach the HGMM stage.")
        q = np.asarray(xyz, dtype=np.float64).reshape(1, 3)
        out = field_.predict(q, return_grad=return_grad)
        mean, std = float(out[0][0]), float(np.sqrt(max(out[1][0], 0.0)))
        if return_grad:
            return mean, std, np.asarray(out[2][0], dtype=np.float64)
        return mean, std

    def save(self, directory) -> Path:
        """Save the current map (``SurfaceMap.save``) to ``directory``."""
        if self.results.smap is None:
            raise ViewerError("No map to save yet (the GP stage has not finished); wait for "
                              "the run to finish, then save.")
        return self.results.smap.save(directory)


#: Seconds a run's worker waits for the window to draw a finished stage before it computes
#: the next one (:func:`wait_for_frame`); past it the run goes on, the frame follows later.
FRAME_WAIT_S = 5.0


def wait_for_frame(drawn: threading.Event, cancelled: Callable[[], bool] = lambda: False,
                   timeout: float = FRAME_WAIT_S, poll: float = 0.05) -> str:
    """Block a run's worker until the frame showing its last stage is drawn.

    The app's controller sets ``drawn`` once the 3D view has drawn the frame after a
    stage's geometry was added (or at once when nothing is drawn). Waiting for it
    before the next stage keeps the stages from competing with that frame: on Mesa's
    CPU renderer the frame is rasterized on the same cores, and the stages' parallel
    numba kernels hold the GIL while they run, so the window's Python callbacks (layout,
    the read-back that marks the frame drawn) waited behind them; the frame showing new
    HGMM levels came seconds after the levels were in the scene. The wait is bounded:
    after ``timeout`` seconds (a frame stalled by the renderer) the run goes on.

    Parameters
    ----------
    drawn : threading.Event
    cancelled : callable() -> bool
        Polled every ``poll`` seconds; True (the run was superseded or the window
        closed) ends the wait.
    timeout : float
        Seconds.
    poll : float
        Seconds.

    Returns
    -------
    "drawn", "cancelled" or "timeout".
    """
    t_end = time.monotonic() + max(float(timeout), 0.0)
    while True:
        left = t_end - time.monotonic()
        if drawn.wait(min(poll, max(left, 0.0))):
            return "drawn"
        if cancelled():
            return "cancelled"
        if time.monotonic() >= t_end:
            return "drawn" if drawn.is_set() else "timeout"


class ProgressThrottle:
    """Pass progress reports on at most every ``interval`` seconds (and the last one).

    The surface stage reports once per block batch; each report posted to the GUI
    thread redraws the window, and each callback needs the GIL the stages hold.
    """

    def __init__(self, interval: float = 0.25, clock: Callable[[], float] = time.monotonic):
        self.interval, self.clock = float(interval), clock
        self._last: dict = {}

    def __call__(self, stage: str, frac: float) -> bool:
        """Whether the report (``stage``, ``frac`` in [0, 1]) should be shown."""
        now = self.clock()
        last = self._last.get(stage)
        if frac >= 1.0 or last is None or now - last >= self.interval:
            self._last[stage] = now
            return True
        return False


class _ProgressBar:
    """Adapts extract_surface's tqdm-like ``progress(total, desc)`` to a fraction callback."""

    def __init__(self, report):
        self.report = report

    def __call__(self, total, desc=""):
        self.total, self.done = max(int(total), 1), 0
        return self

    def update(self, n=1):
        self.done += n
        self.report("surface", min(self.done / self.total, 1.0))

    def close(self):
        pass
