"""Occupied voxels by a hashed pass (stages/_distinct.py) against np.unique."""

import numpy as np
import pytest

from gmmgp_app.config import PrepareConfig
from gmmgp_app.stages._distinct import voxel_count, voxel_first
from gmmgp_app.stages.prepare import _first_of_rows, subsample


def _unique_first(points, size, order):
    """np.unique's first occurrence per voxel (lexicographic order of the voxels)."""
    keys = np.floor((points[order] - points.min(axis=0)) / size).astype(np.int64)
    return np.unique(keys, axis=0, return_index=True)[1]


@pytest.mark.parametrize("n, size", [(0, 0.1), (1, 0.1), (7, 10.0), (3000, 0.05),
                                     (20000, 0.013)])
def test_voxel_first_and_count_are_uniques(n, size):
    """Same voxels as np.unique of the floored keys (the set of first occurrences in the
    given order, increasing) and the same count; duplicated points, negative and large
    coordinates (a local frame far from the origin) included."""
    rng = np.random.default_rng(n)
    pts = rng.normal(size=(n, 3)) * [3.0, 1.0, 0.2] + [-500.0, 2000.0, 0.0]
    if n > 10:
        pts[n // 2:n // 2 + 10] = pts[:10]             # exact duplicates
    order = rng.permutation(n)
    got = voxel_first(pts, size, order)
    want = np.sort(_unique_first(pts, size, order)) if n else np.zeros(0, np.int64)
    np.testing.assert_array_equal(got, want)
    assert voxel_count(pts, size) == len(want)
    assert voxel_first(pts, size) is not None and len(voxel_first(pts, size)) == len(want)


def test_grid_too_large_to_pack_returns_none():
    pts = np.array([[0.0, 0.0, 0.0], [1e7, 1e7, 1e7]])
    assert voxel_first(pts, 1e-4) is None and voxel_count(pts, 1e-4) is None


def test_voxel_subsample_keeps_the_points_uniques_first_index_kept():
    """prepare.subsample's voxel branch (hashed) keeps the points the np.unique-based
    selection kept (one per voxel, the first of a seeded permutation)."""
    rng = np.random.default_rng(5)
    pts = rng.uniform(-2, 2, size=(30000, 3)) * [4, 1, 0.5]
    cfg = PrepareConfig(subsample_rate=1.0, subsample_voxel=0.07)
    got = subsample(pts, cfg, np.random.default_rng(11))
    perm = np.random.default_rng(11).permutation(len(pts))
    keys = np.floor((pts[perm] - pts.min(axis=0)) / 0.07).astype(np.int64)
    np.testing.assert_array_equal(got, np.sort(perm[_first_of_rows(keys)]))
    assert 1000 < len(got) < len(pts)


@pytest.mark.parametrize("n, size", [(0, 0.1), (1, 0.1), (7, 10.0), (3000, 0.05),
                                     (20000, 0.013)])
def test_cell_first_and_count_are_uniques_anchored_at_zero(n, size):
    """Cells floor(p / size) (anchored at 0, the surface seeds' cells): the first index
    of each, increasing, and their number, as np.unique of the floored keys; negative
    coordinates, points on cell borders and duplicates included."""
    from gmmgp_app.stages._distinct import cell_count, cell_first

    rng = np.random.default_rng(100 + n)
    pts = rng.normal(size=(n, 3)) * [3.0, 1.0, 0.2] + [-500.0, 2000.0, 0.0]
    if n > 10:
        pts[n // 2:n // 2 + 10] = pts[:10]
        pts[20:30] = np.round(pts[20:30] / size) * size       # on cell borders
    keys = np.floor(pts / size).astype(np.int64)
    want = np.sort(np.unique(keys, axis=0, return_index=True)[1]) if n else np.zeros(0, int)
    np.testing.assert_array_equal(cell_first(pts, size), want)
    assert cell_count(pts, size) == len(want)


def test_surface_seeds_hashed_equal_the_sorted_ones(monkeypatch):
    """stages.surface.surface_seeds and estimate_grid_nodes through the hashed cells give
    what the np.unique path (their fallback) gives."""
    from gmmgp_app.config import SurfaceConfig
    from gmmgp_app.stages import _distinct, surface

    rng = np.random.default_rng(3)
    pts = rng.uniform(-3, 3, size=(40000, 3)) * [5, 1, 0.3] + [100.0, -40.0, 2.0]
    cfg = SurfaceConfig(voxel_size=0.05)
    seeds = surface.surface_seeds(pts, cfg)
    nodes = surface.estimate_grid_nodes(seeds, 0.05, 3)
    monkeypatch.setattr(_distinct, "cell_first", lambda p, s: None)
    monkeypatch.setattr(_distinct, "cell_count", lambda p, s: None)
    np.testing.assert_array_equal(seeds, surface.surface_seeds(pts, cfg))
    assert nodes == surface.estimate_grid_nodes(seeds, 0.05, 3)
    assert 1000 < len(seeds) < len(pts)
