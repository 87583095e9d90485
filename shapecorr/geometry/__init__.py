"""Geometry core: pure functions on meshes.

Precomputation (numpy in/out, float64): :func:`laplacian`, :func:`eigenbasis`, :func:`hks`, :func:`wks`,
:func:`shot`, :func:`geodesic_distances`, :func:`farthest_point_sampling`, :func:`remesh`.
Differentiable (torch): :func:`spectral_coefficients`, :func:`smooth_shell`, :func:`sigmoid_shell_weights`,
:func:`vertex_normals`, :func:`face_normals`.
"""

from shapecorr.geometry.descriptors import hks, wks
from shapecorr.geometry.geodesics import geodesic_distances
from shapecorr.geometry.laplace_beltrami import ORIGINAL_EIGENVALUE_FACTOR, eigenbasis, laplacian
from shapecorr.geometry.normals import face_normals, vertex_normals
from shapecorr.geometry.remeshing import remesh
from shapecorr.geometry.sampling import farthest_point_sampling
from shapecorr.geometry.shells import sigmoid_shell_weights, smooth_shell, spectral_coefficients
from shapecorr.geometry.shot_descriptor import shot

__all__ = [
    "ORIGINAL_EIGENVALUE_FACTOR",
    "eigenbasis",
    "face_normals",
    "farthest_point_sampling",
    "geodesic_distances",
    "hks",
    "laplacian",
    "remesh",
    "shot",
    "sigmoid_shell_weights",
    "smooth_shell",
    "spectral_coefficients",
    "vertex_normals",
    "wks",
]
