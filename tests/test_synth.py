"""Synthetic scenes: exact SDF, watertight meshes, the simulated scanners, outputs."""

import json
from pathlib import Path

import numpy as np
import pytest

from gmmgp_app.synth import (
    LABELS, SCENES, MeshDistance, MeshError, SynthError, box_sdf, cast_rays, make_scene,
    mesh_signed_distance, mesh_topology, scan_scene, simulate_mms, simulate_static,
    sphere_sdf, write_scene)

ROOT = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------------------
# brute-force numpy oracles, independent of the numba code
#
# Distance: for every triangle, the distance to its plane when the projection
# falls inside (barycentric test), else the nearest of the three edge segments,
# all from four dot products per point-triangle pair. Sign: the generalized
# winding number (sum of signed solid angles, Van Oosterom & Strackee), which
# needs no pseudo-normals and no spatial index.


def _tri_terms(v, f):
    a = v[f[:, 0]]
    e0 = v[f[:, 1]] - a
    e1 = v[f[:, 2]] - a
    e2 = e1 - e0
    n = np.cross(e0, e1)
    d00 = np.einsum("ij,ij->i", e0, e0)
    d01 = np.einsum("ij,ij->i", e0, e1)
    d11 = np.einsum("ij,ij->i", e1, e1)
    d22 = np.einsum("ij,ij->i", e2, e2)
    nn = np.einsum("ij,ij->i", n, n)
    return a, e0, e1, n, d00, d01, d11, d22, nn


def brute_unsigned_distance(v, f, xyz, chunk=16):
    """(K,) unsigned distance from each point to the nearest of ALL triangles."""
    a, e0, e1, n, d00, d01, d11, d22, nn = _tri_terms(v, f)
    den = d00 * d11 - d01 * d01
    out = np.empty(len(xyz))
    for s in range(0, len(xyz), chunk):
        p = xyz[s:s + chunk]
        apx = p[:, 0:1] - a[None, :, 0]
        apy = p[:, 1:2] - a[None, :, 1]
        apz = p[:, 2:3] - a[None, :, 2]
        d20 = apx * e0[:, 0] + apy * e0[:, 1] + apz * e0[:, 2]
        d21 = apx * e1[:, 0] + apy * e1[:, 1] + apz * e1[:, 2]
        apn = apx * n[:, 0] + apy * n[:, 1] + apz * n[:, 2]
        apap = apx * apx + apy * apy + apz * apz
        bv = (d11 * d20 - d01 * d21) / den
        bw = (d00 * d21 - d01 * d20) / den
        inside = (bv >= 0) & (bw >= 0) & (bv + bw <= 1)
        best = np.where(inside, apn * apn / nn, np.inf)
        # segment a-b: |ap - t e0|^2 with t clipped
        t = np.clip(d20 / d00, 0, 1)
        best = np.minimum(best, apap - 2 * t * d20 + t * t * d00)
        t = np.clip(d21 / d11, 0, 1)
        best = np.minimum(best, apap - 2 * t * d21 + t * t * d11)
        # segment b-c: bp = ap - e0, e2 = e1 - e0
        bpe2 = (d21 - d20) - (d01 - d00)
        bpbp = apap - 2 * d20 + d00
        t = np.clip(bpe2 / d22, 0, 1)
        best = np.minimum(best, bpbp - 2 * t * bpe2 + t * t * d22)
        out[s:s + chunk] = np.sqrt(np.maximum(best.min(axis=1), 0.0))
    return out


def winding_number(v, f, xyz, chunk=16):
    """(K,) generalized winding number: 1 inside a closed outward mesh, 0 outside."""
    out = np.empty(len(xyz))
    A, B, C = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    for s in range(0, len(xyz), chunk):
        p = xyz[s:s + chunk]
        ax, ay, az = (A[None, :, i] - p[:, i:i + 1] for i in range(3))
        bx, by, bz = (B[None, :, i] - p[:, i:i + 1] for i in range(3))
        cx, cy, cz = (C[None, :, i] - p[:, i:i + 1] for i in range(3))
        la = np.sqrt(ax * ax + ay * ay + az * az)
        lb = np.sqrt(bx * bx + by * by + bz * bz)
        lc = np.sqrt(cx * cx + cy * cy + cz * cz)
        det = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
        den = (la * lb * lc + (ax * bx + ay * by + az * bz) * lc
               + (bx * cx + by * cy + bz * cz) * la + (cx * ax + cy * ay + cz * az) * lb)
        out[s:s + chunk] = np.arctan2(det, den).sum(axis=1) / (2 * np.pi)
    return out


def brute_signed_distance(v, f, xyz):
    """(K,) signed distance, free space positive, by brute force over all triangles."""
    v = np.asarray(v, dtype=np.float64)
    f = np.asarray(f, dtype=np.int64)
    xyz = np.asarray(xyz, dtype=np.float64)
    d = brute_unsigned_distance(v, f, xyz)
    w = winding_number(v, f, xyz)
    return np.where(w > 0.5, -d, d)


@pytest.fixture(scope="module")
def street():
    return make_scene("street")


@pytest.fixture(scope="module")
def street_scan(street):
    # about 25k points: enough for 10 % noise statistics, fast to simulate
    return simulate_mms(street, line_rate=75 * 0.15, points_per_line=int(1800 * 0.15), seed=1)


def _test_points(scene, n, rng, band=0.5, far=0.2):
    """Points near faces, edges and vertices (within +-band) and some far away."""
    v, f = scene.vertices, scene.faces
    n_far = int(far * n)
    n_vert = (n - n_far) // 4
    n_face = n - n_far - n_vert
    fi = rng.integers(0, len(f), n_face)
    bc = rng.dirichlet([1.0, 1.0, 1.0], n_face)
    on_face = np.einsum("ki,kij->kj", bc, v[f[fi]])
    # near vertices and edges too, where the pseudo-normal sign is delicate
    on_vert = v[rng.integers(0, len(v), n_vert)]
    base = np.concatenate([on_face, on_vert])
    dirs = rng.normal(size=base.shape)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    near = base + dirs * rng.uniform(-band, band, (len(base), 1))
    lo, hi = scene.bounds
    far_pts = rng.uniform(lo - 5.0, hi + 5.0, (n_far, 3))
    return np.concatenate([near, far_pts])


# ---------------------------------------------------------------------------
# exact signed distance


def _check_against_oracle(scene, n, seed):
    rng = np.random.default_rng(seed)
    x = _test_points(scene, n, rng)
    got = scene.sdf(x)
    want = brute_signed_distance(scene.vertices, scene.faces, x)
    assert np.abs(got - want).max() < 1e-6
    # the sample really probes both sides and the band
    assert (got < 0).sum() > n // 10 and (got > 0).sum() > n // 10


def test_street_sdf_matches_brute_force_oracle_small(street):
    _check_against_oracle(street, 250, seed=0)


@pytest.mark.slow
def test_street_sdf_matches_brute_force_oracle_2000_points(street):
    # the acceptance check: street SDF vs the mesh at random points to 1e-6
    _check_against_oracle(street, 2000, seed=1)


@pytest.mark.slow
def test_street2_sdf_matches_brute_force_oracle():
    _check_against_oracle(make_scene("street2"), 400, seed=2)


@pytest.mark.parametrize("name", ["plane", "box"])
def test_box_like_mesh_sdf_equals_closed_form(name):
    scene = make_scene(name)
    rng = np.random.default_rng(3)
    x = _test_points(scene, 3000, rng, band=1.0)
    assert np.abs(scene.sdf(x) - scene.analytic_sdf(x)).max() < 1e-9
    want = brute_signed_distance(scene.vertices, scene.faces, x[:500])
    assert np.abs(scene.sdf(x[:500]) - want).max() < 1e-9


def test_sphere_mesh_sdf_within_sagitta_of_true_sphere():
    scene = make_scene("sphere", radius=1.0, subdivisions=4)
    v, f = scene.vertices, scene.faces
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    # vertices lie on the sphere, so the surfaces are at most the deepest face apart
    sagitta = 1.0 - np.einsum("ij,ij->i", n, v[f[:, 0]]).min()
    assert 0 < sagitta < 1.2e-3
    rng = np.random.default_rng(4)
    x = rng.uniform(-2.0, 2.0, (4000, 3))
    diff = scene.sdf(x) - sphere_sdf(x, (0, 0, 0), 1.0)
    assert np.abs(diff).max() <= sagitta + 1e-12
    want = brute_signed_distance(v, f, x[:300])
    assert np.abs(scene.sdf(x[:300]) - want).max() < 1e-9


def test_closed_form_sdfs_hand_values():
    assert box_sdf([[2.0, 0.0, 0.0]], (0, 0, 0), (1, 1, 1))[0] == pytest.approx(1.0)
    assert box_sdf([[2.0, 2.0, 1.0]], (0, 0, 0), (1, 1, 1))[0] == pytest.approx(np.sqrt(2))
    assert box_sdf([[0.5, 0.0, 0.0]], (0, 0, 0), (1, 1, 1))[0] == pytest.approx(-0.5)
    # turned 90 degrees: the long axis now lies along y
    assert box_sdf([[0.0, 1.5, 0.0]], (0, 0, 0), (2, 1, 1), yaw_deg=90)[0] == pytest.approx(-0.5)
    assert sphere_sdf([[0.0, 0.0, 3.0]], (0, 0, 1), 1.0)[0] == pytest.approx(1.0)


def test_mesh_signed_distance_one_shot_equals_structure():
    scene = make_scene("box")
    x = np.random.default_rng(5).normal(size=(200, 3))
    np.testing.assert_array_equal(mesh_signed_distance(scene.vertices, scene.faces, x),
                                  MeshDistance(scene.vertices, scene.faces)(x))
    d, tri, reg = MeshDistance(scene.vertices, scene.faces)(x, return_closest=True)
    assert tri.min() >= 0 and tri.max() < 12 and set(np.unique(reg)) <= set(range(7))


def test_cell_size_does_not_change_the_answer(street):
    x = _test_points(street, 2000, np.random.default_rng(6))
    ref = street.sdf(x)
    for h in (0.3, 5.0):
        np.testing.assert_array_equal(MeshDistance(street.vertices, street.faces, h)(x), ref)


# ---------------------------------------------------------------------------
# meshes


@pytest.mark.parametrize("name,euler", [("plane", 2), ("sphere", 2), ("box", 2),
                                        ("street", -4), ("street2", -10)])
def test_meshes_watertight_and_outward(name, euler):
    # streets: genus 3 per car, whose body stands on four wheel blocks
    scene = make_scene(name)
    topo = mesh_topology(scene.vertices, scene.faces)
    assert topo["n_bad_edges"] == 0
    assert topo["euler"] == euler
    assert topo["volume"] > 0
    assert scene.vertices.dtype == np.float64 and scene.faces.dtype == np.int64
    assert len(scene.face_labels) == len(scene.faces)
    # outward: points just off each face centroid along its normal are outside
    rng = np.random.default_rng(7)
    fi = rng.choice(len(scene.faces), min(40, len(scene.faces)), replace=False)
    tri = scene.vertices[scene.faces[fi]]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    c = tri.mean(axis=1)
    assert np.all(winding_number(scene.vertices, scene.faces, c + 1e-4 * n) < 0.5)
    assert np.all(winding_number(scene.vertices, scene.faces, c - 1e-4 * n) > 0.5)


def test_box_volume_and_street_contents(street):
    topo = mesh_topology(*(lambda s: (s.vertices, s.faces))(make_scene("box")))
    assert topo["volume"] == pytest.approx(8 * 1.0 * 0.6 * 0.4, rel=1e-12)
    labels = set(np.unique(street.face_labels))
    assert {1, 2, 3, 4, 5, 6} <= labels
    lo, hi = street.bounds
    assert 30 <= hi[0] - lo[0] <= 50
    # a window recess is 0.2 m deep: inside the recess, 0.1 m from its back wall
    # (front of the long building at y = -8, first upper-floor window at z 3.9-5.4)
    assert street.sdf([[1.5, -8.1, 4.5]])[0] == pytest.approx(0.1, abs=1e-12)
    assert street.sdf([[-3.0, 0.0, 0.5]])[0] == pytest.approx(0.5, abs=1e-12)


def test_scenes_tuple_lists_every_scene():
    assert SCENES == ("plane", "sphere", "box", "street", "street2", "street_van")
    for name in SCENES:
        assert make_scene(name).name == name


# ---------------------------------------------------------------------------
# scanners


def test_noise_free_hits_lie_on_the_surface(street):
    scan = simulate_mms(street, line_rate=5, points_per_line=600, range_noise=0.0, dropout=0.0)
    assert len(scan) > 5000
    assert np.abs(street.sdf(scan.points)).max() < 1e-5


def test_noisy_hits_have_the_range_noise_along_the_ray(street, street_scan):
    scan = street_scan
    assert 15_000 < len(scan) < 40_000
    o, p = scan.origins, scan.points
    rng_meas = np.linalg.norm(p - o, axis=1)
    d = (p - o) / rng_meas[:, None]
    t_true, face = cast_rays(street, o, d)
    assert np.all(face >= 0)
    eps = rng_meas - t_true
    assert abs(eps.std() / 0.008 - 1.0) < 0.1
    assert abs(eps.mean()) < 0.0005
    # the SDF is 1-Lipschitz: a hit is no farther from the surface than its range error
    sdf = street.sdf(p)
    assert np.all(np.abs(sdf) <= np.abs(eps) + 1e-6)
    assert 0.003 < np.abs(sdf).mean() < 0.008


def test_origins_in_free_space_and_hits_visible(street):
    scan = simulate_mms(street, line_rate=5, points_per_line=600, range_noise=0.0, seed=3)
    assert np.all(street.sdf(scan.origins) > 0)
    sub = np.random.default_rng(0).choice(len(scan), 1500, replace=False)
    o, p = scan.origins[sub], scan.points[sub]
    r = np.linalg.norm(p - o, axis=1)
    frac = np.linspace(0.0, 1.0, 24)[None, :] * ((r - 1e-3) / r)[:, None]
    seg = o[:, None, :] + frac[..., None] * (p - o)[:, None, :]
    assert np.all(street.sdf(seg.reshape(-1, 3)) > 0)


def test_mms_origins_follow_the_drive(street_scan):
    o = street_scan.origins
    assert np.all(np.isin(np.round(o[:, 1], 9), [1.15, 1.85]))
    assert np.allclose(o[:, 2], 2.3)
    assert 0 <= o[:, 0].min() < 1.0 and 35.0 < o[:, 0].max() <= 36.0
    counts = np.bincount(street_scan.labels, minlength=8)
    assert counts[1] > 0 and counts[2] > 0 and counts[6] > 0


def test_seeds_reproduce_and_differ(street):
    kw = dict(line_rate=4, points_per_line=400)
    a = simulate_mms(street, seed=5, **kw)
    b = simulate_mms(street, seed=5, **kw)
    c = simulate_mms(street, seed=6, **kw)
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.origins, b.origins)
    assert len(a) != len(c) or not np.array_equal(a.points, c.points)


def test_dropout_removes_the_asked_fraction(street):
    kw = dict(line_rate=6, points_per_line=1000, seed=2)
    full = len(simulate_mms(street, dropout=0.0, **kw))
    part = len(simulate_mms(street, dropout=0.3, **kw))
    assert part / full == pytest.approx(0.7, abs=0.01)


def test_static_sphere_scan():
    scan, scene = scan_scene("sphere", density=0.05, range_noise=0.0, dropout=0.0)
    assert 5_000 < len(scan) < 40_000
    assert np.abs(scene.sdf(scan.points)).max() < 1e-5
    # every origin is one of the four stations, all in free space
    stations = np.unique(scan.origins, axis=0)
    assert len(stations) == 4 and np.all(scene.sdf(stations) > 0)
    # points are spread over the sphere (seen from all sides)
    assert np.all(np.abs(scan.points.mean(axis=0)) < 0.3)


def test_scan_scene_density_scales_point_count():
    small, _ = scan_scene("box", density=0.05)
    big, _ = scan_scene("box", density=0.2)
    assert big.points.shape[0] / small.points.shape[0] == pytest.approx(4.0, rel=0.15)


@pytest.mark.slow
def test_default_street_scan_is_about_1_3_million_points():
    scan, scene = scan_scene("street")
    assert 1.1e6 < len(scan) < 1.5e6


# ---------------------------------------------------------------------------
# outputs


def test_write_scene_outputs(tmp_path):
    import open3d as o3d

    paths = write_scene("box", tmp_path / "out", density=0.02, seed=4)
    assert set(paths) == {"scan", "mesh", "scene"}
    with np.load(paths["scan"], allow_pickle=False) as z:
        assert z["points"].dtype == np.float64 and z["origins"].shape == z["points"].shape
        assert z["labels"].dtype == np.int64
        n = len(z["points"])
    meta = json.loads(paths["scene"].read_text())
    assert meta["n_points"] == n and meta["seed"] == 4 and meta["name"] == "box"
    mesh = o3d.io.read_triangle_mesh(str(paths["mesh"]))
    assert len(mesh.triangles) == meta["n_faces"] == 12
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        "mesh.ply", "scan.npz", "scene.json"]


def test_demo_asset_small_and_loadable():
    npz = ROOT / "assets" / "demo_street.npz"
    ply = ROOT / "assets" / "demo_street_mesh.ply"
    assert npz.stat().st_size + ply.stat().st_size < 5_000_000
    with np.load(npz, allow_pickle=False) as z:
        pts = z["points"].astype(np.float64)
        org = z["origins"].astype(np.float64)
        lab = z["labels"]
    assert pts.shape == org.shape and len(pts) > 50_000 and lab.shape == (len(pts),)
    assert set(np.unique(lab)) <= set(LABELS)
    # the bundled scan is the street scene, 8 mm range noise
    d = make_scene("street").sdf(pts[:20000])
    assert 0.004 < d.std() < 0.008


# ---------------------------------------------------------------------------
# errors


def test_error_messages(street, tmp_path):
    with pytest.raises(SynthError, match="Unknown synthetic scene 'moon'"):
        make_scene("moon")
    with pytest.raises(SynthError, match=r"Unknown parameter\(s\) \['radius'\] for scene 'box'"):
        make_scene("box", radius=2)
    with pytest.raises(SynthError, match="Expected sphere parameter 'radius' in"):
        make_scene("sphere", radius=-1.0)
    with pytest.raises(SynthError, match="Expected sphere parameter 'subdivisions' in"):
        make_scene("sphere", subdivisions=9)
    with pytest.raises(SynthError, match="Expected street parameter 'length' in"):
        make_scene("street", length=5.0)
    with pytest.raises(SynthError, match="has no closed-form SDF"):
        street.analytic_sdf([[0.0, 0.0, 0.0]])
    with pytest.raises(SynthError, match="Expected every station in free space"):
        simulate_static(make_scene("sphere", subdivisions=2), [[0.0, 0.0, 0.0]])
    with pytest.raises(SynthError, match="Expected stations of shape"):
        simulate_static(make_scene("box"), np.zeros((2, 2)))
    with pytest.raises(SynthError, match="Expected angular_step_deg in"):
        simulate_static(make_scene("box"), [[5.0, 0, 0]], angular_step_deg=0.0)
    with pytest.raises(SynthError, match="Expected dropout in"):
        simulate_mms(street, dropout=1.0)
    with pytest.raises(SynthError, match="Expected range_noise >= 0"):
        simulate_mms(street, range_noise=-0.1)
    with pytest.raises(SynthError, match="Expected 0 <= min_range < max_range"):
        simulate_mms(street, min_range=5.0, max_range=2.0)
    with pytest.raises(SynthError, match="Expected simulate_mms parameter 'speed' > 0"):
        simulate_mms(street, speed=0.0)
    with pytest.raises(SynthError, match="Expected density in"):
        scan_scene("box", density=0.0)
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(SynthError, match="Expected an output folder, found the file"):
        write_scene("box", f)


def test_mesh_error_messages():
    v, f = make_scene("box").vertices, make_scene("box").faces
    with pytest.raises(MeshError, match="Expected a closed oriented 2-manifold"):
        MeshDistance(v, f[:-1])
    with pytest.raises(MeshError, match="Expected a closed oriented 2-manifold"):
        MeshDistance(v, np.concatenate([f[:-1], f[-1:, ::-1]]))
    with pytest.raises(MeshError, match=r"Expected vertices \(V, 3\) and faces \(F, 3\)"):
        MeshDistance(v[:, :2], f)
    with pytest.raises(MeshError, match="Expected face indices in"):
        MeshDistance(v, f + 1)
    with pytest.raises(MeshError, match="Expected non-degenerate triangles"):
        MeshDistance(np.concatenate([v, v[:1]]), np.concatenate([f, [[0, 8, 1]]]))
    with pytest.raises(MeshError, match="Expected finite vertex coordinates"):
        MeshDistance(np.where(np.arange(8)[:, None] == 0, np.nan, v), f)
    with pytest.raises(MeshError, match="Expected cell_size > 0 m"):
        MeshDistance(v, f, cell_size=-1.0)
    md = MeshDistance(v, f)
    with pytest.raises(MeshError, match=r"Expected query points of shape \(K, 3\)"):
        md(np.zeros((3, 2)))
    with pytest.raises(MeshError, match="Expected finite query points"):
        md([[np.nan, 0.0, 0.0]])
