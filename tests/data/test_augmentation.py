"""Pair augmentation: remeshing with carried ground truth, the bounded remesh pool, caching, the shared rotation.

Shapes: a 642-vertex icosphere stretched into an ellipsoid with a bump (no symmetry that could hide a wrong
index) and a bent, vertex-permuted copy of it; ground truth: x's vertex i is y's vertex perm[i].
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

import shapecorr.data.augmentation as aug
from shapecorr.data.augmentation import (
    AugmentationConfig,
    PairAugmenter,
    cached_remesh,
    pool_resolutions,
    remesh_with_correspondence,
    remeshed_sample,
    rotation_about_axis,
)
from shapecorr.data.cache import ShapeCache, content_hash
from shapecorr.data.datasets import PairSample, ShapeSample
from shapecorr.data.shape import make_shape, triangle_areas
from shapecorr.errors import ConfigError

TARGET = 300


def _sample(verts, faces, name, corres) -> ShapeSample:
    shape = make_shape(verts, faces, name)
    n = shape.n_verts
    return ShapeSample(
        shape=shape,
        operators={"eigenbasis": {"evals": torch.zeros(0), "evecs": torch.zeros(n, 0), "mass": torch.ones(n)}},
        corres=torch.as_tensor(corres, dtype=torch.int64),
        corres_sym=torch.as_tensor(corres[::-1].copy(), dtype=torch.int64),
    )


@pytest.fixture(scope="module")
def pair():
    mesh = trimesh.creation.icosphere(subdivisions=3)
    v, f = np.asarray(mesh.vertices) * [1.4, 1.0, 0.7], np.asarray(mesh.faces)
    v[:, 1] += 0.3 * np.exp(-4.0 * ((v[:, 0] - 0.5) ** 2 + v[:, 2] ** 2))
    perm = np.random.default_rng(0).permutation(len(v))
    bent = v.copy()
    bent[:, 2] += 0.25 * np.sin(1.5 * bent[:, 0])
    vy = np.empty_like(bent)
    vy[perm] = bent
    return PairSample(_sample(v, f, "x", np.arange(len(v))), _sample(vy, perm[f], "y", perm)), perm


def _mean_edge(verts, faces) -> float:
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return float(np.linalg.norm(verts[e[:, 0]] - verts[e[:, 1]], axis=1).mean())


@pytest.fixture(scope="module")
def remeshed(pair):
    x = pair[0].x
    return remesh_with_correspondence(x.verts, x.faces, TARGET)


def test_remesh_correspondence_lands_near_the_right_points(pair, remeshed):
    x = pair[0].x
    v, f = x.verts.numpy().astype(np.float64), x.faces.numpy()
    r = remeshed
    n, m = v.shape[0], r.n_verts
    assert abs(m - TARGET) <= 0.03 * TARGET
    assert r.verts.dtype == np.float32 and r.faces.shape[1] == 3 and r.faces.max() == m - 1
    assert r.source_vertex.shape == (m,) and 0 <= r.source_vertex.min() and r.source_vertex.max() < n
    assert r.nearest_vertex.shape == (n,) and 0 <= r.nearest_vertex.min() and r.nearest_vertex.max() < m
    h_new, h_old = _mean_edge(r.verts, r.faces), _mean_edge(v, f)
    new_v = r.verts.astype(np.float64)
    # ground truth carried: reference point at old vertex i is at new vertex nearest_vertex[i], within one new edge
    assert np.linalg.norm(new_v[r.nearest_vertex] - v, axis=1).max() < h_new
    # and each new vertex comes from an old vertex within one old edge
    assert np.linalg.norm(v[r.source_vertex] - new_v, axis=1).max() < h_old
    # the round trip old -> new -> old stays in the neighbourhood (a remesh vertex covers ~2 old vertices here)
    assert np.linalg.norm(v[r.source_vertex[r.nearest_vertex]] - v, axis=1).mean() < h_new
    # barycentric lift: rows sum to 1; lifting the remesh positions gives points next to the old vertices
    np.testing.assert_allclose(r.lift_weights.sum(1), 1.0, atol=1e-6)
    lifted = r.lift(torch.from_numpy(r.verts)).double().numpy()
    assert np.linalg.norm(lifted - v, axis=1).max() < 0.25 * h_new
    # lifting is linear: a constant field stays constant, a field of the remesh's coordinates is linear too
    const = torch.full((m, 2), 3.5)
    torch.testing.assert_close(r.lift(const), torch.full((n, 2), 3.5))


def test_remeshed_sample_carries_ground_truth_and_names(pair, remeshed):
    batch, perm = pair
    x, y = batch.x, batch.y
    rx = remeshed
    ry = remesh_with_correspondence(y.verts, y.faces, TARGET + 40)
    sx, sy = remeshed_sample(x, rx), remeshed_sample(y, ry)
    assert sx.name == f"x@{rx.n_verts}" and sx.shape.scale == x.shape.scale
    assert torch.equal(sx.corres, torch.from_numpy(rx.nearest_vertex)[x.corres])
    assert torch.equal(sx.corres_sym, torch.from_numpy(rx.nearest_vertex)[x.corres_sym])
    assert sx.evecs.shape == (rx.n_verts, 0) and not sx.features
    np.testing.assert_allclose(float(sx.mass.sum()), triangle_areas(rx.verts, rx.faces).sum(), rtol=1e-5)
    # GT composed with the remeshes: reference point r lies on x at corres_x[r] and on y at corres_y[r]; after
    # remeshing both, the carried indices still point at (nearly) the same places as before.
    for orig, new, r in ((x, sx, rx), (y, sy, ry)):
        h = _mean_edge(r.verts, r.faces)
        d = (new.verts[new.corres] - orig.verts[orig.corres]).norm(dim=1)
        assert float(d.max()) < h
    # and the composition x_remesh -> x -> y -> y_remesh of the ground-truth map is close to y's own GT
    gt_small = torch.from_numpy(ry.nearest_vertex)[torch.as_tensor(perm)[torch.from_numpy(rx.source_vertex)]]
    err = (sy.verts[gt_small] - y.verts[torch.as_tensor(perm)[torch.from_numpy(rx.source_vertex)]]).norm(dim=1)
    assert float(err.max()) < _mean_edge(ry.verts, ry.faces)


def test_cached_remesh_hits_the_cache_the_second_time(pair, tmp_path, monkeypatch):
    x = pair[0].x
    calls = []
    original = aug.remesh_with_correspondence
    monkeypatch.setattr(aug, "remesh_with_correspondence", lambda *a, **k: calls.append(a[2]) or original(*a, **k))
    cache = ShapeCache(tmp_path)
    first = cached_remesh(cache, x.verts, x.faces, 250)
    assert calls == [250]
    assert len(list((tmp_path / "remesh").rglob("*.npz"))) == 1
    second = cached_remesh(ShapeCache(tmp_path), x.verts, x.faces, 250)
    assert calls == [250]  # no recomputation
    for key, value in first.as_arrays().items():
        np.testing.assert_array_equal(value, getattr(second, key))
    cached_remesh(cache, x.verts, x.faces, 260)  # another resolution is another entry
    assert calls == [250, 260]


def test_pool_resolutions_fixed_bounded_and_clipped():
    h = "ab" * 32
    pool = pool_resolutions(h, 5000, (200, 2000), 8, seed=3)
    assert pool.shape == (8,) and np.all(np.diff(pool) > 0) and pool.min() >= 200 and pool.max() <= 2000
    np.testing.assert_array_equal(pool, pool_resolutions(h, 5000, (200, 2000), 8, seed=3))
    assert not np.array_equal(pool, pool_resolutions(h, 5000, (200, 2000), 8, seed=4))
    assert not np.array_equal(pool, pool_resolutions("cd" * 32, 5000, (200, 2000), 8, seed=3))
    clipped = pool_resolutions(h, 300, (200, 2000), 8, seed=3)  # never above the shape's own count
    assert clipped.max() <= 300 and clipped.min() >= 200
    np.testing.assert_array_equal(pool_resolutions(h, 150, (200, 2000), 8), [150])  # smaller than the range
    assert pool_resolutions(h, 5000, (200, 203), 8).tolist() == [200, 201, 202, 203]


def test_augmenter_is_deterministic_per_seed_and_uses_the_pool(pair, tmp_path):
    batch, _ = pair
    cfg = dict(resolution=[200, 400], variants=3)
    augmenter = PairAugmenter(cfg, ShapeCache(tmp_path), seed=0)
    a = augmenter(batch, np.random.default_rng(7), geodesics=False)
    b = PairAugmenter(cfg, ShapeCache(tmp_path), seed=0)(batch, np.random.default_rng(7), geodesics=False)
    for s, t in ((a.pair.x, b.pair.x), (a.pair.y, b.pair.y)):
        assert torch.equal(s.verts, t.verts) and torch.equal(s.faces, t.faces) and torch.equal(s.corres, t.corres)
    assert torch.equal(a.rotation, b.rotation)
    pools = [augmenter.resolutions(batch.x), augmenter.resolutions(batch.y)]
    # every draw is a remesh of the shape's pool (the remesher lands within 3% of the target count)
    seen = set()
    for seed in range(12):
        out = augmenter(batch, np.random.default_rng(seed), geodesics=False)
        for remeshed, pool in ((out.remeshed_x, pools[0]), (out.remeshed_y, pools[1])):
            assert np.min(np.abs(pool - remeshed.n_verts)) <= 0.03 * pool.max()
            seen.add(remeshed.n_verts)
    assert len(seen) <= 6  # at most 3 remeshes per shape, ever
    assert len(list((tmp_path / "remesh").rglob("*.npz"))) <= 6
    c = augmenter(batch, np.random.default_rng(8), geodesics=False)
    assert not torch.equal(c.rotation, a.rotation)


def test_rotation_is_shared_and_about_the_up_axis(pair, tmp_path):
    batch, _ = pair
    augmenter = PairAugmenter(dict(remesh=False, rotate=True, axis="y"), ShapeCache(tmp_path))
    out = augmenter(batch, np.random.default_rng(1), geodesics=False)
    assert out.remeshed_x is None and out.remeshed_y is None
    rot = out.rotation.double()
    torch.testing.assert_close(rot @ rot.T, torch.eye(3, dtype=torch.float64))
    assert float(torch.linalg.det(rot)) == pytest.approx(1.0, abs=1e-6)
    assert not torch.allclose(rot, torch.eye(3, dtype=torch.float64))
    torch.testing.assert_close(rot[:, 1], torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    torch.testing.assert_close(rot[1, :], torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    # the same rotation for both shapes: recover it from each shape independently (Procrustes)
    for before, after in ((batch.x, out.pair.x), (batch.y, out.pair.y)):
        u, _, vt = np.linalg.svd(after.verts.double().numpy().T @ before.verts.double().numpy())
        np.testing.assert_allclose(u @ vt, rot.numpy(), atol=1e-5)
        torch.testing.assert_close(after.verts[:, 1], before.verts[:, 1])  # heights unchanged
    np.testing.assert_allclose(rotation_about_axis(np.pi / 2, "z").numpy() @ [1.0, 0, 0], [0, 1.0, 0], atol=1e-7)
    no_rot = PairAugmenter(dict(remesh=False, rotate=False), ShapeCache(tmp_path))(batch, None, geodesics=False)
    assert torch.equal(no_rot.pair.x.verts, batch.x.verts) and torch.equal(no_rot.rotation, torch.eye(3))


def test_geodesics_of_the_augmented_shapes_are_cached(pair, tmp_path):
    batch, _ = pair
    augmenter = PairAugmenter(dict(resolution=[200, 300], variants=1, rotate=True), ShapeCache(tmp_path))
    out = augmenter(batch, np.random.default_rng(0), geodesics=True)
    n_x, n_y = out.pair.x.shape.n_verts, out.pair.y.shape.n_verts
    assert out.dist_x.shape == (n_x, n_x) and out.dist_y.shape == (n_y, n_y)
    assert torch.equal(out.dist_x, out.dist_x.T) and float(out.dist_x.diagonal().abs().max()) == 0.0
    # rotation-invariant: the matrix belongs to the unrotated remesh, looked up again (cache hit) next time
    files = sorted((tmp_path / "geodesics").rglob("*.npz"))
    assert len(files) == 2
    again = augmenter(batch, np.random.default_rng(5), geodesics=True)
    assert sorted((tmp_path / "geodesics").rglob("*.npz")) == files
    assert torch.equal(again.dist_x, out.dist_x)
    # keyed by the remesh content
    key_x = content_hash(out.remeshed_x.verts, out.remeshed_x.faces)
    assert (tmp_path / "geodesics" / key_x).is_dir()


def test_working_resolution_without_remeshing(pair, tmp_path):
    batch, _ = pair
    augmenter = PairAugmenter(dict(remesh=False, rotate=False), ShapeCache(tmp_path), max_vertices=400)
    out = augmenter(batch, None, geodesics=False)
    assert out.remeshed_x is not None and abs(out.pair.x.shape.n_verts - 400) <= 12
    big = PairAugmenter(dict(remesh=False, rotate=False), ShapeCache(tmp_path), max_vertices=5000)
    assert big(batch, None, geodesics=False).remeshed_x is None


@pytest.mark.parametrize("options", [dict(resolution=[300, 200]), dict(resolution=[2, 10]), dict(variants=0),
                                     dict(axis="w"), dict(unknown=1), dict(resolution=[100])])
def test_invalid_options_raise_config_error(options):
    with pytest.raises(ConfigError):
        AugmentationConfig.from_options(options)


def test_random_draws_need_a_generator(pair, tmp_path):
    with pytest.raises(ConfigError):
        PairAugmenter({}, ShapeCache(tmp_path))(pair[0], None)


# -- on the data side ----------------------------------------------------------------------------------------
class _OnePair:
    """A PairDataset stand-in holding one pair (picklable)."""

    def __init__(self, pair):
        self.pair = pair

    def __len__(self):
        return 1

    def __getitem__(self, k):
        return self.pair

    def names(self, k):
        return self.pair.x.name, self.pair.y.name


def test_augmented_pair_dataset_draws_per_epoch_and_position(pair, tmp_path):
    import pickle

    from shapecorr.data.augmentation import AugmentedPairDataset, SampleKey, step_rng

    batch, _ = pair
    augmenter = PairAugmenter(dict(resolution=[200, 400], variants=2), ShapeCache(tmp_path), seed=3)
    dataset = AugmentedPairDataset(_OnePair(batch), augmenter, geodesics=lambda epoch: epoch < 1)
    a = dataset[SampleKey(0, 5, 0)]
    expected = augmenter(batch, step_rng(3, 0, 5), geodesics=True)
    assert a.pair.x.shape.n_verts == expected.pair.x.shape.n_verts and torch.equal(a.rotation, expected.rotation)
    torch.testing.assert_close(a.pair.x.verts, expected.pair.x.verts)
    assert a.dist_x is not None and a.dist_x.shape == (a.pair.x.shape.n_verts,) * 2
    later = dataset[SampleKey(1, 5, 0)]  # another epoch: other draws, and (here) no geodesics
    assert later.dist_x is None and not torch.equal(later.rotation, a.rotation)
    # a plain index (a sampler without keys): position = index, epoch = set_epoch's
    dataset.set_epoch(0)
    assert torch.equal(dataset[0].rotation, dataset[SampleKey(0, 0, 0)].rotation)
    # the dataset travels to DataLoader workers
    clone = pickle.loads(pickle.dumps(AugmentedPairDataset(_OnePair(batch), augmenter, geodesics=False)))
    assert torch.equal(clone[SampleKey(0, 5, 0)].rotation, a.rotation)
    moved = a.to("cpu")
    assert moved.name == a.pair.name and moved.dist_x.shape == a.dist_x.shape


def test_keyed_sampler_yields_epoch_position_index_and_resumes():
    from shapecorr.data.augmentation import SampleKey
    from shapecorr.data.datamodule import ResumableShuffleSampler

    plain = ResumableShuffleSampler(10, seed=2)
    keyed = ResumableShuffleSampler(10, seed=2, keys=True)
    plain.set_epoch(3)
    keyed.set_epoch(3)
    order = list(plain)
    assert list(keyed) == [SampleKey(3, k, i) for k, i in enumerate(order)]
    keyed.resume_at(3, 4)
    assert list(keyed) == [SampleKey(3, k, i) for k, i in enumerate(order)][4:]


def test_keyed_distributed_sampler_shards_like_lightnings_sampler():
    from torch.utils.data import DistributedSampler

    from shapecorr.data.augmentation import SampleKey
    from shapecorr.data.datamodule import KeyedDistributedSampler

    data = list(range(9))
    for rank in (0, 1):
        keyed = KeyedDistributedSampler(data, num_replicas=2, rank=rank, shuffle=True, seed=4)
        plain = DistributedSampler(data, num_replicas=2, rank=rank, shuffle=True, seed=4)
        keyed.set_epoch(2)
        plain.set_epoch(2)
        assert list(keyed) == [SampleKey(2, k, i) for k, i in enumerate(plain)]
    keyed.set_epoch(3)
    assert [key.epoch for key in keyed] == [3] * len(keyed)


def _small_sample(name: str, offset=None) -> ShapeSample:
    mesh = trimesh.creation.icosphere(subdivisions=2)
    v, f = np.asarray(mesh.vertices) * [1.4, 1.0, 0.7], np.asarray(mesh.faces)
    if offset is not None:  # a second, disjoint copy: two components
        v, f = np.concatenate((v, v + offset)), np.concatenate((f, f + len(v)))
    return _sample(v, f, name, np.arange(len(v)))


def test_original_geodesics_are_clamped_submatrices_of_the_working_mesh(tmp_path, monkeypatch):
    from shapecorr.geometry import geodesics as geo

    x = _small_sample("x")
    calls = []
    real = geo.geodesic_distances
    monkeypatch.setattr(geo, "geodesic_distances", lambda *a, **k: calls.append(k.get("method")) or real(*a, **k))
    augmenter = PairAugmenter(dict(resolution=[60, 110], variants=2, rotate=False), ShapeCache(tmp_path),
                              geodesics="original")
    work_verts, work = augmenter.working_geodesics(x)
    assert np.array_equal(work_verts, x.shape.verts.numpy())  # no max_vertices: the shape itself
    exact = real(x.shape.verts.numpy(), x.shape.faces.numpy(), method="exact")
    np.testing.assert_allclose(work, exact, rtol=1e-6, atol=1e-7)
    out = augmenter(PairSample(x, x), np.random.default_rng(1), geodesics=True)
    n = out.pair.x.shape.n_verts
    assert n < x.shape.n_verts and out.dist_x.shape == (n, n)
    # a sub-matrix of the working matrix at the nearest working vertices, not a matrix of the remesh
    nearest = np.linalg.norm(out.pair.x.shape.verts.numpy()[:, None] - work_verts[None], axis=-1).argmin(1)
    np.testing.assert_array_equal(out.dist_x.numpy(), work[np.ix_(nearest, nearest)])
    assert torch.equal(out.dist_x, out.dist_x.T) and float(out.dist_x.diagonal().abs().max()) == 0.0
    # close to the remesh's own exact geodesics: off by about one working-resolution edge length at most
    own = real(out.pair.x.shape.verts.numpy(), out.pair.x.shape.faces.numpy(), method="exact")
    assert np.abs(out.dist_x.numpy() - own).max() < 1.5 * _mean_edge(x.shape.verts.numpy(), x.shape.faces.numpy())
    assert calls == ["exact"]  # one exact matrix per shape (cached), none per remesh
    # unreachable pairs (two components) are set to 2, as the original's loader does
    two = _small_sample("two", offset=[10.0, 0.0, 0.0])
    _, dist = augmenter.working_geodesics(two)
    m = two.shape.n_verts // 2
    assert np.all(dist[:m, m:] == aug.ORIGINAL_GEODESIC_CLAMP_VALUE) and np.isfinite(dist).all()
    with pytest.raises(ConfigError, match="geodesics"):
        PairAugmenter({}, ShapeCache(tmp_path), geodesics="fast-marching")
