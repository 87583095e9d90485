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

Distances from a few sources (evaluation, large scans): :func:`geodesic_distances_from` returns the rows
``(s, n)`` float32 for ``s`` sources only, building one heat-method solver (one factorization) per connected
component and reusing it for every source, one row at a time into a preallocated float32 array: memory
``O(s n)`` plus one solver, never ``n^2``. :class:`SourceDistances` holds such rows with their sources and
answers ``d(source, target)`` lookups. The evaluation protocol only needs distances from the target's
ground-truth points (``e_r = d_Y(p(gx[r]), gy[r])`` is row ``gy[r]``), so a 150k-vertex scan with R reference
points costs ``4 R n`` bytes instead of ``8 n^2``. The rows are not symmetrized: the heat method's
``D[a, b]`` and ``D[b, a]`` differ slightly, so errors read from rows differ from errors read from the
symmetrized all-pairs matrix by the method's asymmetry: on 20 FAUST_r pairs (``descriptor_nn``) the mean error
moves by 0.006 %, at most 0.05 % per pair (``benchmarks/geodesic_rows_parity.py``).
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import igl
import numpy as np
import potpourri3d as pp3d
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from shapecorr.errors import ConfigError, InvalidMeshError, NumericalError
from shapecorr.geometry.laplace_beltrami import mesh_arrays
from shapecorr.geometry.memory import check_fits
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
    if n_jobs < 1:
        raise ConfigError(f"n_jobs must be >= 1, got {n_jobs}")
    all_pairs = sources is None
    v, f, src, n_comp, labels = _checked_inputs(verts, faces, sources, method, allow_disconnected)
    n = v.shape[0]

    if all_pairs:
        # the float64 matrix and the transposed copy of the symmetrization
        check_fits(2 * 8 * n * n, f"the all-pairs geodesic matrix of a {n}-vertex mesh",
                   "compute distances from the needed sources only (geodesic_distances_from), or work at a "
                   "lower resolution (e.g. NeuroMorph: model.query_resolution)")
    D = np.full((src.size, n), np.inf)
    for rows, members, sub_v, sub_f, local in _components_of_sources(v, f, src, n_comp, labels):
        if sub_f is None:  # an isolated vertex
            D[rows, src[rows]] = 0.0
            continue
        block = _distances_parallel(sub_v, sub_f, local, method, t_coef, robust, n_jobs)
        if members is None:
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


def _components_of_sources(v, f, src, n_comp: int, labels):
    """Per connected component holding a source: ``(rows, members, sub_v, sub_f, local)``.

    ``rows``: positions in ``src`` of its sources; ``members``: its vertices (None for a connected mesh, whose
    single component is the whole mesh); ``sub_v, sub_f``: the component as its own mesh (``sub_f`` None for
    an isolated vertex); ``local``: its sources in the component's numbering.
    """
    face_comp = labels[f[:, 0]]
    for comp in np.unique(labels[src]):
        rows = np.flatnonzero(labels[src] == comp)
        comp_faces = f[face_comp == comp]
        if comp_faces.shape[0] == 0:
            yield rows, None, None, None, None
        elif n_comp == 1:
            yield rows, None, v, f, src[rows]
        else:
            members = np.flatnonzero(labels == comp)
            remap = np.full(v.shape[0], -1, dtype=np.int64)
            remap[members] = np.arange(members.size)
            yield rows, members, v[members], remap[comp_faces], remap[src[rows]]


def _checked_inputs(verts, faces, sources, method: str, allow_disconnected: bool):
    """Checked ``(v, f, sources (s,) int64, n_components, labels)``; ``sources=None`` means every vertex."""
    v, f = mesh_arrays(verts, faces)
    n = v.shape[0]
    if method not in GEODESIC_METHODS:
        raise ConfigError(f"geodesic method must be one of {GEODESIC_METHODS}, got {method!r}")
    src = np.arange(n) if sources is None else np.atleast_1d(_as_numpy(sources)).astype(np.int64).ravel()
    if src.size and (src.min() < 0 or src.max() >= n):
        raise ConfigError(f"source indices must be in [0, {n}), got min {src.min()}, max {src.max()}")
    n_comp, labels = vertex_components(n, f)
    if n_comp > 1 and not allow_disconnected:
        sizes = np.bincount(labels)
        raise InvalidMeshError(
            f"mesh has {n_comp} connected components (sizes {sorted(sizes.tolist(), reverse=True)[:5]}...); "
            "geodesic distances between them are infinite: pass allow_disconnected=True to get inf there "
            "(evaluation: data.validation.allow_disconnected=true)"
        )
    return v, f, src, n_comp, labels


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
    for a, row in enumerate(_rows_in_component(v, f, sources, method, t_coef, robust)):
        out[a] = row
    return out


def geodesic_distances_from(
    verts,
    faces,
    sources,
    method: str = "heat",
    t_coef: float = HEAT_T_COEF,
    robust: bool = True,
    allow_disconnected: bool = True,
) -> np.ndarray:
    """Geodesic distances from a few source vertices to every vertex, in float32, memory ``O(s n)``.

    One solver (one factorization) is built per connected component holding a source and reused for all
    its sources; rows are computed one source at a time straight into the float32 output, so nothing of
    size ``n^2`` (nor a float64 copy of the output) is ever allocated.

    Parameters
    ----------
    verts : (n, 3) float
    faces : (f, 3) int
    sources : (s,) int
        Source vertex indices (repeats allowed; each gets its own row).
    method : {"heat", "exact"}
    t_coef : float
        Heat method time step in units of the squared mean edge length.
    robust : bool
        Heat method on the intrinsic Delaunay tufted cover (potpourri3d's ``use_robust``).
    allow_disconnected : bool
        With several components, distances to the other components are ``inf`` (default); False raises.

    Returns
    -------
    (s, n) float32
        ``D[a, j]`` is the distance from ``sources[a]`` to vertex ``j`` (not symmetrized); ``D[a, sources[a]]``
        is 0; ``inf`` across components.

    Raises
    ------
    InvalidMeshError
        Invalid arrays, or several components without ``allow_disconnected``.
    ConfigError
        Unknown method, sources out of range.
    NumericalError
        The solver returned NaN/Inf inside a component.
    """
    v, f, src, n_comp, labels = _checked_inputs(verts, faces, sources, method, allow_disconnected)
    n = v.shape[0]
    out = np.full((src.size, n), np.inf, dtype=np.float32)
    for rows, members, sub_v, sub_f, local in _components_of_sources(v, f, src, n_comp, labels):
        if sub_f is None:  # an isolated vertex
            out[rows, src[rows]] = 0.0
            continue
        for row, d in zip(rows, _rows_in_component(sub_v, sub_f, local, method, t_coef, robust)):
            if members is None:
                out[row] = d
            else:
                out[row, members] = d
    return out


def _rows_in_component(v, f, sources, method: str, t_coef: float, robust: bool):
    """Yield the distance row ``(n_c,)`` float64 of each source inside one connected component."""
    if method == "heat":
        solver = pp3d.MeshHeatMethodDistanceSolver(v, f, t_coef=t_coef, use_robust=robust)
        solve = lambda s: solver.compute_distance(int(s))  # noqa: E731
    else:
        targets = np.arange(v.shape[0], dtype=np.int64)
        no_faces = np.zeros(0, dtype=np.int64)
        solve = lambda s: igl.exact_geodesic(  # noqa: E731
            v, f, np.array([s], dtype=np.int64), no_faces, targets, no_faces
        )
    for s in sources:
        d = np.asarray(solve(s), dtype=np.float64)
        if not np.isfinite(d).all():
            raise NumericalError(f"{method} geodesic solver returned NaN/Inf inside a connected component")
        np.maximum(d, 0.0, out=d)  # the heat method can give tiny negative values next to the source
        d[int(s)] = 0.0
        yield d


@dataclass(frozen=True, eq=False)
class SourceDistances:
    """Geodesic distances from a set of source vertices of one shape.

    Attributes
    ----------
    sources : (s,) int64
        Sorted, unique source vertices.
    rows : (s, n) float32
        ``rows[a, j]`` = distance from ``sources[a]`` to vertex ``j``.
    """

    sources: np.ndarray
    rows: np.ndarray

    @property
    def n_verts(self) -> int:
        """Number of vertices of the shape (columns of the rows)."""
        return int(self.rows.shape[1])

    def row_index(self, vertices) -> np.ndarray:
        """Row of each vertex of ``vertices (R,)`` int; raises ConfigError for a vertex that is no source."""
        vertices = np.asarray(vertices, dtype=np.int64)
        pos = np.searchsorted(self.sources, vertices)
        pos = np.minimum(pos, max(self.sources.size - 1, 0))
        bad = self.sources.size == 0 or not np.array_equal(self.sources[pos], vertices)
        if bad:
            missing = np.setdiff1d(vertices, self.sources)[:5].tolist()
            raise ConfigError(f"no geodesic row for vertices {missing}: they are not among the sources")
        return pos

    def lookup(self, sources, targets) -> np.ndarray:
        """``d(sources[r], targets[r])`` for ``(R,)`` int arrays, as float64 ``(R,)``."""
        return self.rows[self.row_index(sources), np.asarray(targets, dtype=np.int64)].astype(np.float64)


def distances_from_sources(verts, faces, sources, method: str = "heat") -> SourceDistances:
    """:class:`SourceDistances` for the unique ``sources (s,) int`` of a mesh (:func:`geodesic_distances_from`)."""
    unique = np.unique(np.asarray(sources, dtype=np.int64))
    return SourceDistances(unique, geodesic_distances_from(verts, faces, unique, method=method))
