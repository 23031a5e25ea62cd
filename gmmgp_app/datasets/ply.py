"""PLY point clouds (and the vertices of PLY meshes) through Open3D.

Open3D fills a truncated PLY's missing vertices with garbage instead of
failing, so the header is parsed here and the data size checked against it
before Open3D reads the file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ._common import RawScan, ScanReadError, qname, read_open3d_points, require_points

__all__ = ["read_ply", "parse_ply_header"]

_PLY_SIZES = {
    "char": 1, "int8": 1, "uchar": 1, "uint8": 1,
    "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
    "int": 4, "int32": 4, "uint": 4, "uint32": 4,
    "float": 4, "float32": 4, "double": 8, "float64": 8,
}


@dataclass
class PlyElement:
    name: str
    count: int
    properties: list  # (name, type) for scalars, (name, "list") for lists

    @property
    def row_size(self):
        """Bytes per binary row, or None when a list property makes it variable."""
        if any(t == "list" for _, t in self.properties):
            return None
        return sum(_PLY_SIZES[t] for _, t in self.properties)


def parse_ply_header(path: Path):
    """Return (format, elements, header_length_in_bytes) of a PLY file."""
    with open(path, "rb") as fh:
        head = fh.read(1 << 16)
    if not head.startswith(b"ply"):
        raise ScanReadError(
            f"{qname(path)} is not a PLY file (it does not start with 'ply'); "
            f"check the file or its extension."
        )
    end = head.find(b"end_header")
    if end < 0:
        raise ScanReadError(
            f"PLY header of {qname(path)} has no 'end_header' line; the file is truncated or not PLY."
        )
    nl = head.find(b"\n", end)
    header_len = nl + 1 if nl >= 0 else len(head)
    fmt, elements = None, []
    for line in head[:end].decode("ascii", errors="replace").splitlines():
        tok = line.split()
        if not tok:
            continue
        if tok[0] == "format" and len(tok) >= 2:
            fmt = tok[1]
        elif tok[0] == "element" and len(tok) >= 3:
            try:
                elements.append(PlyElement(tok[1], int(tok[2]), []))
            except ValueError:
                raise ScanReadError(
                    f"PLY header of {qname(path)} has a bad element line {line!r}; the file is corrupt."
                ) from None
        elif tok[0] == "property" and elements and len(tok) >= 3:
            if tok[1] == "list":
                elements[-1].properties.append((tok[-1], "list"))
            elif tok[1] in _PLY_SIZES:
                elements[-1].properties.append((tok[2], tok[1]))
            else:
                raise ScanReadError(
                    f"PLY header of {qname(path)} has an unknown property type {tok[1]!r}; the file is corrupt."
                )
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ScanReadError(
            f"PLY header of {qname(path)} has format {fmt!r}; expected ascii, "
            f"binary_little_endian or binary_big_endian."
        )
    return fmt, elements, header_len


def _check_ply_size(path: Path, fmt: str, elements, header_len: int) -> int:
    """Raise if the data section is shorter than the header promises; return the vertex count."""
    vertex = next((e for e in elements if e.name == "vertex"), None)
    if vertex is None or not {"x", "y", "z"} <= {p for p, _ in vertex.properties}:
        raise ScanReadError(
            f"PLY file {qname(path)} has no vertex element with x, y, z properties; "
            f"it holds no points."
        )
    require_points(vertex.count, path)
    size = path.stat().st_size
    if fmt != "ascii":
        # Only rows of fixed size (no list properties) up to the vertex block can be checked.
        upto = elements[: elements.index(vertex) + 1]
        if all(e.row_size is not None for e in upto):
            need = header_len + sum(e.row_size * e.count for e in upto)
            if size < need:
                before = need - vertex.row_size * vertex.count
                have = max(0, (size - before) // vertex.row_size)
                raise ScanReadError(
                    f"PLY file {qname(path)} is truncated: the header declares {vertex.count} "
                    f"vertices ({need} bytes) but the file has {size} bytes (about {have} "
                    f"vertices); export or download it again."
                )
        return vertex.count
    # ascii: one line per element row
    with open(path, "rb") as fh:
        fh.seek(header_len)
        data = fh.read()
    lines = data.split(b"\n")
    while lines and not lines[-1].strip():
        lines.pop()
    total = sum(e.count for e in elements)
    vstart = sum(e.count for e in elements[: elements.index(vertex)])
    n_lines = len(lines)
    truncated = n_lines < total
    if not truncated and vertex.row_size is not None:
        # a cut inside the last vertex row leaves it with too few values
        last = lines[vstart + vertex.count - 1].split()
        truncated = len(last) < len(vertex.properties)
    if truncated:
        have = max(0, min(n_lines - vstart, vertex.count))
        raise ScanReadError(
            f"PLY file {qname(path)} is truncated: the header declares {vertex.count} vertices "
            f"but only about {have} complete rows follow; export or download it again."
        )
    return vertex.count


def read_ply(path: Path, **_) -> RawScan:
    """Read the vertices of a PLY file (binary or ascii) as points.

    Raises
    ------
    ScanReadError
        Not PLY, no x/y/z vertex element, zero vertices, or truncated data.
    """

    fmt, elements, header_len = parse_ply_header(path)
    n = _check_ply_size(path, fmt, elements, header_len)
    return RawScan(points=read_open3d_points(path, "ply", n, "vertices"), source=str(path))
