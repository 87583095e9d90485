"""Edge lists and one-rings from faces: oracles from libigl, Euler characteristic, boundary counts, errors."""

import igl
import numpy as np
import pytest
import torch
import trimesh

from shapecorr.errors import InvalidMeshError
from shapecorr.geometry.mesh_graph import directed_edges, undirected_edges, vertex_one_rings


def _meshes():
    return {
        "icosphere": trimesh.creation.icosphere(subdivisions=2),
        "torus": trimesh.creation.torus(1.0, 0.3, major_sections=16, minor_sections=8),
        "box": trimesh.creation.box(),
    }


def _open_grid(n: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """A flat n x n vertex grid triangulated into 2 (n-1)^2 triangles (has a boundary)."""
    ij = np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), -1).reshape(-1, 2)
    verts = np.concatenate([ij, np.zeros((n * n, 1))], axis=1).astype(float)
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j, (i + 1) * n + j + 1
            faces += [(a, b, d), (a, d, c)]
    return verts, np.asarray(faces)


@pytest.mark.parametrize("name", ["icosphere", "torus", "box"])
def test_undirected_edges_match_igl(name):
    mesh = _meshes()[name]
    faces = np.asarray(mesh.faces, dtype=np.int64)
    edges = undirected_edges(torch.from_numpy(faces))
    expected = igl.edges(faces)
    expected = expected[np.lexsort((expected[:, 1], expected[:, 0]))]
    assert edges.dtype == torch.int64
    np.testing.assert_array_equal(edges.numpy(), expected)
    assert bool((edges[:, 0] < edges[:, 1]).all())


@pytest.mark.parametrize("name, chi", [("icosphere", 2), ("torus", 0), ("box", 2)])
def test_euler_characteristic_and_closed_counts(name, chi):
    mesh = _meshes()[name]
    edges, counts = undirected_edges(torch.from_numpy(mesh.faces), return_counts=True)
    assert len(mesh.vertices) - edges.shape[0] + len(mesh.faces) == chi
    assert bool((counts == 2).all())  # closed manifold: every edge in two faces


def test_boundary_edges_counted_once():
    verts, faces = _open_grid(5)
    edges, counts = undirected_edges(faces, n_verts=len(verts), return_counts=True)
    boundary = igl.boundary_facets(faces)[0]  # (edges, face index, local index)
    assert int((counts == 1).sum()) == len(boundary) == 16
    assert int(counts.sum()) == 3 * len(faces)


def test_directed_edges_both_ways_sorted_unique():
    faces = torch.from_numpy(_meshes()["torus"].faces)
    und = undirected_edges(faces)
    both = directed_edges(faces)
    assert both.shape == (2 * und.shape[0], 2)
    pairs = {tuple(e) for e in both.tolist()}
    assert len(pairs) == both.shape[0]
    assert all((j, i) in pairs for i, j in pairs)
    key = both[:, 0] * 10_000 + both[:, 1]
    assert bool((key[1:] > key[:-1]).all())


def test_one_rings_match_igl_adjacency():
    faces = np.asarray(_meshes()["icosphere"].faces, dtype=np.int64)
    rings = vertex_one_rings(faces)
    expected = igl.adjacency_list(faces)
    assert rings.indptr.shape == (len(expected) + 1,)
    for v, nbrs in enumerate(expected):
        assert rings.neighbours(v).tolist() == sorted(nbrs)
    assert int(rings.degrees().sum()) == rings.indices.shape[0]


def test_isolated_vertex_gets_empty_ring():
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    rings = vertex_one_rings(faces, n_verts=6)
    assert rings.degrees().tolist() == [3, 2, 3, 2, 0, 0]
    assert rings.neighbours(4).numel() == 0


def test_keeps_device_and_accepts_numpy():
    faces = _meshes()["box"].faces
    from_np = undirected_edges(faces)
    from_t = undirected_edges(torch.from_numpy(faces).to(torch.int32))
    assert from_np.device == torch.device("cpu")
    assert torch.equal(from_np, from_t)


@pytest.mark.parametrize(
    "faces, n_verts, match",
    [
        (np.array([[0.0, 1.0, 2.0]]), None, "integer"),
        (np.array([[0, 1, 2, 3]]), None, r"shape \(f, 3\)"),
        (np.zeros((0, 3), dtype=int), None, "no faces"),
        (np.array([[0, -1, 2]]), None, "negative"),
        (np.array([[0, 1, 5]]), 4, "only 4 vertices"),
        (np.array([[0, 1, 2], [3, 3, 1]]), None, "repeat a vertex"),
    ],
)
def test_invalid_faces_raise(faces, n_verts, match):
    with pytest.raises(InvalidMeshError, match=match):
        undirected_edges(faces, n_verts=n_verts)
    with pytest.raises(InvalidMeshError):
        vertex_one_rings(faces, n_verts=n_verts)


def test_non_array_faces_raise():
    with pytest.raises(InvalidMeshError, match="tensor or a numpy array"):
        directed_edges([[0, 1, 2]])
