"""Farthest point sampling (FPS) of mesh vertices.

Greedy Euclidean FPS (Gonzalez 1985): start from a given vertex, then repeatedly add the vertex farthest
from the samples chosen so far. The covering radius ``max_v min_s |v - s|`` never increases and is within
a factor 2 of the optimal one for the same number of samples. Written with numpy (one vectorized distance
update per sample, O(n * n_samples) time, O(n) memory) because none of the project's libraries offers a
deterministic FPS with a chosen start vertex (torch_cluster/PyG fps start at random and are not
dependencies; igl/trimesh/gpytoolbox sample the surface, not the vertices).
"""

from __future__ import annotations

import numpy as np

from shapecorr.errors import ConfigError, InvalidMeshError, NumericalError
from shapecorr.geometry.mesh import as_numpy as _as_numpy


def farthest_point_sampling(verts, n_samples: int, start: int = 0) -> np.ndarray:
    """Indices of ``n_samples`` vertices chosen by farthest point sampling.

    Parameters
    ----------
    verts : (n, 3) float
        Points (numpy array or CPU torch tensor).
    n_samples : int
        ``1 <= n_samples <= n``.
    start : int
        First sample.

    Returns
    -------
    (n_samples,) int64
        Distinct indices, ``out[0] == start``; ties (equal distances) go to the smallest index.
        Coincident points are still returned as distinct indices once all distinct positions are taken.
    """
    v = np.asarray(_as_numpy(verts), dtype=np.float64)
    if v.ndim != 2 or v.shape[0] == 0:
        raise InvalidMeshError(f"points must have shape (n, d) with n >= 1, got {v.shape}")
    if not np.isfinite(v).all():
        raise NumericalError("points contain NaN/Inf")
    n = v.shape[0]
    if not 1 <= n_samples <= n:
        raise ConfigError(f"n_samples must be in [1, {n}], got {n_samples}")
    if not 0 <= start < n:
        raise ConfigError(f"start must be in [0, {n}), got {start}")
    out = np.empty(n_samples, dtype=np.int64)
    # Squared distances to the nearest sample; chosen samples get -1 so they are never chosen again.
    nearest = np.full(n, np.inf)
    current = int(start)
    for i in range(n_samples):
        out[i] = current
        diff = v - v[current]
        np.minimum(nearest, np.einsum("ij,ij->i", diff, diff), out=nearest)
        nearest[current] = -1.0
        current = int(np.argmax(nearest))
    return out
