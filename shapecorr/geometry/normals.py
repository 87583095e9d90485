"""Vertex and face normals (differentiable torch).

Area-weighted vertex normals: the sum of the unnormalized face normals (twice the triangle area times the
unit normal) of the adjacent faces, normalized. This equals libigl's ``per_vertex_normals`` with area
weighting; it is written in torch (one ``index_add_``) because the matching layers need gradients through
the normals of deformed shells, which libigl cannot give.
"""

from __future__ import annotations

import torch

#: Added to norms before division so that isolated / degenerate vertices give a zero normal, not NaN
#: (the Deep Shells / NeuroMorph code uses 1e-5 after scaling edges by 1e4, i.e. the same relative size).
NORMAL_EPS = 1e-12


def face_normals(verts: torch.Tensor, faces: torch.Tensor, normalize: bool = True) -> torch.Tensor:
    """Face normals.

    Parameters
    ----------
    verts : (n, 3) float
    faces : (f, 3) int64
    normalize : bool
        Unit normals (True) or cross products whose length is twice the triangle area (False).

    Returns
    -------
    (f, 3) float
    """
    v0, v1, v2 = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    n = torch.linalg.cross(v1 - v0, v2 - v0, dim=-1)
    if normalize:
        n = n / (n.norm(dim=-1, keepdim=True) + NORMAL_EPS)
    return n


def vertex_normals(verts: torch.Tensor, faces: torch.Tensor, eps: float = NORMAL_EPS) -> torch.Tensor:
    """Area-weighted unit vertex normals.

    Parameters
    ----------
    verts : (n, 3) float
    faces : (f, 3) int64
    eps : float
        Added to the norm before normalizing; vertices in no face get the zero vector.

    Returns
    -------
    (n, 3) float
    """
    fn = face_normals(verts, faces, normalize=False)
    acc = torch.zeros_like(verts)
    for c in range(3):
        acc = acc.index_add(0, faces[:, c], fn)
    # Scale-free normalization: divide by the norm relative to the mean face size so eps is meaningful for
    # any unit of length.
    return acc / (acc.norm(dim=-1, keepdim=True) + eps * fn.norm(dim=-1).mean().clamp_min(1e-30))
