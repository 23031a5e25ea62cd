"""PCD point clouds (PCL format) through Open3D.

Open3D returns an empty cloud for a truncated binary PCD and a cloud padded
with garbage for a truncated ascii one, so the header is checked here first.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._common import RawScan, ScanReadError, qname, read_open3d_points, require_points

__all__ = ["read_pcd"]


def _parse_header(path: Path):
    with open(path, "rb") as fh:
        head = fh.read(1 << 16)
    fields, sizes, types, counts, n_points, data, header_len = [], [], [], [], None, None, None
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
            elif key == "TYPE":
                types = [t.upper() for t in tok[1:]]
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
    return fields, sizes, types, counts, n_points, data, header_len


_PCD_TYPES = {("F", 4): "<f4", ("F", 8): "<f8", ("I", 1): "i1", ("I", 2): "<i2",
              ("I", 4): "<i4", ("I", 8): "<i8", ("U", 1): "u1", ("U", 2): "<u2",
              ("U", 4): "<u4", ("U", 8): "<u8"}


def _record_dtype(fields, sizes, types, counts):
    """numpy dtype of one binary PCD record, or None when the header does not define it."""
    if not (len(fields) == len(sizes) == len(types) == len(counts)):
        return None
    parts = []
    for i, (name, size, typ, cnt) in enumerate(zip(fields, sizes, types, counts)):
        code = _PCD_TYPES.get((typ, size))
        if code is None:
            return None
        # PCL pads with fields named "_"; names must be unique for numpy.
        key = name if name in "xyz" and name not in [p[0] for p in parts] else f"_{i}"
        parts.append((key, code, (cnt,)) if cnt > 1 else (key, code))
    return np.dtype(parts)


def _ascii_columns(fields, counts):
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(int)
    return [int(starts[fields.index(c)]) for c in "xyz"]


def _count_lines(path: Path, header_len: int) -> int:
    with open(path, "rb") as fh:
        return fh.read(header_len).count(b"\n")


def read_pcd(path: Path, **_) -> RawScan:
    """Read x, y, z of a PCD file (ascii, binary or binary_compressed).

    Raises
    ------
    ScanReadError
        Bad header, zero points, or data shorter than the header declares.
    """

    fields, sizes, types, counts, n, data, header_len = _parse_header(path)
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
    dtype = _record_dtype(fields, sizes, types, counts)
    if data == "binary" and dtype is not None:
        # Read here, not by Open3D: it returns zeros for double-precision (SIZE 8) fields.
        rec = np.fromfile(path, dtype=dtype, count=n, offset=header_len)
        return RawScan(points=np.stack([rec[c].astype(np.float64) for c in "xyz"], axis=1),
                       source=str(path))
    if data == "ascii":
        cols = _ascii_columns(fields, counts)
        try:
            arr = np.loadtxt(path, dtype=np.float64, skiprows=_count_lines(path, header_len),
                             usecols=cols, ndmin=2, max_rows=n)
        except ValueError as exc:
            raise ScanReadError(
                f"Cannot parse the ascii data of PCD file {qname(path)} "
                f"({str(exc).splitlines()[0]}); the file is corrupt."
            ) from None
        return RawScan(points=np.ascontiguousarray(arr), source=str(path))
    xyz_sizes = [sizes[fields.index(c)] for c in "xyz"] if len(sizes) == len(fields) else []
    if any(sz == 8 for sz in xyz_sizes):
        raise ScanReadError(
            f"PCD file {qname(path)} stores double-precision x, y, z as binary_compressed, "
            f"which Open3D misreads; convert it to binary or ascii PCD (e.g. pcl_convert_pcd_"
            f"ascii_binary) or to PLY."
        )
    return RawScan(points=read_open3d_points(path, "pcd", n, "points"), source=str(path))
