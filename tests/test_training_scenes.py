"""The random training scenes of the variance fit (gmmgp_app.synth.training_scenes):
closed meshes, reproducible from the seed, scans on the exact surface."""

import numpy as np
import pytest

from gmmgp_app.synth.scenes import SynthError, mesh_topology
from gmmgp_app.synth.training_scenes import make_training_scene, scan_training_scene


@pytest.mark.parametrize("kind", ["yard", "objects"])
def test_training_scenes_closed_and_reproducible(kind):
    meshes = [make_training_scene(kind, s) for s in (1, 2, 3)]
    for m in meshes:
        topo = mesh_topology(m.vertices, m.faces)
        assert topo["n_bad_edges"] == 0 and topo["volume"] > 0
    again = make_training_scene(kind, 2)
    np.testing.assert_array_equal(again.vertices, meshes[1].vertices)
    np.testing.assert_array_equal(again.faces, meshes[1].faces)
    # different seeds draw different layouts
    assert len({(len(m.vertices), round(float(m.vertices.sum()), 6)) for m in meshes}) == 3


@pytest.mark.parametrize("kind,seed", [("yard", 5), ("objects", 5)])
def test_training_scans_lie_on_the_exact_surface(kind, seed):
    scan, scene, k = scan_training_scene(kind, seed, density=0.05)
    assert len(scan) > 1000
    d = scene.sdf(scan.points)
    # range noise at most 12 mm (yards) or 8 mm x the scale (objects), along the rays
    bound = 4 * (0.012 if kind == "yard" else 0.008 * k)
    assert np.quantile(np.abs(d), 0.99) < bound
    assert np.all(scene.sdf(np.unique(scan.origins, axis=0)) > 0)
    if kind == "objects":
        assert 0.2 <= k <= 1.5 and scene.params["scale"] == k
    else:
        assert k == 1.0


def test_training_scene_unknown_kind():
    with pytest.raises(SynthError, match="Unknown training scene kind"):
        make_training_scene("street", 1)


@pytest.mark.parametrize("kind", ["yard", "objects"])
def test_training_scan_at_a_chosen_noise_level(kind):
    """``range_noise`` replaces the random draw only: the same layout, stations and
    scale, the scan's spread about the exact surface follows the given noise."""
    lo, _, k_lo = scan_training_scene(kind, 6, density=0.05, range_noise=0.001)
    hi, scene, k_hi = scan_training_scene(kind, 6, density=0.05, range_noise=0.016)
    assert k_lo == k_hi
    np.testing.assert_array_equal(lo.origins, hi.origins)
    d_lo, d_hi = np.abs(scene.sdf(lo.points)), np.abs(scene.sdf(hi.points))
    # the median |sdf| of a Gaussian range error is 0.67 sigma x the ray's incidence
    # cosine (<= 1); the scene was scaled by k with its noise
    assert np.median(d_lo) < 0.001 * k_lo and np.median(d_hi) < 0.016 * k_hi
    assert np.median(d_hi) > 5 * np.median(d_lo)
    with pytest.raises(SynthError, match="positive finite range noise"):
        scan_training_scene(kind, 6, density=0.05, range_noise=-1.0)
