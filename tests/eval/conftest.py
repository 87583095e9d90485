"""Fixtures for the evaluation tests: a small in-memory dataset of permuted, rotated unit spheres.

Every shape is the same unit icosphere (162 vertices) with its vertices permuted and rotated, so
the ground truth is known exactly, the geodesic distances are the great-circle arc lengths, and the
mirrored ground truth (reflection x -> -x of the base sphere) is known as well. The dataset duck-types the
parts of :class:`shapecorr.data.datasets.ShapeDataset` the evaluation uses.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree

from shapecorr.data.datasets import ShapeSample
from shapecorr.data.shape import make_shape

N_REF = 120  # reference points per shape (a subset of the 162 vertices)
FEATURE_DIM = 8


class SphereShapes:
    """Shapes ``s0..s{n-1}``: permuted/rotated copies of a unit icosphere with exact ground truth."""

    def __init__(self, n_shapes: int = 3, seed: int = 0, root: Path = Path("spheres")):
        rng = np.random.default_rng(seed)
        mesh = trimesh.creation.icosphere(subdivisions=2)
        base = np.asarray(mesh.vertices, dtype=np.float64)
        base /= np.linalg.norm(base, axis=1, keepdims=True)
        faces = np.asarray(mesh.faces, dtype=np.int64)
        n = len(base)
        reflected = base * [-1.0, 1.0, 1.0]
        mirror = cKDTree(base).query(reflected)[1]
        ref = np.sort(rng.choice(n, N_REF, replace=False))
        # per base vertex, a random descriptor: the same on every shape, so descriptor NN is exact
        features = rng.normal(size=(n, FEATURE_DIM)).astype(np.float32)
        self.root = Path(root)
        self.names = [f"s{k}" for k in range(n_shapes)]
        self.normalization = "none"
        self._data = []
        for _ in range(n_shapes):
            perm = rng.permutation(n)  # base vertex i is vertex perm[i] of this shape
            rot, _ = np.linalg.qr(rng.normal(size=(3, 3)))
            verts = np.empty_like(base)
            verts[perm] = base @ rot.T
            feats = np.empty_like(features)
            feats[perm] = features
            self._data.append(
                {
                    "verts": verts,
                    "faces": perm[faces],
                    "corres": perm[ref],
                    "corres_sym": perm[mirror[ref]],
                    "features": feats,
                    "perm": perm,
                }
            )
        self.mirror = mirror
        self.geodesic_calls = 0

    def __len__(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        return self.names.index(name)

    def load_shape(self, i: int):
        d = self._data[i]
        return make_shape(d["verts"], d["faces"], self.names[i], normalization=None)

    def __getitem__(self, i: int) -> ShapeSample:
        d = self._data[i]
        n = len(d["verts"])
        return ShapeSample(
            shape=self.load_shape(i),
            operators={
                "eigenbasis": {"evals": torch.zeros(1), "evecs": torch.ones(n, 1), "mass": torch.ones(n)},
                "wks": {"wks": torch.from_numpy(d["features"])},
            },
            corres=torch.from_numpy(d["corres"]),
            corres_sym=torch.from_numpy(d["corres_sym"]),
        )

    def geodesics(self, i: int, method: str = "heat") -> np.ndarray:
        self.geodesic_calls += 1
        v = self._data[i]["verts"]
        d = np.arccos(np.clip(v @ v.T, -1.0, 1.0))
        np.fill_diagonal(d, 0.0)
        return d.astype(np.float32)

    def ground_truth_geodesics(self, i: int, method: str = "heat"):
        """Exact rows from the ground-truth points (what the evaluation reads), as SourceDistances."""
        from shapecorr.geometry.geodesics import SourceDistances

        self.geodesic_calls += 1
        d = self._data[i]
        sources = np.unique(np.concatenate([d["corres"], d["corres_sym"]]))
        v = d["verts"]
        rows = np.arccos(np.clip(v[sources] @ v.T, -1.0, 1.0))
        rows[np.arange(sources.size), sources] = 0.0
        return SourceDistances(sources.astype(np.int64), rows.astype(np.float32))

    def true_map(self, i: int, j: int) -> np.ndarray:
        """The exact map from shape i to shape j (same base vertex)."""
        inv_i = np.argsort(self._data[i]["perm"])
        return self._data[j]["perm"][inv_i]

    def mirror_map(self, i: int, j: int) -> np.ndarray:
        """The left/right flipped map: each vertex to the mirror image of its true match."""
        inv_i = np.argsort(self._data[i]["perm"])
        return self._data[j]["perm"][self.mirror[inv_i]]

    def antipodal_map(self, i: int, j: int) -> np.ndarray:
        """Each vertex of shape i to the antipode of its true match on shape j (error pi everywhere)."""
        vj = self._data[j]["verts"]
        return cKDTree(vj).query(-vj[self.true_map(i, j)])[1]


@pytest.fixture
def spheres():
    return SphereShapes(n_shapes=3, seed=0)
