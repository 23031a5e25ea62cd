"""Scan readers on the real files in ../shared/data (skipped when it is absent).

The expected figures are those of ../shared/data/DATA.md, checked against
what these readers measure.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.spatial import cKDTree

from gmmgp_app.datasets import ScanWarning, read_scan, scan_summary
from gmmgp_app.datasets._common import quat_to_matrix
from gmmgp_app.datasets.bunny import parse_conf

pytestmark = pytest.mark.shared


def test_kitti_scan0_with_labels(shared_data):
    path = shared_data / "kitti_odometry_seq00" / "velodyne" / "000000.bin"
    scan = read_scan(path)
    assert len(scan) == 124_668
    np.testing.assert_array_equal(scan.origins, 0)
    s = scan_summary(scan)
    # DATA.md: about 158 x 100 x 14 m, spacing about 3 cm, about 18k building points
    np.testing.assert_allclose(s["extent_m"], [156.05, 100.60, 14.38], atol=0.01)
    assert 0.025 < s["spacing_m"] < 0.04
    assert 17_000 < s["classes"][50] < 19_000
    assert s["classes"][50] == 18_268
    buildings = read_scan(path, classes=[50])
    assert len(buildings) == 18_268 and np.all(buildings.labels == 50)


def test_bunny_registration_needs_conjugated_quaternion(shared_data):
    bunny = shared_data / "stanford_bunny"
    ref = cKDTree(read_scan(bunny / "reconstruction" / "bun_zipper.ply").points)
    scan = read_scan(bunny / "raw_scans")
    assert scan.origins is None
    assert len(scan) == 362_272
    sample = np.random.default_rng(0).choice(len(scan), 60_000, replace=False)
    d, _ = ref.query(scan.points[sample])
    # DATA.md: about 0.55 mm (median) from the reference; measured 0.54 mm
    assert np.median(d) < 1.5e-3
    assert np.median(d) == pytest.approx(0.55e-3, abs=0.1e-3)
    # with R(q) instead of R(q)^T the rotated scans are centimetres off
    entries = parse_conf(bunny / "raw_scans" / "bun.conf")
    ply, t, q = next(e for e in entries if e[0].name == "chin.ply")
    local = read_scan(ply).points[::4]
    R = quat_to_matrix(q[3], q[0], q[1], q[2])
    good = np.median(ref.query(local @ R + t)[0])
    bad = np.median(ref.query(local @ R.T + t)[0])
    assert good < 1.5e-3 and bad > 20 * good
    np.testing.assert_allclose(read_scan(bunny / "raw_scans" / "bun.conf", scans=["chin"]).points,
                               read_scan(ply).points @ R + t, atol=1e-12)


def test_airborne_laz_in_feet(shared_data):
    path = shared_data / "airborne" / "autzen_trim.laz"
    scan = read_scan(path)
    assert len(scan) == 110_000
    assert scan.units == "ft"
    s = scan_summary(scan)
    # DATA.md: about 359 x 172 x 35 m in metres (measured 358.89 x 171.51 x 34.82)
    np.testing.assert_allclose(s["extent_m"], [359, 172, 35], atol=1.0)
    np.testing.assert_allclose(s["extent_m"], [358.890, 171.511, 34.823], atol=1e-3)
    assert s["classes"] == {1: 83_893, 2: 26_107}
    # State-plane sized coordinates are shifted to a local frame with a round offset
    np.testing.assert_array_equal(scan.offset, [193000.0, 258000.0, 0.0])
    assert np.abs(scan.points).max() < 1300
    # the user's units override the CRS: raw feet
    feet = read_scan(path, units="m")
    np.testing.assert_allclose(scan_summary(feet)["extent_m"], np.array(s["extent_m"]) / 0.3048, rtol=1e-9)


def test_kitti_folder_with_poses(shared_data):
    seq = shared_data / "kitti_odometry_seq00"
    poses = np.loadtxt(seq / "poses_gicp_estimated.txt", comments="#").reshape(-1, 3, 4)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ScanWarning)  # scans 3-5 have no labels
        scan = read_scan(seq, max_scans=3)
    sizes = [len(read_scan(seq / "velodyne" / f"{i:06d}.bin")) for i in range(3)]
    assert len(scan) == sum(sizes)
    starts = np.cumsum([0] + sizes)
    for i in range(3):
        org = scan.origins[starts[i]: starts[i + 1]]
        np.testing.assert_allclose(org, np.broadcast_to(poses[i, :, 3], org.shape), atol=1e-12)
        local = read_scan(seq / "velodyne" / f"{i:06d}.bin").points
        np.testing.assert_allclose(scan.points[starts[i]: starts[i + 1]],
                                   local @ poses[i, :, :3].T + poses[i, :, 3], atol=1e-9)
    # all three have labels, so the merged scan keeps them
    assert scan.labels is not None and len(scan.labels) == len(scan)
    # consecutive scans about 0.7 m apart along x (DATA.md)
    assert 0.5 < np.linalg.norm(poses[1, :, 3] - poses[0, :, 3]) < 0.9
    with pytest.warns(ScanWarning, match=r"Only 3 of 6 scans have labels"):
        everything = read_scan(seq)
    assert everything.labels is None and everything.origins is not None


def test_the_bunny_stands_along_y_and_the_app_views_it_so(shared_data):
    """The Stanford bunny's up axis is y (datasets.registry.up_axis): its height (15 cm,
    as long as it is from nose to tail along x) runs along y and the open holes of the
    reference mesh, at its bottom, lie near the lowest y; the app's model of the scan
    set carries that up axis to its view."""
    from gmmgp_app.viz.gui_model import ViewerModel

    bunny = shared_data / "stanford_bunny"
    mesh = read_scan(bunny / "reconstruction" / "bun_zipper.ply").points
    ext = np.ptp(mesh, axis=0)
    assert 0.14 < ext[1] < 0.17 and ext[2] < 0.8 * ext[1]
    import open3d as o3d

    m = o3d.io.read_triangle_mesh(str(bunny / "reconstruction" / "bun_zipper.ply"))
    v, f = np.asarray(m.vertices), np.asarray(m.triangles)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    u, c = np.unique(e, axis=0, return_counts=True)
    hole = v[np.unique(u[c == 1])]
    assert hole[:, 1].max() - v[:, 1].min() < 0.2 * ext[1]     # the holes: at the bottom
    model = ViewerModel.open(bunny / "raw_scans" / "bun.conf")
    np.testing.assert_array_equal(model.up, [0, 1, 0])
