"""LAS / LAZ through laspy (LAZ needs the lazrs backend), with the CRS unit honoured.

The horizontal and vertical linear units come from the GeoTIFF key directory
VLR (``ProjLinearUnitsGeoKey`` 3076, ``GeogLinearUnitsGeoKey`` 2052 for
geocentric data, ``VerticalUnitsGeoKey`` 4099) or, failing that, from the
OGC WKT VLR. Both are parsed here so pyproj is not needed. When no vertical
unit is given, z is taken to share the horizontal unit (the common practice
for airborne LAS in feet, e.g. Autzen). ``units=`` overrides everything.
Coordinates are ``X * scale + offset`` computed from the stored integers in
float64, so millimetres survive UTM-sized values.
"""

from __future__ import annotations

import logging
import re
import struct
import warnings
from contextlib import contextmanager
from pathlib import Path
from typing import Optional

import numpy as np

from ._common import (
    RawScan,
    ScanReadError,
    ScanWarning,
    qname,
    require_points,
    unit_name,
)

__all__ = ["read_las", "read_las_header", "crs_units", "EPSG_LINEAR_UNITS", "parse_geokeys",
           "wkt_units"]

#: EPSG linear unit codes -> metres per unit (the ones met in practice).
EPSG_LINEAR_UNITS = {
    9001: 1.0,                  # metre
    9002: 0.3048,               # international foot
    9003: 1200.0 / 3937.0,      # US survey foot
    9005: 0.3047972654,         # Clarke's foot
    9014: 1.8288,               # fathom
    9030: 1852.0,               # nautical mile
    9031: 1.0000135965,         # German legal metre
    9035: 1609.347218694,       # US survey mile
    9036: 1000.0,               # kilometre
    9037: 0.9143917962,         # Clarke's yard
    9040: 0.914398415,          # British yard (Sears 1922)
    9041: 0.3047994715,         # British foot (Sears 1922)
    9093: 1609.344,             # statute mile
    9096: 0.9144,               # yard
    1025: 0.001,                # millimetre
    1033: 0.01,                 # centimetre
}
_USER_DEFINED = 32767
_KEY_MODEL_TYPE = 1024
_KEY_GEOG_LINEAR = 2052
_KEY_GEOG_LINEAR_SIZE = 2053
_KEY_PROJ_LINEAR = 3076
_KEY_PROJ_LINEAR_SIZE = 3077
_KEY_VERTICAL = 4099
_KEY_PROJECTED_CS = 3072
_TAG_DOUBLES = 34736


def _metric_projected_cs(code) -> bool:
    """EPSG projected CRS codes known to be in metres without a database (UTM zones)."""
    return code is not None and (
        32601 <= code <= 32660 or 32701 <= code <= 32760  # WGS 84 / UTM north, south
        or 25828 <= code <= 25838                        # ETRS89 / UTM
        or 26901 <= code <= 26923                        # NAD83 / UTM
    )


def _vlr_bytes(vlr) -> bytes:
    if hasattr(vlr, "record_data_bytes"):
        return bytes(vlr.record_data_bytes())
    return bytes(getattr(vlr, "record_data", b""))


def parse_geokeys(directory: bytes, doubles: bytes = b"") -> dict:
    """Decode a GeoKeyDirectoryTag (VLR 34735) into {key_id: value}.

    Values stored in the GeoDoubleParamsTag (34736) are resolved from
    ``doubles``; ASCII values are skipped (not needed for units).
    """
    n_words = len(directory) // 2
    if n_words < 4:
        return {}
    words = struct.unpack(f"<{n_words}H", directory[: 2 * n_words])
    n_keys = words[3]
    dbl = struct.unpack(f"<{len(doubles) // 8}d", doubles[: 8 * (len(doubles) // 8)]) if doubles else ()
    out = {}
    for k in range(n_keys):
        i = 4 + 4 * k
        if i + 4 > n_words:
            break
        key, loc, count, value = words[i: i + 4]
        if loc == 0:
            out[key] = value
        elif loc == _TAG_DOUBLES and value < len(dbl):
            out[key] = dbl[value]
    return out


def _wkt_tree(text: str):
    """Parse WKT into nested [name, args...] lists (strings, numbers, sub-lists)."""
    tokens = re.findall(r'"[^"]*"|[A-Za-z_][A-Za-z0-9_]*|[-+0-9.eE]+|[\[\](),]', text)
    pos = 0

    def node():
        nonlocal pos
        name = tokens[pos]
        pos += 1
        out = [name.upper()]
        if pos < len(tokens) and tokens[pos] in "[(":
            pos += 1
            while pos < len(tokens) and tokens[pos] not in "])":
                t = tokens[pos]
                if t == ",":
                    pos += 1
                elif t.startswith('"'):
                    out.append(t.strip('"'))
                    pos += 1
                elif re.fullmatch(r"[-+0-9.eE]+", t):
                    try:
                        out.append(float(t))
                    except ValueError:
                        out.append(t)
                    pos += 1
                else:
                    out.append(node())
            pos += 1
        return out

    return node() if tokens else None


def _unit_of(crs) -> Optional[float]:
    """Linear unit factor of a WKT1/WKT2 horizontal or vertical CRS node."""
    for child in crs[1:]:
        if isinstance(child, list) and child[0] in ("UNIT", "LENGTHUNIT") and len(child) >= 3:
            return float(child[2])
    # WKT2 may give the unit per axis only
    for child in crs[1:]:
        if isinstance(child, list) and child[0] == "AXIS":
            for sub in child[1:]:
                if isinstance(sub, list) and sub[0] == "LENGTHUNIT" and len(sub) >= 3:
                    return float(sub[2])
    return None


_HORIZONTAL = ("PROJCS", "PROJCRS", "PROJECTEDCRS")
_GEOGRAPHIC = ("GEOGCS", "GEOGCRS", "GEOGRAPHICCRS", "GEODCRS")
_GEOCENTRIC = ("GEOCCS",)
_VERTICAL = ("VERT_CS", "VERTCRS", "VERTICALCRS")


def wkt_units(text: str):
    """(horizontal factor or "degrees" or None, vertical factor or None) from a WKT string."""
    try:
        tree = _wkt_tree(text.strip("\x00 \n"))
    except (IndexError, ValueError):
        return None, None
    if not tree:
        return None, None
    parts = [c for c in tree[1:] if isinstance(c, list)] if tree[0] in ("COMPD_CS", "COMPOUNDCRS") else [tree]
    horiz = vert = None
    for p in parts:
        if p[0] in _HORIZONTAL or p[0] in _GEOCENTRIC:
            horiz = _unit_of(p)
        elif p[0] in _GEOGRAPHIC:
            horiz = "degrees"
        elif p[0] in _VERTICAL:
            vert = _unit_of(p)
    return horiz, vert


def crs_units(header) -> tuple[Optional[object], Optional[float], str]:
    """Find (horizontal, vertical, where) units of a laspy header's CRS.

    horizontal is metres per unit, "degrees" for a geographic CRS, or None
    when the file has no CRS or no unit in it; where says which record answered.
    """
    vlrs = list(header.vlrs) + list(getattr(header, "evlrs", None) or [])
    by_id = {}
    for v in vlrs:
        if str(v.user_id).strip("\x00") == "LASF_Projection":
            by_id.setdefault(int(v.record_id), v)
    horiz = vert = None
    where = ""
    if 34735 in by_id:
        keys = parse_geokeys(_vlr_bytes(by_id[34735]),
                             _vlr_bytes(by_id[_TAG_DOUBLES]) if _TAG_DOUBLES in by_id else b"")
        model = keys.get(_KEY_MODEL_TYPE)
        code = keys.get(_KEY_PROJ_LINEAR) if model != 3 else keys.get(_KEY_GEOG_LINEAR)
        size_key = _KEY_PROJ_LINEAR_SIZE if model != 3 else _KEY_GEOG_LINEAR_SIZE
        if code == _USER_DEFINED and size_key in keys:
            horiz = float(keys[size_key])
        elif code in EPSG_LINEAR_UNITS:
            horiz = EPSG_LINEAR_UNITS[code]
        elif model == 2:
            horiz = "degrees"
        elif _metric_projected_cs(keys.get(_KEY_PROJECTED_CS)):
            horiz = 1.0
        vcode = keys.get(_KEY_VERTICAL)
        if vcode in EPSG_LINEAR_UNITS:
            vert = EPSG_LINEAR_UNITS[vcode]
        if horiz is not None:
            where = "GeoKeyDirectory VLR"
    if horiz is None and 2112 in by_id:
        h, v = wkt_units(_vlr_bytes(by_id[2112]).decode("utf-8", errors="replace"))
        if h is not None:
            horiz, vert, where = h, (v if v is not None else vert), "WKT VLR"
    return horiz, vert, where


#: A LAZ file decompresses to at most this many times its size; a header declaring more
#: is corrupt (LASzip reaches about 5-20x on real scans, far more only for constant data).
_MAX_LAZ_RATIO = 1000


def _check_declared_size(path: Path) -> None:
    """Refuse a LAS header that cannot describe this file, before laspy allocates for it.

    laspy trusts the header: a corrupt one declaring billions of points or VLRs
    makes it allocate many GiB before it finds out. The public header block is
    read here (LAS 1.0-1.4: offset to point data at byte 96, VLR count at 100,
    point format at 104 with bit 7 set for LAZ, record length at 105, legacy point
    count at 107, 64-bit count at 247 from 1.4) and checked against the file size.
    """
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(375)
    bad = None
    if len(head) < 227 or head[:4] != b"LASF":
        bad = "no LAS public header (it must start with 'LASF' and be at least 227 bytes)"
    else:
        minor = head[25]
        header_size, = struct.unpack_from("<H", head, 94)
        offset, n_vlrs = struct.unpack_from("<II", head, 96)
        fmt, rec = head[104], struct.unpack_from("<H", head, 105)[0]
        n, = struct.unpack_from("<I", head, 107)
        if minor >= 4 and len(head) >= 255 and header_size >= 255:
            n = max(n, struct.unpack_from("<Q", head, 247)[0])
        compressed = bool(fmt & 0x80)
        if not 227 <= header_size <= offset <= size:
            bad = (f"header size {header_size} and offset to point data {offset} do not fit "
                   f"a {size}-byte file")
        elif n_vlrs * 54 > offset - header_size:
            bad = f"{n_vlrs} VLRs declared in {offset - header_size} bytes"
        elif not compressed and offset + n * rec > size:
            bad = (f"the header declares {n} points ({offset + n * rec} bytes) but the file "
                   f"has {size} bytes")
        elif compressed and n * rec > _MAX_LAZ_RATIO * size:
            bad = (f"the header declares {n} points ({n * rec / 2**30:.1f} GiB uncompressed), "
                   f"implausible for a {size}-byte LAZ file")
    if bad:
        raise ScanReadError(
            f"Cannot read {qname(path)} as LAS/LAZ: {bad}; the file is corrupt or truncated, "
            f"export or download it again."
        )


@contextmanager
def _laspy_log_silenced():
    """Mute laspy's own ERROR log records while reading: the failure is raised as a
    ScanReadError with the same text, and the CLI must print exactly one line."""
    log = logging.getLogger("laspy")
    old = log.level
    log.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        log.setLevel(old)


def read_las(path: Path, *, units=None, **_) -> RawScan:
    """Read a LAS/LAZ file: scaled coordinates, classification, intensity.

    Raises
    ------
    ScanReadError
        Unreadable or truncated file, no LAZ backend, or a geographic CRS
        (degrees) without a ``units=`` override.
    """
    import laspy

    _check_declared_size(path)
    try:
        with _laspy_log_silenced():
            las = laspy.read(str(path))
    except PermissionError:
        raise
    except laspy.errors.LaspyException as exc:
        msg = str(exc)
        fix = ("install the LAZ backend: pip install 'laspy[lazrs]'" if "backend" in msg.lower()
               else "the file is corrupt or truncated; export or download it again")
        raise ScanReadError(f"Cannot read {qname(path)} as LAS/LAZ: {msg}; {fix}.") from None
    except (ValueError, OSError, EOFError, struct.error, RuntimeError) as exc:
        # RuntimeError: lazrs.LazrsError, raised for a truncated or corrupt LAZ chunk.
        raise ScanReadError(
            f"Cannot read {qname(path)} as LAS/LAZ ({type(exc).__name__}: {exc}); "
            f"the file is corrupt or truncated; export or download it again."
        ) from None
    hdr = las.header
    n = len(las.points)
    if hdr.point_count and n < hdr.point_count:
        raise ScanReadError(
            f"LAS file {qname(path)} declares {hdr.point_count} points but holds {n}; "
            f"the file is truncated."
        )
    require_points(n, path)
    scale = np.asarray(hdr.scales, dtype=np.float64)
    off = np.asarray(hdr.offsets, dtype=np.float64)
    # From the stored integers in float64: ~1e-9 m resolution even at UTM magnitudes.
    pts = np.empty((n, 3), dtype=np.float64)
    for j, name in enumerate("XYZ"):
        np.multiply(np.asarray(las[name], dtype=np.float64), scale[j], out=pts[:, j])
        pts[:, j] += off[j]

    horiz, vert, where = crs_units(hdr)
    if units is None:
        if horiz == "degrees":
            raise ScanReadError(
                f"{qname(path)} is in a geographic CRS (degrees of latitude/longitude); "
                f"reproject it to a projected CRS in metres (e.g. with PDAL or pyproj), "
                f"or pass units= to force a factor."
            )
        if horiz is None:
            h = 1.0
            if vlr_crs_present(hdr):
                warnings.warn(
                    f"Could not find a linear unit in the CRS of {qname(path)}; assuming metres. "
                    f"Pass units='ft' or units='us-ft' if that is wrong.",
                    ScanWarning,
                    stacklevel=3,
                )
        else:
            h = float(horiz)
        v = h if vert is None else float(vert)
        factor = np.array([h, h, v])
        name = unit_name(h) if v == h else f"{unit_name(h)} (z {unit_name(v)})"
    else:
        factor, name = np.ones(3), "m"  # the caller applies units=

    dims = set(las.point_format.dimension_names)
    labels = np.asarray(las.classification, dtype=np.int64) if "classification" in dims else None
    intensity = np.asarray(las.intensity, dtype=np.float64) if "intensity" in dims else None
    # Sensor origins as extra dimensions origin_x/y/z (same frame and units as the
    # points), as written by gmmgp and read by the streaming tiler.
    origins = None
    if {"origin_x", "origin_y", "origin_z"} <= dims:
        origins = np.column_stack([np.asarray(las[f"origin_{a}"], dtype=np.float64)
                                   for a in "xyz"])
    src = str(path) + (f" (CRS unit from {where})" if where and units is None else "")
    return RawScan(points=pts, origins=origins, labels=labels, intensity=intensity, units=name,
                   factor=factor, source=src)


def read_las_header(path) -> Optional[dict]:
    """What streaming a LAS/LAZ file needs from its header, without reading points.

    A header that cannot describe the file (declared sizes beyond it) is refused
    here with the reader's error; one laspy cannot parse gives None (the reader
    then reports it with the fix).

    Returns
    -------
    dict with ``mins``, ``maxs`` ((3,) float64), ``origins`` (extra dimensions
    origin_x/y/z present), ``horizontal``, ``vertical`` (CRS unit factors or None,
    see :func:`crs_units`) and ``crs`` (a CRS record is present); or None.
    """
    import laspy

    from ._common import check_file

    path = Path(path)
    check_file(path)
    _check_declared_size(path)  # a corrupt header fails here, before any work
    try:
        with laspy.open(str(path)) as reader:
            hdr = reader.header
            has_org = {"origin_x", "origin_y", "origin_z"} <= set(
                hdr.point_format.dimension_names)
            horiz, vert, _ = crs_units(hdr)
            return {"mins": np.asarray(hdr.mins, dtype=np.float64),
                    "maxs": np.asarray(hdr.maxs, dtype=np.float64), "origins": has_org,
                    "horizontal": horiz, "vertical": vert, "crs": vlr_crs_present(hdr)}
    except (laspy.errors.LaspyException, ValueError, OSError):
        return None


def vlr_crs_present(header) -> bool:
    return any(str(v.user_id).strip("\x00") == "LASF_Projection" for v in header.vlrs)


def write_las(path, scan, *, scale: float = 1e-4, header_offset=None) -> Path:
    """Write a scan as LAS/LAZ (the extension decides), readable by :func:`read_las`.

    Coordinates are the original ones (``scan.points + scan.offset``), stored as
    integers of ``scale`` metres around ``header_offset`` (default ``scan.offset``).
    Sensor origins go to float64 extra dimensions ``origin_x/y/z`` (original frame),
    labels to ``classification`` (0-255) and intensity to ``intensity`` (clipped to
    0-65535). Written to a temporary name and renamed.

    Parameters
    ----------
    path : str or Path
    scan : Scan
    scale : float
        Quantum of the stored coordinates (m); 1e-4 keeps 0.1 mm.
    header_offset : (3,) array_like, optional

    Returns
    -------
    Path
    """
    import laspy

    from .._atomic import atomic_path

    path = Path(path)
    if path.suffix.lower() not in (".las", ".laz"):
        raise ValueError(f"Expected a .las or .laz path, found '{path.name}'; name the "
                         "file e.g. scan.laz.")
    off = np.asarray(scan.offset if header_offset is None else header_offset,
                     dtype=np.float64).reshape(3)
    hdr = laspy.LasHeader(point_format=3, version="1.4")
    hdr.offsets, hdr.scales = off, np.full(3, float(scale))
    if scan.origins is not None:
        hdr.add_extra_dims([laspy.ExtraBytesParams(name=f"origin_{a}", type=np.float64)
                            for a in "xyz"])
    las = laspy.LasData(hdr)
    p = scan.points + scan.offset
    las.x, las.y, las.z = p[:, 0], p[:, 1], p[:, 2]
    if scan.origins is not None:
        o = scan.origins + scan.offset
        for i, a in enumerate("xyz"):
            las[f"origin_{a}"] = o[:, i]
    if scan.labels is not None:
        las.classification = np.clip(scan.labels, 0, 255).astype(np.uint8)
    if scan.intensity is not None:
        las.intensity = np.clip(np.round(scan.intensity), 0, 65535).astype(np.uint16)
    with atomic_path(path, suffix=path.suffix) as tmp:
        las.write(str(tmp))
    return path
