"""What changed from one run of the app to the next (no GUI): counts and the field's change.

After each run the app shows one line per run: the split threshold and d_m it used,
the HGMM leaf count, the GP point count and the RMS difference of the SDF mean
between this run's field and the previous run's, at the scan's points (a fixed
subsample). The scan's points are where the surface is, so this is the change a
threshold or d_m edit makes where it matters.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from .gui_model import StageResults

__all__ = ["RunRecord", "field_change", "run_record", "compare_shift", "FIELD_CHANGE_POINTS"]

#: Most scan points the field change is evaluated at (fixed-seed subsample beyond).
FIELD_CHANGE_POINTS = 5000


@dataclass(frozen=True)
class RunRecord:
    """One run as listed in the panel.

    Attributes
    ----------
    threshold : float
        Split threshold c* of the run.
    d_m : float
        GP point selection distance (m).
    leaves : int or None
        HGMM leaf count.
    gp_points : int or None
    field_change_rms : float or None
        RMS of the SDF mean change against the previous run at the scan points (m);
        None for the first run or when either run has no field.
    """

    threshold: float
    d_m: float
    leaves: Optional[int]
    gp_points: Optional[int]
    field_change_rms: Optional[float]

    def label(self) -> str:
        parts = [f"c* {self.threshold:.4g}", f"d_m {self.d_m:.3g}"]
        if self.leaves is not None:
            parts.append(f"leaves {self.leaves}")
        if self.gp_points is not None:
            parts.append(f"GP pts {self.gp_points}")
        if self.field_change_rms is not None:
            parts.append(f"change {1000 * self.field_change_rms:.1f} mm rms")
        return ", ".join(parts)


def _field(r: StageResults):
    return r.smap if r.smap is not None else r.prior


def field_change(prev: StageResults, new: StageResults,
                 n_max: int = FIELD_CHANGE_POINTS) -> Optional[float]:
    """RMS of (new SDF mean - previous SDF mean) at the scan's points (m).

    Both fields are evaluated at the same points: the new results' scan, a fixed-seed
    subsample of ``n_max`` points beyond that. None if either run has no field.
    """
    fa, fb = _field(prev), _field(new)
    if fa is None or fb is None or new.scan is None or len(new.scan) == 0:
        return None
    pts = new.scan.points
    if len(pts) > n_max:
        pts = pts[np.sort(np.random.default_rng(0).choice(len(pts), n_max, replace=False))]
    a = np.asarray(fa.predict(pts)[0], dtype=np.float64)
    b = np.asarray(fb.predict(pts)[0], dtype=np.float64)
    return float(np.sqrt(np.mean((b - a) ** 2)))


def resolved_setting(results: StageResults, dotted: str) -> float:
    """A config value of a run: the number set, or for ``"auto"`` the value the run
    resolved from the scan (its summary's "auto" table); NaN when neither is known."""
    sec, _, name = dotted.partition(".")
    v = getattr(getattr(results.config, sec), name)
    if not isinstance(v, str):
        return float(v)
    rec = (results.summary or {}).get("auto", {}).get(dotted)
    return float(rec["value"]) if isinstance(rec, dict) and "value" in rec else float("nan")


def run_record(prev: Optional[StageResults], new: StageResults) -> RunRecord:
    """The :class:`RunRecord` of ``new``, its field compared with ``prev`` (may be None)."""
    c = new.counts()
    change = field_change(prev, new) if prev is not None else None
    return RunRecord(threshold=float(new.config.hgmm.split_threshold),
                     d_m=resolved_setting(new, "gp.d_m"), leaves=c.get("leaves"),
                     gp_points=c.get("gp_points"), field_change_rms=change)


def compare_shift(points: np.ndarray, gap: float = 0.15, up=None) -> np.ndarray:
    """(3,) translation placing the previous run's geometry beside the new one.

    Along the horizontal axis across the default view (:func:`gui_camera.across_axis`:
    x for a compact scene seen from -y, the short side of a street seen along its long
    side; horizontal for the data's up axis ``up``, default z), by the points' range on
    that axis plus ``gap`` of it, so the two copies stand side by side in the picture
    and never overlap (along the line of sight one copy stood behind the other).
    """
    from .gui_camera import across_axis

    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.zeros(3)
    if len(pts):
        ax = across_axis(pts, up)
        out[ax] = (1.0 + gap) * max(float(np.ptp(pts[:, ax])), 1e-6)
    return out
