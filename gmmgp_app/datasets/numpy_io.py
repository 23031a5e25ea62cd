"""NumPy arrays: ``.npy`` (N, >=3) and ``.npz`` archives, never unpickled.

An ``.npz`` holds ``points`` (N, 3) and optionally ``origins`` (N, 3),
``labels`` (N,), ``intensity`` (N,) and ``offset`` (3,); when ``offset`` is
present the stored points are local and original = points + offset. This is
the layout :mod:`gmmgp_app.synth` writes.
"""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np

from ._common import RawScan, ScanReadError, qname

__all__ = ["read_npy", "read_npz", "NPZ_KEYS"]

NPZ_KEYS = ("points", "origins", "labels", "intensity", "offset")


def _points_array(arr, path: Path, what: str) -> np.ndarray:
    if arr.dtype.names:  # structured array with x, y, z fields
        if not {"x", "y", "z"} <= set(arr.dtype.names):
            raise ScanReadError(
                f"{what} in {qname(path)} is a structured array without x, y, z fields "
                f"(fields: {list(arr.dtype.names)}); store an (N, 3) float array."
            )
        return np.stack([arr[c].astype(np.float64) for c in "xyz"], axis=1).reshape(-1, 3)
    if arr.ndim != 2 or arr.shape[1] < 3 or not np.issubdtype(arr.dtype, np.number):
        raise ScanReadError(
            f"Expected {what} in {qname(path)} with shape (N, 3) (or (N, >=3), x y z first) "
            f"and a numeric dtype, found shape {arr.shape} dtype {arr.dtype}."
        )
    return np.ascontiguousarray(arr[:, :3], dtype=np.float64)


def read_npy(path: Path, **_) -> RawScan:
    """Read an (N, >=3) array; the first three columns are x, y, z."""
    try:
        arr = np.load(path, allow_pickle=False)
    except ValueError as exc:
        raise ScanReadError(
            f"Cannot load {qname(path)} as a NumPy array without pickle ({exc}); "
            f"save it with np.save(path, points.astype(float)) or check it is not truncated."
        ) from None
    return RawScan(points=_points_array(arr, path, "the array"), source=str(path))


def _npz_member(z, key: str) -> np.ndarray:
    """``z[key]`` of an open ``np.load`` archive, the same array, with the member read
    and inflated in one call instead of numpy's 256 KiB chunks: zlib and the CRC then
    run on the whole member with the GIL released, so a read on a second thread
    (``gmmgp run`` reads while its compute modules import) does not wait for the GIL
    between chunks. Anything but a plain version 1 or 2 header with a non-object dtype
    and enough bytes is left to ``z[key]`` (and its errors)."""
    name = key + ".npy" if key + ".npy" in z.zip.namelist() else key
    with z.zip.open(name) as f:
        data = f.read()
    buf = io.BytesIO(data)
    try:
        version = np.lib.format.read_magic(buf)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(buf)
        elif version == (2, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(buf)
        else:
            return z[key]
    except ValueError:
        return z[key]
    count = 1
    for d in shape:
        count *= int(d)
    offset = buf.tell()
    if dtype.hasobject or len(data) - offset < count * dtype.itemsize:
        return z[key]
    arr = np.frombuffer(data, dtype=dtype, count=count, offset=offset)
    arr = arr.reshape(shape[::-1]).transpose() if fortran else arr.reshape(shape)
    return arr.copy(order="K")  # writable, like np.load's


def read_npz(path: Path, **_) -> RawScan:
    """Read ``points`` and the optional per-point fields of an ``.npz`` archive."""
    try:
        with np.load(path, allow_pickle=False) as z:
            keys = set(z.files)
            if "points" not in keys:
                raise ScanReadError(
                    f"{qname(path)} has no 'points' array (found {sorted(keys)}); "
                    f"save with np.savez(path, points=xyz, ...)."
                )
            data = {k: _npz_member(z, k) for k in NPZ_KEYS if k in keys}
    except (ValueError, zipfile.BadZipFile, EOFError) as exc:
        if isinstance(exc, ScanReadError):
            raise
        raise ScanReadError(
            f"Cannot load {qname(path)} as an .npz archive without pickle ({exc}); "
            f"the file is truncated or holds object arrays."
        ) from None
    pts = _points_array(data["points"], path, "'points'")
    n = len(pts)
    out = RawScan(points=pts, source=str(path))
    if "origins" in data:
        org = np.asarray(data["origins"], dtype=np.float64)
        if org.shape != (n, 3):
            raise ScanReadError(
                f"Expected 'origins' in {qname(path)} with shape ({n}, 3), found {org.shape}."
            )
        out.origins = org
    for name, dtype in (("labels", np.int64), ("intensity", np.float64)):
        if name in data:
            v = np.asarray(data[name]).reshape(-1) if data[name].ndim == 2 and 1 in data[name].shape else data[name]
            if v.shape != (n,):
                raise ScanReadError(
                    f"Expected '{name}' in {qname(path)} with shape ({n},), found {data[name].shape}."
                )
            setattr(out, name, v.astype(dtype))
    if "offset" in data:
        off = np.asarray(data["offset"], dtype=np.float64)
        if off.size != 3 or not np.isfinite(off).all():
            raise ScanReadError(
                f"Expected 'offset' in {qname(path)} with shape (3,) and finite values, "
                f"found {off.shape} {off.ravel()[:6].tolist()}."
            )
        out.base = off.reshape(3)
    return out
