"""Which reader handles which extension, and how folders and lists are read.

A folder is read as

* a Stanford range-scan set when it holds a ``.conf`` file with ``bmesh`` lines;
* otherwise a sequence: the scans in it (or in its ``velodyne/`` subfolder),
  sorted by name, each placed by its pose when a pose file is given
  (``poses=PATH``) or found (``poses*.txt`` next to the scans or next to the
  ``velodyne/`` folder), then merged.

A scan's pose index is its numeric file stem (KITTI ``000003.bin`` -> line 3)
when every stem is a number, else its position in the sorted list.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional

import numpy as np

from . import bunny, e57, kitti, las, numpy_io, pcd, ply, text
from ._common import RawScan, ScanReadError, check_file, merge, qname, to_metres, transform

__all__ = ["READERS", "SUPPORTED_EXTENSIONS", "read_file", "read_folder", "read_list",
           "up_axis"]

#: extension -> reader(path, **options) -> RawScan (input units)
READERS: dict[str, Callable[..., RawScan]] = {
    ".ply": ply.read_ply,
    ".pcd": pcd.read_pcd,
    ".xyz": text.read_text,
    ".pts": text.read_text,
    ".txt": text.read_text,
    ".csv": text.read_text,
    ".npy": numpy_io.read_npy,
    ".npz": numpy_io.read_npz,
    ".las": las.read_las,
    ".laz": las.read_las,
    ".e57": e57.read_e57,
    ".bin": kitti.read_kitti_bin,
}
#: Every extension read_scan accepts (case-insensitive); ".conf" is a Stanford scan set.
SUPPORTED_EXTENSIONS: tuple[str, ...] = tuple(READERS) + (".conf",)
_TEXT = {".xyz", ".pts", ".txt", ".csv"}
_NOT_SCANS_TXT = ("poses", "calib", "times")


#: The up axis of a Stanford range-scan set (``.conf``): y. The repository's objects
#: stand along +y; on the bunny the reference mesh spans 15.4 cm in y (its height) and
#: its open holes, at the bottom, lie within 2.6 cm of the lowest y.
STANFORD_UP = (0.0, 1.0, 0.0)


def up_axis(path) -> np.ndarray:
    """(3,) the up axis of the data at ``path``: y for a Stanford range-scan set (a
    ``.conf`` file, or a folder holding one), z for every other input."""
    p = Path(path)
    conf = p.suffix.lower() == ".conf" or (p.is_dir() and any(p.glob("*.conf")))
    return np.array(STANFORD_UP if conf else (0.0, 0.0, 1.0))


def _unknown_extension(path: Path) -> ScanReadError:
    return ScanReadError(
        f"Unknown scan extension {path.suffix or '(none)'!r} of {qname(path)}; supported: "
        f"{', '.join(SUPPORTED_EXTENSIONS)} (or a folder of scans). Convert the file or rename it."
    )


def read_file(path, *, units=None, labels=None, scans=None) -> RawScan:
    """Read one scan file into a RawScan in metres (units= applied)."""
    path = check_file(Path(path))
    ext = path.suffix.lower()
    if ext not in READERS:
        raise _unknown_extension(path)
    if labels is not None and ext != ".bin":
        raise ScanReadError(
            f"labels= applies to KITTI .bin scans only, not {qname(path)}; drop the option."
        )
    reader = READERS[ext]
    try:
        raw = reader(path, units=units, labels=labels, scans=scans)
    except PermissionError:
        raise ScanReadError(
            f"Permission denied reading {qname(path)}; make the file readable (e.g. chmod a+r)."
        ) from None
    return to_metres(raw, units)


def _pose_index(paths: list[Path]) -> list[int]:
    stems = [p.stem for p in paths]
    if all(s.isdigit() for s in stems):
        return [int(s) for s in stems]
    return list(range(len(paths)))


def _find_pose_file(dirs: list[Path]) -> Optional[Path]:
    found = []
    for d in dirs:
        found += sorted(p for p in d.glob("poses*.txt") if p.is_file())
    found = list(dict.fromkeys(found))
    if len(found) > 1:
        raise ScanReadError(
            f"Found several pose files ({', '.join(qname(p) for p in found)}); choose one with poses=PATH."
        )
    return found[0] if found else None


def _select(paths: list[Path], scans, max_scans, where: str) -> list[Path]:
    if scans is not None:
        names = [p.name for p in paths]
        stems = [p.stem for p in paths]
        chosen = []
        for s in scans:
            if isinstance(s, (int, np.integer)):
                if not 0 <= s < len(paths):
                    raise ScanReadError(
                        f"scans=[... {s} ...] is out of range for {where} with {len(paths)} scans "
                        f"(positions 0..{len(paths) - 1} in name order)."
                    )
                chosen.append(paths[int(s)])
            elif str(s) in names:
                chosen.append(paths[names.index(str(s))])
            elif str(s) in stems:
                chosen.append(paths[stems.index(str(s))])
            else:
                raise ScanReadError(
                    f"scans=[... {s!r} ...] names no scan of {where}; available: "
                    f"{stems[:8]}{' ...' if len(stems) > 8 else ''}."
                )
        paths = chosen
    if max_scans is not None:
        if int(max_scans) < 1:
            raise ScanReadError(f"max_scans={max_scans!r} must be at least 1.")
        paths = paths[: int(max_scans)]
    return paths


def _read_sequence(paths: list[Path], pose_file, *, units, scans, max_scans, where) -> RawScan:
    """Read, place by pose (when given) and merge a list of scan files."""
    index = dict(zip(paths, _pose_index(paths)))
    paths = _select(paths, scans, max_scans, where)
    poses = kitti.read_poses(pose_file) if pose_file else None
    raws = []
    for p in paths:
        raw = read_file(p, units=units)
        if poses is not None:
            i = index[p]
            if i >= len(poses):
                raise ScanReadError(
                    f"Scan {qname(p)} needs pose {i} but {qname(pose_file)} has only {len(poses)}; "
                    f"give the matching pose file with poses=PATH."
                )
            raw = transform(raw, poses[i, :, :3], poses[i, :, 3], origin_from_pose=True)
        raws.append(raw)
    src = where + (f" with poses {pose_file}" if pose_file else "")
    return merge(raws, source=src)


def _scan_files(folder: Path) -> list[Path]:
    try:
        files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in READERS)
    except PermissionError:
        raise ScanReadError(
            f"Permission denied listing folder {qname(folder)}; make it readable (chmod a+rx)."
        ) from None
    non_text = [p for p in files if p.suffix.lower() not in _TEXT]
    if non_text:
        # A folder of binary scans keeps its metadata (calib.txt, times.txt) as text.
        return non_text
    return [p for p in files if not p.name.lower().startswith(_NOT_SCANS_TXT)]


def read_folder(folder: Path, *, units=None, poses=None, scans=None, max_scans=None):
    """Read a folder: a ``.conf`` scan set, or a sequence of scans (see module doc).

    Returns a list of RawScans (one per scan, in metres, already placed).
    """
    folder = check_file(Path(folder))
    confs = sorted(folder.glob("*.conf"))
    if confs and poses is None:
        conf = folder / "bun.conf" if (folder / "bun.conf").is_file() else confs[0]
        return read_conf_file(conf, units=units, scans=scans, max_scans=max_scans)
    scan_dir = folder / "velodyne" if (folder / "velodyne").is_dir() else folder
    files = _scan_files(scan_dir)
    if not files:
        raise ScanReadError(
            f"Folder {qname(folder)} contains no scan files (supported: {', '.join(SUPPORTED_EXTENSIONS)}); "
            f"point read_scan at the folder that holds the scans."
        )
    if poses is False:
        pose_file = None
    elif poses is not None:
        pose_file = Path(poses)
    else:
        pose_file = _find_pose_file(list(dict.fromkeys([folder, scan_dir, scan_dir.parent])))
    return [_read_sequence(files, pose_file, units=units, scans=scans, max_scans=max_scans,
                           where=str(folder))]


def read_conf_file(conf: Path, *, units=None, scans=None, max_scans=None):
    conf = check_file(Path(conf))
    return bunny.read_conf(conf, scans=scans, max_scans=max_scans,
                           read_file=lambda p: read_file(p, units=units))


def read_list(paths, *, units=None, poses=None, scans=None, max_scans=None):
    """Read and merge a list of scan files, placed by a pose file when one applies.

    A pose file is used when given (``poses=PATH``) or, when every file sits
    in one ``velodyne/`` folder, when one is found next to that folder.
    """
    paths = [Path(p) for p in paths]
    if not paths:
        raise ScanReadError("read_scan got an empty list of scans; give at least one path.")
    where = f"{len(paths)} scans from {paths[0]}"
    if poses is False:
        pose_file = None
    elif poses is not None:
        pose_file = Path(poses)
    else:
        parents = {p.parent for p in paths}
        pose_file = None
        if len(parents) == 1:
            parent = parents.pop()
            if parent.name == "velodyne":
                pose_file = _find_pose_file([parent, parent.parent])
    out = []
    for p in paths:
        if p.is_dir():
            out += read_folder(p, units=units)
        elif p.suffix.lower() == ".conf":
            out += read_conf_file(p, units=units)
    files = [p for p in paths if not p.is_dir() and p.suffix.lower() != ".conf"]
    if files:
        out.append(_read_sequence(files, pose_file, units=units, scans=scans,
                                  max_scans=max_scans, where=where))
    return out

