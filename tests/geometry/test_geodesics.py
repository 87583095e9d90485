"""Tests of shapecorr.geometry.geodesics: accuracy on the sphere, all-pairs properties, components."""

from __future__ import annotations

import numpy as np
import potpourri3d as pp3d
import pytest
import torch
import trimesh

from shapecorr.errors import ConfigError, InvalidMeshError
from shapecorr.geometry.geodesics import geodesic_distances, vertex_components


@pytest.fixture(scope="module")
def sphere(unit_sphere):
    v, f = unit_sphere(4)  # 2562 vertices
    sources = np.array([0, 417, 1300, 2561])
    great_circle = np.arccos(np.clip(v[sources] @ v.T, -1.0, 1.0))
    return v, f, sources, great_circle


def test_heat_method_within_two_percent_of_great_circle(sphere):
    v, f, sources, gc = sphere
    D = geodesic_distances(v, f, sources)
    assert D.shape == (len(sources), len(v)) and D.dtype == np.float64
    assert np.abs(D - gc).max() < 0.02 * np.pi  # measured 1.0% of the half circumference
    far = gc > 0.2  # away from the source, where the heat method smooths the cone
    assert np.mean(np.abs(D - gc)[far] / gc[far]) < 0.02  # measured 1.0%
    np.testing.assert_array_equal(D[np.arange(len(sources)), sources], 0.0)


def test_exact_method_is_tighter(sphere):
    v, f, sources, gc = sphere
    D = geodesic_distances(v, f, sources[:2], method="exact")
    # Polyhedral geodesics of the inscribed mesh are slightly shorter: measured 0.07% of pi at most.
    assert np.abs(D - gc[:2]).max() < 0.002 * np.pi
    assert (D <= gc[:2] + 1e-9).mean() > 0.95


def test_rows_equal_potpourri3d(sphere):
    v, f, sources, _ = sphere
    D = geodesic_distances(v, f, sources[:2])
    solver = pp3d.MeshHeatMethodDistanceSolver(v, f)
    for a, s in enumerate(sources[:2]):
        np.testing.assert_allclose(D[a], np.maximum(solver.compute_distance(int(s)), 0.0), atol=1e-12)


@pytest.mark.parametrize("method", ["heat", "exact"])
def test_all_pairs_symmetric_zero_diagonal_triangle_inequality(method, unit_sphere):
    v, f = unit_sphere(2)  # 162 vertices
    D = geodesic_distances(torch.from_numpy(v), torch.from_numpy(f), method=method)
    assert D.shape == (len(v), len(v))
    np.testing.assert_array_equal(D, D.T)
    np.testing.assert_array_equal(np.diag(D), 0.0)
    assert (D >= 0).all() and np.isfinite(D).all()
    if method == "exact":
        # d(i, j) <= d(i, k) + d(k, j) for all triples (vectorized over j, k).
        for i in range(0, len(v), 7):
            assert (D[i][None, :] <= D[i][:, None] + D + 1e-9).all()


def test_heat_close_to_exact_on_a_torus():
    t = trimesh.creation.torus(1.0, 0.35, 48, 24)
    v, f = np.asarray(t.vertices), np.asarray(t.faces)
    sources = np.array([0, 500])
    heat = geodesic_distances(v, f, sources)
    exact = geodesic_distances(v, f, sources, method="exact")
    far = exact > 0.3
    # Coarse, anisotropic triangles (aspect ~2): measured 3.5% mean relative difference.
    assert np.mean(np.abs(heat - exact)[far] / exact[far]) < 0.05


def test_disconnected_mesh(unit_sphere):
    v1, f1 = unit_sphere(1)
    v = np.vstack([v1, v1 + [4.0, 0.0, 0.0], [[9.0, 9.0, 9.0]]])  # two spheres and an isolated vertex
    f = np.vstack([f1, f1 + len(v1)])
    n1 = len(v1)
    assert vertex_components(len(v), f)[0] == 3
    with pytest.raises(InvalidMeshError, match="components"):
        geodesic_distances(v, f)
    D = geodesic_distances(v, f, allow_disconnected=True)
    assert not np.isnan(D).any()
    assert np.isinf(D[:n1, n1:]).all() and np.isinf(D[n1:2 * n1, :n1]).all() and np.isinf(D[-1, :-1]).all()
    assert D[-1, -1] == 0.0
    alone = geodesic_distances(v1, f1)
    np.testing.assert_allclose(D[:n1, :n1], alone, atol=1e-12)
    np.testing.assert_allclose(D[n1 : 2 * n1, n1 : 2 * n1], alone, atol=1e-12)


def test_invalid_arguments(unit_sphere):
    v, f = unit_sphere(1)
    with pytest.raises(ConfigError, match="method"):
        geodesic_distances(v, f, [0], method="dijkstra")
    with pytest.raises(ConfigError, match="source"):
        geodesic_distances(v, f, [len(v)])
    with pytest.raises(InvalidMeshError):
        geodesic_distances(v, np.vstack([f, [[0, 1, 99]]]), [0])
