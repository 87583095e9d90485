"""Mesh arrays at the bottom of the stack: conversion to numpy, structure checks, triangle areas.

Everything above :mod:`shapecorr.geometry` (data, eval, viz) uses these; they import nothing from shapecorr
except :mod:`shapecorr.errors`, so the geometry layer stays free of the data layer (see the import contracts
in ``pyproject.toml``).
"""

from __future__ import annotations

from os import PathLike

import numpy as np

from shapecorr.errors import CorrespondenceError, InvalidMeshError

#: How many offending indices an error or warning message lists before "...".
MAX_LISTED_INDICES = 5


def as_numpy(a, dtype=None) -> np.ndarray:
    """NumPy view of an array or of a torch tensor, without importing torch here.

    Tensors on any device, grad-tracking or not, are detached and copied to the CPU.

    Parameters
    ----------
    a : array-like or torch.Tensor
    dtype : numpy dtype, optional
        Convert to it (no copy when it already has it).

    Returns
    -------
    numpy.ndarray
    """
    if hasattr(a, "detach"):
        a = a.detach().cpu().numpy()
    return np.asarray(a) if dtype is None else np.asarray(a, dtype=dtype)


def format_indices(indices: np.ndarray) -> str:
    """The first :data:`MAX_LISTED_INDICES` of ``indices`` as ``"3, 7, 9, ..."`` for error messages."""
    shown = ", ".join(str(int(i)) for i in indices[:MAX_LISTED_INDICES])
    return shown + (", ..." if len(indices) > MAX_LISTED_INDICES else "")


def triangle_areas(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Areas of the triangles.

    Parameters
    ----------
    verts : (n, 3) float
    faces : (f, 3) int

    Returns
    -------
    (f,) float64
    """
    v = np.asarray(verts, dtype=np.float64)
    tri = v[np.asarray(faces)]
    return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)


def check_index(idx, n: int, what: str) -> np.ndarray:
    """Check a vertex index array against a vertex count.

    Parameters
    ----------
    idx : (m,) int
        Zero-based vertex indices (numpy array or torch tensor).
    n : int
        Vertex count of the shape the indices point into.
    what : str
        Name of the array in error messages.

    Returns
    -------
    (m,) int64

    Raises
    ------
    CorrespondenceError
        Not 1-D, not integer, or an index outside ``[0, n)``.
    """
    idx = as_numpy(idx)
    if idx.ndim != 1:
        raise CorrespondenceError(f"{what} must be a 1-D index array, got shape {idx.shape}")
    if idx.size and not np.issubdtype(idx.dtype, np.integer):
        raise CorrespondenceError(f"{what} must hold integer vertex indices, got dtype {idx.dtype}")
    idx = idx.astype(np.int64, copy=False)
    if idx.size and (idx.min() < 0 or idx.max() >= n):
        raise CorrespondenceError(
            f"{what} has indices in [{idx.min()}, {idx.max()}] but the shape has {n} vertices (valid: 0..{n - 1})"
        )
    return idx


def check_mesh_arrays(
    verts: np.ndarray, faces: np.ndarray, path: str | PathLike | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Check the structure of a triangle mesh and return it as float64 / int64 arrays.

    Parameters
    ----------
    verts : (n, 3) float
        Vertex positions; must be finite.
    faces : (f, 3) int
        Zero-based triangle indices in ``[0, n)``.
    path
        File the mesh came from, named in error messages.

    Returns
    -------
    verts : (n, 3) float64
    faces : (f, 3) int64

    Raises
    ------
    InvalidMeshError
        Empty arrays, wrong shapes or dtypes, NaN/Inf coordinates, face indices out of range.
    """
    v = np.asarray(verts)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise InvalidMeshError(f"vertices must have shape (n, 3), got {v.shape}", path)
    if f.ndim != 2 or f.shape[1] != 3:
        raise InvalidMeshError(f"faces must have shape (f, 3) (triangles), got {f.shape}", path)
    if v.shape[0] == 0:
        raise InvalidMeshError("mesh has no vertices", path)
    if f.shape[0] == 0:
        raise InvalidMeshError("mesh has no faces", path)
    if v.dtype.kind not in "fiu":
        raise InvalidMeshError(f"vertices must be numeric, got dtype {v.dtype}", path)
    if f.dtype.kind not in "iu":
        raise InvalidMeshError(f"faces must be integers, got dtype {f.dtype}", path)
    v = v.astype(np.float64, copy=False)
    bad_rows = np.flatnonzero(~np.isfinite(v).all(axis=1))
    if len(bad_rows):
        raise InvalidMeshError(
            f"{len(bad_rows)} vertices have NaN/Inf coordinates (vertex {format_indices(bad_rows)}, zero-based)",
            path,
        )
    n = v.shape[0]
    bad_faces = np.flatnonzero(((f < 0) | (f >= n)).any(axis=1))
    if len(bad_faces):
        first = f[bad_faces[0]].tolist()
        raise InvalidMeshError(
            f"{len(bad_faces)} faces have a vertex index outside [0, {n}) (face {format_indices(bad_faces)}, "
            f"zero-based; first is {first})",
            path,
        )
    return v, f.astype(np.int64, copy=False)
