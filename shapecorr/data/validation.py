"""Checks on mesh arrays, shared by the readers in :mod:`shapecorr.data.io` and by the datasets.

Two levels:

* :func:`check_mesh_arrays` checks only the structure: array shapes, dtypes, finite coordinates, face
  indices in range. Every mesh that enters or leaves shapecorr must pass it (``write_mesh`` uses it too).
* :func:`validate_mesh` adds the checks that the spectral pipeline needs (a cotangent Laplacian with a
  lumped mass matrix): no face repeating a vertex, no unreferenced vertex (zero mass), at most a small
  fraction of zero-area faces. Those problems raise :class:`~shapecorr.errors.InvalidMeshError`.

Properties that real meshes often have and that most methods tolerate (non-manifold edges or vertices,
several connected components, a few degenerate faces, duplicate faces) emit a :class:`MeshWarning` naming the
file and the mesh still loads: a method that cannot handle them must refuse them itself.

Every relaxation is an option of :class:`ValidationOptions`, set from the command line as
``data.validation.<name>=<value>`` (``configs/data/folder.yaml``); each error names the file and the option
that relaxes it (:data:`CLI_PREFIX`).

Degenerate faces. A face counts as degenerate when its area is at most ``degenerate_tol`` times the mean
face area of the mesh (relative, so the test does not depend on the units). Remeshed scans contain a few
such slivers, so the mesh is rejected only when more than ``max_degenerate_fraction`` of its faces are
degenerate; fewer produce a warning. A face that repeats a vertex index is always rejected: it is a
connectivity error, not a sliver.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from os import PathLike

import igl
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from shapecorr.errors import ConfigError, InvalidMeshError
from shapecorr.geometry.mesh import check_mesh_arrays
from shapecorr.geometry.mesh import format_indices as _listing

#: A face is degenerate when area <= DEFAULT_DEGENERATE_TOL * mean face area. Project choice (no published
#: value): 1e-12 relative area is far below any sliver a remesher produces on purpose and well above
#: float64 round-off of a genuinely flat triangle (~1e-16 relative).
DEFAULT_DEGENERATE_TOL = 1e-12

#: Largest fraction of degenerate faces accepted (with a warning). Project choice: 1e-3 lets through the
#: handful of slivers found in remeshed scans (10 faces of a 10k-face FAUST_r shape) but rejects meshes
#: whose Laplacian would be dominated by them.
DEFAULT_MAX_DEGENERATE_FRACTION = 1e-3

#: Where the validation options live in the data config (named in error messages).
CLI_PREFIX = "data.validation."


@dataclass(frozen=True)
class ValidationOptions:
    """How strictly meshes are checked on load (``data.validation.*``; see the module docstring).

    Attributes
    ----------
    max_degenerate_fraction
        Largest fraction of zero-area faces accepted (with a warning); more raises.
    degenerate_tol
        A face is zero-area when its area is at most this times the mean face area.
    allow_unreferenced
        Accept vertices no face uses (with a warning; they get zero mass).
    allow_disconnected
        Accept several connected components (with a warning); the evaluation then computes geodesics per
        component and excludes reference points on small islands (counted in ``metrics.json``). False raises.
    laplacian_fallback
        Where the cotangent Laplacian has infinite weights (zero-area faces), use the robust Laplacian for
        that shape, with a warning naming the file. False raises.
    """

    max_degenerate_fraction: float = DEFAULT_MAX_DEGENERATE_FRACTION
    degenerate_tol: float = DEFAULT_DEGENERATE_TOL
    allow_unreferenced: bool = False
    allow_disconnected: bool = True
    laplacian_fallback: bool = True

    def __post_init__(self):
        if not 0.0 <= float(self.max_degenerate_fraction) <= 1.0:
            raise ConfigError(
                f"{CLI_PREFIX}max_degenerate_fraction must be in [0, 1], got {self.max_degenerate_fraction}"
            )
        if not float(self.degenerate_tol) >= 0.0:
            raise ConfigError(f"{CLI_PREFIX}degenerate_tol must be >= 0, got {self.degenerate_tol}")


class MeshWarning(UserWarning):
    """A mesh has a property some methods cannot handle (non-manifold, several components, slivers)."""


def _where(path: str | PathLike | None) -> str:
    return f"{path}: " if path is not None else ""


def non_manifold_edges(faces: np.ndarray) -> np.ndarray:
    """Undirected edges shared by more than two faces.

    Parameters
    ----------
    faces : (f, 3) int

    Returns
    -------
    (e, 2) int64
        Each edge as (smaller index, larger index), sorted.
    """
    f = np.asarray(faces, dtype=np.int64)
    edges = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    # One int64 code per undirected edge: a 1-D unique is much faster than unique(axis=0).
    base = int(f.max()) + 1 if f.size else 1
    codes, counts = np.unique(edges[:, 0] * base + edges[:, 1], return_counts=True)
    shared = codes[counts > 2]
    return np.stack([shared // base, shared % base], axis=1)


def duplicate_faces(faces: np.ndarray) -> np.ndarray:
    """Faces using the same three vertices as an earlier face (in any order).

    Parameters
    ----------
    faces : (f, 3) int

    Returns
    -------
    (d,) int64
        Indices of the repeats (the first occurrence is not listed).
    """
    f = np.sort(np.asarray(faces, dtype=np.int64), axis=1)
    _, first = np.unique(f, axis=0, return_index=True)
    repeats = np.ones(len(f), dtype=bool)
    repeats[first] = False
    return np.flatnonzero(repeats)


def _fraction_needed(count: int, total: int) -> str:
    """A round fraction just above ``count / total`` (for the option value an error suggests)."""
    needed = count / max(total, 1)
    return f"{float(f'{needed * 1.5:.1g}'):g}" if needed > 0 else "0"


def validate_mesh(
    verts: np.ndarray,
    faces: np.ndarray,
    path: str | PathLike | None = None,
    degenerate_tol: float = DEFAULT_DEGENERATE_TOL,
    max_degenerate_fraction: float = DEFAULT_MAX_DEGENERATE_FRACTION,
    allow_unreferenced: bool = False,
    allow_disconnected: bool = True,
) -> list[str]:
    """Check that a triangle mesh is usable by the spectral pipeline.

    Parameters
    ----------
    verts : (n, 3) float
    faces : (f, 3) int
        Zero-based triangles.
    path
        File the mesh came from, named in errors and warnings.
    degenerate_tol
        A face is degenerate when its area is at most ``degenerate_tol`` times the mean face area.
    max_degenerate_fraction
        Largest fraction of degenerate faces accepted (with a warning); more raises.
    allow_unreferenced
        Accept vertices that no face uses (with a warning) instead of raising.
    allow_disconnected
        Accept several connected components (with a warning) instead of raising.

    Returns
    -------
    list[str]
        The messages emitted as :class:`MeshWarning` (prefixed with the path), empty for a clean mesh.

    Raises
    ------
    InvalidMeshError
        Structure errors (see :func:`check_mesh_arrays`), a face repeating a vertex index, unreferenced
        vertices (unless allowed), too many degenerate faces.
    """
    v, f = check_mesh_arrays(verts, faces, path)
    n = v.shape[0]
    messages: list[str] = []

    repeated = np.flatnonzero((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0]))
    if len(repeated):
        raise InvalidMeshError(
            f"{len(repeated)} faces repeat a vertex index (face {_listing(repeated)}, zero-based; "
            f"first is {f[repeated[0]].tolist()})",
            path,
        )

    referenced = np.zeros(n, dtype=bool)
    referenced[f.ravel()] = True
    unreferenced = np.flatnonzero(~referenced)
    if len(unreferenced):
        message = (
            f"{len(unreferenced)} of {n} vertices are not used by any face (vertex {_listing(unreferenced)}, "
            "zero-based)"
        )
        if not allow_unreferenced:
            hint = (f"; they would get zero mass: remove them, or accept them with {CLI_PREFIX}allow_unreferenced=true "
                    "(Python: allow_unreferenced=True)")
            raise InvalidMeshError(message + hint, path)
        messages.append(message)

    tri = v[f]
    areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    degenerate = np.flatnonzero(areas <= degenerate_tol * areas.mean())
    if len(degenerate):
        message = (
            f"{len(degenerate)} of {len(f)} faces are degenerate (area <= {degenerate_tol:g} x mean face area; "
            f"face {_listing(degenerate)}, zero-based)"
        )
        if len(degenerate) > max_degenerate_fraction * len(f):
            raise InvalidMeshError(
                message + f", more than the allowed fraction {max_degenerate_fraction:g}; accept them with "
                f"{CLI_PREFIX}max_degenerate_fraction={_fraction_needed(len(degenerate), len(f))} (the robust "
                "Laplacian is used where cotangent weights become infinite) or clean the mesh",
                path,
            )
        messages.append(message)

    duplicates = duplicate_faces(f)
    if len(duplicates):
        messages.append(
            f"{len(duplicates)} duplicate faces (the same three vertices as an earlier face; face "
            f"{_listing(duplicates)}, zero-based): they make their edges look non-manifold"
        )

    bad_edges = non_manifold_edges(f)
    if len(bad_edges):
        messages.append(
            f"{len(bad_edges)} non-manifold edges (shared by more than two faces; first is {bad_edges[0].tolist()})"
        )

    # igl reports unreferenced vertices as non-manifold too (zero incident face fans): mask them out.
    # Its output has max(faces) + 1 entries, not n.
    vertex_ok = np.ones(n, dtype=bool)
    flags = np.asarray(igl.is_vertex_manifold(np.ascontiguousarray(f)), dtype=bool)
    vertex_ok[: len(flags)] = flags
    bad_verts = np.flatnonzero(~vertex_ok & referenced)
    if len(bad_verts):
        messages.append(
            f"{len(bad_verts)} non-manifold vertices (their faces form more than one fan; vertex "
            f"{_listing(bad_verts)}, zero-based)"
        )

    rows = f[:, [0, 1, 2]].ravel()
    cols = f[:, [1, 2, 0]].ravel()
    adjacency = sp.coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n, n))
    _, labels = connected_components(adjacency, directed=False)
    sizes = np.bincount(labels[referenced])
    sizes = np.sort(sizes[sizes > 0])[::-1]
    if len(sizes) > 1:
        message = f"mesh has {len(sizes)} connected components (vertex counts {_listing(sizes)})"
        if not allow_disconnected:
            raise InvalidMeshError(
                message + f"; accept it with {CLI_PREFIX}allow_disconnected=true (geodesics per component, "
                "reference points on the smaller components excluded from the errors)",
                path,
            )
        messages.append(message + "; geodesics are computed per component and reference points on the smaller "
                        "ones are excluded from the geodesic errors")

    messages = [f"{_where(path)}{message}" for message in messages]
    for message in messages:
        warnings.warn(message, MeshWarning, stacklevel=2)
    return messages
