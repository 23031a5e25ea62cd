"""E57 (ASTM E2807) through pye57: every scan, placed by its pose, merged.

Each scan's points are in its own frame; its pose (rotation quaternion
w, x, y, z and translation, metres) maps them to the file's world frame, and
the translation is the scanner position, used as the per-point origin.
The transform is done here in float64 rather than by pye57.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._common import RawScan, ScanReadError, merge, qname, quat_to_matrix, transform

__all__ = ["read_e57"]


def _scan_xyz(data: dict) -> np.ndarray:
    if "cartesianX" in data:
        return np.stack([np.asarray(data[c], dtype=np.float64)
                         for c in ("cartesianX", "cartesianY", "cartesianZ")], axis=1)
    r = np.asarray(data["sphericalRange"], dtype=np.float64)
    az = np.asarray(data["sphericalAzimuth"], dtype=np.float64)
    el = np.asarray(data["sphericalElevation"], dtype=np.float64)
    ce = np.cos(el)
    return np.stack([r * ce * np.cos(az), r * ce * np.sin(az), r * np.sin(el)], axis=1)


def read_e57(path: Path, *, scans=None, **_) -> RawScan:
    """Read all scans of an E57 file (or those chosen by index with ``scans=``).

    Raises
    ------
    ScanReadError
        Not an E57 file, corrupt, or no scans with points.
    """
    import pye57

    try:
        e57 = pye57.E57(str(path))
    except Exception as exc:  # libe57 raises its own exception type
        raise ScanReadError(
            f"Cannot open {qname(path)} as E57 ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__}); "
            f"the file is corrupt, truncated or not E57."
        ) from None
    try:
        count = e57.scan_count
        if count == 0:
            raise ScanReadError(f"E57 file {qname(path)} contains no scans; export the point data again.")
        index = list(range(count)) if scans is None else [int(s) for s in scans]
        bad = [i for i in index if not 0 <= i < count]
        if bad:
            raise ScanReadError(
                f"scans={list(scans)!r} selects scan(s) {bad} but {qname(path)} has {count} "
                f"(indices 0..{count - 1})."
            )
        raws = []
        for i in index:
            header = e57.get_header(i)
            if header.point_count == 0:
                continue
            try:
                data = e57.read_scan(i, intensity=True, transform=False, ignore_missing_fields=True)
            except Exception as exc:
                raise ScanReadError(
                    f"Cannot read scan {i} of {qname(path)} ({exc}); the file is corrupt or truncated."
                ) from None
            raw = RawScan(points=_scan_xyz(data), source=f"{path}[{i}]")
            if "intensity" in data:
                raw.intensity = np.asarray(data["intensity"], dtype=np.float64)
            if header.has_pose():
                w, x, y, z = (float(v) for v in header.rotation)
                R = quat_to_matrix(w, x, y, z)
                t = np.asarray(header.translation, dtype=np.float64)
            else:
                R, t = np.eye(3), np.zeros(3)
            raws.append(transform(raw, R, t, origin_from_pose=True))
    finally:
        e57.close()
    if not raws:
        raise ScanReadError(
            f"Expected at least 1 point with finite coordinates, found 0 in {qname(path)}; "
            f"its scans are empty."
        )
    return merge(raws, source=str(path))
