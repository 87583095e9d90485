"""Geodesic distances on triangle meshes.

Two methods, both from libraries:

- ``"heat"``: the heat method (Crane, Weischedel & Wardetzky, TOG 2013) of ``potpourri3d``
  (``MeshHeatMethodDistanceSolver``, by default on the intrinsic Delaunay tufted cover, which makes it robust
  to poor triangles). One solver (two sparse factorizations) is built per connected component and reused for
  every source; each source then costs two triangular solves. Approximate: about 1% error on a
  2.5k-vertex sphere, smoothed near the cut locus.
- ``"exact"``: the MMP exact polyhedral geodesics of libigl (``igl.exact_geodesic``), one run per source;
  exact on the mesh but ~100x slower than the heat method (use it for evaluation targets, not all pairs
  of large meshes).

All pairs (``sources=None``): the heat method is not symmetric, so the returned matrix is the symmetrized
``(D + D^T) / 2`` with an exact zero diagonal (NeuroMorph's MATLAB preprocessing symmetrizes its
fast-marching matrices the same way, docs/neuromorph.md §2); the exact method is symmetric up to round-off and
gets the same treatment.

Disconnected meshes: the distance between vertices of different components is infinite. By default a
mesh with several components raises :class:`InvalidMeshError`; with ``allow_disconnected=True`` each
component is solved on its own and the cross-component entries are ``inf`` (a vertex in no face is a
component of its own). No NaN is ever returned.
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor

import igl
import numpy as np
import potpourri3d as pp3d
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from shapecorr.errors import ConfigError, InvalidMeshError, NumericalError
from shapecorr.geometry.laplace_beltrami import mesh_arrays
from shapecorr.geometry.mesh import as_numpy as _as_numpy

#: Heat method time step t = HEAT_T_COEF * h^2, h the mean edge length (Crane et al. 2013, §3.2.4: m = 1).
HEAT_T_COEF = 1.0
GEODESIC_METHODS = ("heat", "exact")


def vertex_components(n_verts: int, faces: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected components of a mesh (vertices joined by the edges of its faces).

    Parameters
    ----------
    n_verts : int
    faces : (f, 3) int

    Returns
    -------
    n_components : int
    labels : (n_verts,) int, component of every vertex (a vertex in no face is its own component)
    """
    f = np.asarray(faces, dtype=np.int64)
    i = f[:, [0, 1, 2]].ravel()
    j = f[:, [1, 2, 0]].ravel()
    adj = sp.coo_matrix((np.ones(i.shape[0]), (i, j)), shape=(n_verts, n_verts))
    n_comp, labels = connected_components(adj, directed=False)
    return int(n_comp), labels


def geodesic_distances(
    verts,
    faces,
    sources=None,
    method: str = "heat",
    allow_disconnected: bool = False,
    t_coef: float = HEAT_T_COEF,
    robust: bool = True,
    n_jobs: int = 1,
) -> np.ndarray:
    """Geodesic distances from source vertices to all vertices.

    Parameters
    ----------
    verts : (n, 3) float
    faces : (f, 3) int
    sources : (s,) int, optional
        Source vertex indices; ``None`` for all vertices (an ``(n, n)`` symmetrized matrix, see the module
        docstring).
    method : {"heat", "exact"}
    allow_disconnected : bool
        Accept several connected components (cross-component distances are ``inf``).
    t_coef : float
        Heat method time step in units of the squared mean edge length.
    robust : bool
        Heat method on the intrinsic Delaunay tufted cover (potpourri3d's ``use_robust``).
    n_jobs : int
        Worker processes sharing the sources (potpourri3d holds the GIL, so threads do not help). Each
        worker builds its own solver; worth it for many sources (all pairs of a 5k mesh: ~14 s of CPU).

    Returns
    -------
    (s, n) float64
        ``D[a, j]`` is the distance from ``sources[a]`` to vertex ``j``; ``D[a, sources[a]] == 0``.

    Raises
    ------
    InvalidMeshError
        Invalid arrays, or several components without ``allow_disconnected``.
    ConfigError
        Unknown method, sources out of range.
    NumericalError
        The solver returned NaN/Inf inside a component.
    """
    v, f = mesh_arrays(verts, faces)
    n = v.shape[0]
    if method not in GEODESIC_METHODS:
        raise ConfigError(f"geodesic method must be one of {GEODESIC_METHODS}, got {method!r}")
    if n_jobs < 1:
        raise ConfigError(f"n_jobs must be >= 1, got {n_jobs}")
    all_pairs = sources is None
    src = np.arange(n) if all_pairs else np.atleast_1d(_as_numpy(sources)).astype(np.int64).ravel()
    if src.size and (src.min() < 0 or src.max() >= n):
        raise ConfigError(f"source indices must be in [0, {n}), got min {src.min()}, max {src.max()}")
    n_comp, labels = vertex_components(n, f)
    if n_comp > 1 and not allow_disconnected:
        sizes = np.bincount(labels)
        raise InvalidMeshError(
            f"mesh has {n_comp} connected components (sizes {sorted(sizes.tolist(), reverse=True)[:5]}...); "
            "geodesic distances between them are infinite: pass allow_disconnected=True to get inf there"
        )

    D = np.full((src.size, n), np.inf)
    face_comp = labels[f[:, 0]]
    for comp in np.unique(labels[src]):
        rows = np.flatnonzero(labels[src] == comp)
        members = np.flatnonzero(labels == comp)
        comp_faces = f[face_comp == comp]
        if comp_faces.shape[0] == 0:  # an isolated vertex
            D[rows, src[rows]] = 0.0
            continue
        if n_comp == 1:
            sub_v, sub_f, local = v, f, src[rows]
        else:
            remap = np.full(n, -1, dtype=np.int64)
            remap[members] = np.arange(members.size)
            sub_v, sub_f, local = v[members], remap[comp_faces], remap[src[rows]]
        block = _distances_parallel(sub_v, sub_f, local, method, t_coef, robust, n_jobs)
        if n_comp == 1:
            D[rows] = block
        else:
            D[np.ix_(rows, members)] = block

    if all_pairs:
        D += D.T
        D *= 0.5
        np.fill_diagonal(D, 0.0)
    if np.isnan(D).any():
        raise NumericalError(f"{method} geodesic distances contain NaN")
    return D


def _distances_parallel(v, f, sources, method, t_coef, robust, n_jobs: int) -> np.ndarray:
    """:func:`_component_distances` with the sources split between ``n_jobs`` spawned processes."""
    n_jobs = min(n_jobs, sources.size)
    if n_jobs <= 1:
        return _component_distances(v, f, sources, method, t_coef, robust)
    chunks = np.array_split(sources, n_jobs)
    # "spawn": a forked child of a process with torch / OpenMP threads can deadlock.
    with ProcessPoolExecutor(n_jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
        parts = pool.map(_component_distances, *zip(*[(v, f, c, method, t_coef, robust) for c in chunks]))
        return np.concatenate(list(parts), axis=0)


def _component_distances(v, f, sources, method: str, t_coef: float, robust: bool) -> np.ndarray:
    """Distances (s, n_c) inside one connected component."""
    out = np.empty((sources.size, v.shape[0]))
    if method == "heat":
        solver = pp3d.MeshHeatMethodDistanceSolver(v, f, t_coef=t_coef, use_robust=robust)
        for a, s in enumerate(sources):
            out[a] = solver.compute_distance(int(s))
    else:
        targets = np.arange(v.shape[0], dtype=np.int64)
        no_faces = np.zeros(0, dtype=np.int64)
        for a, s in enumerate(sources):
            out[a] = igl.exact_geodesic(v, f, np.array([s], dtype=np.int64), no_faces, targets, no_faces)
    if not np.isfinite(out).all():
        raise NumericalError(f"{method} geodesic solver returned NaN/Inf inside a connected component")
    # The heat method can give tiny negative values next to the source; distances are >= 0.
    np.maximum(out, 0.0, out=out)
    out[np.arange(sources.size), sources] = 0.0
    return out
