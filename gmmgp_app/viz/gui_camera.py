"""The app's default view of a scene: where the camera stands and where it looks.

Pure functions of the points (no Open3D), shared by the window
(:meth:`gmmgp_app.viz.gui.ViewerApp.reset_camera`), the offscreen screenshots
(:func:`gmmgp_app.viz.gui_screenshot.render_png`) and the compare layer's shift
(:func:`gmmgp_app.viz.gui_tuning.compare_shift`).

Two kinds of scene (z is up, unless the data says otherwise: ``up``, e.g. y for the
Stanford scan sets, :func:`gmmgp_app.datasets.registry.up_axis`):

* long in one horizontal direction (a street, a corridor: the longer horizontal side of
  the points' box at least :data:`ELONGATED` times the shorter): the camera stands
  above the street (inside the short side, a quarter off its middle), behind the near
  end, and looks down along the long side. Facades on both sides are seen from the street, where the sensor was
  (from the side, the near facade hid the far one and was seen from behind);
* compact (an object, a room): oblique, from the side (-y) and above.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..types import as_up_axis

__all__ = ["ELONGATED", "DefaultView", "default_view", "up_frame", "across_axis",
           "sun_direction"]

#: Longer / shorter horizontal side of the points' 1-99 % box from which a scene is
#: viewed along its long side (the demo street: 37.4 m x 16.4 m = 2.3).
ELONGATED = 1.6
#: Camera offset from the box centre, in units of the box diagonal: compact scenes
#: (x, y, z), and for elongated ones (along the long side, up).
_OBLIQUE = np.array([0.25, -0.75, 0.55])
_ALONG, _UP = -1.0, 0.42
#: ... and across an elongated scene, in units of its short side: a quarter of the way
#: towards -y (or -x) from the middle, inside the street, so that the far side's facade
#: is seen a little more from the front than the near one.
_ACROSS = -0.25
#: ... and looked at: this much of the long side nearer than the box centre, at this
#: fraction of the height above the box's floor.
_NEAR, _LOW = 0.12, 0.3


@dataclass(frozen=True)
class DefaultView:
    """The default camera of a scene.

    Attributes
    ----------
    lo, hi : (3,) corners of the framed box (the 1-99 % range of the points: a few far
        points do not shrink the scene)
    centre : (3,) the point looked at
    eye : (3,) the camera position
    up : (3,) the up vector
    along : int or None
        The long horizontal axis (0: x, 1: y) an elongated scene is viewed along; None
        for a compact one (axes of the frame whose z is ``up``).
    frame : (3, 3) rotation from the data's axes to a frame whose z is ``up`` (the
        identity for z-up data)
    """

    lo: np.ndarray
    hi: np.ndarray
    centre: np.ndarray
    eye: np.ndarray
    up: np.ndarray
    along: object
    frame: np.ndarray = None

    @property
    def extent(self) -> float:
        """Diagonal of the framed box (m), at least 1e-6."""
        return max(float(np.linalg.norm(self.hi - self.lo)), 1e-6)

    @property
    def distance(self) -> float:
        """Distance from the eye to the centre (m)."""
        return float(np.linalg.norm(self.eye - self.centre))


def _box(points):
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return np.zeros(3), np.ones(3)
    return np.percentile(pts, 1, axis=0), np.percentile(pts, 99, axis=0)


def _long_axis(lo, hi):
    """0 or 1 when the box is elongated horizontally along x or y, else None."""
    ex, ey = float(hi[0] - lo[0]), float(hi[1] - lo[1])
    if max(ex, ey) >= ELONGATED * max(min(ex, ey), 1e-9):
        return 0 if ex >= ey else 1
    return None


def up_frame(up) -> np.ndarray:
    """(3, 3) the rotation taking the coordinate axis ``up`` (+-x, +-y or +-z) to +z."""
    u = as_up_axis(up)
    if u[2] == 1.0:
        return np.eye(3)
    if u[2] == -1.0:
        return np.diag([1.0, -1.0, -1.0])
    k = np.cross(u, [0.0, 0.0, 1.0])                   # a quarter turn about k
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + K + K @ K


def default_view(points, like=None, up=None) -> DefaultView:
    """The default camera for ``points`` (N, 3) (see the module's docstring).

    ``like`` (M, 3), optional: the points whose box decides the kind of view (the
    compare layer frames the scan and its shifted copy, but views them as it views
    the scan: a street along its long side, the copy beside it). ``up`` (3,),
    optional: the data's up axis (+-x, +-y or +-z; default z): the view is the one of
    the points turned so that ``up`` is z, turned back."""
    R = np.eye(3) if up is None else up_frame(up)
    if not np.array_equal(R, np.eye(3)):
        turn = lambda p: np.asarray(p, dtype=np.float64).reshape(-1, 3) @ R.T  # noqa: E731
        v = default_view(turn(points), None if like is None else turn(like))
        corners = np.stack([v.lo, v.hi]) @ R                 # back to the data's axes
        return DefaultView(corners.min(0), corners.max(0), R.T @ v.centre, R.T @ v.eye,
                           R.T @ v.up, v.along, R)
    lo, hi = _box(points)
    centre = 0.5 * (lo + hi)
    ext = float(np.linalg.norm(hi - lo)) or 1.0
    along = _long_axis(*_box(points if like is None else like))
    if along is None:
        offset = _OBLIQUE
    else:
        offset = np.zeros(3)
        offset[along] = _ALONG
        offset[2] = _UP
        offset[1 - along] = _ACROSS * float(hi[1 - along] - lo[1 - along]) / ext
        # look at a point low and on the near side of the middle: the near end and the
        # road stay in the picture (aimed at the box centre, the upper half was sky)
        eye = centre + ext * offset
        centre = centre.copy()
        centre[along] -= _NEAR * float(hi[along] - lo[along])
        centre[2] = lo[2] + _LOW * float(hi[2] - lo[2])
        return DefaultView(lo, hi, centre, eye, np.array([0.0, 0.0, 1.0]), along)
    return DefaultView(lo, hi, centre, centre + ext * offset, np.array([0.0, 0.0, 1.0]), along)


def across_axis(points, up=None) -> int:
    """The horizontal axis (0: x, 1: y, 2: z) across the default view: copies shifted
    along it stand side by side in the picture (the compare layer). ``up`` (3,),
    optional: the data's up axis (default z); the axis is never the up one."""
    R = np.eye(3) if up is None else up_frame(up)
    lo, hi = _box(np.asarray(points, dtype=np.float64).reshape(-1, 3) @ R.T)
    along = _long_axis(lo, hi)
    across = 0 if along is None else 1 - along         # in the frame whose z is up
    return int(np.flatnonzero(R[across])[0])            # that axis in the data's frame


def sun_direction(view: DefaultView) -> np.ndarray:
    """(3,) unit direction the sun's light travels for ``view``: from over the camera's
    shoulder (beside it, towards -y or -x, and above it) onto the scene, so the faces
    turned to the viewer, the ground and one side of a street are lit."""
    R = np.eye(3) if view.frame is None else view.frame   # in the frame whose z is up
    to_eye = R @ (view.eye - view.centre)
    to_eye = to_eye / max(float(np.linalg.norm(to_eye)), 1e-12)
    side = np.zeros(3)
    side[0 if view.along == 1 else 1] = -1.0
    toward = to_eye + 0.45 * side + np.array([0.0, 0.0, 0.35])
    return R.T @ (-toward / np.linalg.norm(toward))
