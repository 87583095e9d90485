"""Geodesics that scale: rows from a few sources (float32, O(s n)), their cache entry, their use in the
geodesic error, island handling in score_map, and the memory estimates that pick the preparation workers."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
import trimesh

from shapecorr.data.cache import ShapeCache
from shapecorr.data.datasets import ShapeSample
from shapecorr.geometry.memory import prepare_bytes, workers_for_memory
from shapecorr.data.operators import geodesics_from_cached
from shapecorr.data.shape import make_shape
from shapecorr.errors import ConfigError
from shapecorr.eval import metrics, scoring
from shapecorr.geometry.geodesics import (
    SourceDistances,
    distances_from_sources,
    geodesic_distances,
    geodesic_distances_from,
)


def sphere(subdivisions: int = 2, offset=(0.0, 0.0, 0.0)):
    s = trimesh.creation.icosphere(subdivisions)
    v = np.asarray(s.vertices)
    v = v / np.linalg.norm(v, axis=1, keepdims=True) + np.asarray(offset)
    return v, np.asarray(s.faces, dtype=np.int64)


def body_with_island():
    """A 642-vertex sphere plus a 12-vertex icosahedron floating beside it (one mesh, two components)."""
    v1, f1 = sphere(3)
    v2, f2 = sphere(0, offset=(5.0, 0.0, 0.0))
    return np.vstack([v1, 0.2 * (v2 - [5.0, 0, 0]) + [5.0, 0, 0]]), np.vstack([f1, f2 + len(v1)]), len(v1)


def sample(verts, faces, name, corres=None, path=None):
    shape = make_shape(verts, faces, name, path=path, normalization=None)
    n = shape.n_verts
    c = None if corres is None else torch.as_tensor(corres, dtype=torch.int64)
    return ShapeSample(
        shape=shape,
        operators={"eigenbasis": {"evals": torch.zeros(1), "evecs": torch.ones(n, 1), "mass": torch.ones(n)}},
        corres=c,
    )


def test_rows_equal_the_rows_of_the_full_solver_in_float32():
    v, f = sphere(3)
    src = np.array([5, 0, 300, 5])  # unsorted, with a repeat
    rows = geodesic_distances_from(v, f, src)
    assert rows.shape == (4, len(v)) and rows.dtype == np.float32
    ref = geodesic_distances(v, f, src)
    np.testing.assert_allclose(rows, ref, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(rows[np.arange(4), src], 0.0)


def test_rows_differ_from_the_symmetrized_matrix_only_by_the_heat_asymmetry():
    v, f = sphere(3)
    src = np.arange(0, len(v), 7)
    rows = geodesic_distances_from(v, f, src)
    full = geodesic_distances(v, f)  # (D + D^T) / 2
    rel = np.abs(rows - full[src]).max() / full.max()
    assert 0 < rel < 0.01  # the heat method is not exactly symmetric, but nearly


def test_disconnected_rows_are_inf_across_components_and_zero_at_the_source():
    v, f, n_body = body_with_island()
    rows = geodesic_distances_from(v, f, [0, n_body + 1])
    assert np.isinf(rows[0, n_body:]).all() and np.isfinite(rows[0, :n_body]).all()
    assert np.isinf(rows[1, :n_body]).all() and rows[1, n_body + 1] == 0.0
    with pytest.raises(Exception, match="connected components"):
        geodesic_distances_from(v, f, [0], allow_disconnected=False)


def test_geodesic_errors_from_rows_equal_errors_from_a_symmetric_matrix():
    v, f = sphere(2)
    full = np.arccos(np.clip(v @ v.T, -1, 1))
    np.fill_diagonal(full, 0.0)
    rng = np.random.default_rng(0)
    ref_y = rng.choice(len(v), 40, replace=False)
    ref_x = rng.choice(len(v), 40, replace=False)
    p2p = rng.integers(0, len(v), len(v))
    src = np.unique(ref_y)
    rows = SourceDistances(src, full[src].astype(np.float32))
    a = metrics.geodesic_errors(p2p, full, ref_x, ref_y, 2.0)
    b = metrics.geodesic_errors(p2p, rows, ref_x, ref_y, 2.0)
    np.testing.assert_allclose(a, b, rtol=1e-6)
    with pytest.raises(ConfigError, match="not among the sources"):
        metrics.geodesic_errors(p2p, rows, ref_x, np.setdiff1d(np.arange(len(v)), src)[:40], 2.0)


def test_cached_rows_round_trip_inf_and_hit(tmp_path):
    v, f, n_body = body_with_island()
    cache = ShapeCache(tmp_path)
    first = geodesics_from_cached(cache, v, f, [3, n_body + 2, 3])
    assert first.sources.tolist() == [3, n_body + 2] and np.isinf(first.rows[0, n_body:]).all()
    again = geodesics_from_cached(cache, v, f, [n_body + 2, 3])
    np.testing.assert_array_equal(first.rows, again.rows)
    direct = distances_from_sources(v, f, [3, n_body + 2])
    np.testing.assert_allclose(again.rows, direct.rows)


def test_score_map_excludes_island_points_and_names_the_file(tmp_path):
    v, f, n_body = body_with_island()
    refs = np.array([0, 10, 20, n_body + 1, n_body + 3])
    x = sample(v, f, "x", refs, path=tmp_path / "scan_x.off")
    path = tmp_path / "scan_y.off"
    y = sample(v, f, "y", refs, path=path)
    dist = distances_from_sources(v, f, refs)
    p2p = np.arange(len(v))
    p2p[n_body + 1] = 0  # not scored: on the island of x
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = scoring.score_map(p2p, x, y, dist)
    assert out["n_excluded"] == 2 and out["errors"].shape == (3,)
    np.testing.assert_allclose(out["errors"], 0.0, atol=1e-7)
    messages = [str(w.message) for w in caught if issubclass(w.category, scoring.IslandWarning)]
    assert len(messages) == 2 and str(path) in messages[1] and "n_excluded_points" in messages[1]
    with warnings.catch_warnings(record=True) as caught:  # once per file
        warnings.simplefilter("always")
        scoring.score_map(p2p, x, y, dist)
    assert not [w for w in caught if issubclass(w.category, scoring.IslandWarning)]


def test_prediction_on_an_island_of_the_target_is_scored_on_the_body():
    v, f, n_body = body_with_island()
    refs = np.array([0, 10])
    x, y = sample(v, f, "x", refs), sample(v, f, "y", refs)
    p2p = np.arange(len(v))
    p2p[10] = n_body + 1  # x's point 10 lands on y's island
    out = scoring.score_map(p2p, x, y, distances_from_sources(v, f, refs))
    assert np.isfinite(out["errors"]).all() and out["errors"][1] > 0 and out["n_excluded"] == 0


@pytest.mark.parametrize(
    "estimates, requested, available, expected",
    [
        ([10, 10, 10, 10], 4, 100, 4),  # fits
        ([40, 40, 40, 40], 4, 100, 2),  # 0.8 * 100 // 40
        ([40, 10], None, 1000, 2),  # at most one per job
    ],
)
def test_workers_follow_the_memory_estimate(estimates, requested, available, expected):
    assert workers_for_memory(estimates, requested, "x", "use fewer", available=available) == expected


def test_a_job_larger_than_memory_stops_with_the_option():
    with pytest.raises(ConfigError, match="data.prepare_workers=1"):
        workers_for_memory([10 * 1024**3], 2, "preparing s", "set data.prepare_workers=1", available=1024**3)


def test_prepare_estimate_is_linear_in_sources_not_quadratic():
    n = 150_000
    rows = prepare_bytes(n, 200, 5000)
    full = prepare_bytes(n, 200, n)
    assert rows < 5e9 < 8e10 < full


def test_all_pairs_matrix_of_a_large_mesh_stops_before_allocating(monkeypatch):
    import shapecorr.geometry.memory as memory

    monkeypatch.setattr(memory, "available_memory_bytes", lambda: 1024**2)  # 1 MiB
    v, f = sphere(3)  # 642 vertices: 6.6 MB for the all-pairs matrix
    with pytest.raises(ConfigError, match="geodesic_distances_from.*query_resolution"):
        geodesic_distances(v, f)
    assert geodesic_distances_from(v, f, [0]).shape == (1, len(v))  # rows still work
