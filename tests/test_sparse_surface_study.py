"""scripts/sparse_surface_study.py's binning of a mesh by the distance to the scan: on a
flat square whose scan covers only a strip, the area shares and the per-bin distances
are the geometry's."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree


@pytest.fixture(scope="module")
def study(load_script):
    return load_script("sparse_surface_study")


def _square(n: int = 200):
    """The unit square at z = 0 as 2 n^2 triangles."""
    g = np.linspace(0.0, 1.0, n + 1)
    x, y = np.meshgrid(g, g, indexing="ij")
    v = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    i = np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]
    a, b, c, d = i, i + n + 1, i + 1, i + n + 2
    f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                        np.stack([c, b, d], -1).reshape(-1, 3)])
    return v, f


def test_bins_follow_the_distance_to_a_strip_of_scan_points(study):
    v, f = _square()
    # scan points on the strip x <= 0.3, 5 mm apart: a point of the square at x lies
    # max(0, x - 0.3) from the scan (to within the points' 2.5 mm half-spacing)
    g = np.arange(0.0, 0.3 + 1e-9, 0.005)
    px, py = np.meshgrid(g, np.arange(0.0, 1.0 + 1e-9, 0.005), indexing="ij")
    pts = np.column_stack([px.ravel(), py.ravel(), np.zeros(px.size)])
    out = study.binned(v, f, cKDTree(pts), None, 100_000, 0)
    # x < 0.35, 0.35-0.5, 0.5-0.8, >= 0.8
    expect = {"<5cm": 0.35, "5-20cm": 0.15, "20-50cm": 0.30, ">50cm": 0.20}
    assert sum(b["faces"] for b in out.values()) == len(f)
    for name, share in expect.items():
        assert out[name]["area_frac"] == pytest.approx(share, abs=0.01), name
        assert out[name]["sample_frac"] == pytest.approx(share, abs=0.01), name
    # with no reference mesh the accuracy is the distance to the scan: the bin's
    # mean distance, e.g. 5-20 cm -> x - 0.3 uniform on (0.05, 0.2): 12.5 cm
    assert out["5-20cm"]["acc_mean_mm"] == pytest.approx(125.0, abs=3.0)
    assert out["20-50cm"]["acc_mean_mm"] == pytest.approx(350.0, abs=3.0)


def test_a_reference_mesh_gives_its_own_distance_not_the_scans(study):
    from gmmgp_app.evaluation import Reference

    v, f = _square(40)
    pts = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0]])
    ref = Reference.from_mesh(v + [0.0, 0.0, 0.01], f)     # the same square 1 cm above
    out = study.binned(v, f, cKDTree(pts), ref, 20_000, 0)
    for b in out.values():
        if b["sample_frac"] > 0:
            assert b["acc_mean_mm"] == pytest.approx(10.0, abs=1e-6)
