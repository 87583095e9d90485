"""Smooth Shells: axiomatic multi-scale shape registration with functional maps.

Eisenberger, Lähner, Cremers, "Smooth Shells: Multi-Scale Shape Registration with Functional Maps", CVPR 2020
(docs/smooth_shells.md). No training: for a pair (X, Y) with mass-orthonormal eigenbases, a deformation of X's
smooth shells (spectral coefficients ``tau``) and a functional map ``C`` are fitted coarse to fine, alternating
with bidirectional nearest neighbours in a product space of coordinates, normals and the functional-map image
of the eigenfunctions. Pipeline (:func:`smooth_shells`):

1. **Basis features** (:func:`basis_features`): spectral coefficients ``Phi^T A [SHOT, HKS]``, each block divided
   by its joint Frobenius norm over X and Y, then every row (eigen-index) by the mean of its row norms in X
   and Y. They enter the functional-map solve only.
2. **Rigid alignment** (:func:`rigid_alignment`, skipped by ``no_rigid``): the first non-constant spectral
   coordinate of X onto that of Y, an ICP about Y's axis, area-weighted centroids, then surrogate shell runs
   over 2 rotations about X's 3rd principal axis and 4 about its 1st, keeping the lowest residual.
3. **Random-search initialization** (:func:`random_search_init`, "MCMC" in the original): ``num_mcmc``
   perturbations of the 6 lowest spectral coordinates of X, each matched by a surrogate layered run
   (k = 6..20) on farthest-point samples and scored by the area-weighted residual after re-attaching the
   detail; the best supplies ``tau`` (20 x 3) and a fixed 29 x 29 block of ``C``. Proposals run batched.
4. **Layered matching** over the quartic schedule (:func:`k_schedule`: 20, 21, 21, ..., 470, 500) at full
   resolution, with ARAP (weight ``0.02 sqrt(max(k - 20, 0))``) in the ``tau`` solve and area preservation
   (orthogonal ``C``).

One layer of the layered matching: :mod:`shapecorr.axiomatic.smooth_shells.layers`. Modules: ``config``
(hyperparameters, schedule), ``shapes`` (inputs, result, basis features), ``layers``, ``surrogates`` (the short
runs of the rigid stage and the random search), ``rigid``, ``random_search``, ``pipeline`` (:func:`smooth_shells`,
:func:`refine`), ``matcher`` (:class:`SmoothShells` for evaluate.py).

All of it is torch on any device (the precomputed SHOT / HKS come from :mod:`shapecorr.geometry`);
least-squares solves are float64 with the project's relative ridge. Decisions on the ambiguous points of the
original are listed in docs/smooth_shells.md §6.
"""

from shapecorr.axiomatic.smooth_shells.config import (
    K_START,
    MCMC_K_MIN,
    NORMAL_K_MIN,
    RIGID_K_MIN,
    SmoothShellsConfig,
    k_schedule,
)
from shapecorr.axiomatic.smooth_shells.matcher import SmoothShells
from shapecorr.axiomatic.smooth_shells.pipeline import refine, smooth_shells
from shapecorr.axiomatic.smooth_shells.random_search import random_search_init
from shapecorr.axiomatic.smooth_shells.rigid import rigid_alignment
from shapecorr.axiomatic.smooth_shells.shapes import (
    ShellsShape,
    SmoothShellsResult,
    basis_features,
    shape_from_sample,
    shells_shape,
)

__all__ = [
    "K_START",
    "MCMC_K_MIN",
    "NORMAL_K_MIN",
    "RIGID_K_MIN",
    "ShellsShape",
    "SmoothShells",
    "SmoothShellsConfig",
    "SmoothShellsResult",
    "basis_features",
    "k_schedule",
    "random_search_init",
    "refine",
    "rigid_alignment",
    "shape_from_sample",
    "shells_shape",
    "smooth_shells",
]
