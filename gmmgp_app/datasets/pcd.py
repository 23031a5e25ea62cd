"""PCD point clouds (PCL format) through Open3D.

Open3D returns an empty cloud for a truncated binary PCD and a cloud padded
with garbage for a truncated ascii one, so the header is checked here first.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._common import RawScan, ScanReadError, qname, require_points

__all__ = ["read_pcd"]


def _parse_header(path: Path):
    with open(path, "rb") as fh:
        head = fh.read(1 << 16)
    fields, sizes, counts, n_points, data, header_len = [], [], [], None, None, None
    pos = 0
    while pos < len(head):
        nl = head.find(b"\n", pos)
        if nl < 0:
            break
        line = head[pos:nl].decode("ascii", errors="replace").strip()
        pos = nl + 1
        tok = line.split()
        if not tok or tok[0].startswith("#"):
            continue
        key = tok[0].upper()
        try:
            if key == "FIELDS":
                fields = tok[1:]
            elif key == "SIZE":
                sizes = [int(t) for t in tok[1:]]
            elif key == "COUNT":
                counts = [int(t) for t in tok[1:]]
            elif key == "POINTS":
                n_points = int(tok[1])
            elif key == "DATA":
                data = tok[1].lower()
                header_len = pos
                break
        except (ValueError, IndexError):
            raise ScanReadError(
                f"PCD header of {qname(path)} has a bad line {line!r}; the file is corrupt."
            ) from None
    if data is None or n_points is None or not {"x", "y", "z"} <= set(fields):
        raise ScanReadError(
            f"{qname(path)} is not a readable PCD file (missing FIELDS x y z, POINTS or DATA "
            f"in the header); check the file or its extension."
        )
    if not counts:
        counts = [1] * len(fields)
    return fields, sizes, counts, n_points, data, header_len


def read_pcd(path: Path, **_) -> RawScan:
    """Read x, y, z of a PCD file (ascii, binary or binary_compressed).

    Raises
    ------
    ScanReadError
        Bad header, zero points, or data shorter than the header declares.
    """
    import open3d as o3d

    fields, sizes, counts, n, data, header_len = _parse_header(path)
    require_points(n, path)
    size = path.stat().st_size
    if data == "binary" and len(sizes) == len(fields):
        need = header_len + n * sum(s * c for s, c in zip(sizes, counts))
        if size < need:
            raise ScanReadError(
                f"PCD file {qname(path)} is truncated: the header declares {n} points "
                f"({need} bytes) but the file has {size} bytes; export or download it again."
            )
    elif data == "ascii":
        with open(path, "rb") as fh:
            fh.seek(header_len)
            rows = [ln for ln in fh.read().split(b"\n") if ln.strip()]
        if len(rows) < n or len(rows[n - 1].split()) < sum(counts):
            raise ScanReadError(
                f"PCD file {qname(path)} is truncated: the header declares {n} points but "
                f"only {min(len(rows), n)} rows (the last may be cut) follow; export it again."
            )
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        pc = o3d.io.read_point_cloud(str(path), format="pcd")
    pts = np.asarray(pc.points, dtype=np.float64)
    if len(pts) != n:
        raise ScanReadError(
            f"PCD file {qname(path)} declares {n} points but Open3D read {len(pts)}; "
            f"the file is corrupt or truncated."
        )
    return RawScan(points=pts, source=str(path))
