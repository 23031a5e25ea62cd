"""KITTI / SemanticKITTI Velodyne scans and KITTI pose files.

A ``.bin`` scan is float32 records ``x y z reflectance`` in the sensor frame
(metres), so a single scan's origins are all zero. SemanticKITTI ``.label``
files hold one uint32 per point: low 16 bits semantic class, high 16 bits
instance id. The label file is found next to the scan
(``.../velodyne/000000.bin`` -> ``.../labels/000000.label``, or the same
folder and stem) unless given with ``labels=PATH`` (``labels=False`` skips it).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from ._common import RawScan, ScanReadError, qname, require_points

__all__ = ["read_kitti_bin", "find_label_file", "read_label_file", "read_poses"]


def find_label_file(bin_path: Path) -> Optional[Path]:
    """The SemanticKITTI label file of a scan, or None when there is none."""
    bin_path = Path(bin_path)
    candidates = [bin_path.with_suffix(".label")]
    if bin_path.parent.name == "velodyne":
        candidates.insert(0, bin_path.parent.parent / "labels" / (bin_path.stem + ".label"))
    return next((c for c in candidates if c.is_file()), None)


def read_label_file(path: Path, n: int, scan_path: Path) -> np.ndarray:
    """Semantic classes (low 16 bits) of a ``.label`` file with ``n`` entries."""
    path = Path(path)
    if not path.is_file():
        raise ScanReadError(f"Label file {qname(path)} does not exist; check labels=PATH.")
    size = path.stat().st_size
    if size != 4 * n:
        raise ScanReadError(
            f"Label file {qname(path)} has {size // 4} entries ({size} bytes) but scan "
            f"{qname(scan_path)} has {n} points; the label file belongs to another scan or is truncated."
        )
    raw = np.fromfile(path, dtype="<u4")
    return (raw & 0xFFFF).astype(np.int64)


def read_kitti_bin(path: Path, *, labels=None, **_) -> RawScan:
    """Read a KITTI Velodyne ``.bin`` scan with its SemanticKITTI labels if found.

    Parameters
    ----------
    path : Path
    labels : path, None or False
        Label file; None looks for it next to the scan; False ignores labels.

    Raises
    ------
    ScanReadError
        File size not a multiple of 16 bytes (truncated), label count mismatch.
    """
    size = path.stat().st_size
    if size % 16:
        raise ScanReadError(
            f"KITTI scan {qname(path)} has {size} bytes, not a multiple of 16 (float32 x y z "
            f"reflectance records); the file is truncated or not a KITTI scan."
        )
    rec = np.fromfile(path, dtype="<f4").reshape(-1, 4)
    n = len(rec)
    require_points(n, path)
    raw = RawScan(
        points=rec[:, :3].astype(np.float64),
        origins=np.zeros((n, 3)),
        intensity=rec[:, 3].astype(np.float64),
        source=str(path),
    )
    if labels is False:
        return raw
    label_path = Path(labels) if labels is not None else find_label_file(path)
    if label_path is not None:
        raw.labels = read_label_file(label_path, n, path)
        raw.source = f"{path} + {label_path.name}"
    return raw


def read_poses(path: Path) -> np.ndarray:
    """Read a KITTI pose file: one pose per line, 12 numbers (3x4 row-major) or 16 (4x4).

    Lines starting with ``#`` are comments.

    Returns
    -------
    (M, 3, 4) float64
        ``[R | t]`` mapping scan (sensor) coordinates to the common frame.
    """
    path = Path(path)
    if not path.is_file():
        raise ScanReadError(f"Pose file {qname(path)} does not exist; check poses=PATH.")
    rows = []
    with open(path, "r", encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            try:
                vals = [float(t) for t in s.replace(",", " ").split()]
            except ValueError:
                raise ScanReadError(
                    f"Line {lineno} of pose file {qname(path)} is not numbers: {s[:60]!r}; "
                    f"expected 12 numbers (3x4 row-major) per line."
                ) from None
            if len(vals) not in (12, 16):
                raise ScanReadError(
                    f"Line {lineno} of pose file {qname(path)} has {len(vals)} numbers; "
                    f"expected 12 (KITTI 3x4 row-major) or 16 (4x4)."
                )
            rows.append(vals[:12])
    if not rows:
        raise ScanReadError(f"Pose file {qname(path)} holds no poses; expected 12 numbers per line.")
    poses = np.asarray(rows, dtype=np.float64).reshape(-1, 3, 4)
    if not np.isfinite(poses).all():
        raise ScanReadError(f"Pose file {qname(path)} holds non-finite numbers; fix the poses.")
    return poses
