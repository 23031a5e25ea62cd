"""Executors, batching, tiles and incremental updates (gmmgp_app.distributed / .tiling)."""

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

import gmmgp_app as gm
from gmmgp_app.config import GPConfig
from gmmgp_app.distributed import (DistributedError, SerialExecutor, batch_by_cost,
                                   imap_unordered, map_batched, open_executor)
from gmmgp_app.stages.gp import ConstantPrior, fit_local_gps
from gmmgp_app.tiling import (TiledMap, TileSpec, TilingError, build_tiled_map, tile_owners,
                              build_tiled_map_from_las)



@pytest.fixture(autouse=True, scope="module")
def _one_blas_thread():
    """Multithreaded BLAS on a loaded 2-core machine makes a 480x480 Cholesky 100x
    slower (measured: 1 s vs 10 ms); Dask workers run with one BLAS thread too."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        yield


# ---------------------------------------------------------------- executors


def _square(x):
    return x * x


def _boom(x):
    raise KeyError(x)


def test_serial_executor_runs_inline_and_keeps_exceptions():
    ex = SerialExecutor()
    assert ex.submit(_square, 7).result() == 49
    with pytest.raises(KeyError):
        ex.submit(_boom, 1).result()


def test_map_batched_order_and_one_progress_across_tasks():
    calls = []
    out = map_batched(SerialExecutor(), sum, [[1, 2], [3], [4, 5, 6]], sizes=[2, 1, 3],
                      progress=lambda d, t: calls.append((d, t)))
    assert out == [3, 3, 15]
    assert calls[0] == (0, 6) and calls[-1] == (6, 6)
    assert [d for d, _ in calls] == sorted(d for d, _ in calls)


@pytest.mark.parametrize("target", [0.0, 0.01, 0.05, 1.0])
def test_batch_by_cost_partitions_in_order(target):
    rng = np.random.default_rng(1)
    costs = rng.exponential(0.004, size=200)
    batches = batch_by_cost(costs, target)
    assert np.array_equal(np.concatenate(batches), np.arange(200))
    sums = [costs[b].sum() for b in batches]
    # every batch but the last reaches the target; the last is at least half of it
    # unless it is the only one
    assert all(s >= target for s in sums[:-1])
    assert len(batches) == 1 or sums[-1] >= 0.5 * target
    if target == 0.0:
        assert len(batches) == 200


def test_batch_by_cost_max_batches():
    assert len(batch_by_cost(np.full(100, 1e-3), 0.0, max_batches=4)) == 4


def test_batch_errors():
    with pytest.raises(DistributedError, match="min_task_seconds >= 0"):
        batch_by_cost([1.0], -1)
    with pytest.raises(DistributedError, match="non-negative item costs"):
        batch_by_cost([1.0, np.nan], 0.01)


def test_open_executor_errors():
    with pytest.raises(DistributedError, match="kind 'dask' or 'processes'"):
        with open_executor(2, kind="threads"):
            pass
    with pytest.raises(DistributedError, match="workers to be an integer >= 0"):
        with open_executor(-1):
            pass
    with pytest.raises(DistributedError, match="scheduler address like"):
        with open_executor(scheduler="localhost:8786"):
            pass
    with open_executor(0) as ex:
        assert isinstance(ex, SerialExecutor)


class _CountingPool(ThreadPoolExecutor):
    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.submitted = 0

    def submit(self, fn, *args, **kwargs):
        self.submitted += 1
        return super().submit(fn, *args, **kwargs)


def _sleep_square(x):
    import time

    time.sleep(0.002 * (x % 5))
    return x * x


@pytest.mark.parametrize("window", [1, 3])
def test_imap_unordered_every_result_once_at_most_window_in_flight(window):
    tasks = list(range(23))
    with _CountingPool(max_workers=4) as ex:
        got = {}
        for i, r in imap_unordered(ex, _sleep_square, tasks, window=window):
            assert ex.submitted - len(got) <= window  # submitted, not yet handed back
            got[i] = r
    assert got == {i: i * i for i in tasks}
    # serially (None or SerialExecutor): in order, one at a time; errors surface
    assert list(imap_unordered(None, _square, [3, 1, 2])) == [(0, 9), (1, 1), (2, 4)]
    with pytest.raises(KeyError):
        list(imap_unordered(SerialExecutor(), _boom, [1]))
    with pytest.raises(DistributedError, match="window to be an integer >= 1"):
        list(imap_unordered(None, _square, [1], window=0))


# ---------------------------------------------------------------- GP blocks on executors


def _plane_points(n=1500, seed=0):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 1.2, size=(n, 2))
    z = 0.05 * np.sin(3 * xy[:, 0])
    pts = np.column_stack([xy, z])
    nrm = np.column_stack([-0.15 * np.cos(3 * xy[:, 0]), np.zeros(n), np.ones(n)])
    return pts, nrm / np.linalg.norm(nrm, axis=1, keepdims=True)


def test_fit_local_gps_executor_matches_serial():
    pts, nrm = _plane_points()
    cfg = GPConfig(block_size=0.3, max_block_points=120)
    prior = ConstantPrior(0.1, 0.01)
    ref = fit_local_gps(pts, nrm, prior, cfg)
    calls = []
    ser = fit_local_gps(pts, nrm, prior, cfg, executor=SerialExecutor(),
                        progress=lambda d, t: calls.append((d, t)))
    with ThreadPoolExecutor(2) as ex:
        par = fit_local_gps(pts, nrm, prior, cfg, executor=ex)
    assert calls[-1] == (ref.info["n_blocks"], ref.info["n_blocks"])
    assert ref.info == ser.info == par.info
    q = np.random.default_rng(3).uniform([0, 0, -0.2], [1.2, 1.2, 0.2], size=(500, 3))
    m0, v0, g0 = ref.predict(q, return_grad=True)
    m1, v1, g1 = ser.predict(q, return_grad=True)
    m2, v2, g2 = par.predict(q, return_grad=True)
    # same process, same arithmetic: bitwise
    assert np.array_equal(m0, m1) and np.array_equal(v0, v1) and np.array_equal(g0, g1)
    # other threads may use another BLAS thread split: round-off only
    assert np.abs(m2 - m0).max() < 1e-9 and np.abs(v2 - v0).max() < 1e-9
    assert np.abs(g2 - g0).max() < 1e-8


# ---------------------------------------------------------------- tiles


def test_tilespec_errors():
    with pytest.raises(TilingError, match="positive tile size"):
        TileSpec(size=0)
    with pytest.raises(TilingError, match="overlap <= size / 2"):
        TileSpec(size=10, overlap=6)
    with pytest.raises(TilingError, match="blend 'smooth' or 'core'"):
        TileSpec(blend="linear")
    with pytest.raises(TilingError, match="min_points >= 10"):
        TileSpec(min_points=3)


def test_assign_brute_force():
    spec = TileSpec(size=5.0, overlap=1.0)
    xyz = np.random.default_rng(0).uniform(-12, 12, size=(3000, 3))
    got = spec.assign(xyz)
    for key, idx in got.items():
        lo = np.array(key) * 5.0 - 1.0
        inside = np.all((xyz[:, :2] >= lo) & (xyz[:, :2] < lo + 7.0), axis=1)
        assert np.array_equal(idx, np.flatnonzero(inside))
    assert sum(map(len, got.values())) >= len(xyz)


@pytest.mark.parametrize("blend", ["smooth", "core"])
def test_weights_partition_of_unity_and_gradient(blend):
    spec = TileSpec(size=4.0, overlap=1.5, blend=blend)
    xy = np.random.default_rng(2).uniform(-9, 9, size=(2000, 2))
    total = np.zeros(len(xy))
    for i in range(-4, 4):
        for j in range(-4, 4):
            w, g = spec.weights(xy, (i, j))
            total += w
            if blend == "smooth":
                e = 1e-6
                for c in range(2):
                    d = np.zeros(2)
                    d[c] = e
                    fd = (spec.weights(xy + d, (i, j))[0] - spec.weights(xy - d, (i, j))[0])
                    assert np.allclose(fd / (2 * e), g[:, c], atol=1e-6)
    assert np.allclose(total, 1.0, atol=1e-12)


@pytest.fixture(scope="module")
def street():
    from gmmgp_app.synth import scan_scene

    scan, scene = scan_scene("street", density=0.01, scene_params=dict(length=20.0), seed=0)
    keep = (scan.points[:, 0] > 0) & (scan.points[:, 0] < 16)
    scan = scan.select(keep)
    # shift to x in (16, 32), y in (9, 31): one 100 m tile holds it all, 8 m tiles
    # meet at x = 24
    shift = np.array([16.0, 20.0, 0.0])
    scan = gm.Scan(points=scan.points + shift, origins=scan.origins + shift)
    return scan, lambda q: scene.sdf(np.asarray(q) - shift)


@pytest.fixture(scope="module")
def tiled(street):
    scan, _ = street
    return build_tiled_map(scan, gm.MappingConfig(), TileSpec(size=8.0, overlap=2.0))


def test_single_tile_equals_build_map(street):
    scan, _ = street
    cfg = gm.MappingConfig()
    tm = build_tiled_map(scan, cfg, TileSpec(size=100.0, overlap=1.0))
    order = np.lexsort((scan.points[:, 2], scan.points[:, 1], scan.points[:, 0]))
    ref = gm.build_map(scan.select(order), cfg)
    q = scan.points[::7] + 0.03
    a, b = tm.predict(q, return_grad=True), ref.predict(q, return_grad=True)
    for x, y in zip(a, b):
        assert np.abs(x - y).max() == 0, np.abs(x - y).max()
    # the stitched surface is followed as far from the seeds as the map's (the reach of
    # the extent cell, not of the voxel) and meshed at its voxel: the same faces
    assert tm.config == ref.config
    assert tm.surface_reach(tm.stitched_seeds()) == ref.surface_reach()
    mt, mr = tm.extract_surface(), ref.extract_surface()
    assert len(mt.faces) == len(mr.faces) > 100
    np.testing.assert_allclose(np.sort(mt.vertices, axis=0), np.sort(mr.vertices, axis=0),
                               rtol=0, atol=1e-9)


def test_tiles_share_one_set_of_auto_values_measured_tile_by_tile(street, tiled):
    """What README's tiling section says: a tiled map resolves the "auto" fields once,
    from the points each tile owns, pooled (tiling/auto.py): every tile has the same
    lengths, the stitched mesh the same voxel, and the spacing and noise are the whole
    scan's (another sample of it: within 3 % of measure_scan on the whole scan)."""
    from gmmgp_app.stages.autoscale import measure_scan

    scan, _ = street
    auto = tiled.summary["auto"]
    assert isinstance(tiled.config.surface.voxel_size, float)
    for key, tile in tiled.tiles.items():
        assert tile.config == tiled.config, key
        assert tile.summary["auto"]["surface.voxel_size"]["value"] == \
            tiled.config.surface.voxel_size
    assert tiled.surface_voxel() == tiled.config.surface.voxel_size
    whole = measure_scan(scan.points, scan.origins)
    assert auto["scan"]["n_points"] == len(scan)
    assert auto["scan"]["spacing"] == pytest.approx(whole.spacing, rel=0.03)
    assert auto["scan"]["noise"] == pytest.approx(whole.noise, rel=0.03)
    # every tile here holds fewer points than the training budget: all points, h_t = h
    assert tiled.config.surface.voxel_size == pytest.approx(auto["scan"]["spacing"])
    assert "tiles" in auto and "4 tiles" in auto["tiles"]["reason"] or \
        f"{len(tiled.tiles)} tiles" in auto["tiles"]["reason"]


def test_pooled_tile_samples_are_measure_scan_for_one_tile_and_the_scan_for_many():
    """sample_scale + pool_scale: one part owning every point is measure_scan bit for
    bit; a plane of known spacing cut into four owned quarters (each quarter's tree
    holding a margin of its neighbours' points) gives the whole plane's spacing and
    noise (within 3 % of the whole plane's: the quarters' samples are another sample)."""
    from gmmgp_app.stages.autoscale import measure_scan, pool_scale, sample_scale

    rng = np.random.default_rng(3)
    g = np.arange(0.0, 12.0, 0.03)          # 160k points, spacing 0.03 m, noise 3 mm
    xy = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    pts = np.column_stack([xy, 0.003 * rng.standard_normal(len(xy))])
    org = pts + np.array([0.0, 0.0, 5.0])
    whole = measure_scan(pts, org)
    one = pool_scale([sample_scale(pts, org)])
    assert one == whole
    parts = []
    for qx in (0, 1):
        for qy in (0, 1):
            lo, hi = np.array([qx, qy]) * 6.0, np.array([qx, qy]) * 6.0 + 6.0
            near = np.all((xy >= lo - 0.5) & (xy < hi + 0.5), axis=1)
            own = np.all((xy[near] >= lo) & (xy[near] < hi), axis=1)
            parts.append(sample_scale(pts[near], org[near], owned=own, n_total=len(pts)))
    pooled = pool_scale(parts)
    assert pooled.n_points == len(pts)
    assert sum(len(p.points) for p in parts) == pytest.approx(20_000, abs=4)
    assert pooled.spacing == pytest.approx(0.03, rel=0.03)
    assert pooled.noise == pytest.approx(whole.noise, rel=0.03)   # (0.0028: the estimator's)
    assert pooled.sensor_distance == pytest.approx(5.0)
    assert pooled.extent == pytest.approx(whole.extent, rel=0.01)


def test_smooth_blend_has_no_seam(street, tiled):
    """Across the tile border x = 24 m the stitched mean is continuous."""
    scan, sdf = street
    near = scan.points[np.abs(scan.points[:, 0] - 24.0) < 0.5][::5]
    left, right = near.copy(), near.copy()
    left[:, 0], right[:, 0] = 24.0 - 1e-7, 24.0 + 1e-7
    jump = np.abs(tiled.predict(left)[0] - tiled.predict(right)[0])
    assert jump.max() < 1e-5
    core = TiledMap(TileSpec(size=8.0, overlap=2.0, blend="core"), tiled.tiles,
                    tiled.config, tiled.method)
    jump_core = np.abs(core.predict(left)[0] - core.predict(right)[0])
    assert jump_core.max() > 10 * jump.max()
    # the stitched field is as accurate as its tiles near the surface
    err = np.abs(tiled.predict(near)[0] - sdf(near))
    assert np.median(err) < 0.05


def test_tiled_predict_mean_is_predicts_mean_and_the_mesh_is_unchanged(street, tiled):
    """TiledMap.predict_mean (each tile's mean alone, stitched by the same weights,
    which depend on the position only) returns predict's mean bit for bit: inside
    tiles, across borders in the blend band, and beyond every tile (the nearest
    tile answers); with smooth and core blending, and for the tiled prior (the hgmm
    baseline of compare). The stitched surface, whose lattice now takes the mean
    alone, is the mesh of the full predict, array for array."""
    from gmmgp_app.compare import _tiled_priors
    from gmmgp_app.pipeline import mesh_field

    scan, _ = street
    rng = np.random.default_rng(3)
    q = np.concatenate([scan.points[::11] + rng.normal(0, 0.05, (len(scan.points[::11]), 3)),
                        np.c_[np.full(50, 24.0) + rng.uniform(-1.5, 1.5, 50),
                              rng.uniform(10, 30, 50), rng.uniform(-0.5, 3, 50)],
                        np.c_[rng.uniform(-20, 80, 50), rng.uniform(-20, 80, 50),
                              rng.uniform(-1, 5, 50)]])
    core = TiledMap(TileSpec(size=8.0, overlap=2.0, blend="core"), tiled.tiles,
                    tiled.config, tiled.method)
    for tm in (tiled, core, _tiled_priors(tiled)):
        assert np.array_equal(tm.predict_mean(q), tm.predict(q)[0])
    # tiles on surface.lattice_field "map": the lattice is predict's mean, the stitched
    # surface the mesh of the full predict, array for array (as before "far")
    tmap = _with_lattice_field(tiled, "map")
    for tm in (tmap, _tiled_priors(tiled)):  # (the prior has no far field: its mean)
        assert np.array_equal(tm.lattice_mean(q), tm.predict(q)[0])
    seeds = tmap.stitched_seeds()
    full = mesh_field(tmap.predict, seeds, tmap.config.surface, 0.1, None, None,
                      tmap.surface_reach(seeds))
    mesh = tmap.extract_surface(voxel_size=0.1)
    assert len(mesh.faces) > 1000
    for a, b in ((mesh.vertices, full.vertices), (mesh.faces, full.faces),
                 (mesh.vertex_variance, full.vertex_variance)):
        assert np.array_equal(a, b)


def _with_lattice_field(tm, field, **surface):
    """``tm`` with every tile's ``surface.lattice_field`` set to ``field`` and the other
    ``surface`` settings given, in the tiles' and the tiled map's configs (copies of the
    tiles; the fixture's are left as they are)."""
    import copy

    updates = {"surface.lattice_field": field,
               **{f"surface.{k}": v for k, v in surface.items()}}
    tiles = {}
    for k, t in tm.tiles.items():
        tiles[k] = copy.copy(t)
        tiles[k].config = t.config.replace(updates)
    return TiledMap(tm.spec, tiles, tm.config.replace(updates), tm.method, owners=tm.owners)


def test_tiled_lattice_is_the_tiles_far_fields_stitched(street, tiled):
    """With the tiles' surface.lattice_field "far" (the default) the stitched lattice
    field is each tile's far-field mean, stitched by predict's weights (checked against
    the weights of TileSpec.weights by hand, the nearest tile beyond every tile); the
    mesh's vertices carry predict's mean and variance, and lie as near the tiled map's
    zero level as the untiled map's vertices lie near its own (|m(v)| / voxel, the
    seventh pass's statistic, docs/speed.md)."""
    from gmmgp_app.tiling.geometry import members

    scan, _ = street
    assert all(t.config.surface.lattice_field == "far" for _, t in tiled.tiles.items())
    q = _blend_queries(scan, np.random.default_rng(5))
    # by hand: sum_t w_t far_t(q) / sum_t w_t over the squares' weights
    W, Wm = np.zeros(len(q)), np.zeros(len(q))
    for k in tiled.keys:
        w = sum(tiled.spec.weights(q[:, :2], s)[0] for s in members(tiled.owners, k))
        on = w > 0
        W[on] += w[on]
        Wm[on] += w[on] * tiled.tiles[k].far.components(q[on])["mean"]
    ok = W > 0
    assert ok.sum() > 500 and (~ok).sum() > 10
    lat = tiled.lattice_mean(q)
    np.testing.assert_allclose(lat[ok], Wm[ok] / W[ok], rtol=1e-12, atol=1e-12)
    for key, r in tiled._nearest_tiles(q, ~ok):
        assert np.array_equal(lat[r], tiled.tiles[key].far.components(q[r])["mean"])
    # the far field is not the map's mean: the lattice differs from predict_mean
    assert np.abs(lat - tiled.predict_mean(q)).max() > 1e-6

    vox = 0.1
    mesh = tiled.extract_surface(voxel_size=vox)
    assert len(mesh.faces) > 1000
    m, var = tiled.predict(mesh.vertices)
    np.testing.assert_allclose(mesh.vertex_variance, var, rtol=1e-12, atol=0)
    # The zero-level statistics on the meshes with their cells whole (trim_to_reach off,
    # the meshes these figures were measured on): the trim drops faces far from the data,
    # where the far field is the map's mean, and so changes the p99's mix of vertices,
    # not how near the lattice puts them to the zero level (with the trim: tiled 0.47,
    # untiled 0.23 voxels at p99).
    whole = _with_lattice_field(tiled, "far", trim_to_reach=False)
    mesh_whole = whole.extract_surface(voxel_size=vox)
    r = np.abs(tiled.predict_mean(mesh_whole.vertices)) / vox
    r_map = np.abs(tiled.predict_mean(_with_lattice_field(tiled, "map", trim_to_reach=False)
                                      .extract_surface(voxel_size=vox).vertices)) / vox
    single = gm.build_map(scan, gm.MappingConfig().replace({"surface.trim_to_reach": False}))
    r_one = np.abs(single.predict_mean(single.extract_surface(voxel_size=vox).vertices)) / vox
    # measured (median / p99 voxels): tiled "far" 1.7e-3 / 0.43, tiled "map" 5.6e-4 /
    # 0.42, untiled "far" 5.1e-4 / 0.25. The tail is the tiled map's own (its "map"
    # lattice has it too: the sparse tiles resolve a 5x coarser automatic h_t than the
    # untiled map); the median grows where those tiles' far field departs from their
    # map's mean (3-4e-3 voxels there, 2e-5 - 3e-4 in the dense tiles, 1e-4 untiled).
    assert np.quantile(r, 0.99) < 1.1 * np.quantile(r_map, 0.99)
    assert np.quantile(r, 0.99) < 2 * np.quantile(r_one, 0.99)
    assert np.median(r) < 5e-3 and np.median(r) < 5 * np.median(r_one)
    # surface.project_steps (the tiled config's): Newton steps onto the stitched zero level
    proj = TiledMap(tiled.spec, tiled.tiles,
                    tiled.config.replace({"surface.project_steps": 1}), tiled.method,
                    owners=tiled.owners)
    pm = proj.extract_surface(voxel_size=vox, trim_to_reach=False)
    assert len(pm.faces) == len(mesh_whole.faces)
    rp = np.abs(tiled.predict(pm.vertices)[0]) / vox
    assert np.median(rp) < 0.1 * np.median(r) and np.quantile(rp, 0.9) < np.quantile(r, 0.9)


def _blend_queries(scan, rng):
    """Queries inside tiles, across the tile border x = 24 m in the blend band, and
    beyond every tile (the nearest tile answers)."""
    near = scan.points[::9]
    return np.concatenate([near + rng.normal(0, 0.1, near.shape),
                           np.c_[np.full(300, 24.0) + rng.uniform(-1.0, 1.0, 300),
                                 rng.uniform(10, 30, 300), rng.uniform(-0.5, 3, 300)],
                           np.c_[rng.uniform(-20, 80, 50), rng.uniform(-20, 80, 50),
                                 rng.uniform(-1, 5, 50)]])


def test_tiled_distribution_is_the_owning_tiles_and_predicts_stitched_moments(street, tiled):
    """TiledMap.distribution: where one tile weighs a query it is that tile's
    SurfaceMap.distribution exactly (log density, std, half-widths); everywhere its
    mean and std are TiledMap.predict's bit for bit, for the gmmgp tiles and for the
    stitched GMR priors (compare's hgmm baseline, Gaussian tiles)."""
    from gmmgp_app.compare import _tiled_priors

    scan, sdf = street
    q = _blend_queries(scan, np.random.default_rng(5))
    y = sdf(q)
    for tm in (tiled, _tiled_priors(tiled)):
        dist = tm.distribution(q)
        mean, var = tm.predict(q)
        assert np.array_equal(dist.mean, mean) and np.array_equal(dist.var, var)
        assert np.array_equal(dist.std, np.sqrt(var))
        parts = tm._tile_weights(q)
        count = np.zeros(len(q), int)
        for _, rows, _, _ in parts:
            count[rows] += 1
        assert (count >= 2).sum() > 100 and (count == 1).sum() > 100
        owned = owned_w1 = 0
        for owner, rows, w, _ in parts:
            one = rows[count[rows] == 1]
            full = w[count[rows] == 1] == 1.0
            own, _ = tm._tile_distribution(owner, q[one])
            np.testing.assert_array_equal(dist.logpdf(y)[one], own.logpdf(y[one]))
            # weight 1: predict's std is the tile's; a lone tile of weight w < 1 (its
            # neighbour square unmapped) gives w v / w, within rounding of it
            np.testing.assert_array_equal(dist.std[one][full], own.std[full])
            np.testing.assert_allclose(dist.std[one], own.std, rtol=1e-12)
            np.testing.assert_array_equal(dist.mean[one][full], own.mean[full])
            owned_w1 += int(full.sum())
            for level in (0.5, 0.6827, 0.95):
                np.testing.assert_array_equal(dist.half_width(level)[one],
                                              own.half_width(level))
            owned += len(one)
        # beyond every tile: the nearest tile's distribution
        miss = count == 0
        assert miss.sum() > 20
        for key, r in tm._nearest_tiles(q, miss):
            own, _ = tm._tile_distribution(key, q[r])
            np.testing.assert_array_equal(dist.logpdf(y)[r], own.logpdf(y[r]))
            np.testing.assert_array_equal(dist.half_width(0.9)[r], own.half_width(0.9))
        assert owned == (count == 1).sum() and owned_w1 > 100


@pytest.mark.parametrize("far", [dict(unseen_predictive="gaussian"), dict(calibrated=False),
                                 dict(unseen_weight=0.0)])
def test_distribution_variance_is_predicts_in_every_far_field_setting(street, tiled, far):
    """Where a map's predictive is Gaussian its ``var`` is predict's variance bit for
    bit (not sqrt(v)^2), for a single map and stitched: so a tiled map's stitched std
    is its predict's in every far-field setting, not only with the default mixture."""
    import copy
    import dataclasses

    scan, _ = street
    tiles = {}
    for k, t in tiled.tiles.items():
        tiles[k] = copy.copy(t)
        tiles[k].config = dataclasses.replace(t.config, far=dataclasses.replace(
            t.config.far, **far))
    tm = TiledMap(tiled.spec, tiles, tiles[tiled.keys[0]].config, tiled.method,
                  owners=tiled.owners)
    q = _blend_queries(scan, np.random.default_rng(7))
    one = tiles[tiled.keys[0]]
    assert np.array_equal(one.distribution(q).var, one.predict(q)[1])
    dist, (mean, var) = tm.distribution(q), tm.predict(q)
    assert np.array_equal(dist.mean, mean) and np.array_equal(dist.var, var)
    assert np.array_equal(dist.std, np.sqrt(var))


def test_tiled_distribution_in_the_blend_is_the_weighted_mixture(street, tiled):
    """In the blend band the log density is that of sum_t w_t p_t / W (the tiles'
    densities from their own distributions), and half_width(level) holds exactly
    ``level`` of it about the stitched mean (against a 200-step bisection)."""
    from scipy.special import ndtr, stdtr

    scan, sdf = street
    q = _blend_queries(scan, np.random.default_rng(6))
    y = sdf(q)
    dist = tiled.distribution(q)
    parts = tiled._tile_weights(q)
    K = len(q)
    dens, W, lo_c, hi_c = np.zeros(K), np.zeros(K), {}, {}
    tiles = []
    for owner, rows, w, _ in parts:
        d, _ = tiled._tile_distribution(owner, q[rows])
        dens[rows] += w * np.exp(d.logpdf(y[rows]))
        W[rows] += w
        tiles.append((rows, w, d))
    blend = np.flatnonzero(np.isin(np.arange(K), dist._multi))
    assert len(blend) > 100
    np.testing.assert_allclose(dist.logpdf(y)[blend], np.log(dens[blend] / W[blend]),
                               rtol=1e-12, atol=1e-12)
    # the tiles' means differ there: a mixture, not one tile's distribution
    assert np.max(np.abs(dist.std[blend] - dist.half_width(0.6826894921370859)[blend])) > 0

    def mass(t):
        out = np.zeros(K)
        for rows, w, d in tiles:
            c = dist.mean[rows]
            # the tiles' components: Student-t of d.dof with the Gaussians' 68.27 %
            # half-widths (eq. unseen_mixture_t), Gaussian at dof 0
            cdf = ndtr if d.dof == 0 else (lambda x, nu=d.dof: stdtr(nu, x))
            for p, v in ((1 - d.q, d.var_observed), (d.q, d.var_unseen)):
                s = np.sqrt(v) / d.scale
                out[rows] += w * p * (cdf((c + t[rows] - d.mean) / s)
                                      - cdf((c - t[rows] - d.mean) / s))
        return out / np.where(W > 0, W, 1.0)

    for level in (0.3, 0.6827, 0.9545, 0.999):
        hw = dist.half_width(level)
        np.testing.assert_allclose(mass(hw)[blend], level, atol=1e-12)
        lo, hi = np.zeros(K), np.full(K, 50.0)
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            below = mass(mid) < level
            lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
        np.testing.assert_allclose(hw[blend], lo[blend], rtol=1e-10)


def test_tiled_gradient_matches_finite_differences(street):
    """The blend's gradient (tiles' gradients plus the weights' gradient) is exact.

    The tiles here are HGMM/GMR maps, whose gradient is exact: a gmmgp tile's GP
    blend treats its inverse-variance block weights as constant in the gradient
    (documented in LocalGPField.predict), which differs from finite differences by
    up to ~2e-3 where blocks disagree and would hide what this test checks.
    """
    scan, _ = street
    tiled = build_tiled_map(scan, gm.MappingConfig(), TileSpec(size=8.0, overlap=2.0),
                            method="hgmm")
    q = scan.points[np.abs(scan.points[:, 0] - 24.0) < 1.0][::11] + 0.02
    _, _, g = tiled.predict(q, return_grad=True)
    e = 1e-6
    for c in range(3):
        d = np.zeros(3)
        d[c] = e
        fd = (tiled.predict(q + d)[0] - tiled.predict(q - d)[0]) / (2 * e)
        assert np.allclose(fd, g[:, c], atol=1e-4)


def test_tiled_map_errors(street):
    scan, _ = street
    with pytest.raises(TilingError, match="at least one tile with"):
        build_tiled_map(scan.select(np.arange(50)), gm.MappingConfig(),
                        TileSpec(size=8.0, overlap=2.0, min_points=100))


# ---------------------------------------------------------------- incremental update


@pytest.mark.parametrize("cut", [24.0, 23.0])
def test_update_with_hgmm_refit_matches_whole_build(street, tiled, cut):
    """Half the street, then the other half (refit_hgmm=True) == the whole street
    mapped with the values the first half resolved (an update keeps the map's lengths,
    as ``update_map`` does; the tiles rebuilt get them too, tiling/update.py).

    With the cut at 23 m the first map's tiles at x >= 24 m hold only a 1 m strip
    (< min_points): they start as small tiles owned by a neighbour and become tiles
    of their own in the update, and their former owners are rebuilt without them.
    """
    scan, _ = street
    first = scan.points[:, 0] < cut
    tm = build_tiled_map(scan.select(first), gm.MappingConfig(), tiled.spec)
    small_before = {k for k in tm.owners if k[0] == 3}
    cfg_first = tm.config
    rep = tm.update(scan.select(~first), refit_hgmm=True)
    assert tm.config == cfg_first
    assert all(t.config == cfg_first for _, t in tm.tiles.items())
    tiled = build_tiled_map(scan, cfg_first, tiled.spec)
    assert rep["rebuilt_tiles"]
    assert tm.keys == tiled.keys
    assert tm.owners == tiled.owners
    if cut == 23.0:
        assert small_before and small_before <= set(rep["rebuilt_tiles"])
    q = scan.points[::9] + 0.02
    a, b = tm.predict(q), tiled.predict(q)
    # a tile's map depends only on its set of points: equal to round-off
    assert np.abs(a[0] - b[0]).max() < 1e-9 and np.abs(a[1] - b[1]).max() < 1e-9


def test_gp_only_update_changes_only_touched_blocks(street):
    """Without HGMM refit: far from the new points the field is bitwise unchanged."""
    scan, sdf = street
    spec = TileSpec(size=100.0, overlap=1.0)  # one tile: the GP-only path
    cfg = gm.MappingConfig()
    old = scan.points[:, 0] < 27.0
    tm = build_tiled_map(scan, cfg, spec)
    base = build_tiled_map(scan.select(old), cfg, spec)
    before_q = scan.points[scan.points[:, 0] < 25.0][::5] + 0.01
    before = base.predict(before_q)
    rep = base.update(scan.select(~old), new_space_fraction=None)
    assert rep["gp_updated_tiles"] == [(0, 0)] and rep["refit_blocks"] > 0
    after = base.predict(before_q)
    assert np.array_equal(before[0], after[0]) and np.array_equal(before[1], after[1])
    # near the new points the updated GP pulls the field onto the surface: median error
    # within 1 cm of a map built from the whole scan (which also refits the HGMM)
    new_q = scan.points[scan.points[:, 0] > 28.0][::5]
    e_upd = np.median(np.abs(base.predict(new_q)[0] - sdf(new_q)))
    e_all = np.median(np.abs(tm.predict(new_q)[0] - sdf(new_q)))
    assert e_upd < e_all + 0.01


@pytest.mark.slow
def test_dask_local_cluster_matches_serial(street):
    scan, _ = street
    cfg = gm.MappingConfig()
    spec = TileSpec(size=8.0, overlap=2.0)
    ref = build_tiled_map(scan, cfg, spec)
    with open_executor(workers=2) as ex:
        par = build_tiled_map(scan, cfg, spec, executor=ex)
        pts, nrm = _plane_points()
        gcfg = GPConfig(block_size=0.3, max_block_points=120)
        g0 = fit_local_gps(pts, nrm, ConstantPrior(0.1, 0.01), gcfg)
        g1 = fit_local_gps(pts, nrm, ConstantPrior(0.1, 0.01), gcfg, executor=ex)
    q = np.random.default_rng(5).uniform(scan.points.min(0), scan.points.max(0), (3000, 3))
    a, b = ref.predict(q), par.predict(q)
    assert np.abs(a[0] - b[0]).max() < 1e-6 and np.abs(a[1] - b[1]).max() < 1e-6
    assert np.abs(g0.predict(pts)[0] - g1.predict(pts)[0]).max() < 1e-6


@pytest.mark.slow
def test_fit_local_gps_process_pool_matches_serial():
    pts, nrm = _plane_points()
    cfg = GPConfig(block_size=0.3, max_block_points=120)
    prior = ConstantPrior(0.1, 0.01)
    ref = fit_local_gps(pts, nrm, prior, cfg)  # parallel numba kernels run in this process
    with open_executor(workers=2, kind="processes") as ex:  # so the pool must not fork
        par = fit_local_gps(pts, nrm, prior, cfg, executor=ex)
    q = np.random.default_rng(3).uniform([0, 0, -0.2], [1.2, 1.2, 0.2], size=(500, 3))
    assert np.abs(ref.predict(q)[0] - par.predict(q)[0]).max() < 1e-9


# ---------------------------------------------------------------- streaming LAS/LAZ


def write_laz(path, scan, offset=(500000.0, 5400000.0, 100.0)):
    """A LAZ file of a scan (georeferenced by ``offset``) with origins as extra dims."""
    from gmmgp_app.datasets import write_las

    return write_las(path, gm.Scan(points=scan.points, origins=scan.origins,
                                   offset=np.asarray(offset, dtype=float)))


def streamed_map(scan, tiled, tmp_path, off):
    """The street written as a georeferenced LAZ and streamed into ``tiled``'s tiles."""
    write_laz(tmp_path / "street.laz", scan, off)
    return build_tiled_map_from_las(tmp_path / "street.laz", tiled.config, tiled.spec,
                                    work_dir=tmp_path / "work", chunk_size=3000,
                                    cache_tiles=1, offset=off)


def test_tile_store_put_saved_writes_the_workers_files(tiled, tmp_path):
    """A streamed build stores each tile from its worker's saved files as they are (no
    load and re-save): the folder holds exactly those bytes, which a load predicts with
    bit for bit; a read-only store keeps the map in memory and writes nothing."""
    from gmmgp_app.map_io import folder_files
    from gmmgp_app.tiling.store import TileStore
    from gmmgp_app.tiling.tasks import map_to_bytes

    key = sorted(tiled.tiles)[0]
    smap = tiled.tiles[key]
    files = map_to_bytes(smap)
    store = TileStore(tmp_path / "maps", [])
    store.put_saved(key, files)
    assert list(store) == [key]
    assert folder_files(store._path(key)) == files and "map.json" in files
    q = np.random.default_rng(2).uniform(smap.gp_points.min(0), smap.gp_points.max(0),
                                         (500, 3))
    for a, b in zip(smap.predict(q), store[key].predict(q)):
        assert np.array_equal(a, b)
    ro = TileStore(tmp_path / "ro", [], read_only=True)
    ro.put_saved(key, files)
    assert list(ro) == [key] and not (tmp_path / "ro").exists()
    assert np.array_equal(ro[key].predict(q)[0], smap.predict(q)[0])


def test_streamed_laz_equals_in_memory_tiles(street, tiled, tmp_path):
    """Chunked LAZ reading into tiles gives the same tile maps as the in-memory split."""
    scan, _ = street
    off = np.array([500000.0, 5400000.0, 100.0])
    tm = streamed_map(scan, tiled, tmp_path, off)
    assert np.array_equal(tm.offset, off)
    # The LAS file stores coordinates on a 0.1 mm integer grid; the hierarchy's EM is
    # sensitive enough that such a shift moves the map by ~2 mm (median), so the
    # in-memory reference is built from the same quantised points.
    quant = gm.Scan(points=np.round(scan.points / 1e-4) * 1e-4, origins=scan.origins)
    ref = build_tiled_map(quant, tiled.config, tiled.spec)
    q = scan.points[::9] + 0.02
    a = tm.predict(q)
    b = ref.predict(q)
    assert tm.keys == ref.keys == tiled.keys
    assert np.median(np.abs(a[0] - b[0])) < 1e-6


def test_update_needs_points(street, tiled):
    scan, _ = street
    bare = TiledMap(tiled.spec, tiled.tiles, tiled.config, tiled.method)
    with pytest.raises(TilingError, match="without keeping its points"):
        bare.update(scan)
    with pytest.raises(TilingError, match="Expected the update's offset"):
        tiled.update(gm.Scan(points=scan.points, offset=[1.0, 0.0, 0.0]))


def test_spill_errors(tmp_path):
    from gmmgp_app.tiling import spill_las_to_tiles

    with pytest.raises(TilingError, match="chunk_size >= 1"):
        spill_las_to_tiles(tmp_path / "x.laz", TileSpec(), tmp_path, chunk_size=0)


def test_update_remaps_tiles_in_new_space(street):
    """New points far from a tile's old ones trigger a remap, not a GP-only refit."""
    scan, _ = street
    spec = TileSpec(size=100.0, overlap=1.0)
    old = scan.points[:, 0] < 24.0
    base = build_tiled_map(scan.select(old), gm.MappingConfig(), spec)
    rep = base.update(scan.select(~old))
    assert rep["rebuilt_tiles"] == [(0, 0)] and not rep["gp_updated_tiles"]
    # densifying already-seen space (every other point of the old half) stays GP-only
    dense = scan.select(np.flatnonzero(old)[::2])
    base2 = build_tiled_map(scan.select(np.flatnonzero(old)[1::2]), gm.MappingConfig(), spec)
    rep2 = base2.update(dense, new_space_voxel=2.0)
    assert rep2["gp_updated_tiles"] == [(0, 0)] and not rep2["rebuilt_tiles"]


def test_tile_owners_prefer_the_nearest_square_then_the_fullest():
    counts = {(0, 0): 500, (1, 0): 900, (1, 1): 5000, (2, 0): 10, (0, 1): 3, (5, 5): 1}
    owners = tile_owners(counts, 200)
    # (2, 0): (1, 0) across an edge beats the fuller (1, 1) across a corner
    assert owners[(2, 0)] == (1, 0)
    # (0, 1): (0, 0) and (1, 1) share an edge with it, (1, 1) has more points
    assert owners[(0, 1)] == (1, 1)
    assert owners[(5, 5)] == (1, 1)
    assert set(owners) == {(2, 0), (0, 1), (5, 5)}
    # two big tiles equally near: the one with more points
    assert tile_owners({(0, 0): 300, (2, 0): 400, (1, 0): 5}, 200) == {(1, 0): (2, 0)}
    assert tile_owners({(0, 0): 5}, 200) == {}


def test_points_of_small_tiles_are_mapped_by_their_owner():
    """A tile below min_points is not dropped: its points train its owner, which
    answers for its square, so the field there follows the data. Here the ground
    bends up (slope 0.5) in a 1 m strip beyond the last full tiles; before small
    tiles had owners, the points beyond the owner's margin (x > 8.5) were dropped:
    median |m| 0.25 m on them and no surface there."""
    rng = np.random.default_rng(4)
    n = 8000
    xy = np.c_[rng.uniform(0, 9.0, n), rng.uniform(0, 8.0, n)]
    height = 0.5 * np.maximum(xy[:, 0] - 8.0, 0.0)
    pts = np.c_[xy, height + rng.normal(0, 0.002, n)]
    org = np.c_[pts[:, :2], np.full(n, 2.0)]  # looked at from above
    scan = gm.Scan(points=pts, origins=org)
    spec = TileSpec(size=4.0, overlap=0.5, min_points=800)
    tm = build_tiled_map(scan, gm.MappingConfig(), spec)
    # the strip's squares, and the margin-only squares around the plane, are small
    assert tm.owners[(2, 0)] == (1, 0) and tm.owners[(2, 1)] == (1, 1), tm.owners
    assert tm.keys == [(0, 0), (0, 1), (1, 0), (1, 1)]
    assert tm.summary["absorbed_tiles"]["(2, 0)"] == "(1, 0)"
    parts = spec.assign(pts)
    for owner in tm.keys:
        union = np.unique(np.concatenate(
            [parts[owner]] + [parts[k] for k, o in tm.owners.items() if o == owner]))
        assert tm.tiles[owner].summary["n_scan_points"] == len(union)
    strip = pts[:, 0] > 8.6  # beyond every big tile's margin, 0.3-0.5 m up
    m = tm.predict(pts[strip])[0]
    assert np.median(np.abs(m)) < 0.02, np.median(np.abs(m))  # measured 7 mm
    # squares answered by their owner: the lattice's mean (predict_mean) is predict's
    assert np.array_equal(tm.predict_mean(pts[strip]), m)
    v = tm.extract_surface(voxel_size=0.05).vertices
    end = v[v[:, 0] > 8.6]
    assert len(end) > 50
    assert np.median(np.abs(end[:, 2] - 0.5 * (end[:, 0] - 8.0))) < 0.02


@pytest.mark.slow
def test_tiled_mesh_has_no_cracks_along_tile_borders():
    """One field, one lattice: the mesh of a tiled map has no extra boundary along the
    tile borders compared with the untiled map's mesh of the same scan.

    Compared where the untiled map has training data (the box of its prepared hit
    points, 1 m in): beyond it the sparse scan lines near the plane's edge give
    normals to neither map, and only the tiled map (its HGMM fitted per tile, and
    small edge tiles joined to their owner) still meshes them, in patches.
    """
    import gmmgp_app as gm
    from gmmgp_app.stages.prepare import prepare
    from gmmgp_app.synth import scan_scene
    from gmmgp_app.tiling import TileSpec, build_tiled_map

    scan, _ = scan_scene("plane", density=0.05, seed=0)
    span = np.ptp(scan.points[:, 0])
    tiled = build_tiled_map(scan, gm.MappingConfig(), TileSpec(size=span / 2.2, overlap=1.0))
    assert tiled.owners  # thin strips at the edges are small tiles here
    mesh = tiled.extract_surface(voxel_size=0.1)
    plain = gm.build_map(scan, gm.MappingConfig()).extract_surface(voxel_size=0.1)
    hits = prepare(scan, gm.MappingConfig()).points
    lo, hi = hits[:, :2].min(0) + 1.0, hits[:, :2].max(0) - 1.0

    def boundary_midpoints(m):
        e = np.sort(np.concatenate([m.faces[:, [0, 1]], m.faces[:, [1, 2]],
                                    m.faces[:, [2, 0]]]), axis=1)
        u, c = np.unique(e, axis=0, return_counts=True)
        mid = m.vertices[u[c == 1]].mean(axis=1)
        return mid[np.all((mid[:, :2] > lo) & (mid[:, :2] < hi), axis=1)]

    mid_t, mid_p = boundary_midpoints(mesh), boundary_midpoints(plain)
    assert len(mid_p) > 100
    assert len(mid_t) < 1.1 * len(mid_p)
    borders = np.unique(np.concatenate([[k[0] * tiled.spec.size for k in tiled.keys],
                                        [(k[0] + 1) * tiled.spec.size for k in tiled.keys]]))
    inner = borders[(borders > scan.points[:, 0].min() + 1) &
                    (borders < scan.points[:, 0].max() - 1)]
    assert len(inner) >= 1
    for b in inner:  # boundary edges in a 0.6 m strip around the border: no crack line
        near_t = np.sum(np.abs(mid_t[:, 0] - b) < 0.3)
        near_p = np.sum(np.abs(mid_p[:, 0] - b) < 0.3)
        assert near_t <= 1.5 * near_p + 20


# ---------------------------------------------------------------- save / load


def _assert_same_prediction(a, b, q):
    for x, y in zip(a.predict(q, return_grad=True), b.predict(q, return_grad=True)):
        assert np.array_equal(x, y), np.abs(x - y).max()


def test_saved_tiled_map_predicts_bit_for_bit(street, tiled, tmp_path):
    from gmmgp_app.tiling import load_tiled_map
    from gmmgp_app.tiling.store import TileStore

    scan, _ = street
    d = tiled.save(tmp_path / "tm")
    assert (d / "tiled.json").is_file()
    assert sorted(p.name for p in (d / "tiles").iterdir()) == sorted(
        f"tile_{i}_{j}" for i, j in tiled.keys)
    assert len(list((d / "points").iterdir())) == len(tiled.tile_points)
    loaded = load_tiled_map(d, cache_tiles=1)
    # tiles stay on disk until a query needs them, one at a time here
    assert isinstance(loaded.tiles, TileStore) and not loaded.tiles._cache
    assert loaded.keys == tiled.keys and loaded.owners == tiled.owners
    assert loaded.spec == tiled.spec and loaded.method == tiled.method
    assert loaded.config == tiled.config and np.array_equal(loaded.offset, tiled.offset)
    assert loaded.summary == tiled.summary
    for k, (p, o) in tiled.tile_points.items():
        assert np.array_equal(loaded.tile_points[k][0], p)
        assert np.array_equal(loaded.tile_points[k][1], o)
    q = np.concatenate([scan.points[::7] + 0.03, [[0.0, 0.0, 0.0], [100.0, 50.0, 1.0]]])
    _assert_same_prediction(loaded, tiled, q)
    assert len(loaded.tiles._cache) == 1
    # overwriting a saved tiled map replaces it whole and leaves no temporary behind
    core = TiledMap(TileSpec(size=8.0, overlap=2.0, blend="core"), tiled.tiles, tiled.config,
                    tiled.method)
    core.save(d)
    again = load_tiled_map(d)
    assert again.spec.blend == "core" and again.tile_points == {}
    assert not (d / "points").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tm"]
    _assert_same_prediction(again, core, q)


def test_saved_streamed_tiled_map_predicts_bit_for_bit(street, tiled, tmp_path):
    from gmmgp_app.tiling import load_tiled_map

    scan, _ = street
    off = np.array([500000.0, 5400000.0, 100.0])
    tm = streamed_map(scan, tiled, tmp_path, off)
    loaded = load_tiled_map(tm.save(tmp_path / "saved"), cache_tiles=2)
    assert not (tmp_path / "saved" / "points").exists()
    assert np.array_equal(loaded.offset, off) and loaded.owners == tm.owners
    _assert_same_prediction(loaded, tm, scan.points[::7] + 0.03)
    with pytest.raises(TilingError, match="without keeping its points"):
        loaded.update(gm.Scan(points=scan.points, offset=off))


def test_update_of_a_loaded_map_equals_updating_the_original(street, tmp_path):
    """Part of the street, saved and loaded, then the rest in two updates: the same as
    updating the map in memory, for rebuilt tiles (new space beyond x = 23 m, small
    tiles becoming tiles of their own) and GP-only refits (denser old space) alike; the
    saved folder is untouched until the updated map is saved again (here over itself)."""
    from gmmgp_app.tiling import load_tiled_map

    scan, _ = street
    left = scan.points[:, 0] < 23.0
    later = left & (np.arange(len(scan)) % 4 == 0)
    first = left & ~later
    original = build_tiled_map(scan.select(first), gm.MappingConfig(),
                               TileSpec(size=8.0, overlap=2.0))
    d = original.save(tmp_path / "tm")
    loaded = load_tiled_map(d, cache_tiles=1)
    q = scan.points[::9] + 0.02
    before = original.predict(q)
    reports = []
    for part in (~left, later):
        rep_a = original.update(scan.select(part))
        rep_b = loaded.update(scan.select(part))
        assert rep_a == rep_b
        reports.append(rep_a)
        _assert_same_prediction(loaded, original, q)
    assert reports[0]["rebuilt_tiles"] and reports[1]["gp_updated_tiles"]
    assert loaded.owners == original.owners and loaded.keys == original.keys
    untouched = load_tiled_map(d)
    assert all(np.array_equal(x, y) for x, y in zip(untouched.predict(q), before))
    loaded.save(d)
    _assert_same_prediction(load_tiled_map(d), original, q)


def test_load_tiled_map_errors(tiled, tmp_path):
    import json
    import shutil

    from gmmgp_app.tiling import load_tiled_map

    good = tiled.save(tmp_path / "good")
    with pytest.raises(TilingError, match=r"is not a saved tiled map \(does not exist\); "
                                          r"save one with TiledMap.save"):
        load_tiled_map(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(TilingError, match=r"is not a saved tiled map \(has no tiled.json\); "
                                          r".*--tile-size 20"):
        load_tiled_map(tmp_path / "empty")
    tiled.tiles[tiled.keys[0]].save(tmp_path / "single")
    with pytest.raises(TilingError, match=r"holds a single map \(map.json\), not a tiled "
                                          r"map .*open it with gmmgp_app.pipeline.load_map"):
        load_tiled_map(tmp_path / "single")

    def broken(name, edit):
        d = tmp_path / name
        shutil.copytree(good, d)
        edit(d)
        return d

    def set_field(key, value):
        def edit(d):
            meta = json.loads((d / "tiled.json").read_text())
            if value is None:
                del meta[key]
            else:
                meta[key] = value
            (d / "tiled.json").write_text(json.dumps(meta))
        return edit

    cases = [
        (set_field("format_version", 99), (r"Tiled map format version 99 in .* is not "
                                           r"supported \(expected 1\); rebuild the map")),
        (set_field("format", "other"), (r"is not a tiled map description \(format 'other', "
                                        r"expected 'gmmgp-tiled-map'\)")),
        (lambda d: (d / "tiled.json").write_text("{not json"),
         r"is not valid JSON .*; save the tiled map again"),
        (set_field("owners", None), r"lacks the field 'owners'; save the tiled map again"),
        (lambda d: shutil.rmtree(d / "tiles" / "tile_2_1"),
         r"is incomplete: tiles/tile_2_1 is missing \(1 of \d+ tiles\)"),
        (lambda d: (d / "points" / "tile_3_2.npz").unlink(),
         r"is incomplete: points/tile_3_2.npz is missing; .*load_points=False"),
    ]
    for i, (edit, match) in enumerate(cases):
        with pytest.raises(TilingError, match=match):
            load_tiled_map(broken(f"bad{i}", edit))
    # without its points a tiled map still opens, for prediction only
    assert load_tiled_map(tmp_path / "bad5", load_points=False).tile_points == {}


# ---------------------------------------------------------------- gmmgp run --tile-size


def test_cli_run_tiled_end_to_end(street, tmp_path, capsys):
    """``gmmgp run --tile-size``: a tiled map in DIR/map that predicts the scan's
    surface, a stitched mesh in the original frame, config and summary."""
    import json

    from gmmgp_app.cli import main
    from gmmgp_app.config import MappingConfig
    from gmmgp_app.tiling import load_tiled_map

    scan, _ = street
    off = np.array([500000.0, 5400000.0, 100.0])
    np.savez(tmp_path / "scan.npz", points=scan.points, origins=scan.origins, offset=off)
    out = tmp_path / "out"
    assert main(["run", str(tmp_path / "scan.npz"), "--out", str(out), "--tile-size", "8",
                 "--tile-overlap", "2", "--min-tile-points", "200", "--set",
                 "surface.voxel_size=0.2"]) == 0
    err = capsys.readouterr().err
    assert "mapped 9 tiles" in err and "wrote" in err
    assert {p.name for p in out.iterdir()} == {"map", "mesh_gmmgp.ply", "config.toml",
                                                "summary.json"}
    summary = json.loads((out / "summary.json").read_text())
    tm = load_tiled_map(out / "map")
    # x in (16, 32), y in (12, 28): 4 x 3 squares of 8 m, 3 small ones joined a neighbour
    assert summary["n_tiles"] == len(tm.keys) == 9 and summary["n_absorbed_tiles"] == 3
    assert summary["n_absorbed_tiles"] == len(tm.owners)
    assert summary["tile_spec"] == {"size": 8.0, "overlap": 2.0, "blend": "smooth",
                                    "min_points": 200}
    assert {"read", "tiles", "save", "surface", "total"} <= set(summary["seconds"])
    assert summary["n_points"] == len(scan)
    assert np.array_equal(tm.offset, off)
    assert MappingConfig.from_toml(out / "config.toml") == tm.config
    assert tm.config.surface.voxel_size == 0.2
    assert np.median(np.abs(tm.predict(scan.points)[0])) < 0.01
    import open3d as o3d

    v = np.asarray(o3d.io.read_triangle_mesh(str(out / "mesh_gmmgp.ply")).vertices)
    assert len(v) == summary["counts"]["surface"]["gmmgp"]["vertices"] > 100
    # vertices are written in the original frame, near the scan's points
    lo, hi = scan.points.min(0) + off - 0.5, scan.points.max(0) + off + 0.5
    assert np.all((v >= lo) & (v <= hi))


@pytest.mark.parametrize("extra,match", [
    (["--tile-size", "8", "--stage", "hgmm"],
     "--tile-size maps every stage of each tile, found --stage hgmm; drop --stage"),
    (["--tile-size", "8", "--rrd", "x.rrd"], "--rrd records the stages of a single map"),
    (["--tile-size", "8", "--spawn"], "--spawn records the stages of a single map"),
    (["--tile-overlap", "1"], ("--tile-overlap only applies to tiled mapping, found it "
                               "without --tile-size")),
    (["--tile-size", "8", "--tile-overlap", "5"], r"Expected 0 <= tile overlap <= size / 2"),
])
def test_cli_run_tiled_bad_combinations(extra, match, tmp_path, capsys):
    import re

    from gmmgp_app.cli import main

    out = tmp_path / "out"
    # the scan need not exist: the options are refused before anything is read
    assert main(["run", str(tmp_path / "scan.npz"), "--out", str(out), *extra]) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in lines[0]
    assert lines[0].startswith("gmmgp run: error: ") and re.search(match, lines[0]), lines[0]
    assert not out.exists()


def test_cli_run_help_shows_the_tiled_example(capsys):
    from gmmgp_app.cli import main

    with pytest.raises(SystemExit):
        main(["run", "--help"])
    text = capsys.readouterr().out
    assert "--tile-size 20" in text and "--min-tile-points" in text


def test_tiled_build_refuses_a_too_large_surface_grid_before_mapping_a_tile(street,
                                                                          monkeypatch):
    """``check_grid`` (``gmmgp run --tile-size`` with a mesh): the stitched surface's grid
    at the tiles' shared voxel is checked before any tile is mapped, so an impossible
    grid ends the run at once, not after every tile was fitted (the region-by-region
    mesh makes the same check at the end)."""
    import gmmgp_app.stages.surface as surface
    import gmmgp_app.tiling.tiled_map as tiled_map
    from gmmgp_app.pipeline import surface_seeds

    scan, _ = street
    spec = TileSpec(size=8.0, overlap=2.0)
    mapped = []

    class Mapping(Exception):
        pass

    def run_tiles(ex, tasks, progress):
        mapped.append(len(tasks))
        raise Mapping

    monkeypatch.setattr(tiled_map, "run_tiles", run_tiles)
    cfg = tiled_map.resolve_tiles  # the shared values the check must use
    shared = {}

    def resolve(cfg_, parts, spec_, n):
        shared["cfg"] = cfg(cfg_, parts, spec_, n)[0]
        return shared["cfg"], {}

    monkeypatch.setattr(tiled_map, "resolve_tiles", resolve)
    monkeypatch.setattr(surface, "MAX_GRID_NODES", 1000)
    with pytest.raises(surface.GridTooLargeError) as err:
        build_tiled_map(scan, gm.MappingConfig(), spec, check_grid=True)
    assert mapped == []
    voxel = shared["cfg"].surface.voxel_size
    assert f"voxel_size={voxel} m" in str(err.value)
    seeds = surface_seeds(scan, shared["cfg"])
    assert surface.estimate_grid_nodes(seeds, voxel, 2) > 1000
    # without the check the build goes on to map the tiles
    with pytest.raises(Mapping):
        build_tiled_map(scan, gm.MappingConfig(), spec)
    assert mapped and mapped[0] > 1


def test_streamed_build_checks_the_stitched_grid_before_mapping_a_tile(street, tmp_path,
                                                                      monkeypatch):
    """A streamed LAS build with ``check_grid`` checks the stitched surface's grid before
    any tile is mapped, on exactly the seeds the tile maps will have (those the
    region-by-region mesh checks at the end), reading one tile at a time."""
    import gmmgp_app.pipeline as pipeline
    import gmmgp_app.stages.surface as surface
    import gmmgp_app.tiling.las as las

    scan, _ = street
    off = (500000.0, 5400000.0, 100.0)
    write_laz(tmp_path / "street.laz", scan, off)
    spec = TileSpec(size=8.0, overlap=2.0)
    checked = []
    check = pipeline.check_grid_size

    def recording(seeds, voxel, *a):
        checked.append((np.array(seeds), voxel))
        return check(seeds, voxel, *a)

    monkeypatch.setattr(pipeline, "check_grid_size", recording)

    def build(work, **kw):
        return build_tiled_map_from_las(tmp_path / "street.laz", gm.MappingConfig(), spec,
                                        work_dir=tmp_path / work, chunk_size=3000, offset=off,
                                        **kw)

    tm = build("a", check_grid=True)
    assert len(checked) == 1 and len(tm.tiles) > 1
    seeds, voxel = checked[0]
    assert voxel == tm.config.surface.voxel_size
    assert np.array_equal(seeds, tm.stitched_seeds())
    # an impossible grid ends the build before a tile is mapped
    mapped = []

    class Mapping(Exception):
        pass

    def map_tiles(*a, **k):
        mapped.append(1)
        raise Mapping

    monkeypatch.setattr(las, "map_tiles_to_store", map_tiles)
    monkeypatch.setattr(surface, "MAX_GRID_NODES", 1000)
    with pytest.raises(surface.GridTooLargeError, match=f"voxel_size={voxel} m"):
        build("b", check_grid=True)
    assert mapped == []
    with pytest.raises(Mapping):                 # without the check it maps the tiles
        build("c")


def test_tiled_surface_of_a_map_whose_tiles_resolved_their_own_values_uses_the_median(
        monkeypatch):
    """A tiled map saved before the tiles shared one set of "auto" values (each tile
    resolved them from its own points, its config "auto"): the stitched mesh uses the
    median of the tiles' surface voxels (gmmgp run --tile-size with defaults failed on
    'auto' > 0 before that)."""
    import gmmgp_app.tiling.tiled_map as tiled_map
    from gmmgp_app.synth import scan_scene

    monkeypatch.setattr(tiled_map, "resolve_tiles", lambda cfg, parts, spec, n: (cfg, {}))
    scan, _ = scan_scene("box", density=0.08)
    tm = build_tiled_map(scan, gm.MappingConfig(), TileSpec(size=1.5, overlap=0.4))
    per_tile = [t.config.surface.voxel_size for _, t in tm.tiles.items()]
    assert len(per_tile) > 1 and all(isinstance(v, float) for v in per_tile)
    assert len(set(per_tile)) > 1
    assert tm.surface_voxel() == pytest.approx(float(np.median(per_tile)), rel=1e-12)
    mesh = tm.extract_surface()
    ref = tm.extract_surface(voxel_size=tm.surface_voxel())
    assert len(mesh.faces) > 100
    np.testing.assert_array_equal(mesh.vertices, ref.vertices)


def test_a_tiled_build_into_a_work_folder_holds_a_few_tile_maps_not_all(street, tiled,
                                                                        tmp_path, monkeypatch):
    """``build_tiled_map(work_dir=)`` (``gmmgp run --tile-size``): each finished tile map
    goes to disk as it comes (at most one alive while a serial build maps tiles) and
    none is held when the build returns, where the in-memory build holds all of them;
    the map predicts bit for bit as the in-memory one, loading its tiles on demand,
    ``cache_tiles`` at a time."""
    import gc
    import weakref

    from gmmgp_app import pipeline
    from gmmgp_app.tiling.store import TileStore

    scan, _ = street
    alive, real_init = [], pipeline.SurfaceMap.__init__

    def tracking_init(self, *a, **k):
        real_init(self, *a, **k)
        alive.append(weakref.ref(self))

    monkeypatch.setattr(pipeline.SurfaceMap, "__init__", tracking_init)

    def live_maps(peak):
        def progress(done, total):
            gc.collect()
            peak.append(sum(r() is not None for r in alive))
        return progress

    def held():
        gc.collect()
        return sum(r() is not None for r in alive)

    in_memory, on_disk = [], []
    ref = build_tiled_map(scan, tiled.config, tiled.spec, progress=live_maps(in_memory))
    n = len(ref.keys)
    assert n >= 4 and held() == n                 # the in-memory build holds every tile map
    del ref
    alive.clear()
    tm = build_tiled_map(scan, tiled.config, tiled.spec, progress=live_maps(on_disk),
                         work_dir=tmp_path / "work", cache_tiles=2)
    assert held() == 0
    assert len(on_disk) == n and max(on_disk) <= 1, on_disk
    assert isinstance(tm.tiles, TileStore) and tm.keys == tiled.keys
    assert sorted(p.name for p in (tmp_path / "work" / "maps").iterdir()) == sorted(
        f"tile_{i}_{j}" for i, j in tiled.keys)
    q = np.random.default_rng(4).uniform(scan.points.min(0), scan.points.max(0), (2000, 3))
    for a, b in zip(tm.predict(q, return_grad=True), tiled.predict(q, return_grad=True)):
        assert np.array_equal(a, b)
    assert held() <= 2                            # cache_tiles loaded, no more


def test_a_tiled_build_warns_when_the_scan_is_not_z_up():
    """Tiles are cut in x and y (z up): a y-up scan (a Stanford set) gets one warning
    line saying so; a z-up scan none. The scans are too small to map: the build stops
    right after with its own error, so the test maps nothing."""
    import warnings

    from gmmgp_app.tiling import TilingWarning

    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 1, size=(50, 3))
    spec = TileSpec(size=5.0, overlap=0.5, min_points=200)
    with pytest.warns(TilingWarning, match="up axis is y") as rec, \
            pytest.raises(TilingError, match="at least one tile"):
        build_tiled_map(gm.Scan(pts, up=(0.0, 1.0, 0.0)), spec=spec)
    msgs = [str(w.message) for w in rec if issubclass(w.category, TilingWarning)]
    assert len(msgs) == 1 and "\n" not in msgs[0]
    with warnings.catch_warnings():
        warnings.simplefilter("error", TilingWarning)
        for up in (None, (0.0, 0.0, -1.0)):
            with pytest.raises(TilingError, match="at least one tile"):
                build_tiled_map(gm.Scan(pts, up=up), spec=spec)


# ---------------------------------------------------------------- streamed surface


def _face_set(m):
    """The faces of a mesh as a sorted array of their vertices' coordinates (each face's
    three vertices in lexicographic order): equal for the same faces on the same
    vertices in any vertex and face order."""
    tri = m.vertices[m.faces]                                   # (F, 3, 3)
    key = np.lexsort(tri.transpose(2, 0, 1)[::-1], axis=1)      # order within a face
    tri = np.take_along_axis(tri, key[:, :, None], axis=1).reshape(len(tri), 9)
    return tri[np.lexsort(tri.T[::-1])]


def test_streamed_tiled_surface_is_the_whole_lattice_mesh(tiled, tmp_path):
    """Meshed region by region (tiling/mesh.py) the stitched surface has the same
    vertices, variances and faces, bit for bit, as TiledMap.extract_surface's single
    lattice; the PLY written from pieces on disk is byte for byte write_mesh_ply's of
    that mesh; on a saved map every tile is loaded once for the seeds and once more for
    the regions."""
    from gmmgp_app.pipeline import read_mesh_ply, std_colour_max, write_mesh_ply
    from gmmgp_app.tiling import load_tiled_map
    from gmmgp_app.tiling.mesh import streamed_surface_mesh, write_tiled_surface_ply

    whole = tiled.extract_surface(voxel_size=0.15)
    stats = {}
    parts = streamed_surface_mesh(tiled, voxel_size=0.15, stats=stats)
    assert stats["regions"] >= 4 and len(whole.faces) > 5000
    assert len(parts.vertices) == len(whole.vertices) and len(parts.faces) == len(whole.faces)
    ow, op = (np.lexsort(m.vertices.T[::-1]) for m in (whole, parts))
    assert np.array_equal(whole.vertices[ow], parts.vertices[op])
    assert np.array_equal(whole.vertex_variance[ow], parts.vertex_variance[op])
    assert np.array_equal(_face_set(whole), _face_set(parts))
    # a face moved to other vertices would be caught
    bad = type(parts)(parts.vertices, parts.faces.copy(), parts.vertex_variance)
    bad.faces[0, 0] = bad.faces[1, 1] if bad.faces[1, 1] != bad.faces[0, 0] else bad.faces[2, 2]
    assert not np.array_equal(_face_set(whole), _face_set(bad))

    saved = load_tiled_map(tiled.save(tmp_path / "tm"), load_points=False)
    made = write_tiled_surface_ply(saved, tmp_path / "s.ply", offset=saved.offset,
                                   voxel_size=0.15)
    assert made["tile_loads"] == 2 * len(saved.keys)
    assert made["vertices"] == len(parts.vertices) and made["faces"] == len(parts.faces)
    write_mesh_ply(parts, tmp_path / "w.ply", offset=saved.offset,
                   vmax=std_colour_max([parts]))
    assert (tmp_path / "s.ply").read_bytes() == (tmp_path / "w.ply").read_bytes()
    back = read_mesh_ply(tmp_path / "s.ply")
    assert np.array_equal(_face_set(back), _face_set(parts))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.ply", "tm", "w.ply"]


def test_streamed_tiled_surface_with_projection_is_the_whole_lattice_mesh(street):
    """With surface.project_steps = 1 (vertices projected onto the stitched zero level)
    the region-by-region mesh still has the whole lattice mesh's vertices and faces:
    the faces go to the region of their projected centroid, and the vertices two
    regions share are merged within the projection's reach of the border planes."""
    import dataclasses

    from gmmgp_app.tiling.mesh import streamed_surface_mesh

    scan, _ = street
    cfg = gm.MappingConfig()
    cfg = dataclasses.replace(cfg, surface=dataclasses.replace(cfg.surface, project_steps=1))
    tm = build_tiled_map(scan, cfg, TileSpec(size=8.0, overlap=2.0))
    whole = tm.extract_surface(voxel_size=0.2)
    parts = streamed_surface_mesh(tm, voxel_size=0.2)
    assert len(whole.faces) > 2000
    assert len(parts.vertices) == len(whole.vertices)
    ow, op = (np.lexsort(m.vertices.T[::-1]) for m in (whole, parts))
    assert np.array_equal(whole.vertices[ow], parts.vertices[op])
    assert np.array_equal(_face_set(whole), _face_set(parts))


def test_streamed_tiled_surface_trimmed_to_the_reach_is_the_whole_lattice_mesh(tiled):
    """With surface.trim_to_reach on, the region-by-region mesh is still the whole
    lattice's (each region's seeds reach a margin beyond its box, wider than the reach),
    and the whole mesh's faces are the untrimmed mesh's within the reach of the stitched
    seeds (brute-force distances)."""
    import dataclasses

    from gmmgp_app.tiling.mesh import streamed_surface_mesh

    old = tiled.config
    try:
        tiled.config = dataclasses.replace(
            old, surface=dataclasses.replace(old.surface, trim_to_reach=False))
        full = tiled.extract_surface(voxel_size=0.2)
        tiled.config = dataclasses.replace(
            old, surface=dataclasses.replace(old.surface, trim_to_reach=True))
        whole = tiled.extract_surface(voxel_size=0.2)
        parts = streamed_surface_mesh(tiled, voxel_size=0.2)
    finally:
        tiled.config = old
    seeds = tiled.stitched_seeds()
    reach = tiled.surface_reach(seeds)
    c = full.vertices[full.faces].mean(axis=1)
    d = np.concatenate([np.sqrt(((c[i:i + 256, None] - seeds[None]) ** 2).sum(-1).min(1))
                        for i in range(0, len(c), 256)])
    within = d <= reach
    assert (~within).sum() > 10 and within.sum() > 2000
    kept = type(full)(full.vertices, full.faces[within], full.vertex_variance)
    assert len(whole.faces) == within.sum()
    assert np.array_equal(_face_set(whole), _face_set(kept))
    assert len(parts.vertices) == len(whole.vertices)
    ow, op = (np.lexsort(m.vertices.T[::-1]) for m in (whole, parts))
    assert np.array_equal(whole.vertices[ow], parts.vertices[op])
    assert np.array_equal(whole.vertex_variance[ow], parts.vertex_variance[op])
    assert np.array_equal(_face_set(whole), _face_set(parts))


def test_chunked_quantile_is_numpys_quantile_bit_for_bit():
    """The PLY colour scale's percentile, computed a chunk at a time (no array of every
    vertex variance), equals np.quantile exactly: skewed, tied, tiny and NaN inputs."""
    from gmmgp_app.tiling.mesh import chunked_quantile

    rng = np.random.default_rng(1)
    for x in (rng.exponential(size=5003), rng.integers(0, 4, 2000).astype(float),
              rng.normal(size=333) ** 4, np.array([2.5]), np.full(10, 1e-9)):
        for q in (0.98, 0.5, 0.0, 1.0, 0.123):
            for c in (1, 64, 10000):
                got = chunked_quantile(lambda: (x[s:s + c] for s in range(0, len(x), c)), q)
                assert got == float(np.quantile(x, q))
    assert np.isnan(chunked_quantile(lambda: iter([np.array([1.0, np.nan])]), 0.98))
    with pytest.raises(ValueError, match="at least one value"):
        chunked_quantile(lambda: iter([]), 0.5)


# ------------------------------------------------- session 8: workers write, largest first


class _ProcessBoundary(SerialExecutor):
    """Runs each task in this thread, but as a worker process would get and give it:
    the task and the result pickled both ways; records the result sizes."""

    def __init__(self, shared):
        self.shared_filesystem = shared
        self.result_bytes = []

    def submit(self, fn, /, *args, **kwargs):
        import pickle

        args = pickle.loads(pickle.dumps(args))
        fut = super().submit(fn, *args, **kwargs)
        if fut.exception() is None:
            blob = pickle.dumps(fut.result())
            self.result_bytes.append(len(blob))
            fut = super().submit(pickle.loads, blob)
        return fut


def test_workers_save_their_tiles_into_the_store_and_tiles_go_largest_first(street, tiled,
                                                                            tmp_path,
                                                                            monkeypatch):
    """A streamed build on workers that share the filesystem: each worker reads its
    tile's pieces and saves its map into the store itself, so a tile's result is a few
    hundred bytes of numbers (the maps' files came back whole before), and the map
    predicts bit for bit as when the maps come back as bytes and the caller writes
    them; the tiles are handed out largest first; one timing record per tile."""
    scan, _ = street
    off = np.array([500000.0, 5400000.0, 100.0])
    write_laz(tmp_path / "street.laz", scan, off)
    from gmmgp_app.tiling import las, tasks

    runs = {}
    for shared in (True, False):
        if not shared:  # the reference: the maps' files come back, the caller writes them
            monkeypatch.setattr(las, "map_tiles_to_store", lambda *a, **k: tasks.
                                map_tiles_to_store(*a, **dict(k, workers_write=False)))
        ex, stats = _ProcessBoundary(False), []
        tm = build_tiled_map_from_las(tmp_path / "street.laz", tiled.config, tiled.spec,
                                      work_dir=tmp_path / f"work_{shared}", chunk_size=3000,
                                      offset=off, executor=ex, tile_stats=stats)
        runs[shared] = (tm, ex, stats)
    (tw, ew, sw), (tb, eb, sb) = runs[True], runs[False]
    n = len(tw.keys)
    assert tw.keys == tb.keys == tiled.keys and len(sw) == len(sb) == n
    # build_tiled_map_from_las passes workers_write=True: the pieces' paths already
    # assume a shared filesystem, so even an executor that does not say so gets it
    assert max(ew.result_bytes) < 2000 and all(s["bytes_returned"] == 0 for s in sw)
    assert min(eb.result_bytes) > 10000 and all(s["bytes_returned"] > 0 for s in sb)
    q = np.random.default_rng(6).uniform(scan.points.min(0), scan.points.max(0), (2000, 3))
    for a, b in zip(tw.predict(q, return_grad=True), tb.predict(q, return_grad=True)):
        assert np.array_equal(a, b)
    sizes = [s["n_points"] for s in sorted(sw, key=lambda s: s["start"])]
    assert sizes == sorted(sizes, reverse=True) and sizes[0] > sizes[-1]
    for s in sw:
        assert s["cpu_s"] > 0 and s["seconds"] >= s["read_s"] + s["map_s"] - 1e-9
        assert s["numba_threads"] >= 1 and s["store_s"] >= 0


def test_map_tiles_to_store_returns_bytes_unless_the_workers_share_the_files(street,
                                                                             tiled, tmp_path):
    """``map_tiles_to_store`` without ``workers_write``: an executor that does not say
    it shares the filesystem (a remote cluster) gets the maps' files back as bytes and
    the caller writes them; one that does (``shared_filesystem``, the serial and local
    executors of ``open_executor``) has the task save into the store; both stores
    predict bit for bit alike."""
    from gmmgp_app.tiling.geometry import split_into_tiles
    from gmmgp_app.tiling.store import TileStore
    from gmmgp_app.tiling.tasks import map_tiles_to_store

    scan, _ = street
    tiles = split_into_tiles(scan, tiled.spec)
    key = max(tiles, key=lambda k: len(tiles[k]))
    task = (key, tiles[key].points, tiles[key].origins, tiled.config, tiled.method)
    stores = {}
    for shared in (False, True):
        ex, stats = _ProcessBoundary(shared), []
        store = TileStore(tmp_path / f"maps_{shared}", [])
        assert map_tiles_to_store(ex, [task], store, stats=stats) == {}
        assert list(store) == [key] and len(stats) == 1
        assert (stats[0]["bytes_returned"] > 10000) == (not shared)
        assert (ex.result_bytes[0] > 10000) == (not shared)
        stores[shared] = store
    q = np.random.default_rng(7).uniform(tiles[key].points.min(0),
                                         tiles[key].points.max(0), (1000, 3))
    for a, b in zip(stores[False][key].predict(q), stores[True][key].predict(q)):
        assert np.array_equal(a, b)


def test_largest_first_is_stable():
    from gmmgp_app.tiling.tasks import largest_first

    assert largest_first(list("abcde"), [3, 9, 3, 1, 9]) == list("beacd")
    assert largest_first([], []) == []


def _numba_in_worker():
    import os

    import numba

    return numba.get_num_threads(), os.environ.get("NUMBA_NUM_THREADS")


def test_local_workers_share_the_cores_among_their_numba_threads():
    """``open_executor``'s local workers run numba on ``cores // workers`` threads (or
    ``numba_threads``) and say they share the caller's filesystem."""
    with open_executor(workers=1, kind="processes", numba_threads=1) as ex:
        assert ex.shared_filesystem
        assert ex.submit(_numba_in_worker).result() == (1, "1")
    assert SerialExecutor.shared_filesystem
    with pytest.raises(DistributedError, match="numba_threads"):
        with open_executor(workers=2, numba_threads=0):
            pass


@pytest.mark.slow
def test_dask_workers_save_tiles_and_match_serial_bit_for_bit(street, tiled, tmp_path):
    """Two Dask workers map the streamed street with one numba thread each (on this
    2-core machine), save the tiles themselves, and the map is the serial one bit for
    bit."""
    scan, _ = street
    off = np.array([500000.0, 5400000.0, 100.0])
    write_laz(tmp_path / "street.laz", scan, off)
    ref = build_tiled_map_from_las(tmp_path / "street.laz", tiled.config, tiled.spec,
                                   work_dir=tmp_path / "w0", chunk_size=3000, offset=off)
    stats = []
    with open_executor(workers=2, numba_threads=1) as ex:
        tm = build_tiled_map_from_las(tmp_path / "street.laz", tiled.config, tiled.spec,
                                      work_dir=tmp_path / "w2", chunk_size=3000, offset=off,
                                      executor=ex, tile_stats=stats)
    assert {s["numba_threads"] for s in stats} == {1}
    assert all(s["bytes_returned"] == 0 for s in stats) and len(stats) == len(tm.keys)
    q = np.random.default_rng(8).uniform(scan.points.min(0), scan.points.max(0), (2000, 3))
    for a, b in zip(tm.predict(q), ref.predict(q)):
        assert np.array_equal(a, b)
