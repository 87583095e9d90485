"""A shape with what the spectral shell methods need: vertices, faces, eigenbasis, mass, coordinate coefficients.

The container shared by Deep Shells (:mod:`shapecorr.matching.deep_shells`), the G-MSM query and Smooth Shells
(:mod:`shapecorr.axiomatic.smooth_shells`). Pure torch; built by :func:`make_spectral_shape`, which validates the
operators against the mesh.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from shapecorr.errors import InvalidMeshError
from shapecorr.geometry.finiteness import all_finite
from shapecorr.geometry.shells import spectral_coefficients


@dataclass(frozen=True, eq=False)
class SpectralShape:
    """Full-resolution per-shape quantities the shell methods need.

    Attributes
    ----------
    verts : (n, 3) float
    faces : (f, 3) int64
    evecs : (n, K) float
        Mass-orthonormal eigenfunctions, ascending eigenvalues.
    mass : (n,) float
        Lumped vertex areas.
    coeffs : (K, 3) float
        Spectral coefficients of the coordinates, ``evecs^T diag(mass) verts``.
    name : str
    """

    verts: torch.Tensor
    faces: torch.Tensor
    evecs: torch.Tensor
    mass: torch.Tensor
    coeffs: torch.Tensor
    name: str = "shape"

    @property
    def n_verts(self) -> int:
        """Number of vertices."""
        return int(self.verts.shape[0])

    @property
    def n_eigs(self) -> int:
        """Number of eigenfunctions."""
        return int(self.evecs.shape[1])

    def to(self, device: torch.device | str) -> "SpectralShape":
        """Copy with all tensors on ``device``."""
        return replace(self, verts=self.verts.to(device), faces=self.faces.to(device), evecs=self.evecs.to(device),
                       mass=self.mass.to(device), coeffs=self.coeffs.to(device))


def make_spectral_shape(
    verts: torch.Tensor, faces: torch.Tensor, evecs: torch.Tensor, mass: torch.Tensor, name: str = "shape"
) -> SpectralShape:
    """Validate the operators of a shape and precompute its coordinate coefficients.

    Parameters
    ----------
    verts : (n, 3) float
    faces : (f, 3) int
    evecs : (n, K) float
    mass : (n,) float
    name : str
        Used in error messages.

    Returns
    -------
    SpectralShape
    """
    verts = torch.as_tensor(verts)
    faces = torch.as_tensor(faces).to(torch.int64)
    evecs = torch.as_tensor(evecs).to(verts.dtype)
    mass = torch.as_tensor(mass).to(verts.dtype)
    n = verts.shape[0]
    if verts.dim() != 2 or verts.shape[1] != 3 or faces.dim() != 2 or faces.shape[1] != 3:
        raise InvalidMeshError(f"{name}: need verts (n, 3) and faces (f, 3), got {tuple(verts.shape)}, "
                               f"{tuple(faces.shape)}")
    if faces.numel() and (int(faces.min()) < 0 or int(faces.max()) >= n):
        raise InvalidMeshError(f"{name}: face indices out of range for {n} vertices")
    if evecs.dim() != 2 or evecs.shape[0] != n or mass.shape != (n,):
        raise InvalidMeshError(f"{name}: operators do not match the {n} vertices: evecs {tuple(evecs.shape)}, "
                               f"mass {tuple(mass.shape)}")
    for label, t in (("vertices", verts), ("eigenvectors", evecs), ("mass", mass)):
        if not all_finite(t):
            raise InvalidMeshError(f"{name}: the {label} contain NaN or Inf")
    coeffs = spectral_coefficients(evecs, mass, verts)
    return SpectralShape(verts=verts, faces=faces, evecs=evecs, mass=mass, coeffs=coeffs, name=name)


def reorder_vertices(shape: SpectralShape, order: torch.Tensor) -> SpectralShape:
    """The same shape with its vertices renumbered: new vertex ``i`` is old vertex ``order[i]``.

    Parameters
    ----------
    shape : SpectralShape
    order : (n,) int64
        A permutation of the vertices.

    Returns
    -------
    SpectralShape
        Rows of ``verts``, ``evecs``, ``mass`` permuted, ``faces`` renumbered (same face order), ``coeffs`` kept
        (they do not depend on the vertex order).
    """
    n = shape.n_verts
    if order.shape != (n,) or not torch.equal(torch.sort(order).values, torch.arange(n, device=order.device)):
        raise InvalidMeshError(f"{shape.name}: the vertex order must be a permutation of its {n} vertices")
    inverse = torch.empty_like(order)
    inverse[order] = torch.arange(n, device=order.device)
    return replace(shape, verts=shape.verts[order], faces=inverse[shape.faces], evecs=shape.evecs[order],
                   mass=shape.mass[order])
