"""JSON scripts for the desktop app: automation of tests and README screenshots.

A script is a list of steps run after the first computation, e.g.::

    [{"stage": "hgmm"}, {"level": 1}, {"screenshot": "hgmm1.png", "window": true},
     {"threshold": 0.03}, {"run": true}, {"state": "state.json"}, {"quit": true}]

Step keys: stage, level, layer + on, colour_by_variance, threshold, d_m, voxel, run
(waits unless ``"wait": false``), segment (a check result's change segment, 1 = the
largest, 0 = none), load_tiles ("view" or "all": a tiled map's tiles; waits),
probe ([x, y, z] or "center"), screenshot (+ window:
whole window through the X server instead of the 3D view alone), save, state, camera
(eye, center), sleep, quit.

The runner drives the app (:class:`gmmgp_app.viz.gui.ViewerApp`) from a thread of
its own through the app's public methods only (setters, ``run``, ``probe``,
``screenshot``, ``save_map``, ``state``, ``post``, ``render_view``, ...), each
executed on the GUI thread.
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

from .gui_model import ViewerError

__all__ = ["load_script", "ScriptRunner"]


def load_script(path) -> list:
    """The steps of a JSON script file (a list of objects)."""
    p = Path(path)
    try:
        steps = json.loads(p.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ViewerError(f"Cannot read the script '{p}' ({e}); expected a JSON list of "
                          "steps like [{\"stage\": \"hgmm\"}, {\"quit\": true}].") from None
    if not isinstance(steps, list) or not all(isinstance(s, dict) for s in steps):
        raise ViewerError(f"Expected a JSON list of step objects in '{p}', found "
                          f"{type(steps).__name__}.")
    return steps


class ScriptRunner:
    """Runs script steps on an app in a driver thread (:meth:`start`)."""

    def __init__(self, app, steps, settle: float = 0.8, timeout: float = 600.0):
        self.app, self.steps, self.settle, self.timeout = app, steps, settle, timeout

    def start(self) -> threading.Thread:
        t = threading.Thread(target=self._drive, name="gmmgp-script", daemon=True)
        t.start()
        return t

    # ------------------------------------------------------------------ plumbing
    def on_main(self, fn):
        """Run ``fn`` on the GUI thread and return its value (re-raising its error)."""
        done, box = threading.Event(), {}

        def call():
            try:
                box["value"] = fn()
            except Exception as e:  # noqa: BLE001 - re-raised in the driver thread
                box["error"] = e
            done.set()
        self.app.post(call)
        if not done.wait(self.timeout):
            raise TimeoutError("a GUI step did not run within the timeout")
        if "error" in box:
            raise box["error"]
        return box.get("value")

    def wait_idle(self):
        if not self.app.idle.wait(self.timeout):
            raise TimeoutError(f"the computation did not finish within {self.timeout:.0f} s")

    def _drive(self):
        try:
            self.wait_idle()
            self.on_main(lambda: None)  # let the last stage's refresh land
            for step in self.steps:
                t0 = time.perf_counter()
                self.step(step)
                if os.environ.get("GMMGP_GUI_TRACE"):
                    print(f"[gmmgp view]   took {time.perf_counter() - t0:.2f} s",
                          file=sys.stderr, flush=True)
        except Exception as e:  # noqa: BLE001 - reported, then the app quits
            msg = f"script failed: {type(e).__name__}: {e}"
            self.app.post(lambda: self.app.fail(msg))

    # ------------------------------------------------------------------ steps
    def step(self, step: dict) -> None:
        """Run one step (driver thread)."""
        app, on_main = self.app, self.on_main
        if os.environ.get("GMMGP_GUI_TRACE"):
            print(f"[gmmgp view] {time.strftime('%H:%M:%S')} step {json.dumps(step)}",
                  file=sys.stderr, flush=True)
        if "stage" in step:
            on_main(lambda: app.set_stage(step["stage"]))
        if "level" in step:
            on_main(lambda: app.set_level(int(step["level"])))
        if "layer" in step:
            on_main(lambda: app.set_layer(step["layer"], bool(step.get("on", True))))
        if "colour_by_variance" in step:
            on_main(lambda: app.set_colour_by_variance(bool(step["colour_by_variance"])))
        if "threshold" in step:
            on_main(lambda: app.set_threshold(float(step["threshold"])))
        if "d_m" in step:
            on_main(lambda: app.set_d_m(float(step["d_m"])))
        if "voxel" in step:
            on_main(lambda: app.set_voxel(float(step["voxel"])))
        if "segment" in step:
            on_main(lambda: app.select_segment(int(step["segment"]) - 1))
        if "load_tiles" in step:
            on_main(lambda: app.load_tiles_around(None, all_tiles=step["load_tiles"] == "all"))
            self.wait_idle()
            on_main(lambda: None)
        if "camera" in step:
            cam = step["camera"]
            on_main(lambda: app.set_camera(cam["center"], cam["eye"], cam.get("up", (0, 0, 1))))
        if step.get("run"):
            on_main(app.run)
            if step.get("wait", True):
                self.wait_idle()
                on_main(lambda: None)
        if "probe" in step:
            p = step["probe"]
            if p == "center":
                p = on_main(app.scan_centre)
            on_main(lambda: app.probe(p))
        if "screenshot" in step:
            path = Path(step["screenshot"])
            time.sleep(self.settle)  # let the window draw the last change
            if step.get("window"):
                self._grab_when_drawn(path)
            else:
                ev = threading.Event()
                on_main(lambda: app.screenshot(path, lambda q: ev.set()))
                self._wait_for_frame(ev, f"screenshot {path}")
        if "save" in step:
            ev, box = threading.Event(), {}
            on_main(lambda: app.save_map(step["save"], lambda m: (box.update(msg=m), ev.set())))
            if not ev.wait(120):
                raise TimeoutError("saving the map took more than 120 s")
        if "state" in step:
            st = on_main(app.state)
            Path(step["state"]).write_text(json.dumps(st, indent=2, default=float))
        if "sleep" in step:
            time.sleep(float(step["sleep"]))
        if step.get("quit"):
            on_main(app.quit)

    # ------------------------------------------------------------------ frames
    def _wait_for_frame(self, ev: threading.Event, what: str, timeout: float = 180.0):
        """Wait (driver thread) for ``ev``, set once a requested frame has been drawn.

        Frames are drawn on demand, and a request can miss the frame in flight, so ask
        again when none came -- with back-off: on a CPU renderer under load one frame
        takes seconds, and re-asking every 0.25 s queued frames faster than they were
        drawn (stalls of minutes, also at exit while the queue drained).
        """
        t_end = time.monotonic() + timeout
        delay = 1.0
        while not ev.wait(delay):
            if time.monotonic() > t_end:
                raise TimeoutError(f"{what} was not rendered within {timeout:.0f} s")
            self.app.post(self.app.request_redraw)
            delay = min(2.0 * delay, 8.0)

    def _frame_fence(self):
        """Return once the window has drawn one more complete frame.

        A read-back of the 3D view is served by the next frame, so its callback is a
        fence: frames are drawn one at a time, never queued ahead of the renderer.
        """
        ev = threading.Event()
        self.on_main(lambda: self.app.render_view(lambda _img: ev.set()))
        self._wait_for_frame(ev, "a frame")

    def _grab_when_drawn(self, path: Path, rounds: int = 6):
        """Grab the whole window (panel included) from the X server once it is drawn.

        Presented frames reach the X server a frame or two late (the Vulkan swapchain
        holds several images), so draw two complete frames per round and grab until
        two grabs (almost) agree.
        """
        previous = None
        for _ in range(rounds):
            for _ in range(2):
                self._frame_fence()
            img = _grab_window(self.on_main(self.app.window_frame))
            if previous is not None:
                a, b = np.asarray(img), np.asarray(previous)
                if a.shape == b.shape and np.mean(np.any(a != b, axis=2)) < 1e-3:
                    break
            previous = img
        path.parent.mkdir(parents=True, exist_ok=True)
        img.save(path)


def _grab_window(frame):
    """The window's pixels (panel included) from the X server, as a PIL image."""
    from PIL import ImageGrab

    x, y, w, h = frame
    return ImageGrab.grab(bbox=(x, y, x + w, y + h), xdisplay=os.environ.get("DISPLAY"))
