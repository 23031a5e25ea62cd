"""Hardening corpus: bad or extreme inputs, faults and interruptions (issue 9).

Every case is generated here in ``tmp_path`` and driven through the ``gmmgp``
command line (in-process through ``cli.main`` where possible, in a subprocess
for signals, other users and mounts). Each ends either in

* exit code 2 and exactly one stderr line ``gmmgp CMD: error: ...`` that names
  the problem and the fix, with no traceback and nothing written under the
  output's final names, or
* exit code 0 with a correct result and a warning.

docs/hardening.md lists every case by its id; ``test_docs_table_lists_every_case``
keeps that table and this file in step.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

import gmmgp_app as gm
from gmmgp_app.cli import main
from gmmgp_app.datasets import ScanReadError, ScanWarning, read_scan
from lasfile import write_las

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "hardening.md"
PY = sys.executable
IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0
FAST = ["--set", "surface.voxel_size=0.2"]


# --------------------------------------------------------------------------- helpers
def _cli(capsys, *args):
    """Run ``gmmgp ARGS`` in-process; return (exit code, stdout, stderr)."""
    rc = main([str(a) for a in args])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def _sub(*args, cwd=None, prefix=(), timeout=120):
    return subprocess.run([*prefix, PY, "-m", "gmmgp_app.cli", *map(str, args)],
                          capture_output=True, text=True, cwd=cwd, timeout=timeout)


def assert_one_line_error(rc, err, cmd, pattern):
    """Exit 2, one stderr line 'gmmgp CMD: error: ...' matching ``pattern``, no traceback."""
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2, err
    assert "Traceback" not in err, err
    assert len(lines) == 1, err
    assert lines[0].startswith(f"gmmgp {cmd}: error: "), lines[0]
    assert re.search(pattern, lines[0]), lines[0]
    return lines[0]


def assert_no_partial_outputs(out: Path):
    """Nothing under a final name, no temporary siblings: the folder is absent or empty."""
    if out.exists():
        left = sorted(p.name for p in out.rglob("*"))
        assert left == [], left


def _plane(n_side=30, h=0.05, z=0.0):
    g = np.stack(np.meshgrid(np.arange(n_side), np.arange(n_side)), -1).reshape(-1, 2) * h
    return np.c_[g, np.full(len(g), z)]


def _cloud(n=200, seed=0):
    return np.random.default_rng(seed).uniform(-2, 2, size=(n, 3))


def _feet_vlr():
    import laspy

    # GeoKeyDirectory: version header, then ProjLinearUnitsGeoKey (3076) = 9002 (foot).
    words = [1, 1, 0, 2, 1024, 0, 1, 1, 3076, 0, 1, 9002]
    return laspy.VLR("LASF_Projection", 34735, "GeoKeys", struct.pack(f"<{len(words)}H", *words))


def _write_e57(path, xyz):
    import pye57

    e = pye57.E57(str(path), mode="w")
    e.write_scan_raw({"cartesianX": xyz[:, 0], "cartesianY": xyz[:, 1],
                      "cartesianZ": xyz[:, 2]})
    e.close()
    return path


def _write_binary_ply(path, xyz):
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(xyz)}\n"
              "property double x\nproperty double y\nproperty double z\nend_header\n")
    path.write_bytes(header.encode() + np.ascontiguousarray(xyz, "<f8").tobytes())
    return path


def _truncate(path, keep: float):
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])
    return path


@pytest.fixture(scope="module")
def box(tmp_path_factory):
    """A ~3k point box scan with sensor origins (npz) and the same points as .xyz."""
    from gmmgp_app.synth import scan_scene
    from gmmgp_app.synth.io import save_scan_npz

    d = tmp_path_factory.mktemp("box")
    scan, _ = scan_scene("box", density=0.02, seed=1)
    save_scan_npz(d / "scan.npz", scan.points, scan.origins)
    return {"dir": d, "scan": scan, "npz": d / "scan.npz"}


# --------------------------------------------------------------------------- corpus A: unreadable input
# (id, maker(tmp_path) -> path, regex on the one error line of 'gmmgp info PATH')
def _make_empty(ext):
    def make(t):
        p = t / f"empty{ext}"
        p.write_bytes(b"")
        return p
    return make


def _make_ply_zero_vertices(t):
    p = t / "zero.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\n"
                 "property float y\nproperty float z\nend_header\n")
    return p


def _make_ply_truncated_binary(t):
    return _truncate(_write_binary_ply(t / "cut.ply", _cloud()), 0.6)


def _make_ply_truncated_ascii(t):
    p = t / "cut_ascii.ply"
    xyz = _cloud()
    body = "\n".join(f"{a} {b} {c}" for a, b, c in xyz)
    p.write_text(f"ply\nformat ascii 1.0\nelement vertex {len(xyz)}\nproperty double x\n"
                 f"property double y\nproperty double z\nend_header\n{body}\n")
    return _truncate(p, 0.5)


def _make_ply_corrupt_header(t):
    p = t / "bad_header.ply"
    p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex many\n"
                  b"property float x\nend_header\n" + os.urandom(64))
    return p


def _make_ply_garbage(t):
    p = t / "garbage.ply"
    p.write_bytes(np.random.default_rng(1).integers(0, 256, 4000, dtype=np.uint8).tobytes())
    return p


def _make_las_truncated(t):
    return _truncate(write_las(t / "cut.las", _cloud(2000)), 0.5)


def _make_laz_truncated(t):
    return _truncate(write_las(t / "cut.laz", _cloud(2000)), 0.5)


def _make_las_garbage(t):
    p = t / "garbage.las"
    p.write_bytes(b"LASF" + np.random.default_rng(2).integers(0, 256, 3000, np.uint8).tobytes())
    return p


def _make_e57_truncated(t):
    return _truncate(_write_e57(t / "cut.e57", _cloud(2000)), 0.5)


def _make_e57_garbage(t):
    p = t / "garbage.e57"
    p.write_bytes(np.random.default_rng(3).integers(0, 256, 5000, np.uint8).tobytes())
    return p


def _make_npy_truncated(t):
    p = t / "cut.npy"
    np.save(p, _cloud())
    return _truncate(p, 0.5)


def _make_npy_garbage(t):
    p = t / "garbage.npy"
    p.write_bytes(b"\x93NUMPY" + os.urandom(200))
    return p


def _make_npy_pickled(t):
    p = t / "objects.npy"
    np.save(p, np.array([{"x": 1}, None], dtype=object), allow_pickle=True)
    return p


def _make_npy_two_columns(t):
    p = t / "xy.npy"
    np.save(p, _cloud()[:, :2])
    return p


def _make_npz_truncated(t):
    p = t / "cut.npz"
    np.savez_compressed(p, points=_cloud(5000))
    return _truncate(p, 0.5)


def _make_kitti_bin_ragged(t):
    p = t / "000000.bin"
    p.write_bytes(np.zeros(4 * 4 * 10 + 3, np.uint8).tobytes())  # 10 records and 3 bytes
    return p


def _make_pcd_truncated(t):
    p = t / "cut.pcd"
    xyz = _cloud().astype("<f4")
    p.write_bytes((f"VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
                   f"WIDTH {len(xyz)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(xyz)}\n"
                   "DATA binary\n").encode() + xyz.tobytes()[:1000])
    return p


def _make_text_two_columns(t):
    p = t / "xy.xyz"
    np.savetxt(p, _cloud()[:, :2])
    return p


def _make_text_bad_row(t):
    p = t / "bad_row.xyz"
    lines = [f"{a} {b} {c}" for a, b, c in _cloud(50)]
    lines[30] = "1.0 oops 2.0"
    p.write_text("\n".join(lines) + "\n")
    return p


def _make_text_binary(t):
    p = t / "binary.txt"
    p.write_bytes(b"\xff\xfe\x00\x81" * 300)
    return p


def _make_text_all_nan(t):
    p = t / "all_nan.xyz"
    p.write_text("nan nan nan\n" * 20)
    return p


def _make_unknown_extension(t):
    p = t / "scan.foo"
    np.savetxt(p, _cloud())
    return p


def _make_missing(t):
    return t / "no_such_scan.ply"


def _make_folder_without_scans(t):
    d = t / "folder"
    d.mkdir()
    (d / "README.md").write_text("no scans here")
    return d


READ_ERRORS = [
    ("empty-xyz", _make_empty(".xyz"), r"'.*empty\.xyz' is empty \(0 bytes\).*write it again"),
    ("empty-ply", _make_empty(".ply"), r"'.*empty\.ply' is empty \(0 bytes\)"),
    ("empty-laz", _make_empty(".laz"), r"'.*empty\.laz' is empty \(0 bytes\)"),
    ("ply-zero-vertices", _make_ply_zero_vertices, r"Expected at least 1 point .* found 0"),
    ("ply-truncated-binary", _make_ply_truncated_binary,
     r"PLY file '.*cut\.ply' is truncated: the header declares 200 vertices .* download it again"),
    ("ply-truncated-ascii", _make_ply_truncated_ascii,
     r"PLY file '.*cut_ascii\.ply' is truncated: .*200 vertices"),
    ("ply-corrupt-header", _make_ply_corrupt_header, r"bad element line .* the file is corrupt"),
    ("ply-garbage", _make_ply_garbage, r"is not a PLY file .*check the file or its extension"),
    ("las-truncated", _make_las_truncated,
     r"(Cannot read '.*cut\.las' as LAS/LAZ|declares 2000 points but holds).*(again|truncated)"),
    ("laz-truncated", _make_laz_truncated,
     r"(Cannot read '.*cut\.laz' as LAS/LAZ|declares 2000 points but holds).*(again|truncated)"),
    ("las-garbage", _make_las_garbage, r"Cannot read '.*garbage\.las' as LAS/LAZ.*again"),
    ("e57-truncated", _make_e57_truncated,
     r"(Cannot open|Cannot read scan 0 of) '.*cut\.e57'.*(corrupt|truncated)"),
    ("e57-garbage", _make_e57_garbage, r"Cannot open '.*garbage\.e57' as E57 .*not E57"),
    ("npy-truncated", _make_npy_truncated,
     r"Cannot load '.*cut\.npy' as a NumPy array .*not truncated"),
    ("npy-garbage", _make_npy_garbage, r"Cannot load '.*garbage\.npy' as a NumPy array"),
    ("npy-pickled-objects", _make_npy_pickled,
     r"Cannot load '.*objects\.npy' as a NumPy array without pickle"),
    ("npy-two-columns", _make_npy_two_columns, r"with shape \(N, 3\).*found shape \(200, 2\)"),
    ("npz-truncated", _make_npz_truncated, r"Cannot load '.*cut\.npz' as an \.npz archive"),
    ("kitti-bin-ragged", _make_kitti_bin_ragged, r"'.*000000\.bin'.*(16|truncated|multiple)"),
    ("pcd-truncated", _make_pcd_truncated, r"PCD file '.*cut\.pcd' is truncated"),
    ("text-two-columns", _make_text_two_columns,
     r"has 2 numeric column\(s\); expected at least 3 \(x y z\)"),
    ("text-bad-row", _make_text_bad_row, r"Cannot parse '.*bad_row\.xyz'.*Fix or remove"),
    ("text-binary-bytes", _make_text_binary, r"'.*binary\.txt' is not a text file"),
    ("text-all-nan", _make_text_all_nan, r"found 0 of 20 in '.*all_nan\.xyz'.*all NaN"),
    ("unknown-extension", _make_unknown_extension,
     r"Unknown scan extension '\.foo' .*supported: .*Convert the file or rename it"),
    ("missing-file", _make_missing, r"'.*no_such_scan\.ply' does not exist; check the path"),
    ("folder-without-scans", _make_folder_without_scans, r"contains no scan files"),
]


@pytest.mark.parametrize("case,make,pattern", READ_ERRORS, ids=[c[0] for c in READ_ERRORS])
def test_unreadable_input_is_one_line_error(case, make, pattern, tmp_path, capsys):
    path = make(tmp_path)
    rc, _, err = _cli(capsys, "info", path)
    assert_one_line_error(rc, err, "info", pattern)
    # 'run' refuses it the same way and writes nothing.
    out = tmp_path / "out"
    rc, _, err = _cli(capsys, "run", path, "--out", out, "-q")
    assert_one_line_error(rc, err, "run", pattern)
    assert_no_partial_outputs(out)


def test_truncated_laz_is_one_line_in_a_real_process(tmp_path):
    """laspy logs LAZ decoding errors itself; with no logging set up Python prints them on
    stderr, so the reader mutes them: the user sees exactly one line."""
    path = _make_laz_truncated(tmp_path)
    r = _sub("info", path, cwd=tmp_path)
    assert_one_line_error(r.returncode, r.stderr, "info", r"Cannot read '.*cut\.laz' as LAS/LAZ")


def test_las_header_declaring_huge_counts_is_refused_before_allocating(tmp_path, capsys):
    """A corrupt header claiming 4e9 points (or VLRs) must not make laspy allocate ~100 GiB."""
    path = write_las(tmp_path / "huge.las", _cloud(100))
    data = bytearray(path.read_bytes())
    struct.pack_into("<I", data, 107, 4_000_000_000)
    path.write_bytes(bytes(data))
    rc, _, err = _cli(capsys, "info", path)
    assert_one_line_error(rc, err, "info", r"header declares 4000000000 points .* but the file "
                          r"has \d+ bytes; the file is corrupt or truncated")
    data = bytearray(write_las(tmp_path / "vlrs.las", _cloud(100)).read_bytes())
    struct.pack_into("<I", data, 100, 3_000_000_000)
    (tmp_path / "vlrs.las").write_bytes(bytes(data))
    rc, _, err = _cli(capsys, "info", tmp_path / "vlrs.las")
    assert_one_line_error(rc, err, "info", r"3000000000 VLRs declared in \d+ bytes")


# --------------------------------------------------------------------------- corpus B: degenerate geometry
def _save_npy(t, name, xyz):
    p = t / name
    np.save(p, xyz)
    return p


DEGENERATE = [
    ("one-point", lambda t: _save_npy(t, "one.npy", np.array([[1.0, 2.0, 3.0]])),
     r"Expected at least 10 points to estimate normals, found 1"),
    ("three-points", lambda t: _save_npy(t, "three.npy", _cloud(3)),
     r"Expected at least 10 points to estimate normals, found 3"),
    ("identical-points", lambda t: _save_npy(t, "same.npy", np.tile([4.0, 5.0, 6.0], (500, 1))),
     r"No normal could be estimated .*identical/collinear.*normal_radius"),
    ("collinear-points", lambda t: _save_npy(
        t, "line.npy", np.outer(np.linspace(0, 5, 400), [1.0, 2.0, 0.5])),
     r"No normal could be estimated .*identical/collinear.*normal_radius"),
    # a normal radius set by hand below the spacing (with 'auto' the radius follows the
    # spacing: test_isolated_points_get_a_normal_radius_from_their_spacing)
    ("isolated-points", lambda t: _save_npy(t, "sparse.npy", _cloud(50) * 100),
     r"No normal could be estimated .*fewer than 3 neighbours within normal_radius=0.3 m"),
]
#: options a case needs besides ``run FILE --out OUT --stage prepare -q``
DEGENERATE_ARGS = {"isolated-points": ["--set", "prepare.normal_radius=0.3"]}


@pytest.mark.parametrize("case,make,pattern", DEGENERATE, ids=[c[0] for c in DEGENERATE])
def test_degenerate_geometry_is_one_line_error(case, make, pattern, tmp_path, capsys):
    path = make(tmp_path)
    out = tmp_path / "out"
    rc, _, err = _cli(capsys, "run", path, "--out", out, "--stage", "prepare", "-q",
                      *DEGENERATE_ARGS.get(case, []))
    assert_one_line_error(rc, err, "run", pattern)
    assert_no_partial_outputs(out)


def test_isolated_points_get_a_normal_radius_from_their_spacing(tmp_path, capsys):
    """50 points about 66 m apart with the default ('auto') normal radius: the radius is
    4 spacings clipped to the field's upper bound (100 m), so normals are estimated and the
    prepare stage succeeds; the summary reports the clipped value that was used and why."""
    path = _save_npy(tmp_path, "sparse.npy", _cloud(50) * 100)
    out = tmp_path / "out"
    with pytest.warns(UserWarning, match="no sensor origins"):
        rc, _, err = _cli(capsys, "run", path, "--out", out, "--stage", "prepare", "-q")
    assert rc == 0, err
    auto = json.loads((out / "summary.json").read_text())["auto"]
    h = auto["scan"]["spacing"]
    assert 30 < h < 150
    rec = auto["prepare.normal_radius"]
    assert rec["auto"] and rec["value"] == 100.0 and "clipped" in rec["reason"]


def test_coplanar_points_map_the_plane_with_a_warning(tmp_path, capsys):
    """A perfectly flat scan (z = 0 exactly) maps to a field that is zero on the plane and
    changes sign across it; no origins, so normals are oriented by a heuristic (warned)."""
    path = tmp_path / "plane.xyz"
    np.savetxt(path, _plane(40, 0.05))
    out = tmp_path / "out"
    with pytest.warns(UserWarning, match="no sensor origins"):
        rc, _, err = _cli(capsys, "run", path, "--out", out, "-q", *FAST)
    assert rc == 0, err
    smap = gm.load_map(out / "map")
    xy = np.random.default_rng(0).uniform(0.4, 1.5, size=(50, 2))
    on = smap.predict(np.c_[xy, np.zeros(50)])[0]
    up = smap.predict(np.c_[xy, np.full(50, 0.1)])[0]
    down = smap.predict(np.c_[xy, np.full(50, -0.1)])[0]
    assert np.abs(on).max() < 0.02
    s = np.sign(np.median(up))
    assert s != 0 and np.all(np.sign(up) == s) and np.all(np.sign(down) == -s)
    assert np.all(np.abs(up) > 0.05) and np.all(np.abs(down) > 0.05)
    assert (out / "mesh_gmmgp.ply").is_file()


def test_duplicated_points_give_a_map(tmp_path, capsys, box):
    """Every return recorded three times (duplicated points, e.g. merged overlapping strips):
    the map still fits (duplicates must not make the GP singular) and is zero on the surface."""
    scan = box["scan"]
    path = tmp_path / "dup.npz"
    np.savez(path, points=np.repeat(scan.points, 3, axis=0),
             origins=np.repeat(scan.origins, 3, axis=0))
    out = tmp_path / "out"
    rc, _, err = _cli(capsys, "run", path, "--out", out, "-q", "--no-mesh")
    assert rc == 0, err
    smap = gm.load_map(out / "map")
    mean, var = smap.predict(scan.points[::7])
    assert np.all(np.isfinite(mean)) and np.all(var > 0)
    assert np.sqrt(np.mean(mean ** 2)) < 0.03


# --------------------------------------------------------------------------- corpus C: dropped points, units, offsets
def test_nan_rows_in_text_are_dropped_with_a_warning(tmp_path, capsys):
    xyz = _plane(30)
    bad = xyz.copy()
    bad[[3, 50, 700]] = np.nan
    bad[100, 2] = np.inf
    path = tmp_path / "nan.xyz"
    np.savetxt(path, bad)
    with pytest.warns(ScanWarning, match=r"Dropped 4 of 900 points with non-finite coordinates"):
        rc, out, err = _cli(capsys, "info", path)
    assert rc == 0, err
    assert "points    896" in out
    with pytest.warns(ScanWarning):
        scan = read_scan(path)
    np.testing.assert_array_equal(scan.points, np.delete(xyz, [3, 50, 100, 700], axis=0))


def test_inf_in_npy_is_dropped_with_a_warning_and_the_run_succeeds(tmp_path, capsys, box):
    pts = box["scan"].points.copy()
    pts[::100] = np.inf
    n_bad = len(pts[::100])
    path = tmp_path / "inf.npy"
    np.save(path, pts)
    out = tmp_path / "out"
    with pytest.warns(ScanWarning, match=rf"Dropped {n_bad} of {len(pts)} points"), \
            pytest.warns(UserWarning, match="no sensor origins"):
        rc, _, err = _cli(capsys, "run", path, "--out", out, "-q", "--stage", "prepare")
    assert rc == 0, err
    assert (out / "map" / "map.json").is_file()


def test_nan_origins_drop_their_points_with_a_warning(tmp_path, box):
    scan = box["scan"]
    org = scan.origins.copy()
    org[:7] = np.nan
    path = tmp_path / "nan_origins.npz"
    np.savez(path, points=scan.points, origins=org)
    with pytest.warns(ScanWarning, match=rf"Dropped 7 of {len(scan.points)} points"):
        got = read_scan(path)
    np.testing.assert_array_equal(got.points, scan.points[7:])
    np.testing.assert_array_equal(got.origins, scan.origins[7:])


UTM = np.array([512345.0, 5812345.0, 100.0])


def test_utm_text_keeps_millimetres(tmp_path, capsys):
    """UTM-sized coordinates written with millimetre digits: the local frame keeps them exactly
    (float64 subtraction before anything else) and 'info' reports the offset."""
    rng = np.random.default_rng(4)
    mm = np.round(rng.uniform(0, 20, size=(500, 3)), 3)  # millimetre grid
    path = tmp_path / "utm.xyz"
    np.savetxt(path, mm + UTM, fmt="%.3f")
    scan = read_scan(path)
    np.testing.assert_array_equal(scan.offset, [512000.0, 5812000.0, 0.0])
    # local + offset reproduces every written millimetre.
    np.testing.assert_allclose(scan.points + scan.offset, mm + UTM, rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.diff(scan.points, axis=0), np.diff(mm, axis=0), rtol=0, atol=1e-6)
    rc, out, err = _cli(capsys, "info", path)
    assert rc == 0, err
    assert "offset    (512000.000, 5812000.000, 0.000)" in out


def test_utm_las_keeps_millimetres_and_maps(tmp_path, capsys, box):
    """A georeferenced LAS (scale 1 mm, UTM offset) of the box: the map built from it is the
    same field as the map of the same points near zero (compared in the original frame)."""
    scan = box["scan"]
    local = np.round(scan.points, 3)
    path = write_las(tmp_path / "utm.las", local + UTM, scale=0.001, offset=UTM)
    got = read_scan(path)
    np.testing.assert_allclose(got.points + got.offset, local + UTM, rtol=0, atol=1e-9)
    near = tmp_path / "near.npy"
    np.save(near, local)
    maps = {}
    for name, src in (("utm", path), ("near", near)):
        out = tmp_path / name
        with pytest.warns(UserWarning, match="no sensor origins"):
            rc, _, err = _cli(capsys, "run", src, "--out", out, "-q", "--method", "hgmm",
                              "--no-mesh")
        assert rc == 0, err
        maps[name] = gm.load_map(out / "map")
    np.testing.assert_array_equal(maps["utm"].offset, got.offset)
    q = local[::11] + np.random.default_rng(0).normal(0, 0.05, size=(len(local[::11]), 3))
    m_utm, v_utm = maps["utm"].predict(q + UTM - maps["utm"].offset)
    m_near, v_near = maps["near"].predict(q)
    np.testing.assert_allclose(m_utm, m_near, rtol=0, atol=1e-6)
    np.testing.assert_allclose(v_utm, v_near, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("how", [["--stage", "prepare"], ["--method", "gpis", "--no-mesh"]],
                         ids=["stage-prepare", "gpis"])
def test_saved_map_of_a_constant_prior_loads(how, tmp_path, capsys, box):
    out = tmp_path / "out"
    rc, _, err = _cli(capsys, "run", box["npz"], "--out", out, "-q", *how)
    assert rc == 0, err
    smap = gm.load_map(out / "map")
    mean, var = smap.predict(box["scan"].points[:20])
    assert np.all(np.isfinite(mean)) and np.all(var > 0)


def test_las_in_feet_is_converted_to_metres(tmp_path, capsys):
    xyz_ft = _cloud(300) * 50 + [1000.0, 2000.0, 300.0]
    path = write_las(tmp_path / "feet.las", xyz_ft, vlrs=[_feet_vlr()], scale=0.01)
    rc, out, err = _cli(capsys, "info", path, "--json")
    assert rc == 0, err
    import json

    s = json.loads(out)
    assert s["units"] == "ft"
    ext_ft = np.round(xyz_ft, 2).max(0) - np.round(xyz_ft, 2).min(0)
    np.testing.assert_allclose(s["extent_m"], ext_ft * 0.3048, rtol=1e-9)


def test_text_in_feet_with_units_option(tmp_path, capsys):
    xyz = _cloud(100)
    path = tmp_path / "feet.xyz"
    np.savetxt(path, xyz, fmt="%.17g")
    rc, out, err = _cli(capsys, "info", path, "--units", "ft", "--json")
    assert rc == 0, err
    import json

    s = json.loads(out)
    np.testing.assert_allclose(s["extent_m"], (xyz.max(0) - xyz.min(0)) * 0.3048, rtol=1e-12)
    rc, _, err = _cli(capsys, "info", path, "--units", "furlong")
    assert_one_line_error(rc, err, "info", r"Unknown units='furlong'; use 'm', 'ft'")


def test_csv_with_header_and_commas(tmp_path, capsys):
    xyz = _cloud(80)
    inten = np.arange(80.0)
    path = tmp_path / "scan.csv"
    rows = "\n".join(f"{i:g},{a!r},{b!r},{c!r}" for i, (a, b, c) in zip(inten, xyz.tolist()))
    path.write_text(f"# exported by a scanner\nintensity,X,Y,Z\n{rows}\n")
    scan = read_scan(path)
    np.testing.assert_array_equal(scan.points, xyz)
    np.testing.assert_array_equal(scan.intensity, inten)
    rc, out, err = _cli(capsys, "info", path)
    assert rc == 0 and "points    80" in out, err


def test_double_precision_pcd_reads_exactly(tmp_path, capsys):
    """PCL writes SIZE 8 fields for georeferenced clouds; Open3D read them as zeros
    (silently), so binary and ascii PCD are parsed by the reader itself."""
    xyz = _cloud(50) + UTM
    path = tmp_path / "double.pcd"
    path.write_bytes(("VERSION .7\nFIELDS x y z\nSIZE 8 8 8\nTYPE F F F\nCOUNT 1 1 1\n"
                      "WIDTH 50\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 50\nDATA binary\n"
                      ).encode() + xyz.astype("<f8").tobytes())
    scan = read_scan(path)
    np.testing.assert_array_equal(scan.points + scan.offset, xyz)
    rc, out, err = _cli(capsys, "info", path)
    assert rc == 0 and "offset    (512000.000, 5812000.000, 0.000)" in out, out + err


def test_semicolon_text_with_comments_and_pts_count(tmp_path):
    xyz = _cloud(40)
    path = tmp_path / "scan.pts"
    body = "\n".join(f"{a!r};{b!r};{c!r};7" for a, b, c in xyz.tolist())
    path.write_text(f"40\n// comment\n{body}\n")
    scan = read_scan(path)
    np.testing.assert_array_equal(scan.points, xyz)
    path.write_text(f"41\n{body}\n")
    with pytest.raises(ScanReadError, match=r"declares 41 points on its first line but holds 40"):
        read_scan(path)


# --------------------------------------------------------------------------- corpus D: configuration
CONFIG_ERRORS = [
    ("config-unknown-section", "[gps]\nd_m = 0.1\n", r"Unknown config field 'gps\.d_m'; expected"),
    ("config-unknown-field", "[hgmm]\nsplit_treshold = 0.02\n",
     r"Unknown config field 'hgmm\.split_treshold'; 'hgmm' has \["),
    ("config-wrong-type", "[gp]\nd_m = \"small\"\n",
     r"Config field 'gp\.d_m' must be a number, found 'small'"),
    ("config-out-of-range", "[prepare]\nsubsample_rate = 1.5\n",
     r"Config field 'prepare\.subsample_rate' must lie in \[0\.0001, 1\.0\], found 1\.5"),
    ("config-bad-choice", "[hgmm]\ncomplexity_metric = \"eigen\"\n",
     r"Config field 'hgmm\.complexity_metric' must be one of \['correlation', 'covariance'\]"),
    ("config-not-toml", "[hgmm\nsplit_threshold = \n",
     r"Config file '.*bad\.toml' is not valid TOML"),
    ("config-float-for-int", "[hgmm]\nn_children = 2.5\n",
     r"Config field 'hgmm\.n_children' must be an integer, found 2\.5"),
]


@pytest.mark.parametrize("case,text,pattern", CONFIG_ERRORS, ids=[c[0] for c in CONFIG_ERRORS])
def test_bad_config_file_is_one_line_error(case, text, pattern, tmp_path, capsys, box):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(text)
    out = tmp_path / "out"
    rc, _, err = _cli(capsys, "run", box["npz"], "--out", out, "--config", cfg, "-q")
    assert_one_line_error(rc, err, "run", pattern)
    assert_no_partial_outputs(out)


SET_ERRORS = [
    ("set-nan", "gp.d_m=nan", r"Config field 'gp\.d_m' must be finite, found nan"),
    ("set-inf", "surface.voxel_size=inf", r"Config field 'surface\.voxel_size' must be finite"),
    ("set-no-equals", "gp.d_m", r"Expected an override like 'hgmm\.split_threshold=0\.02'"),
    ("set-negative-voxel", "surface.voxel_size=-1",
     r"Config field 'surface\.voxel_size' must lie in \[0\.0001, 100\.0\] m, found -1\.0"),
]


@pytest.mark.parametrize("case,setting,pattern", SET_ERRORS, ids=[c[0] for c in SET_ERRORS])
def test_bad_set_override_is_one_line_error(case, setting, pattern, tmp_path, capsys, box):
    out = tmp_path / "out"
    rc, _, err = _cli(capsys, "run", box["npz"], "--out", out, "--set", setting, "-q")
    assert_one_line_error(rc, err, "run", pattern)
    assert_no_partial_outputs(out)


# --------------------------------------------------------------------------- corpus E: file system faults
def _unprivileged():
    """Command prefix that runs as 'nobody', or skip (needs root and setpriv)."""
    if not IS_ROOT or shutil.which("setpriv") is None:
        pytest.skip("needs root and setpriv to run as an unprivileged user")
    return ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"]


@pytest.fixture
def shared_dir():
    """A folder outside root's private pytest tree (0755) that 'nobody' can traverse."""
    d = Path(tempfile.mkdtemp(prefix="gmmgp_hardening_"))
    d.chmod(0o755)
    yield d
    shutil.rmtree(d, ignore_errors=True)


def test_permission_denied_reading_as_unprivileged_user(shared_dir):
    prefix = _unprivileged()
    path = shared_dir / "locked.xyz"
    np.savetxt(path, _plane(10))
    path.chmod(0o600)  # root's file, not readable by nobody
    r = _sub("info", path, prefix=prefix, cwd=shared_dir)
    assert_one_line_error(r.returncode, r.stderr, "info",
                          r"Permission denied reading '.*locked\.xyz'; make the file readable")


def test_permission_denied_reading_in_process(tmp_path, capsys, monkeypatch):
    """The same refusal simulated in-process (works for any user)."""
    import builtins

    from gmmgp_app.datasets import _common

    path = tmp_path / "locked.npy"
    np.save(path, _plane(10))
    real_open = builtins.open

    def refuse(file, *a, **k):
        if os.fspath(file) == os.fspath(path):
            raise PermissionError(errno.EACCES, "Permission denied", os.fspath(file))
        return real_open(file, *a, **k)

    monkeypatch.setattr(_common, "open", refuse, raising=False)
    rc, _, err = _cli(capsys, "info", path)
    assert_one_line_error(rc, err, "info", r"Permission denied reading '.*locked\.npy'")


def test_output_folder_not_writable_by_unprivileged_user(shared_dir):
    prefix = _unprivileged()
    scan = shared_dir / "plane.xyz"
    np.savetxt(scan, _plane(10))
    scan.chmod(0o644)
    locked = shared_dir / "locked"
    locked.mkdir(mode=0o755)  # owned by root: nobody cannot create anything in it
    r = _sub("run", scan, "--out", locked / "out", "-q", prefix=prefix, cwd=shared_dir)
    assert_one_line_error(r.returncode, r.stderr, "run",
                          r"Cannot write to output folder '.*locked/out' .*choose another --out")
    assert list(locked.iterdir()) == []


def test_output_path_is_an_existing_file(tmp_path, capsys, box):
    blocker = tmp_path / "taken"
    blocker.write_text("not a folder")
    rc, _, err = _cli(capsys, "run", box["npz"], "--out", blocker, "-q")
    assert_one_line_error(rc, err, "run", r"Cannot write to output folder '.*taken'")
    assert blocker.read_text() == "not a folder"


@contextlib.contextmanager
def _tmpfs(where: Path, options: str):
    """Mount a small tmpfs (root only); skip when mounting is not allowed."""
    where.mkdir(parents=True, exist_ok=True)
    if not IS_ROOT:
        pytest.skip("mounting a tmpfs needs root")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(where)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], capture_output=True)


def test_output_on_read_only_file_system(tmp_path, capsys, box):
    with _tmpfs(tmp_path / "ro", "ro,size=64k") as ro:
        rc, _, err = _cli(capsys, "run", box["npz"], "--out", ro / "out", "-q")
        assert_one_line_error(rc, err, "run", r"Cannot write to output folder '.*ro/out'")
        assert list(ro.iterdir()) == []


def test_full_disk_leaves_no_half_written_map(tmp_path, capsys):
    """A 4 KiB file system fills while the map is saved: one-line error, the temporary
    folder is removed and no map/ appears under its final name."""
    scan = tmp_path / "plane.xyz"
    np.savetxt(scan, _plane(30))
    with _tmpfs(tmp_path / "full", "size=4k") as full:
        out = full / "out"
        with pytest.warns(UserWarning, match="no sensor origins"):
            rc, _, err = _cli(capsys, "run", scan, "--out", out, "-q", "--stage", "prepare")
        assert_one_line_error(rc, err, "run", r"No space left on device")
        assert_no_partial_outputs(out)


def test_full_disk_simulated_while_writing_the_summary(tmp_path, capsys, monkeypatch, box):
    """ENOSPC raised by the last write: the earlier outputs are complete files, the failed
    one is absent (not truncated) and no temporary file is left behind."""
    from gmmgp_app import _atomic

    real = _atomic.atomic_write_text

    def fail_summary(path, text):
        if Path(path).name == "summary.json":
            with _atomic.atomic_path(path) as tmp:
                tmp.write_text(text[: len(text) // 2])
                raise OSError(errno.ENOSPC, "No space left on device", str(tmp))
        return real(path, text)

    monkeypatch.setattr(_atomic, "atomic_write_text", fail_summary)
    out = tmp_path / "out"
    rc, _, err = _cli(capsys, "run", box["npz"], "--out", out, "-q", "--stage", "prepare")
    assert_one_line_error(rc, err, "run", r"No space left on device: .*free some disk space")
    assert sorted(p.name for p in out.iterdir()) == ["config.toml", "map"]
    # complete: the configuration the saved map was built with ('auto' resolved)
    assert gm.MappingConfig.from_toml(out / "config.toml") == gm.load_map(out / "map").config


# --------------------------------------------------------------------------- corpus F: memory
def _big_plane(t):
    path = t / "big_plane.npy"
    np.save(path, _plane(100, 0.2))  # 20 m x 20 m, 10k points
    return path


def test_surface_grid_too_large_is_refused_with_the_estimate(tmp_path, capsys):
    path = _big_plane(tmp_path)
    out = tmp_path / "out"
    # Refused before fitting (so before prepare's orientation warning).
    rc, _, err = _cli(capsys, "run", path, "--out", out, "-q", "--method", "hgmm",
                      "--set", "surface.voxel_size=0.0005")
    assert_one_line_error(rc, err, "run",
                          r"surface grid at voxel_size=0\.0005 m needs up to [\d,]+ field "
                          r"evaluations \(~[\d.]+ GiB of temporaries\).*use a larger voxel size")


def test_surface_grid_too_large_is_refused_before_fitting(tmp_path, capsys, monkeypatch):
    from gmmgp_app import pipeline

    def must_not_fit(*a, **k):
        raise AssertionError("stages ran although the surface grid was already too large")

    # build_map checks the grid once the scale is measured (one k-d tree of the scan
    # for both), before its first stage
    monkeypatch.setattr(pipeline, "run_stages", must_not_fit)
    path = _big_plane(tmp_path)
    out = tmp_path / "out"
    rc, _, err = _cli(capsys, "run", path, "--out", out, "-q", "--method", "hgmm",
                      "--set", "surface.voxel_size=0.0005")
    assert_one_line_error(rc, err, "run", r"needs up to [\d,]+ field evaluations")
    assert_no_partial_outputs(out)


def test_a_refused_surface_grid_never_starts_a_cluster(tmp_path, capsys, monkeypatch):
    """``run --workers N`` refuses an impossible grid before the Dask cluster starts
    (starting it costs ~0.5 s, and on a refused grid it was started for nothing)."""
    import gmmgp_app.distributed as D

    def no_cluster(*a, **k):
        raise AssertionError("a cluster was started although the grid is refused")

    monkeypatch.setattr(D, "open_executor", no_cluster)
    out = tmp_path / "out"
    for kind in ((), ("--processes",)):
        rc, _, err = _cli(capsys, "run", _big_plane(tmp_path), "--out", out, "-q",
                          "--method", "hgmm", "--workers", "2", *kind,
                          "--set", "surface.voxel_size=0.0005")
        assert_one_line_error(rc, err, "run", r"needs up to [\d,]+ field evaluations")
        assert_no_partial_outputs(out)


@pytest.mark.filterwarnings("ignore:Scan has no sensor origins")  # a sphere / a plane
def test_run_checks_the_grid_then_starts_the_cluster_with_one_kd_tree(
        tmp_path, capsys, monkeypatch, count_scan_trees):
    """On a grid that fits, the check comes before the cluster, and the grid check and
    the map share one k-d tree of the scan, one scale measurement and the surface seeds."""
    import contextlib

    import gmmgp_app.distributed as D
    from gmmgp_app.commands import run as run_cmd
    from gmmgp_app.stages import autoscale, surface

    events = []
    real_open, real_check = D.open_executor, surface.check_grid_size
    real_resolve = autoscale.resolve_config

    @contextlib.contextmanager
    def serial_cluster(*a, **k):          # what the code asked for, run serially here
        events.append(("cluster", k.get("workers")))
        with real_open() as ex:
            yield ex

    def checking(*a, **k):
        events.append("grid")
        return real_check(*a, **k)

    def measuring(*a, **k):
        events.append("measure")
        return real_resolve(*a, **k)

    scan = gm.read_scan(_big_plane(tmp_path))
    monkeypatch.setattr(run_cmd, "read_scan_args", lambda paths, args: scan)
    monkeypatch.setattr(D, "open_executor", serial_cluster)
    monkeypatch.setattr(surface, "check_grid_size", checking)
    monkeypatch.setattr(autoscale, "resolve_config", measuring)
    built = count_scan_trees(scan.points)
    rc, _, err = _cli(capsys, "run", "plane.npy", "--out", tmp_path / "out", "-q",
                      "--method", "hgmm", "--workers", "2", "--no-mesh")
    assert rc == 0, err
    assert events == [("cluster", 2), "measure"]          # --no-mesh: no grid to check
    events.clear()
    built.clear()
    built = count_scan_trees(scan.points)
    sought = []                       # the surface seeds: sought once, for the check
    real_seeds = surface.surface_seeds
    monkeypatch.setattr(surface, "surface_seeds",
                        lambda *a, **k: sought.append(1) or real_seeds(*a, **k))
    rc, _, err = _cli(capsys, "run", "plane.npy", "--out", tmp_path / "out2", "-q",
                      "--method", "hgmm", "--workers", "2")
    assert rc == 0, err
    assert events[:3] == ["measure", "grid", ("cluster", 2)]
    assert "measure" not in events[3:]
    assert built.count(True) == 1, built
    assert len(sought) == 1
    saved = gm.load_map(tmp_path / "out2" / "map")
    np.testing.assert_array_equal(saved.seed_points,
                                  real_seeds(scan.points, saved.config.surface))


# --------------------------------------------------------------------------- corpus G: interruptions
def _default_sigint():
    # A job started in the background by a non-interactive shell (nohup ... &) inherits
    # SIGINT as ignored, and Python then never raises KeyboardInterrupt: restore it.
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start_run(scan, out, rrd, args=FAST):
    return subprocess.Popen([PY, "-m", "gmmgp_app.cli", "run", str(scan), "--out", str(out),
                             "--rrd", str(rrd), *args], preexec_fn=_default_sigint,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for(proc, marker: str, timeout: float = 120.0) -> list:
    """Read stderr lines until one contains ``marker``; return the lines read."""
    lines, t0 = [], time.monotonic()
    while time.monotonic() - t0 < timeout:
        line = proc.stderr.readline()
        if not line:
            break
        lines.append(line)
        if marker in line:
            return lines
    proc.kill()
    raise AssertionError(f"never saw {marker!r}; stderr so far: {''.join(lines)}")


def _rrd_entities(path):
    import warnings

    from rerun.chunk import RrdReader

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "no footer" after a kill is expected
        return {c.entity_path for c in RrdReader(path).stream().to_chunks()}


@pytest.fixture(scope="module")
def medium(tmp_path_factory):
    """A box scan big enough (~16k points) that a run lasts a few seconds."""
    from gmmgp_app.synth import scan_scene
    from gmmgp_app.synth.io import save_scan_npz

    d = tmp_path_factory.mktemp("medium")
    scan, _ = scan_scene("box", density=0.1, seed=2)
    return save_scan_npz(d / "scan.npz", scan.points, scan.origins)


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL], ids=["sigint", "sigkill"])
def test_interrupted_run_leaves_no_half_written_outputs(sig, tmp_path, medium):
    pytest.importorskip("rerun")
    out, rrd = tmp_path / "out", tmp_path / "run.rrd"
    # 1 cm surface voxels: the stages after the signal last seconds, not 0.1 s
    proc = _start_run(medium, out, rrd, ["--set", "surface.voxel_size=0.01"])
    try:
        _wait_for(proc, "[gmr] running")  # every observer has logged hgmm by then
        proc.send_signal(sig)
        _, rest = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    if sig == signal.SIGINT:
        assert proc.returncode == 130, rest
        assert "Traceback" not in rest
        last = [ln for ln in rest.splitlines() if ln.strip()][-1]
        assert re.fullmatch(r"gmmgp: interrupted; nothing half-written was left behind\.", last)
    else:
        assert proc.returncode == -signal.SIGKILL
    # No output under a final name (the map is saved after the fit), and after SIGINT no
    # temporary sibling either (SIGKILL cannot clean up, but temporaries are dot-names).
    if out.exists():
        finals = [p.name for p in out.iterdir() if not p.name.startswith(".")]
        assert finals == []
        if sig == signal.SIGINT:
            assert list(out.iterdir()) == []
    ents = _rrd_entities(rrd)
    assert {"/world/scan", "/world/hgmm/leaves"} <= ents, ents


def test_interrupt_inside_a_compiled_call_is_an_interrupt(tmp_path, capsys, monkeypatch, box):
    """Ctrl-C landing while a numba call returns reaches Python as ``SystemError: ...
    returned a result with an exception set`` caused by the KeyboardInterrupt (seen once
    in the SIGINT test above, the mesh's thread running beside the GMR): exit 130 and
    the interrupted line, not an internal error; nothing half-written."""
    import gmmgp_app.pipeline as pipeline

    def interrupted(*a, **k):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as ki:
            raise SystemError("CPUDispatcher(<function _lookup_cells>) returned a result "
                              "with an exception set") from ki

    monkeypatch.setattr(pipeline, "build_map", interrupted)
    out = tmp_path / "out"
    rc, _, err = _cli(capsys, "run", box["npz"], "--out", out, "-q")
    assert rc == 130
    assert err.strip() == "gmmgp: interrupted; nothing half-written was left behind."
    assert_no_partial_outputs(out)
    # a SystemError of its own is still an internal error
    def broken(*a, **k):
        raise SystemError("a bug")

    monkeypatch.setattr(pipeline, "build_map", broken)
    rc, _, err = _cli(capsys, "run", box["npz"], "--out", out, "-q")
    assert rc == 1 and "internal error: SystemError: a bug" in err


def test_interrupt_while_saving_the_map_leaves_no_map(tmp_path, capsys, monkeypatch, box):
    """Ctrl-C inside the map save (simulated in the array writer, after its first array
    file): exit 130, no map/ and no temporary folder."""
    calls = {"n": 0}
    real = np.save

    def interrupted(file, *a, **k):
        calls["n"] += 1
        real(file, *a, **k)
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "save", interrupted)
    out = tmp_path / "out"
    rc, _, err = _cli(capsys, "run", box["npz"], "--out", out, "-q", "--stage", "prepare")
    assert calls["n"] == 1
    assert rc == 130
    assert err.strip() == "gmmgp: interrupted; nothing half-written was left behind."
    assert_no_partial_outputs(out)


def test_interrupt_while_writing_a_mesh_keeps_only_complete_files(tmp_path, capsys,
                                                                  monkeypatch, box):
    """Ctrl-C in the middle of a mesh file: the mesh is absent (not truncated), the map
    written before it is complete and loads."""
    from gmmgp_app.stages import surface

    real_atomic = surface.atomic_path

    @contextlib.contextmanager
    def half_then_interrupt(path, suffix=""):
        with real_atomic(path, suffix) as tmp:
            yield tmp
            tmp.write_bytes(tmp.read_bytes()[:100])
            raise KeyboardInterrupt

    monkeypatch.setattr(surface, "atomic_path", half_then_interrupt)
    out = tmp_path / "out"
    rc, _, err = _cli(capsys, "run", box["npz"], "--out", out, "-q", *FAST)
    assert rc == 130, err
    assert sorted(p.name for p in out.iterdir()) == ["map"]
    smap = gm.load_map(out / "map")
    assert np.isfinite(smap.predict(box["scan"].points[:5])[0]).all()


# --------------------------------------------------------------------------- findings for cli.py / prepare.py
def test_warning_is_one_line_in_the_cli(tmp_path):
    path = tmp_path / "nan.xyz"
    xyz = _plane(10)
    xyz[0] = np.nan
    np.savetxt(path, xyz)
    r = _sub("info", path, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert lines == ["gmmgp info: warning: Dropped 1 of 100 points with non-finite "
                     f"coordinates in '{path}'."]


def test_bad_choice_is_one_line_error(tmp_path, box):
    r = _sub("run", box["npz"], "--out", tmp_path / "out", "--method", "magic", cwd=tmp_path)
    assert_one_line_error(r.returncode, r.stderr, "run",
                          r"argument --method: invalid choice: 'magic'.*--help")


def test_full_disk_message_names_the_fix(tmp_path, capsys, monkeypatch, box):
    def no_space(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(np, "save", no_space)
    out = tmp_path / "out"
    rc, _, err = _cli(capsys, "run", box["npz"], "--out", out, "-q", "--stage", "prepare")
    assert_one_line_error(rc, err, "run",
                          rf"No space left on device.*'{re.escape(str(out))}.*free some disk "
                          r"space or choose another --out")


def test_orientation_warning_names_a_real_fix(box):
    import inspect

    from gmmgp_app.config import MappingConfig
    from gmmgp_app.stages.prepare import prepare

    scan = gm.read_scan(box["npz"])
    no_origins = type(scan)(points=scan.points, origins=None, offset=scan.offset)
    with pytest.warns(UserWarning, match="no sensor origins") as rec:
        prepare(no_origins, MappingConfig())
    msg = str(rec[0].message)
    m = re.search(r"read_scan\(\.\.\., (\w+)=", msg)
    assert m is None or m.group(1) in inspect.signature(read_scan).parameters, msg


# --------------------------------------------------------------------------- the documented table
def test_docs_table_lists_every_case():
    """docs/hardening.md has one row per corpus case id (and no stale rows)."""
    ids = ({c[0] for c in READ_ERRORS} | {c[0] for c in DEGENERATE}
           | {c[0] for c in CONFIG_ERRORS} | {c[0] for c in SET_ERRORS})
    text = DOC.read_text()
    rows = set(re.findall(r"^\| `([a-z0-9-]+)` \|", text, flags=re.M))
    assert ids <= rows, sorted(ids - rows)
    tests = set(re.findall(r"`(test_\w+)", text))
    here = {n for n in globals() if n.startswith("test_")}
    here |= set(re.findall(r"^def (test_\w+)", (ROOT / "tests" / "test_properties.py").read_text(),
                           flags=re.M))
    assert tests <= here, sorted(tests - here)
    assert len(rows) >= 30
