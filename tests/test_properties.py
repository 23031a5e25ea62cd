"""Property-based tests (hypothesis) of the scan readers and of ``SurfaceMap.predict``.

Readers: random finite point arrays written in each format read back equal
within that format's precision; random garbage bytes under each extension
either read as finite points or fail with :class:`ScanReadError`, never
anything else.

predict: finite means, positive variances, and translation invariance: a scan
written with a large georeferenced offset, read back by ``read_scan`` (which
moves it to a local frame) and mapped, predicts what the unshifted map
predicts at the same (shifted) places, within 1e-6.
"""

from __future__ import annotations

import struct
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import gmmgp_app as gm
from gmmgp_app.datasets import ScanReadError, read_scan

PROPS = settings(max_examples=25, deadline=None,
                 suppress_health_check=[HealthCheck.function_scoped_fixture,
                                        HealthCheck.too_slow])

coords = st.floats(min_value=-1e4, max_value=1e4, allow_nan=False, allow_infinity=False,
                   width=64)


def point_arrays(min_n=1, max_n=60):
    return st.integers(min_n, max_n).flatmap(
        lambda n: arrays(np.float64, (n, 3), elements=coords))


# --------------------------------------------------------------------------- writers
def _w_xyz(path, p):
    np.savetxt(path, p, fmt="%.17g")


def _w_csv(path, p):
    rows = "\n".join(",".join(repr(v) for v in r) for r in p.tolist())
    path.write_text(f"X,Y,Z\n{rows}\n")


def _w_npy(path, p):
    np.save(path, p)


def _w_npz(path, p):
    np.savez(path, points=p)


def _w_ply(path, p):
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(p)}\n"
            "property double x\nproperty double y\nproperty double z\nend_header\n")
    path.write_bytes(head.encode() + np.ascontiguousarray(p, "<f8").tobytes())


def _w_ply_ascii(path, p):
    body = "\n".join(" ".join(repr(v) for v in r) for r in p.tolist())
    path.write_text(f"ply\nformat ascii 1.0\nelement vertex {len(p)}\nproperty double x\n"
                    f"property double y\nproperty double z\nend_header\n{body}\n")


def _w_pcd(path, p):
    head = (f"VERSION .7\nFIELDS x y z\nSIZE 8 8 8\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {len(p)}\n"
            f"HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(p)}\nDATA binary\n")
    path.write_bytes(head.encode() + np.ascontiguousarray(p, "<f8").tobytes())


def _w_las(path, p):
    import laspy

    h = laspy.LasHeader(point_format=3, version="1.2")
    h.scales = np.full(3, 0.001)
    h.offsets = np.zeros(3)
    las = laspy.LasData(h)
    las.x, las.y, las.z = p[:, 0], p[:, 1], p[:, 2]
    las.write(str(path))


def _w_e57(path, p):
    import pye57

    e = pye57.E57(str(path), mode="w")
    e.write_scan_raw({"cartesianX": p[:, 0], "cartesianY": p[:, 1], "cartesianZ": p[:, 2]})
    e.close()


def _w_bin(path, p):
    rec = np.zeros((len(p), 4), np.float32)
    rec[:, :3] = p
    rec.tofile(path)


def _f32(p):
    return p.astype(np.float32).astype(np.float64)


# (extension, writer, expected points read back, absolute tolerance)
FORMATS = [
    (".xyz", _w_xyz, lambda p: p, 0.0),
    (".csv", _w_csv, lambda p: p, 0.0),
    (".npy", _w_npy, lambda p: p, 0.0),
    (".npz", _w_npz, lambda p: p, 0.0),
    (".ply", _w_ply, lambda p: p, 0.0),
    ("ascii.ply", _w_ply_ascii, lambda p: p, 0.0),
    (".pcd", _w_pcd, lambda p: p, 0.0),
    (".las", _w_las, lambda p: p, 0.0005 + 1e-9),   # 1 mm integer grid
    (".laz", _w_las, lambda p: p, 0.0005 + 1e-9),
    (".e57", _w_e57, _f32, 1e-9),                    # stored as float32 by pye57
    (".bin", _w_bin, _f32, 0.0),                     # KITTI: float32 records
]


@pytest.mark.parametrize("ext,write,expect,atol", FORMATS, ids=[f[0] for f in FORMATS])
@PROPS
@given(p=point_arrays())
def test_reader_round_trip(ext, write, expect, atol, p, tmp_path_factory):
    path = tmp_path_factory.mktemp("rt") / ("scan" + (ext if ext.startswith(".") else ".ply"))
    write(path, p)
    scan = read_scan(path, offset=None)
    assert scan.points.dtype == np.float64 and scan.points.shape == p.shape
    np.testing.assert_allclose(scan.points, expect(p), rtol=0, atol=atol)


@PROPS
@given(p=point_arrays(max_n=30),
       shift=st.tuples(st.floats(1e5, 9e5), st.floats(1e6, 9e6), st.floats(-500, 3000)))
def test_auto_offset_keeps_original_coordinates(p, shift, tmp_path_factory):
    """Far coordinates go to a local frame by a round offset; local + offset is the file."""
    path = tmp_path_factory.mktemp("off") / "scan.npy"
    far = p / 10 + np.asarray(shift)
    np.save(path, far)
    scan = read_scan(path)
    assert np.all(np.mod(scan.offset, 1000.0) == 0)
    assert np.abs(scan.points).max() < 1e4 + 1000 + np.abs(p).max()
    np.testing.assert_allclose(scan.points + scan.offset, far, rtol=0, atol=1e-9)


MAGIC = {".xyz": b"", ".ply": b"ply\n", ".pcd": b"# .PCD v.7\nFIELDS x y z\n",
         ".npy": b"\x93NUMPY", ".npz": b"PK\x03\x04", ".las": b"LASF", ".laz": b"LASF",
         ".e57": b"ASTM-E57", ".bin": b"", ".csv": b"x,y,z\n"}


@pytest.mark.parametrize("ext", sorted(MAGIC))
@PROPS
@given(data=st.binary(min_size=0, max_size=600), with_magic=st.booleans())
def test_garbage_bytes_raise_only_scan_read_error(ext, data, with_magic, tmp_path_factory):
    path = tmp_path_factory.mktemp("junk") / f"junk{ext}"
    path.write_bytes((MAGIC[ext] if with_magic else b"") + data)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # dropped NaN rows, unknown CRS units
        try:
            scan = read_scan(path)
        except ScanReadError:
            return
    # Some garbage is a valid scan (e.g. KITTI records, digits): then it is finite points.
    assert scan.points.ndim == 2 and scan.points.shape[1] == 3 and len(scan.points) >= 1
    assert np.isfinite(scan.points).all()


def test_las_header_fuzz_never_allocates_what_it_claims(tmp_path):
    """Every 4-byte count field of a valid LAS header set to a huge value: refused up front."""
    path = tmp_path / "ok.las"
    _w_las(path, np.random.default_rng(0).uniform(-5, 5, (50, 3)))
    good = path.read_bytes()
    for offset in (96, 100, 107):
        bad = bytearray(good)
        struct.pack_into("<I", bad, offset, 0xFFFFFFF0)
        path.write_bytes(bytes(bad))
        with pytest.raises(ScanReadError, match=r"as LAS/LAZ: .*corrupt or truncated"):
            read_scan(path)


# --------------------------------------------------------------------------- predict
SHIFT = np.array([5.0e5, 5.8e6, 100.0])
COARSE = {"surface.voxel_size": 0.2}


def _map_from_file(path):
    scan = read_scan(path)
    return gm.build_map(scan, gm.MappingConfig().replace(COARSE)), scan


@pytest.fixture(scope="module")
def maps(tmp_path_factory):
    """The same box scan mapped twice: as simulated (near 0) and written with a UTM-like
    offset (5e5, 5.8e6, 100) then read back through read_scan's automatic local frame."""
    from gmmgp_app.synth import scan_scene
    from gmmgp_app.synth.io import save_scan_npz

    d = tmp_path_factory.mktemp("maps")
    scan, _ = scan_scene("box", density=0.02, seed=3)
    save_scan_npz(d / "near.npz", scan.points, scan.origins)
    save_scan_npz(d / "far.npz", scan.points + SHIFT, scan.origins + SHIFT)
    near, s_near = _map_from_file(d / "near.npz")
    far, s_far = _map_from_file(d / "far.npz")
    assert np.any(s_far.offset != 0) and np.all(s_near.offset == 0)
    lo, hi = scan.points.min(0), scan.points.max(0)
    return {"near": near, "far": far, "lo": lo, "hi": hi, "points": scan.points,
            "origins": scan.origins}


def queries(n_max=40):
    """Query points in the scan's bounding box grown by 0.5 m, or near scan points."""
    return st.tuples(st.integers(1, n_max), st.integers(0, 2**31 - 1), st.booleans())


def _draw(maps, spec):
    n, seed, near_surface = spec
    rng = np.random.default_rng(seed)
    if near_surface:
        idx = rng.integers(0, len(maps["points"]), n)
        return maps["points"][idx] + rng.normal(0, 0.05, (n, 3))
    return rng.uniform(maps["lo"] - 0.5, maps["hi"] + 0.5, (n, 3))


@settings(max_examples=30, deadline=None)
@given(spec=queries())
def test_predict_is_finite_with_positive_variance(maps, spec):
    q = _draw(maps, spec)
    mean, var, grad = maps["near"].predict(q, return_grad=True)
    assert mean.shape == var.shape == (len(q),) and grad.shape == (len(q), 3)
    assert np.isfinite(mean).all() and np.isfinite(grad).all()
    assert np.all(np.isfinite(var)) and np.all(var > 0)


@settings(max_examples=30, deadline=None)
@given(spec=queries())
def test_predict_is_invariant_to_a_large_offset(maps, spec):
    """Shifted input, read to a local frame, queried at the shifted points: same field."""
    q = _draw(maps, spec)
    far = maps["far"]
    m0, v0 = maps["near"].predict(q)
    m1, v1 = far.predict(q + SHIFT - far.offset)
    np.testing.assert_allclose(m1, m0, rtol=0, atol=1e-6)
    np.testing.assert_allclose(v1, v0, rtol=0, atol=1e-6)
    assert np.all(v1 > 0)


def test_predict_is_invariant_to_a_z_shift_of_a_grazing_scan(maps):
    """The box is scanned from the height of its top face, so its top points are grazing.
    Shifted by (0, 0, 100) in memory (no file round trip to perturb the rounding), the
    mapped field must not change; it does (0.34 m), because one top-face normal flips."""
    from gmmgp_app.types import Scan

    d = np.array([0.0, 0.0, 100.0])
    cfg = gm.MappingConfig().replace(COARSE)
    pts, org = maps["points"], maps["origins"]
    a = gm.build_map(Scan(pts, origins=org), cfg, method="hgmm")
    b = gm.build_map(Scan(pts + d, origins=org + d), cfg, method="hgmm")
    q = pts[::13] + np.random.default_rng(1).normal(0, 0.05, (len(pts[::13]), 3))
    np.testing.assert_allclose(b.predict(q + d)[0], a.predict(q)[0], rtol=0, atol=1e-6)
