"""``gmmgp view``: the desktop app (Open3D GUI) to inspect every stage and tune the map.

Layout: a 3D scene on the left, a side panel on the right with

* **Stage** selector (scan, prepared rows, HGMM, GMR error, GP points, surface) and
  an HGMM **level** slider: split nodes of that level are drawn as wireframe
  ellipsoids, nodes kept as leaves as solid ones, both coloured by c;
* **Layers**: points, ellipsoids, GP points, octree blocks, mesh, and colouring by the
  predicted standard deviation, with a colour-bar legend for the active colouring;
* **Tuning**: split threshold, d_m and surface voxel; **Run** re-computes only the
  stages a change affects (threshold: HGMM, GMR, GP, surface; d_m: GP, surface;
  voxel: surface) in a worker thread, with progress;
* **Probe**: Ctrl+click on anything in the scene to read the SDF mean +- std there;
* **Screenshot** and **Save map** buttons.

Model / view / controller as in Open3D's online-processing example: the model
(:mod:`.gui_model`) computes in worker threads and never touches a widget; results
come back to the main thread through ``post_to_main_thread`` and are dropped when a
newer run has started (a generation counter); the view is rebuilt from the current
results, then ``post_redraw``.

Automation (tests, README screenshots): ``--script steps.json`` runs a list of
steps after the first computation (:mod:`.gui_script`, which drives the app through
its public methods).
"""

from __future__ import annotations

import dataclasses
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

from .gui_model import (FRAME_WAIT_S, STAGE_LABELS, STAGES, Cancelled, ProgressThrottle,
                        StageResults, ViewerError, ViewerModel, first_affected_stage,
                        wait_for_frame)
from .gui_script import ScriptRunner, load_script
from .gui_layers import (LAYERS, STAGE_LAYERS, layer_geometry, scene_view,
                         layer_parts, materials, set_lighting)
from .gui_tuning import run_record
from . import add_view_arguments   # the app's options (gmmgp view's)
from ..config import concrete, is_auto

__all__ = ["add_view_arguments", "open_view", "ViewerApp", "ViewerError", "run_app"]


LAYER_LABELS = {"points": "Points", "ellipsoids": "Ellipsoids (HGMM level)",
                "gp_points": "GP points", "blocks": "Octree blocks", "mesh": "Surface mesh",
                "segments": "Changed segments (check)",
                "compare": "Compare: previous run beside"}
#: Tiles loaded around the view within this many tile sizes of its centre.
TILE_RADIUS = 1.0
#: Most points drawn at once (a fixed-seed subsample beyond); the CPU renderer slows.
MAX_DRAWN_POINTS = 300_000
THRESHOLD_RANGE = (1e-3, 0.25)
THRESHOLD_STEP = 10 ** 0.125  # 8 steps per decade
DM_RANGE = (0.0, 0.2)
VOXEL_RANGE = (0.02, 1.0)
LEGEND_CELLS = 24


# --------------------------------------------------------------------------- options
def open_view(args, cfg) -> int:
    """Open the app on ``args.target`` with ``cfg``; the exit code once the window closes.

    Errors are raised (ViewerError and the readers' errors); the command line turns
    them into exit codes.
    """
    check_display()
    size = _parse_size(args.size)
    if not (VOXEL_RANGE[0] <= args.voxel_size <= VOXEL_RANGE[1]):
        raise ViewerError(f"Expected --voxel-size between {VOXEL_RANGE[0]} and "
                          f"{VOXEL_RANGE[1]} m, found {args.voxel_size}; the app extracts "
                          "surfaces interactively.")
    steps = load_script(args.script) if args.script else None
    compare = _parse_compare(getattr(args, "compare", None) or [])
    segment = getattr(args, "segment", None)
    if not getattr(args, "screenshot", None) and (compare or segment is not None):
        raise ViewerError("--compare and --segment apply to --screenshot; in the window use "
                          "the Compare layer and the segment list.")
    if segment is not None and segment < 1:
        raise ViewerError(f"Expected --segment >= 1 (1 = the largest segment), found {segment}.")
    model = ViewerModel.open(args.target, cfg, voxel_size=args.voxel_size)
    if getattr(args, "screenshot", None):
        from .gui_screenshot import screenshot_target

        screenshot_target(model, args.screenshot, size=size, stage=args.stage,
                          level=getattr(args, "level", 0), compare=compare,
                          segment=None if segment is None else segment - 1,
                          log=lambda m: print(f"[gmmgp view] {m}", file=sys.stderr))
        return 0
    return run_app(model, size=size, first_stage=args.stage, script=steps,
                   draw_scene=not getattr(args, "no_3d", False))


def check_display() -> None:
    """Fail early, in one line, where no window can open (Open3D would abort the process)."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY")
                                                 or os.environ.get("WAYLAND_DISPLAY")):
        raise ViewerError("No display found (DISPLAY and WAYLAND_DISPLAY are unset); run in a "
                          "desktop session, or headless with 'xvfb-run -s \"-screen 0 "
                          "1600x1000x24\" gmmgp view ...'.")


def _parse_compare(items) -> dict:
    """``--compare KEY=VALUE`` items as a settings dict (values parsed as TOML)."""
    from ..config import MappingConfig, parse_value

    out = {}
    for a in items:
        if "=" not in a:
            raise ViewerError(f"Expected --compare like hgmm.split_threshold=0.03, found {a!r}.")
        k, v = a.split("=", 1)
        out[k.strip()] = parse_value(v.strip())
    if out:
        MappingConfig().replace(out)  # unknown keys fail here, before any work
    return out


def _parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        w = h = 0
    if w < 400 or h < 300:
        raise ViewerError(f"Expected --size like 1600x1000 (at least 400x300), found {text!r}.")
    return w, h


def run_app(model: ViewerModel, size=(1600, 1000), first_stage=None, script=None,
            hard_exit: bool = True, draw_scene: bool = True) -> int:
    """Create the window, start the first computation and run the event loop.

    With ``hard_exit`` (the CLI), closing the window ends the process at once (see
    :meth:`ViewerApp.quit`) and this function does not return.
    """
    import open3d.visualization.gui as gui

    app = gui.Application.instance
    app.initialize()
    viewer = ViewerApp(model, size=size, first_stage=first_stage, hard_exit=hard_exit,
                       draw_scene=draw_scene)
    viewer.start_initial_run()
    if script is not None:
        ScriptRunner(viewer, script).start()
    app.run()
    return viewer.exit_code


# --------------------------------------------------------------------------- the app

def _leave_a_core_to_the_frames() -> None:
    """Compute the stages in this (worker) thread on one fewer core than the machine has.

    On Mesa's CPU renderer the window's frames are rasterized on the same cores as the
    stages: with numba's parallel kernels on every core, the frame that shows a new HGMM
    level waited for the surface stage (12-20 s on 2 cores). numba's thread count is
    per calling thread, so only this run's kernels are limited; the thread is also
    niced (Linux: per thread) so that the event loop and the frames come first.
    """
    import os

    try:
        import numba

        numba.set_num_threads(max(1, numba.config.NUMBA_NUM_THREADS - 1))
    except Exception:  # noqa: BLE001 - an optimisation, never a failure
        pass
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 10)
    except (AttributeError, OSError):
        pass


class ViewerApp:
    """The window (view) and its event handlers (controller) around a ViewerModel.

    All methods except the worker bodies and the script runner's driver run on the
    GUI main thread.
    """

    def __init__(self, model: ViewerModel, size=(1600, 1000), first_stage=None,
                 hard_exit: bool = False, draw_scene: bool = True):
        import open3d.visualization.gui as gui
        import open3d.visualization.rendering as rendering

        self.gui, self.rendering = gui, rendering
        self.model = model
        self.app = gui.Application.instance
        self.exit_code = 0
        self.hard_exit = hard_exit
        # False: build no 3D geometry (the panel and controller only; what the 3D view
        # draws is checked offscreen, see gui_screenshot)
        self.draw_scene = draw_scene
        self._savers: list[threading.Thread] = []
        self.runs: list = []  # RunRecord of each finished run
        self.errors: list[str] = []
        self.generation = 0          # bumped by every run; older results are dropped
        self.dropped_results = 0
        self.idle = threading.Event()
        self.idle.set()
        self.stage = first_stage
        self._user_stage = first_stage is not None
        self.level = 0
        self.layers = set(STAGE_LAYERS[first_stage or "scan"])
        self.colour_by_variance = False
        self.pending_cfg = model.results.config
        self.pending_voxel = model.results.voxel_size
        self.probe_text = ""
        self.previous = None  # results before the last run (the compare layer)
        # seconds from Run to each stage's result in the scene (geometry added), and to
        # the first frame drawn after it (a read-back served by that frame)
        self.latency: dict = {}
        self.frame_latency: dict = {}
        # (stage, "drawn" / "timeout" / "cancelled", seconds) of each wait of the run's
        # worker for the frame showing a stage (gui_model.wait_for_frame)
        self.frame_waits: list = []
        self.frame_wait_timeout = FRAME_WAIT_S
        # GMMGP_GUI_FRAME_TIMES=1: also time the frame after the last stage (benchmarks)
        self._time_last_frame = bool(os.environ.get("GMMGP_GUI_FRAME_TIMES"))
        self.selected_segment = None  # a check result's segment shown red
        self.legend_key = "unpainted"
        self._std_cache: dict = {}
        self._camera_set = False
        self._shown: set[str] = set()
        self._geom_keys: dict[str, object] = {}

        w, h = size
        self.window = self.app.create_window(f"gmmgp view - {model.source}", w, h)
        em = self.window.theme.font_size
        self.em = em
        self.scene = gui.SceneWidget()
        self.scene.scene = rendering.Open3DScene(self.window.renderer)
        # Redraw the 3D view only when it changes (request_redraw), not with every panel
        # update (a progress step, a label): on the CPU renderer a frame of the scene
        # costs seconds and blocks the GUI thread while it is drawn.
        self.scene.enable_scene_caching(True)
        self.scene.scene.set_background([1.0, 1.0, 1.0, 1.0])
        self.scene.scene.show_axes(False)
        # Tone mapping would shift the colour maps (and the legend would lie).
        self.scene.scene.view.set_post_processing(False)
        # The sun from the camera's side, no shadow-map pass (gui_layers.set_lighting).
        set_lighting(self.scene.scene, rendering)
        self.scene.set_on_mouse(self._on_mouse)
        self.window.add_child(self.scene)
        self.panel = self._build_panel(gui, em)
        self.window.add_child(self.panel)
        self.window.set_on_layout(self._on_layout)
        self.window.set_on_close(self._on_close)
        self._materials(rendering)
        self._refresh_panel()

    # ------------------------------------------------------------------ building
    def _materials(self, rendering):
        self.mat = materials(rendering, self.window.scaling)

    def _build_panel(self, gui, em):
        panel = gui.ScrollableVert(0.4 * em, gui.Margins(0.6 * em, 0.6 * em, 0.6 * em, 0.6 * em))
        self.title_label = gui.Label(Path(self.model.source).name or self.model.source)
        panel.add_child(self.title_label)
        self.counts_label = gui.Label("")
        panel.add_child(self.counts_label)
        self.summary_label = gui.Label("")
        panel.add_child(self.summary_label)

        # -- stage and level
        sec = gui.CollapsableVert("Stage", 0.3 * em, gui.Margins(0.3 * em, 0, 0, 0))
        self.stage_combo = gui.Combobox()
        for s in STAGES:
            self.stage_combo.add_item(STAGE_LABELS[s])
        self.stage_combo.set_on_selection_changed(lambda text, i: self.set_stage(STAGES[i]))
        sec.add_child(self.stage_combo)
        sec.add_child(gui.Label("HGMM level"))
        self.level_slider = gui.Slider(gui.Slider.INT)
        self.level_slider.set_limits(0, 1)
        self.level_slider.set_on_value_changed(lambda v: self.set_level(int(v)))
        sec.add_child(self.level_slider)
        self.level_label = gui.Label("")
        sec.add_child(self.level_label)
        panel.add_child(sec)

        # -- layers and colouring
        sec = gui.CollapsableVert("Layers", 0.3 * em, gui.Margins(0.3 * em, 0, 0, 0))
        self.layer_boxes = {}
        for name in LAYERS:
            cb = gui.Checkbox(LAYER_LABELS[name])
            cb.set_on_checked(lambda on, n=name: self.set_layer(n, on))
            sec.add_child(cb)
            self.layer_boxes[name] = cb
        self.variance_box = gui.Checkbox("Colour by predicted std")
        self.variance_box.set_on_checked(self.set_colour_by_variance)
        sec.add_child(self.variance_box)
        self.legend_title = gui.Label("")
        sec.add_child(self.legend_title)

        # The colour bar is a row of coloured cells, not an ImageWidget: swapping
        # textures through ImageWidget stalled the CPU renderer for minutes here.
        # Buttons, because a Label never paints its background colour.
        bar = gui.Horiz(0)
        self._legend_bar = bar
        self.legend_cells = []
        for _ in range(LEGEND_CELLS):
            cell = gui.Button(" ")
            cell.horizontal_padding_em = 0.0  # 24 cells of about 0.7 em: fits 22 em
            cell.vertical_padding_em = 0.1
            cell.enabled = False
            bar.add_child(cell)
            self.legend_cells.append(cell)
        sec.add_child(bar)
        self.legend_range = gui.Label("")
        sec.add_child(self.legend_range)
        panel.add_child(sec)

        # -- tuning
        sec = gui.CollapsableVert("Tuning", 0.3 * em, gui.Margins(0.3 * em, 0, 0, 0))
        cfg = self.model.results.config
        self.threshold_label = gui.Label("")
        sec.add_child(self.threshold_label)
        # The threshold itself, stepped on a log scale (Open3D's slider can only show
        # the value it moves linearly: a log10 slider showed "-2.000").
        row = gui.Horiz(0.3 * em)
        down = gui.Button("/")
        down.tooltip = f"divide by {THRESHOLD_STEP:.3g} (log-scale step)"
        down.set_on_clicked(lambda: self.step_threshold(-1))
        self.threshold_edit = gui.NumberEdit(gui.NumberEdit.DOUBLE)
        self.threshold_edit.set_limits(*THRESHOLD_RANGE)
        self.threshold_edit.decimal_precision = 4
        self.threshold_edit.double_value = min(max(cfg.hgmm.split_threshold,
                                                   THRESHOLD_RANGE[0]), THRESHOLD_RANGE[1])
        self.threshold_edit.set_on_value_changed(lambda v: self.set_threshold(v, from_slider=True))
        up = gui.Button("x")
        up.tooltip = f"multiply by {THRESHOLD_STEP:.3g} (log-scale step)"
        up.set_on_clicked(lambda: self.step_threshold(+1))
        for w_ in (down, self.threshold_edit, up):
            row.add_child(w_)
        self.threshold_buttons = (down, up)
        sec.add_child(row)
        self.dm_label = gui.Label("")
        sec.add_child(self.dm_label)
        self.dm_slider = gui.Slider(gui.Slider.DOUBLE)
        self.dm_slider.set_limits(*DM_RANGE)
        # 'auto' (a target without a scan to resolve it from, e.g. a check result):
        # the slider rests at the urban value until a run resolves it
        dm0 = cfg.gp.d_m if not is_auto(cfg.gp.d_m) else concrete(cfg.gp).d_m
        self.dm_slider.double_value = min(dm0, DM_RANGE[1])
        self.dm_slider.set_on_value_changed(lambda v: self.set_d_m(v, from_slider=True))
        sec.add_child(self.dm_slider)
        row = gui.Horiz(0.3 * em)
        row.add_child(gui.Label("voxel (m)"))
        self.voxel_edit = gui.NumberEdit(gui.NumberEdit.DOUBLE)
        self.voxel_edit.set_limits(*VOXEL_RANGE)
        self.voxel_edit.decimal_precision = 3
        self.voxel_edit.double_value = self.pending_voxel
        self.voxel_edit.set_on_value_changed(lambda v: self.set_voxel(v, from_edit=True))
        row.add_child(self.voxel_edit)
        sec.add_child(row)
        self.run_button = gui.Button("Run")
        self.run_button.set_on_clicked(self.run)
        sec.add_child(self.run_button)
        self.progress = gui.ProgressBar()
        sec.add_child(self.progress)
        self.status_label = gui.Label("")
        sec.add_child(self.status_label)
        # one line per run: c*, d_m, leaves, GP points, RMS field change vs the run before
        self.runs_label = gui.Label("")
        sec.add_child(self.runs_label)
        panel.add_child(sec)

        # -- a check result's change segments, a tiled map's tiles
        sec = gui.CollapsableVert("Check and tiles", 0.3 * em, gui.Margins(0.3 * em, 0, 0, 0))
        self.segments_label = gui.Label("(not a check result)")
        sec.add_child(self.segments_label)
        self.segment_combo = gui.Combobox()
        self.segment_combo.set_on_selection_changed(lambda text, i: self.select_segment(i - 1))
        sec.add_child(self.segment_combo)
        self.tiles_label = gui.Label("(not a tiled map)")
        sec.add_child(self.tiles_label)
        self.tiles_button = gui.Button("Load tiles around the view")
        self.tiles_button.set_on_clicked(lambda: self.load_tiles_around(None))
        sec.add_child(self.tiles_button)
        panel.add_child(sec)

        # -- probe and export
        sec = gui.CollapsableVert("Probe and export", 0.3 * em, gui.Margins(0.3 * em, 0, 0, 0))
        sec.add_child(gui.Label("Ctrl+click the scene: SDF mean +- std\nand its gradient"))
        self.probe_label = gui.Label("(no probe yet)")
        sec.add_child(self.probe_label)
        row = gui.Horiz(0.3 * em)
        b = gui.Button("Screenshot")
        b.set_on_clicked(self._on_screenshot_button)
        row.add_child(b)
        b = gui.Button("Save map")
        b.set_on_clicked(self._on_save_button)
        row.add_child(b)
        b = gui.Button("Reset view")
        b.set_on_clicked(self.reset_camera)
        row.add_child(b)
        sec.add_child(row)
        panel.add_child(sec)
        return panel

    def _on_layout(self, ctx):
        r = self.window.content_rect
        width = int(22 * self.em)
        self.scene.frame = self.gui.Rect(r.x, r.y, r.width - width, r.height)
        self.panel.frame = self.gui.Rect(r.get_right() - width, r.y, width, r.height)

    def _on_close(self):
        self.quit()
        return True

    def quit(self):
        """Stop workers, let map saves finish, then end the event loop (or the process).

        With ``hard_exit`` the process ends here: Open3D's renderer teardown (Filament
        on Mesa's CPU Vulkan driver) was seen to rasterise for minutes at 100 % CPU
        after the window closed, with nothing left to show or save.
        """
        self.generation += 1  # workers see they are stale and stop between stages
        for t in self._savers:
            t.join(timeout=120)
        if self.hard_exit:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(self.exit_code)
        self.app.quit()

    # ------------------------------------------------------------------ controller
    def set_stage(self, stage: str):
        """Show ``stage``: switches the layers to that stage's preset."""
        if stage not in STAGES:
            raise ViewerError(f"Unknown stage {stage!r}; expected one of {', '.join(STAGES)}.")
        self.stage = stage
        self._user_stage = True
        self.layers = set(STAGE_LAYERS[stage])
        self._refresh()

    def set_level(self, level: int):
        h = self.model.results.hgmm
        n = len(h.levels) if h is not None else 1
        self.level = int(min(max(level, 0), n - 1))
        if "ellipsoids" not in self.layers:
            self.layers.add("ellipsoids")
        self._refresh()

    def set_layer(self, name: str, on: bool):
        if name not in LAYERS:
            raise ViewerError(f"Unknown layer {name!r}; expected one of {', '.join(LAYERS)}.")
        (self.layers.add if on else self.layers.discard)(name)
        if name == "compare":
            self._camera_set = False  # frame both copies (or the current one again)
        self._refresh()

    def set_colour_by_variance(self, on: bool):
        self.colour_by_variance = bool(on)
        self._refresh()

    def set_threshold(self, value: float, from_slider=False):
        # Sliders hold float32 and fire on programmatic changes too: keep 3 significant
        # digits so 0.03 stays 0.03 (and does not count as a change).
        value = float(f"{min(max(value, THRESHOLD_RANGE[0]), THRESHOLD_RANGE[1]):.3g}")
        if from_slider and value == self.pending_cfg.hgmm.split_threshold:
            return
        self.pending_cfg = self.pending_cfg.replace("hgmm.split_threshold", value)
        if not from_slider:
            self.threshold_edit.double_value = value
        self._refresh_panel()

    def step_threshold(self, steps: int):
        """Multiply the pending threshold by THRESHOLD_STEP ** steps (log-scale steps)."""
        self.set_threshold(self.pending_cfg.hgmm.split_threshold * THRESHOLD_STEP ** steps)

    def set_d_m(self, value: float, from_slider=False):
        value = round(float(min(max(value, DM_RANGE[0]), DM_RANGE[1])), 4)  # 0.1 mm steps
        if from_slider and value == self.pending_cfg.gp.d_m:
            return
        self.pending_cfg = self.pending_cfg.replace("gp.d_m", value)
        if not from_slider:
            self.dm_slider.double_value = value
        self._refresh_panel()

    def set_voxel(self, value: float, from_edit=False):
        self.pending_voxel = round(float(min(max(value, VOXEL_RANGE[0]), VOXEL_RANGE[1])), 4)
        if not from_edit:
            self.voxel_edit.double_value = self.pending_voxel
        self._refresh_panel()

    def start_initial_run(self):
        r = self.model.results
        if r.check is not None or (r.mesh is not None and not self.model.can_refit):
            # a check result, or a run folder with its mesh: nothing to compute
            self.stage = self.stage or ("scan" if r.check is not None else "surface")
            self.layers = set(STAGE_LAYERS[self.stage])
            if r.check is not None:
                self._fill_segments()
            self.status_label.text = f"opened {self.model.kind} {self.model.source}"
            self._refresh()
            return
        if r.tiles is not None:
            self.stage = self.stage or "surface"
            self.layers = set(STAGE_LAYERS[self.stage])
            self.load_tiles_around(r.tiles.centre())
            return
        start = "prepare" if self.model.can_refit else "surface"
        self._start(start, r.config, r.voxel_size)

    # ------------------------------------------------------------------ check / tiles
    def _fill_segments(self):
        ck = self.model.results.check
        self.segment_combo.clear_items()
        self.segment_combo.add_item("(no segment selected)")
        for i in range(len(ck.segments)):
            self.segment_combo.add_item(ck.segment_label(i))
        s = ck.summary
        self.segments_label.text = (
            f"{int(ck.changed.sum()):,} changed points, {len(ck.segments)} segments"
            + (f"\nknown {s['fraction_known']:.1%}" if "fraction_known" in s else ""))

    def select_segment(self, i):
        """Select change segment ``i`` (0 = the largest; None or < 0: none): drawn red,
        the camera turned to it."""
        ck = self.model.results.check
        if ck is None:
            raise ViewerError("No check result is open; open a 'gmmgp check' output folder.")
        if i is None or i < 0:
            self.selected_segment = None
        else:
            if i >= len(ck.segments):
                raise ViewerError(f"Expected a segment between 1 and {len(ck.segments)}, "
                                  f"found {i + 1}.")
            self.selected_segment = int(i)
            sg = ck.segments[i]
            centre = 0.5 * (sg["bbox_min"] + sg["bbox_max"])
            ext = max(float(np.linalg.norm(sg["bbox_max"] - sg["bbox_min"])), 1.0)
            self.set_camera(centre, centre + 2.0 * ext * np.array([0.25, -0.75, 0.55]))
        self.segment_combo.selected_index = 0 if self.selected_segment is None \
            else self.selected_segment + 1
        self._refresh()

    def view_centre_xy(self):
        """(x, y) where the camera's line of sight meets the scene's median height."""
        r = self.model.results
        z0 = float(np.median(r.scan.points[:, 2])) if r.scan is not None and len(r.scan) \
            else 0.0
        cam = self.scene.scene.camera
        m = np.asarray(cam.get_model_matrix())
        eye, fwd = m[:3, 3], -m[:3, 2]
        if abs(fwd[2]) < 1e-6:
            return eye[:2]
        t = (z0 - eye[2]) / fwd[2]
        return (eye + max(t, 0.0) * fwd)[:2]

    def load_tiles_around(self, xy=None, all_tiles: bool = False, on_done=None):
        """Load the tiled map's tiles within TILE_RADIUS tile sizes of ``xy`` (default:
        the view's centre; ``all_tiles``: every tile) in a worker, then show them."""
        tv = self.model.results.tiles
        if tv is None:
            self.status_label.text = "Not a tiled map: nothing to load."
            return
        if xy is None and not all_tiles:
            xy = self.view_centre_xy() if self._camera_set else tv.centre()
        radius = TILE_RADIUS * tv.size
        self.generation += 1
        gen = self.generation
        self.idle.clear()
        self.status_label.text = "loading tiles ..."
        t0 = time.perf_counter()

        def post(fn):
            self.app.post_to_main_thread(self.window, lambda: self._guarded(fn))

        def work():
            try:
                res = self.model.load_tiles(None if all_tiles else xy,
                                            None if all_tiles else radius,
                                            voxel_size=self.pending_voxel)

                def show():
                    if gen == self.generation:
                        self.model.results = res
                        n = len(res.tiles.pieces)
                        self.status_label.text = (f"{n} of {len(res.tiles.keys)} tiles loaded "
                                                  f"({time.perf_counter() - t0:.1f} s)")
                        self._refresh()
                    if on_done is not None:
                        on_done()
                post(show)
            except Exception as e:  # noqa: BLE001 - shown in the panel
                msg = f"{type(e).__name__}: {e}"
                post(lambda: self._on_run_error(gen, msg))
            post(lambda: self.idle.set() if gen == self.generation else None)

        threading.Thread(target=work, name=f"gmmgp-tiles-{gen}", daemon=True).start()

    def run(self):
        """Re-run the stages the pending settings affect (the Run button)."""
        r = self.model.results
        start = first_affected_stage(r, self.pending_cfg, self.pending_voxel)
        missing = next((s for s in STAGES[1:] if not r.has(s)
                        and (self.model.can_refit or s == "surface")), None)
        if missing is not None and (start is None or STAGES.index(missing) < STAGES.index(start)):
            start = missing
        if start is None:
            self.status_label.text = "Nothing changed; move a slider first."
            return
        if start != "surface" and not self.model.can_refit:
            self.status_label.text = "A saved map: only the voxel can change (open the scan)."
            return
        self._start(start, self.pending_cfg, self.pending_voxel)

    def _start(self, start, cfg, voxel):
        self.generation += 1
        gen = self.generation
        self.idle.clear()
        base = self.model.results
        if base.hgmm is not None:  # what the compare layer shows beside the new run
            self.previous = base
        n_stages = len(STAGES) - STAGES.index(start)
        self._run_info = {"start": start, "done": 0, "n": n_stages, "t0": time.perf_counter()}
        self.latency, self.frame_latency, self.frame_waits = {}, {}, []
        self.progress.value = 0.0
        self.status_label.text = f"running from {STAGE_LABELS[start]} ..."
        self._refresh_panel()

        def post(fn):
            self.app.post_to_main_thread(self.window, lambda: self._guarded(fn))

        def on_stage(name, results):
            drawn = threading.Event()
            post(lambda: self._on_stage_result(gen, name, results, drawn))
            if name != STAGES[-1]:
                # the next stage starts once this one is on screen (gui_model.wait_for_frame)
                t = time.perf_counter()
                how = wait_for_frame(drawn, lambda: gen != self.generation,
                                     self.frame_wait_timeout)
                self.frame_waits.append((name, how, round(time.perf_counter() - t, 3)))

        throttle = ProgressThrottle()

        def progress(stage, frac):
            if throttle(stage, frac):
                post(lambda: self._on_progress(gen, stage, frac))

        def work():
            _leave_a_core_to_the_frames()
            try:
                r = self.model.compute(start, cfg, voxel, base=base, on_stage=on_stage,
                                       cancelled=lambda: gen != self.generation,
                                       progress=progress)
                rec = run_record(base, r)  # the field's change: in the worker (predicts)
                post(lambda: self._on_run_record(gen, rec))
            except Cancelled:
                pass
            except Exception as e:  # shown in the panel; the app stays usable
                msg = f"{type(e).__name__}: {e}"
                post(lambda: self._on_run_error(gen, msg))
            post(lambda: self._on_run_finished(gen))

        threading.Thread(target=work, name=f"gmmgp-run-{gen}", daemon=True).start()

    def _guarded(self, fn):
        """Run a posted callback; an exception is shown, never lost in the event loop."""
        try:
            fn()
        except Exception as e:  # noqa: BLE001 - the app must stay usable
            import traceback

            traceback.print_exc()
            msg = f"{type(e).__name__}: {e}"
            self.errors.append(msg)
            self.status_label.text = msg[:200]

    def _on_stage_result(self, gen, name, results: StageResults, drawn=None):
        """Show a stage's results; ``drawn`` (an Event) is set once a frame showing them
        has been drawn (at once when the result is dropped or nothing is drawn)."""
        if drawn is None:
            drawn = threading.Event()
        try:
            self._show_stage_result(gen, name, results, drawn)
        except BaseException:
            drawn.set()  # nothing new to wait for
            raise
        if not self.draw_scene or gen != self.generation:
            drawn.set()

    def _show_stage_result(self, gen, name, results, drawn):
        if gen != self.generation:
            self.dropped_results += 1
            return
        self.model.results = results
        self._run_info["done"] += 1
        self.progress.value = self._run_info["done"] / self._run_info["n"]
        secs = results.seconds.get(name, 0.0)
        rest = STAGES[STAGES.index(name) + 1:]
        self.status_label.text = f"{STAGE_LABELS[name]} done ({secs:.1f} s)" + (
            f"\ncomputing {', '.join(STAGE_LABELS[s] for s in rest)} ..." if rest else "")
        if not self._user_stage:
            self.stage = name
            self.layers = set(STAGE_LAYERS[self.stage])
        if name == "hgmm":
            self.level = min(self.level, len(results.hgmm.levels) - 1)
        self._refresh()
        t_run = self._run_info["t0"]
        self.latency[name] = time.perf_counter() - t_run
        last = name == STAGES[-1]
        if self.draw_scene and (not last or self._time_last_frame):
            # A read-back is served by the next frame of the 3D view: the one showing
            # this. It seems to cost a render of its own (the window's frame of the demo's
            # surface took 7.7 s of rasterizer CPU with it, one offscreen frame 3.8 s), so
            # after the last stage, which nothing waits for, only on request.
            def on_frame(_img, name=name):
                self.frame_latency.setdefault(name, time.perf_counter() - t_run)
                drawn.set()
            self.scene.scene.scene.render_to_image(on_frame)
            self.request_redraw()

    def _on_run_record(self, gen, rec):
        if gen != self.generation:
            return
        self.runs.append(rec)
        self.runs_label.text = "\n".join(f"run {i + 1}: {r.label()}" for i, r in
                                         list(enumerate(self.runs))[-4:])
        self.window.set_needs_layout()

    def _on_progress(self, gen, stage, frac):
        if gen != self.generation:
            return
        i = self._run_info
        self.progress.value = (i["done"] + frac) / i["n"]
        self.status_label.text = f"{STAGE_LABELS[stage]}: {100 * frac:.0f} %"

    def _on_run_error(self, gen, msg):
        if gen != self.generation:
            return
        self.errors.append(msg)
        self.status_label.text = msg[:200]

    def _on_run_finished(self, gen):
        if gen != self.generation:
            return
        try:
            i = self._run_info
            if not self.errors or not self.status_label.text.startswith(self.errors[-1][:20]):
                self.status_label.text = (f"done: {i['done']} stage(s) in "
                                          f"{time.perf_counter() - i['t0']:.1f} s")
            self.progress.value = 1.0
            self._refresh_panel()
        finally:
            self.idle.set()

    # ------------------------------------------------------------------ probing
    def _on_mouse(self, event):
        gui = self.gui
        if (event.type == gui.MouseEvent.Type.BUTTON_DOWN
                and event.is_modifier_down(gui.KeyModifier.CTRL)):
            x = event.x - self.scene.frame.x
            y = event.y - self.scene.frame.y

            def on_depth(depth_image):
                depth = float(np.asarray(depth_image)[y, x])
                if depth >= 1.0:  # the far plane: nothing under the cursor
                    text = "nothing under the cursor"
                    self.app.post_to_main_thread(self.window, lambda: self._set_probe(text))
                    return
                f = self.scene.frame
                world = self.scene.scene.camera.unproject(x, y, depth, f.width, f.height)
                self.app.post_to_main_thread(self.window, lambda: self.probe(world))

            self.scene.scene.scene.render_to_depth_image(on_depth)
            self.scene.force_redraw()
            return gui.Widget.EventCallbackResult.HANDLED
        return gui.Widget.EventCallbackResult.IGNORED

    def probe(self, xyz):
        """Show the SDF mean +- std at ``xyz`` (local frame) and mark the point."""
        xyz = np.asarray(xyz, dtype=np.float64).reshape(3)
        try:
            mean, std, grad = self.model.probe(xyz, return_grad=True)
        except ViewerError as e:
            self._set_probe(str(e))
            return None
        self._set_probe(f"({xyz[0]:.2f}, {xyz[1]:.2f}, {xyz[2]:.2f}):\n"
                        f"SDF {mean:+.4f} +- {std:.4f} m\n"
                        f"grad ({grad[0]:+.2f}, {grad[1]:+.2f}, {grad[2]:+.2f}), "
                        f"|grad| {np.linalg.norm(grad):.2f}")
        from .gui_geometry import probe_marker

        s = probe_marker(xyz, 0.01 * self._extent())
        sc = self.scene.scene
        if sc.has_geometry("probe"):
            sc.remove_geometry("probe")
        sc.add_geometry("probe", s, self.mat["probe"])
        self.request_redraw()
        return mean, std, grad

    def _set_probe(self, text):
        self.probe_text = text
        self.probe_label.text = text
        self.window.post_redraw()

    # ------------------------------------------------------------------ view
    def _extent(self) -> float:
        s = self.model.results.scan
        if s is None or len(s) == 0:
            return 1.0
        return float(np.linalg.norm(np.ptp(s.points, axis=0))) or 1.0

    def reset_camera(self):
        v = scene_view(self)  # a street: along it from above; an object: oblique
        if v is None:
            return
        import open3d as o3d

        from .gui_camera import sun_direction

        bbox = o3d.geometry.AxisAlignedBoundingBox(v.lo, v.hi)
        self.scene.setup_camera(50.0, bbox, v.centre)
        self.scene.look_at(v.centre, v.eye, v.up)
        set_lighting(self.scene.scene, self.rendering, sun_direction(v))
        self._camera_set = True
        self.request_redraw()

    def set_camera(self, center, eye, up=(0.0, 0.0, 1.0)):
        self.scene.look_at(np.asarray(center, float), np.asarray(eye, float),
                           np.asarray(up, float))
        self.request_redraw()

    def _refresh(self):
        self._refresh_scene()
        self._refresh_panel()
        self.request_redraw()

    def _display_points(self, pts):
        if len(pts) <= MAX_DRAWN_POINTS:
            return np.arange(len(pts))
        return np.sort(np.random.default_rng(0).choice(len(pts), MAX_DRAWN_POINTS, replace=False))

    def _layer_geometry(self, name):
        """(key, build, material, legend) of a layer (:func:`gui_layers.layer_geometry`)."""
        return layer_geometry(self, name)

    def _predict_std_async(self, key, results, pts):
        """Predict the std at the drawn points in a worker (seconds on large scans)."""
        if self._std_cache.get("pending") == key:
            return
        self._std_cache["pending"] = key
        field_ = results.smap if results.smap is not None else results.prior

        def work():
            try:
                var = field_.predict(pts)[1]
            except Exception as e:  # noqa: BLE001
                msg = f"{type(e).__name__}: {e}"
                self.app.post_to_main_thread(self.window, lambda: self._on_run_error(
                    self.generation, msg))
                return

            def done():
                if self.model.results is results:
                    self._std_cache = {key: var}
                    self._refresh()
            self.app.post_to_main_thread(self.window, lambda: self._guarded(done))

        threading.Thread(target=work, daemon=True).start()

    def _refresh_scene(self):
        sc = self.scene.scene
        legend = None
        for name in LAYERS:
            if name not in self.layers:
                for g in self._names_of(name):
                    if sc.has_geometry(g):
                        sc.show_geometry(g, False)
                continue
            key, build, mat, leg = self._layer_geometry(name)
            if key is None:
                for g in self._names_of(name):
                    if sc.has_geometry(g):
                        sc.remove_geometry(g)
                self._geom_keys.pop(name, None)
                continue
            if self._geom_keys.get(name) != key and not self.draw_scene:
                self._geom_keys[name] = key  # what would be drawn (tests without frames)
            elif self._geom_keys.get(name) != key:
                for g in self._names_of(name):
                    if sc.has_geometry(g):
                        sc.remove_geometry(g)
                geom = build()
                parts = geom if isinstance(geom, dict) else {name: geom}
                for gname, gg in parts.items():
                    sc.add_geometry(gname, gg, self.mat[gname if mat is None else mat])
                self._geom_keys[name] = key
            for g in self._names_of(name):
                if sc.has_geometry(g):
                    sc.show_geometry(g, True)
            if leg is not None and (legend is None or name in ("ellipsoids", "mesh")):
                legend = leg
        self._set_legend(legend)
        if not self._camera_set and self.model.results.scan is not None:
            self.reset_camera()

    @staticmethod
    def _names_of(layer):
        return layer_parts(layer)

    def _set_legend(self, legend):
        from .gui_geometry import LEGENDS

        if legend is None:
            if self.legend_key is not None:
                self._paint_legend(None)
            self.legend_key = None
            self.legend_title.text = "(no colour scale for the shown layers)"
            self.legend_range.text = ""
            return
        kind, lo, hi = legend
        title, cmap = LEGENDS[kind]
        if kind == "c":
            from .rerun_observer import C_MAX

            t = self.model.results.config.hgmm.split_threshold
            lo, hi = 0.0, C_MAX
            self.legend_range.text = (f"0 ... {hi:.2f}   (threshold {t:.4g})\n"
                                      "wireframe: split, solid: leaf")
        else:
            self.legend_range.text = f"{lo:.3g} ... {hi:.3g}"
        self.legend_title.text = title
        if self.legend_key != kind:
            self._paint_legend(cmap)
            self.legend_key = kind

    def _paint_legend(self, cmap):
        from .gui_geometry import colormap

        gui = self.gui
        if cmap is None:
            cols = np.full((LEGEND_CELLS, 3), 0.16)  # the panel's background
        else:
            cols = colormap(np.linspace(0, 1, LEGEND_CELLS), cmap)
        for cell, c in zip(self.legend_cells, cols):
            cell.background_color = gui.Color(float(c[0]), float(c[1]), float(c[2]), 1.0)

    def _refresh_panel(self):
        r = self.model.results
        c = r.counts()
        parts = []
        for k, label in (("scan_points", "points"), ("training_rows", "rows"),
                         ("levels", "levels"), ("leaves", "leaves"), ("gp_points", "GP points"),
                         ("gp_blocks", "GP blocks"), ("faces", "faces")):
            if k in c:
                parts.append(f"{label} {c[k]:,}")
        if "gmr_rms_error" in c:
            parts.append(f"GMR rms {1000 * c['gmr_rms_error']:.1f} mm")
        lines, line = [], ""
        for p in parts:  # wrap: the panel is narrow
            if len(line) + len(p) > 34 and line:
                lines.append(line)
                line = ""
            line = f"{line} | {p}" if line else p
        lines.append(line)
        self.counts_label.text = "\n".join(lines)
        from .gui_targets import summary_lines

        self.summary_label.text = "\n".join(summary_lines(r.summary, width=38))
        if r.tiles is not None:
            self.tiles_label.text = (f"{len(r.tiles.pieces)} of {len(r.tiles.keys)} tiles "
                                     f"loaded ({r.tiles.size:g} m)")
        self.tiles_button.enabled = r.tiles is not None
        stage = self.stage or "scan"
        self.stage_combo.selected_index = STAGES.index(stage)
        for name, cb in self.layer_boxes.items():
            cb.checked = name in self.layers
        self.variance_box.checked = self.colour_by_variance
        h = r.hgmm
        if h is not None:
            n = len(h.levels)
            self.level_slider.set_limits(0, max(n - 1, 1))
            self.level_slider.int_value = min(self.level, n - 1)
            lv = h.levels[min(self.level, n - 1)]
            ns = int(np.sum(lv.split))
            self.level_label.text = (f"level {self.level} of {n - 1}: "
                                     f"{lv.mixture.n_components} nodes\n"
                                     f"{ns} split (wireframe), "
                                     f"{lv.mixture.n_components - ns} leaves (solid)")
        else:
            self.level_label.text = "(HGMM not fitted yet)"
        t = self.pending_cfg.hgmm.split_threshold
        changed = " *" if t != r.config.hgmm.split_threshold else ""
        self.threshold_label.text = f"split threshold c* {t:.4f}{changed}"
        dm = self.pending_cfg.gp.d_m
        changed = " *" if dm != r.config.gp.d_m else ""
        self.dm_label.text = (f"d_m {dm} (from the scan){changed}" if is_auto(dm)
                              else f"d_m {dm:.3f} m{changed}")
        refit = self.model.can_refit
        self.threshold_edit.enabled = refit
        for b in self.threshold_buttons:
            b.enabled = refit
        self.dm_slider.enabled = refit
        # Multi-line labels change height: lay the panel out again.
        self.window.set_needs_layout()

    # ------------------------------------------------------------------ export
    def screenshot(self, path, on_done=None):
        """Write the 3D view to ``path`` (PNG); ``on_done(path)`` runs on the main thread."""
        import open3d as o3d

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)

        def cb(image):
            o3d.io.write_image(str(path), image)
            if on_done is not None:
                self.app.post_to_main_thread(self.window, lambda: on_done(path))

        self.scene.scene.scene.render_to_image(cb)
        # The request is served by the next frame; with nothing else changing there
        # would be none (the widget caches the scene), so ask for one.
        self.scene.force_redraw()
        self.window.post_redraw()

    def window_frame(self):
        """(x, y, width, height) of the window on the screen, in pixels."""
        f = self.window.os_frame
        return f.x, f.y, f.width, f.height

    def save_map(self, directory, on_done=None):
        """Save the current map in a worker thread; reports on the status line."""
        def work():
            try:
                out = self.model.save(directory)
                msg = f"map saved to {out}"
            except Exception as e:
                msg = f"{type(e).__name__}: {e}"
                self.errors.append(msg)

            def show():
                self.status_label.text = msg
                if on_done is not None:
                    on_done(msg)
            self.app.post_to_main_thread(self.window, show)

        t = threading.Thread(target=work, name="gmmgp-save", daemon=True)
        self._savers = [s for s in self._savers if s.is_alive()] + [t]
        t.start()

    def _file_dialog(self, mode, title, filt, on_done):
        gui = self.gui
        dlg = gui.FileDialog(mode, title, self.window.theme)
        if filt:
            dlg.add_filter(*filt)
        dlg.set_on_cancel(self.window.close_dialog)

        def done(path):
            self.window.close_dialog()
            on_done(path)
        dlg.set_on_done(done)
        self.window.show_dialog(dlg)

    def _on_screenshot_button(self):
        self._file_dialog(self.gui.FileDialog.SAVE, "Save screenshot", (".png", "PNG images"),
                          lambda p: self.screenshot(p, lambda q: setattr(
                              self.status_label, "text", f"screenshot {q}")))

    def _on_save_button(self):
        self._file_dialog(self.gui.FileDialog.OPEN_DIR, "Save map into folder", None,
                          lambda p: self.save_map(Path(p) / "map"))

    # ------------------------------------------------------------------ state / script
    def state(self) -> dict:
        """What the panel shows, for scripts and tests."""
        return {"stage": self.stage, "level": self.level, "layers": sorted(self.layers),
                "colour_by_variance": self.colour_by_variance,
                "counts": self.model.results.counts(),
                "counts_label": self.counts_label.text, "level_label": self.level_label.text,
                "status": self.status_label.text, "probe": self.probe_text,
                "legend": self.legend_title.text, "legend_range": self.legend_range.text,
                "threshold": self.model.results.config.hgmm.split_threshold,
                "threshold_shown": self.threshold_edit.double_value,
                "runs": [dataclasses.asdict(r) for r in self.runs],
                "runs_label": self.runs_label.text,
                "d_m": self.model.results.config.gp.d_m,
                "generation": self.generation, "dropped_results": self.dropped_results,
                "drawn": {k: list(map(str, v)) for k, v in self._geom_keys.items()},
                "legend_bar_right": self.legend_cells[-1].frame.get_right(),
                "panel_right": self.panel.frame.get_right(),
                "seconds": self.model.results.seconds, "errors": list(self.errors),
                "kind": self.model.kind, "summary_label": self.summary_label.text,
                "latency": dict(self.latency), "frame_latency": dict(self.frame_latency),
                "frame_waits": [list(w) for w in self.frame_waits],
                "previous": (None if self.previous is None else self.previous.counts()),
                "selected_segment": self.selected_segment,
                "segments_label": self.segments_label.text,
                "segment_items": self.segment_combo.number_of_items,
                "tiles_label": self.tiles_label.text}

    # ------------------------------------------------------------------ automation API
    def post(self, fn) -> None:
        """Run ``fn`` on the main (GUI) thread."""
        self.app.post_to_main_thread(self.window, fn)

    def request_redraw(self) -> None:
        """Ask for a new frame of the 3D view and the window."""
        self.scene.force_redraw()
        self.window.post_redraw()

    def render_view(self, on_image) -> None:
        """Call ``on_image(image)`` once the 3D view's next frame is drawn (main thread)."""
        self.scene.scene.scene.render_to_image(on_image)
        self.request_redraw()

    def scan_centre(self) -> list:
        """Median of the shown scan's points (a point to probe)."""
        return np.median(self.model.results.scan.points, axis=0).tolist()

    def fail(self, msg: str) -> None:
        """Record a failed automation step: exit code 1 and quit (main thread)."""
        print(msg, file=sys.stderr, flush=True)
        self.errors.append(msg)
        self.exit_code = 1
        self.quit()

def main(argv=None) -> int:
    """``python -m gmmgp_app.viz.gui TARGET [options]``: ``gmmgp view`` without the
    command line's error handling (errors propagate; use ``gmmgp view`` for one-line
    messages and exit codes)."""
    import argparse

    from ..commands.options import add_config_options, load_config

    parser = argparse.ArgumentParser(prog="python -m gmmgp_app.viz.gui",
                                     description="The gmmgp desktop app (gmmgp view).")
    add_view_arguments(parser)
    add_config_options(parser)
    args = parser.parse_args(argv)
    return open_view(args, load_config(args))


if __name__ == "__main__":
    sys.exit(main())
