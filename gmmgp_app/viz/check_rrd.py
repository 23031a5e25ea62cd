"""Record a scan check (:func:`gmmgp_app.check.check_scan`) to a rerun ``.rrd`` file.

Entity paths (one explicit ``rr.RecordingStream``, all static):

=========================  ===========================================================
``world``                  the map's up axis (check.json "up") as the 3D view's
                           coordinate convention: a check of a y-up map opens upright
``world/points``           the scan's points in the map frame (after the registration),
                           coloured by z: blue (d < 0, behind the map's surface) -
                           white (0) - red (in front of it), saturated at
                           2 x the z threshold; grey where the map does not know the
                           surface; per-point distance, std and z as extra values
``world/changed``          changed points, orange
``world/segments``         bounding boxes of the changed segments, with their sizes
``summary``                Markdown table of check.json's main figures
=========================  ===========================================================

The file is written under a temporary name and renamed when complete.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._atomic import atomic_path

__all__ = ["z_colors", "write_check_rrd"]


def z_colors(z, known, z_threshold: float) -> np.ndarray:
    """(N, 3) uint8 colours of z (diverging RdBu, saturated at 2 * z_threshold)."""
    import matplotlib

    t = 0.5 - 0.5 * np.clip(np.nan_to_num(z) / (2.0 * z_threshold), -1.0, 1.0)
    rgb = (matplotlib.colormaps["RdBu"](t)[:, :3] * 255 + 0.5).astype(np.uint8)
    rgb[~np.asarray(known, dtype=bool)] = (150, 150, 150)
    return rgb


def write_check_rrd(result, path, *, application_id: str = "gmmgp-check") -> Path:
    """Write ``result`` (a CheckResult) to the rerun recording ``path``."""
    import rerun as rr

    path = Path(path)
    ok = np.all(np.isfinite(result.points), axis=1)
    z_thr = float(result.summary["z_threshold"])
    with atomic_path(path, ".rrd") as tmp:
        rec = rr.RecordingStream(application_id)
        rec.set_log_time_enabled(False)
        rec.set_log_tick_enabled(False)
        rec.save(str(tmp))
        pts = result.points[ok]
        from .rerun_observer import view_coordinates

        rec.log("world", view_coordinates(result.summary.get("up")), static=True)
        rec.log("world/points", rr.Points3D(pts, colors=z_colors(result.z[ok], result.known[ok],
                                                                 z_thr), radii=-1.5),
                rr.AnyValues(distance=result.distance[ok], std=result.std[ok], z=result.z[ok]),
                static=True)
        ch = result.changed & ok
        rec.log("world/changed", rr.Points3D(result.points[ch], colors=[255, 140, 0],
                                             radii=-2.0), static=True)
        if result.segments:
            lo = np.array([s.bbox_min for s in result.segments])
            hi = np.array([s.bbox_max for s in result.segments])
            rec.log("world/segments", rr.Boxes3D(
                centers=(lo + hi) / 2, half_sizes=np.maximum((hi - lo) / 2, 0.01),
                labels=[f"{s.size} pts, d={s.mean_distance:+.2f} m" for s in result.segments],
                colors=[255, 140, 0]), static=True)
        s = result.summary
        rows = [("points", s["points"]), ("fraction known", f"{s['fraction_known']:.3f}"),
                ("fraction changed", f"{s['fraction_changed']:.4f}"),
                ("robust RMS (m)", f"{s['robust_rms_m']:.4f}"),
                ("segments", s["n_segments"]), ("aligned", s["aligned"]),
                ("iterations", s["iterations"])]
        md = "| figure | value |\n|---|---|\n" + "\n".join(f"| {k} | {v} |" for k, v in rows)
        rec.log("summary", rr.TextDocument(md, media_type="text/markdown"), static=True)
        rec.flush()
        rec.disconnect()
    return path
