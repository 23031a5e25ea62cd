"""Stanford range-scan sets described by a ``.conf`` file (e.g. the bunny's ``bun.conf``).

Each ``bmesh FILE tx ty tz qx qy qz qw`` line places one PLY range scan.
The stored quaternion maps world to scan, so it must be conjugated:
``world = R(q)^T p + t``. Measured on the bunny: the scans then lie about
0.55 mm (median) from the reference mesh; with ``R(q)`` they are centimetres off.
The scanner positions are not recorded, so origins are None.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._common import RawScan, ScanReadError, qname, quat_to_matrix

__all__ = ["read_conf", "parse_conf"]


def parse_conf(path: Path) -> list[tuple[Path, np.ndarray, np.ndarray]]:
    """Return [(ply_path, t (3,), q (4,) as qx qy qz qw)] of every ``bmesh`` line."""
    path = Path(path)
    entries = []
    with open(path, "r", encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            tok = line.split()
            if not tok or tok[0] != "bmesh":
                continue
            if len(tok) != 9:
                raise ScanReadError(
                    f"Line {lineno} of {qname(path)} has {len(tok)} fields; expected "
                    f"'bmesh FILE tx ty tz qx qy qz qw'."
                )
            try:
                vals = np.array([float(t) for t in tok[2:]])
            except ValueError:
                raise ScanReadError(
                    f"Line {lineno} of {qname(path)} has non-numeric pose values: {line.strip()!r}."
                ) from None
            entries.append((path.parent / tok[1], vals[:3], vals[3:]))
    if not entries:
        raise ScanReadError(
            f"{qname(path)} has no 'bmesh FILE tx ty tz qx qy qz qw' lines; it lists no scans."
        )
    return entries


def _select(entries, scans, max_scans, where):
    if scans is not None:
        names = [e[0].name for e in entries]
        stems = [e[0].stem for e in entries]
        chosen = []
        for s in scans:
            if isinstance(s, (int, np.integer)):
                if not 0 <= s < len(entries):
                    raise ScanReadError(
                        f"scans=[... {s} ...] is out of range for {where} with {len(entries)} scans "
                        f"(indices 0..{len(entries) - 1})."
                    )
                chosen.append(entries[int(s)])
            else:
                s = str(s)
                if s in names:
                    chosen.append(entries[names.index(s)])
                elif s in stems:
                    chosen.append(entries[stems.index(s)])
                else:
                    raise ScanReadError(
                        f"scans=[... {s!r} ...] names no scan of {where}; available: {stems}."
                    )
        entries = chosen
    if max_scans is not None:
        entries = entries[: int(max_scans)]
    return entries


def read_conf(path: Path, *, scans=None, max_scans=None, read_file=None, **_) -> list[RawScan]:
    """Read the PLY scans listed in a ``.conf`` file, each placed in the world frame.

    Parameters
    ----------
    scans : sequence of int or str, optional
        Indices (order of the file) or names/stems of the scans to keep.
    max_scans : int, optional
        Keep at most this many (after ``scans``).
    read_file : callable
        Reads one PLY into a RawScan in metres (the registry's reader).
    """
    entries = _select(parse_conf(path), scans, max_scans, qname(path))
    out = []
    for ply, t, q in entries:
        raw = read_file(ply)
        qx, qy, qz, qw = q
        R = quat_to_matrix(qw, qx, qy, qz)
        pts = (raw.points + raw.base) @ R + t  # row-vector form of R^T p + t
        out.append(RawScan(points=pts, units=raw.units, source=str(ply)))
    return out
