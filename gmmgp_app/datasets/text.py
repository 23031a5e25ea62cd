"""Delimited text point clouds: XYZ, PTS, TXT, CSV.

Columns are separated by whitespace, commas or semicolons; lines starting
with ``#`` or ``//`` are comments. Leading non-numeric lines are a header:
when the last one names the columns (``x, y, z, intensity, label``) the
columns are taken by name, otherwise the first three columns are x, y, z.
A PTS file's leading point-count line is recognised and checked. For ``.pts``
without names the fourth column is the intensity, as the format defines.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._common import RawScan, ScanReadError, qname

__all__ = ["read_text"]

_MAX_HEADER_LINES = 50
_INTENSITY_NAMES = {"intensity", "i", "reflectance", "remission", "scalar_intensity"}
_LABEL_NAMES = {"label", "labels", "class", "classification", "semantic", "scalar_label"}


def _split(line: str, delim):
    return [t for t in (line.split(delim) if delim else line.split()) if t.strip()]


def _is_number(tok: str) -> bool:
    try:
        float(tok)
        return True
    except ValueError:
        return False


def _sniff(path: Path):
    """Return (delimiter, header_line_count, column_names, declared_count, ncols)."""
    try:
        with open(path, "r", encoding="utf-8") as fh:
            head = fh.read(1 << 16)
    except UnicodeDecodeError:
        raise ScanReadError(
            f"{qname(path)} is not a text file (it holds binary data); check the extension "
            f"(KITTI scans are .bin, NumPy arrays .npy)."
        ) from None
    lines = head.splitlines()
    if len(head) == (1 << 16) and lines:
        lines = lines[:-1]  # the last line may be cut by the read size
    header = []
    for i, line in enumerate(lines[: _MAX_HEADER_LINES + 1]):
        s = line.strip()
        if not s or s.startswith("#") or s.startswith("//"):
            header.append((i, None))
            continue
        delim = ";" if ";" in s else ("," if "," in s else None)
        tok = _split(s, delim)
        if len(tok) >= 3 and all(_is_number(t) for t in tok):
            names = None
            declared = None
            content = [(j, lines[j].strip()) for j, kind in header if kind == "text"]
            if content:
                last = [t.strip().strip('"').lower().lstrip("/") for t in _split(content[-1][1], delim)]
                if len(last) == len(tok) and {"x", "y", "z"} <= set(last):
                    names = last
                first = content[0][1].split()
                if len(content) == 1 and len(first) == 1 and first[0].isdigit():
                    declared = int(first[0])
            return delim, i, names, declared, len(tok)
        if len(tok) < 3 and not (len(tok) == 1 and tok[0].isdigit()) and all(_is_number(t) for t in tok):
            raise ScanReadError(
                f"Line {i + 1} of {qname(path)} has {len(tok)} numeric column(s); expected at "
                f"least 3 (x y z). Check the delimiter and the file."
            )
        header.append((i, "text"))
    raise ScanReadError(
        f"{qname(path)} has no line of at least 3 numbers in its first "
        f"{min(len(lines), _MAX_HEADER_LINES + 1)} lines (non-numeric text); expected rows of 'x y z ...'."
    )


def read_text(path: Path, **_) -> RawScan:
    """Read an XYZ/PTS/TXT/CSV file.

    Raises
    ------
    ScanReadError
        Non-numeric content, rows with too few columns, or fewer rows than a
        PTS count line declares.
    """
    delim, skip, names, declared, ncols = _sniff(path)
    if names is not None:
        cols = [names.index(c) for c in ("x", "y", "z")]
        icol = next((names.index(n) for n in names if n in _INTENSITY_NAMES), None)
        lcol = next((names.index(n) for n in names if n in _LABEL_NAMES), None)
    else:
        cols = [0, 1, 2]
        icol = 3 if (path.suffix.lower() == ".pts" and ncols >= 4) else None
        lcol = None
    use = cols + [c for c in (icol, lcol) if c is not None]
    try:
        arr = np.loadtxt(
            path, dtype=np.float64, delimiter=delim, comments=("#", "//"), skiprows=skip,
            usecols=use, ndmin=2, encoding="utf-8",
        )
    except (ValueError, IndexError) as exc:
        msg = str(exc).split("\n")[0]
        raise ScanReadError(
            f"Cannot parse {qname(path)} as 'x y z ...' rows after {skip} header line(s): "
            f"{msg} Fix or remove the offending lines."
        ) from None
    except UnicodeDecodeError:
        raise ScanReadError(
            f"{qname(path)} holds non-text bytes after line {skip}; the file is corrupt or not text."
        ) from None
    if declared is not None and len(arr) < declared:
        raise ScanReadError(
            f"{qname(path)} declares {declared} points on its first line but holds {len(arr)} rows; "
            f"the file is truncated."
        )
    k = 3
    intensity = labels = None
    if icol is not None:
        intensity = arr[:, k]
        k += 1
    if lcol is not None:
        labels = arr[:, k]
        if not np.all(np.isfinite(labels)) or np.any(labels != np.round(labels)):
            raise ScanReadError(
                f"Column '{names[lcol]}' of {qname(path)} must hold integer labels; found non-integers."
            )
        labels = labels.astype(np.int64)
    return RawScan(points=np.ascontiguousarray(arr[:, :3]), intensity=intensity, labels=labels,
                   source=str(path))
