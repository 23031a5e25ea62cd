"""Scan readers: every supported format into one :class:`~gmmgp_app.types.Scan`.

>>> import gmmgp_app as gm
>>> scan = gm.read_scan("scan.laz")                               # doctest: +SKIP
>>> scan = gm.read_scan("seq00/", max_scans=3)                    # doctest: +SKIP
>>> scan = gm.read_scan("velodyne/000000.bin", classes=[50, 51])  # doctest: +SKIP

Formats (by extension, case-insensitive):

========================  ==================================================
``.ply`` ``.pcd``         Open3D (header checked here: truncation is an error)
``.xyz .pts .txt .csv``   text columns, whitespace/comma/semicolon, optional header
``.npy`` ``.npz``         NumPy without pickle; npz keys points, origins, labels,
                          intensity, offset
``.las`` ``.laz``         laspy + lazrs; classification -> labels; CRS unit honoured;
                          extra dims origin_x/y/z -> origins
``.e57``                  pye57; all scans merged by pose, scanner positions as origins
``.bin``                  KITTI Velodyne (+ SemanticKITTI ``.label``), origins zero
``.conf``                 Stanford scan set (``bmesh`` lines), e.g. the bunny
folder / list             merged; a KITTI pose file places each scan and gives origins
========================  ==================================================

Coordinates are converted to metres. When they are far from zero
(max |coordinate| > 1e4 m) they are shifted, in float64 and before anything
else, by ``Scan.offset`` = the bounding-box minimum rounded down to a
multiple of 1000 m; ``Scan.points`` are local (original = points + offset).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Optional, Sequence, Union

import numpy as np

from ..types import Scan
from ._common import (
    OFFSET_QUANTUM_M,
    OFFSET_THRESHOLD_M,
    ScanReadError,
    ScanWarning,
    auto_offset,
    check_file,
    filter_classes,
    finalize,
    merge,
    parse_units,
    qname,
)
from .las import read_las_header, write_las
from .registry import (SUPPORTED_EXTENSIONS, read_conf_file, read_file, read_folder, read_list,
                       up_axis)

__all__ = [
    "read_scan",
    "scan_summary",
    "write_las",
    "read_las_header",
    "parse_units",
    "auto_offset",
    "ScanReadError",
    "ScanWarning",
    "SUPPORTED_EXTENSIONS",
    "OFFSET_THRESHOLD_M",
    "OFFSET_QUANTUM_M",
]

PathLike = Union[str, Path]


def read_scan(
    path_or_paths: Union[PathLike, Sequence[PathLike]],
    *,
    units=None,
    offset="auto",
    classes: Optional[Sequence[int]] = None,
    labels=None,
    poses=None,
    scans: Optional[Sequence] = None,
    max_scans: Optional[int] = None,
) -> Scan:
    """Read a scan file, a folder of scans or a list of scans into one Scan.

    Parameters
    ----------
    path_or_paths : path or sequence of paths
        A file (see the module table), a folder (Stanford ``.conf`` set, or a
        sequence of scans, e.g. a KITTI sequence with ``velodyne/`` and a
        ``poses*.txt``), or a list of files/folders merged into one Scan.
    units : str or float, optional
        Input unit, overriding the file's own (LAS CRS): "m", "ft"
        (international foot, 0.3048 m), "us-ft" (US survey foot, 1200/3937 m),
        "mm", "cm", or metres per unit as a number. Default: the file's CRS
        unit for LAS/LAZ, metres for everything else.
    offset : "auto", (3,) array_like or None
        "auto" shifts far-away coordinates (max |coordinate| > 1e4 m) by the
        bounding-box minimum rounded down to a multiple of 1000 m (an NPZ's
        stored ``offset`` is kept as it is); an array is used as the offset
        (metres, original frame); None keeps the original coordinates.
    classes : sequence of int, optional
        Keep only points whose label (SemanticKITTI class, LAS classification)
        is one of these; needs labels.
    labels : path or False, optional
        SemanticKITTI ``.label`` file of a single ``.bin`` scan (found
        automatically when None; False ignores labels).
    poses : path or False, optional
        KITTI pose file (one 3x4 row-major pose per line) for a folder or list
        of scans; found automatically as ``poses*.txt`` when None; False
        disables. Each scan is mapped by its pose and its points get the pose
        translation as sensor origin.
    scans : sequence of int or str, optional
        Which scans of a folder, list, ``.conf`` set or E57 file to read:
        positions (name order; file order for ``.conf`` and E57) or names/stems.
    max_scans : int, optional
        Read at most this many scans (after ``scans``).

    Returns
    -------
    Scan
        ``points`` (N, 3) float64 metres in the local frame, ``origins`` (N, 3)
        when known (KITTI: sensor frame zeros or pose translations; E57 and
        posed sequences: scanner positions; NPZ: as stored), ``offset`` (3,),
        ``labels`` (N,) int64 and ``intensity`` (N,) when the format has them;
        ``up``, the data's up axis (y for a Stanford ``.conf`` set, z otherwise; a
        list takes its inputs' common up axis, z when they differ).

    Raises
    ------
    ScanReadError
        Missing, empty, unreadable, truncated or malformed input, unknown
        extension, folder without scans, or no finite point. The message names
        the file, the problem and a fix.

    Warns
    -----
    ScanWarning
        When points with non-finite coordinates are dropped (the message counts
        them), or optional fields are missing from some merged scans.
    """
    if isinstance(path_or_paths, (str, Path)) or hasattr(path_or_paths, "__fspath__"):
        path = Path(path_or_paths)
        where = qname(path)
        up = up_axis(path)
        if path.is_dir():
            raws = read_folder(path, units=units, poses=poses, scans=scans, max_scans=max_scans)
            if labels is not None:
                raise ScanReadError(
                    f"labels= applies to a single KITTI .bin scan, not the folder {where}; "
                    f"labels next to each scan are found automatically."
                )
        elif path.suffix.lower() == ".conf":
            raws = read_conf_file(path, units=units, scans=scans, max_scans=max_scans)
        elif poses is not None and poses is not False:
            raws = read_list([path], units=units, poses=poses)
        else:
            check_file(path)
            if max_scans is not None or (scans is not None and path.suffix.lower() != ".e57"):
                raise ScanReadError(
                    f"scans=/max_scans= select scans of a folder, list, .conf set or E57 file; "
                    f"{where} is a single scan, drop the option."
                )
            raws = [read_file(path, units=units, labels=labels, scans=scans)]
    else:
        paths = list(path_or_paths)
        if labels is not None:
            raise ScanReadError(
                "labels= applies to a single KITTI .bin scan, not a list; "
                "labels next to each scan are found automatically."
            )
        raws = read_list(paths, units=units, poses=poses, scans=scans, max_scans=max_scans)
        where = qname(paths[0]) + (f" and {len(paths) - 1} more" if len(paths) > 1 else "")
        ups = {tuple(up_axis(p)) for p in paths}
        up = ups.pop() if len(ups) == 1 else None
    raw = merge(raws, source=raws[0].source if len(raws) == 1 else where.strip("'"))
    raw = filter_classes(raw, classes, where)
    scan = finalize(raw, offset=offset, where=where)
    if up is not None and tuple(up) != tuple(scan.up):
        scan = dataclasses.replace(scan, up=up)
    return scan


def scan_summary(scan: Scan, *, max_sample: int = 20_000, seed: int = 0) -> dict:
    """Facts about a scan, for ``gmmgp info`` and logs.

    Parameters
    ----------
    scan : Scan
    max_sample : int
        The spacing is the median distance from at most this many randomly
        chosen points to their nearest other point of the whole scan.
    seed : int
        Seed of that sample (the result is reproducible).

    Returns
    -------
    dict
        ``n_points`` int; ``extent_m`` [dx, dy, dz]; ``bbox_min`` / ``bbox_max``
        [x, y, z] in original coordinates (points + offset), metres;
        ``spacing_m`` median nearest-neighbour distance (metres); ``units``
        of the input; ``has_origins`` bool; ``offset`` [x, y, z];
        ``classes`` {label: count} or None; ``has_intensity`` bool; ``source``.
    """
    from scipy.spatial import cKDTree

    pts = scan.points
    n = len(pts)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    spacing = float("nan")
    if n >= 2:
        rng = np.random.default_rng(seed)
        sample = pts if n <= max_sample else pts[rng.choice(n, max_sample, replace=False)]
        dist, _ = cKDTree(pts).query(sample, k=2)
        spacing = float(np.median(dist[:, 1]))
    classes = None
    if scan.labels is not None:
        vals, counts = np.unique(scan.labels, return_counts=True)
        classes = {int(v): int(c) for v, c in zip(vals, counts)}
    return {
        "n_points": int(n),
        "extent_m": (hi - lo).tolist(),
        "bbox_min": (lo + scan.offset).tolist(),
        "bbox_max": (hi + scan.offset).tolist(),
        "spacing_m": spacing,
        "units": scan.units,
        "has_origins": scan.origins is not None,
        "offset": scan.offset.tolist(),
        "classes": classes,
        "has_intensity": scan.intensity is not None,
        "source": scan.source,
    }
