"""Tests of shapecorr.geometry.sampling (farthest point sampling) and shapecorr.geometry.remeshing."""

from __future__ import annotations

import os
from pathlib import Path

import igl
import numpy as np
import pytest
import torch
import trimesh

from shapecorr.errors import ConfigError, InvalidMeshError
from shapecorr.geometry.remeshing import REMESH_RTOL, remesh
from shapecorr.geometry.sampling import farthest_point_sampling


def naive_fps(points: np.ndarray, n_samples: int, start: int) -> list[int]:
    """Oracle: textbook greedy loop with explicit distance lists."""
    chosen = [start]
    while len(chosen) < n_samples:
        best, best_d = None, -1.0
        for i in range(len(points)):
            if i in chosen:
                continue
            d = min(float(((points[i] - points[c]) ** 2).sum()) for c in chosen)
            if d > best_d:
                best, best_d = i, d
        chosen.append(best)
    return chosen


def covering_radius(points: np.ndarray, idx: np.ndarray) -> float:
    d = np.linalg.norm(points[:, None, :] - points[idx][None, :, :], axis=-1)
    return float(d.min(axis=1).max())


@pytest.fixture(scope="module")
def cloud():
    return np.random.default_rng(0).normal(size=(300, 3))


def test_fps_matches_naive_oracle(cloud):
    out = farthest_point_sampling(cloud, 25, start=7)
    assert out.dtype == np.int64 and out.shape == (25,)
    assert out.tolist() == naive_fps(cloud, 25, 7)


def test_fps_distinct_starts_at_start_and_covers(cloud):
    out = farthest_point_sampling(torch.from_numpy(cloud), 120, start=42)
    assert out[0] == 42 and len(np.unique(out)) == 120
    radii = [covering_radius(cloud, out[:m]) for m in (1, 5, 20, 60, 120)]
    assert all(a > b for a, b in zip(radii, radii[1:]))
    # Greedy FPS is a 2-approximation: the m-th sample's distance bounds the radius from both sides.
    random_idx = np.random.default_rng(1).choice(len(cloud), 120, replace=False)
    assert radii[-1] < covering_radius(cloud, random_idx)


def test_fps_all_points_and_duplicates():
    pts = np.repeat(np.random.default_rng(2).normal(size=(5, 3)), 3, axis=0)  # every point three times
    out = farthest_point_sampling(pts, len(pts))
    assert sorted(out.tolist()) == list(range(len(pts)))
    # The first 5 samples are the 5 distinct positions.
    assert len(np.unique(pts[out[:5]], axis=0)) == 5


def plain_fps(points: np.ndarray, n_samples: int, start: int) -> list[int]:
    """Oracle: the unpruned vectorized greedy loop (every point updated at every sample)."""
    nearest, out, current = np.full(len(points), np.inf), [], start
    for _ in range(n_samples):
        out.append(current)
        diff = points - points[current]
        np.minimum(nearest, np.einsum("ij,ij->i", diff, diff), out=nearest)
        nearest[current] = -1.0
        current = int(np.argmax(nearest))
    return out


@pytest.mark.parametrize("per_box", [1, 4, 16])
def test_fps_box_pruning_matches_plain_loop(monkeypatch, per_box):
    """Many small boxes: the pruned search picks exactly the plain loop's samples, ties and duplicates too."""
    import shapecorr.geometry.sampling as sampling

    monkeypatch.setattr(sampling, "POINTS_PER_BOX", per_box)
    rng = np.random.default_rng(3)
    grid = np.stack(np.meshgrid(np.arange(9.0), np.arange(7.0), np.arange(3.0)), -1).reshape(-1, 3)  # ties
    sphere = rng.normal(size=(800, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    for pts in (grid, sphere, np.repeat(rng.normal(size=(40, 3)), 3, axis=0), rng.normal(size=(500, 2))):
        for n_samples, start in ((len(pts), 0), (len(pts) // 4, len(pts) - 1)):
            out = farthest_point_sampling(pts, n_samples, start=start)
            assert out.tolist() == plain_fps(pts, n_samples, start)


def test_fps_invalid_arguments(cloud):
    with pytest.raises(ConfigError):
        farthest_point_sampling(cloud, 0)
    with pytest.raises(ConfigError):
        farthest_point_sampling(cloud, len(cloud) + 1)
    with pytest.raises(ConfigError):
        farthest_point_sampling(cloud, 3, start=-1)
    with pytest.raises(InvalidMeshError):
        farthest_point_sampling(np.zeros((0, 3)), 1)


def check_valid_closed_mesh(v, f, area, area_rtol=0.03):
    assert v.dtype == np.float64 and f.dtype == np.int64
    assert np.isfinite(v).all()
    assert igl.is_edge_manifold(f)[0]
    assert np.array_equal(np.unique(f), np.arange(len(v)))  # no unreferenced vertex
    mesh = trimesh.Trimesh(v, f, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert igl.doublearea(v, f).min() > 0
    np.testing.assert_allclose(mesh.area, area, rtol=area_rtol)


@pytest.mark.parametrize(
    "name, target",
    [("sphere", 400), ("sphere", 1500), ("torus", 800)],
)
def test_remesh_hits_target_and_is_manifold(name, target):
    if name == "sphere":
        mesh = trimesh.creation.icosphere(4)
    else:
        mesh = trimesh.creation.torus(1.0, 0.3, 64, 32)
    v, f = remesh(mesh.vertices, mesh.faces, target)
    assert abs(len(v) - target) <= REMESH_RTOL * target
    check_valid_closed_mesh(v, f, mesh.area)
    assert (mesh.euler_number == 2) == (trimesh.Trimesh(v, f, process=False).euler_number == 2)


def test_remesh_deterministic():
    mesh = trimesh.creation.icosphere(3)
    a = remesh(mesh.vertices, mesh.faces, 300, seed=0)
    b = remesh(torch.from_numpy(np.asarray(mesh.vertices)), torch.from_numpy(np.asarray(mesh.faces)), 300, seed=5)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])


def test_remesh_invalid_arguments():
    mesh = trimesh.creation.icosphere(1)
    with pytest.raises(ConfigError):
        remesh(mesh.vertices, mesh.faces, 3)
    with pytest.raises(ConfigError):
        remesh(mesh.vertices, mesh.faces, 100, iterations=0)
    with pytest.raises(InvalidMeshError):
        remesh(np.full((3, 3), np.nan), [[0, 1, 2]], 100)


@pytest.mark.reference
def test_remesh_faust_r_shape():
    root = os.environ.get("SHAPECORR_FAUST_R")
    if not root:
        pytest.skip("set SHAPECORR_FAUST_R to the FAUST_r folder to run this test")
    mesh = trimesh.load(Path(root) / "off" / "tr_reg_080.off", process=False)
    for target in (500, 2000):
        v, f = remesh(mesh.vertices, mesh.faces, target)
        assert abs(len(v) - target) <= REMESH_RTOL * target
        # Coarse remeshes cut across thin parts (fingers): area measured -12% at 500 vertices, -6% at 2000.
        check_valid_closed_mesh(v, f, mesh.area, area_rtol=0.15 if target < 1000 else 0.08)
