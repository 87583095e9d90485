"""Inputs and outputs of Smooth Shells: one shape, the result of a pair, and the pair's basis features."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from shapecorr.errors import ConfigError, InvalidMeshError, NumericalError
from shapecorr.geometry.descriptors import hks
from shapecorr.geometry.laplace_beltrami import ORIGINAL_EIGENVALUE_FACTOR
from shapecorr.geometry.shells import spectral_coefficients
from shapecorr.geometry.spectral_shape import SpectralShape, make_spectral_shape


#: HKS of the basis features: 200 eigenpairs (without the constant), 100 times log-spaced in
#: [0.002, 0.05] in the original (doubled) eigenvalue scale.
HKS_NUM_EIGS = 200
HKS_NUM_TIMES = 100
HKS_T_MIN = 0.002
HKS_T_MAX = 0.05


@dataclass(frozen=True, eq=False)
class ShellsShape:
    """One shape with what Smooth Shells needs.

    Attributes
    ----------
    spectral : SpectralShape
        Vertices, faces, eigenfunctions (mass-orthonormal), mass, coordinate coefficients.
    evals : (K,) float
        Eigenvalues in shapecorr's scale (half of the original's; CONVENTIONS.md).
    shot : (n, c) float or None
        SHOT descriptors (for the basis features); None disables the descriptor term.
    """

    spectral: SpectralShape
    evals: torch.Tensor
    shot: torch.Tensor | None = None

    @property
    def name(self) -> str:
        """Name of the underlying spectral shape."""
        return self.spectral.name


def shells_shape(verts, faces, evals, evecs, mass, shot=None, name: str = "shape") -> ShellsShape:
    """Validate and bundle one shape.

    Parameters
    ----------
    verts : (n, 3) float
    faces : (f, 3) int
    evals : (K,) float
        Ascending eigenvalues (shapecorr scale).
    evecs : (n, K) float
        Mass-orthonormal eigenfunctions.
    mass : (n,) float
    shot : (n, c) float, optional
    name : str
        For error messages.

    Returns
    -------
    ShellsShape
    """
    spectral = make_spectral_shape(verts, faces, evecs, mass, name=name)
    evals = torch.as_tensor(evals).to(device=spectral.verts.device, dtype=spectral.verts.dtype)
    if evals.shape != (spectral.n_eigs,):
        raise InvalidMeshError(f"{name}: {spectral.n_eigs} eigenfunctions but evals of shape {tuple(evals.shape)}")
    if shot is not None:
        shot = torch.as_tensor(shot).to(device=spectral.verts.device, dtype=spectral.verts.dtype)
        if shot.dim() != 2 or shot.shape[0] != spectral.n_verts:
            raise InvalidMeshError(f"{name}: SHOT must be ({spectral.n_verts}, c), got {tuple(shot.shape)}")
        if not torch.isfinite(shot).all():
            raise NumericalError(f"{name}: the SHOT descriptor contains NaN or Inf")
    return ShellsShape(spectral=spectral, evals=evals, shot=shot)


def shape_from_sample(sample, need_shot: bool = True) -> ShellsShape:
    """:class:`ShellsShape` from a data-pipeline ``ShapeSample`` (verts, faces, evals, evecs, mass, SHOT)."""
    shot = sample.features.get("shot") if need_shot else None
    if need_shot and shot is None:
        raise ConfigError(f"shape {sample.name!r} has no 'shot' descriptor; add it to data.operators.request "
                          "(e.g. +data.operators.request={shot:{}})")
    return shells_shape(sample.verts, sample.faces, sample.evals, sample.evecs, sample.mass, shot=shot,
                        name=sample.name)


@dataclass(frozen=True, eq=False)
class SmoothShellsResult:
    """Output of :func:`smooth_shells` / :func:`refine`.

    Attributes
    ----------
    map_x_to_y : (n_x,) int64
    map_y_to_x : (n_y,) int64
    tau : (k_max, 3) float
        Spectral deformation coefficients of X (aligned) after the last layer.
    fmap : (k', k') float
        Functional map of the last layer (``Phi_X C ~ Phi_Y``), k' = k_max + 9.
    deformed_x : (n_x, 3) float
        ``X* = X_aligned + Phi_X tau``: X (with its detail) deformed onto Y.
    aligned_x : (n_x, 3) float
        X after the rigid stage (equal to X with ``no_rigid`` or in :func:`refine`).
    rotation : (3, 3) float
        Rigid stage: ``aligned_x = x @ rotation.T + translation``.
    translation : (3,) float
    k_array : tuple of int
        Shell sizes of the layered matching that ran.
    level_objectives : (L, 2) float64
        Per layer: the ``tau`` objective (data + ARAP, with that layer's pairs and rotations) before and after
        the layer's solve; the second column never exceeds the first.
    mcmc_scores : (num_mcmc,) float64 or None
        Score of every random-search proposal (lower is better).
    rigid_scores : list of (c,) float64
        Scores of the rigid candidates, per surrogate set.
    """

    map_x_to_y: torch.Tensor
    map_y_to_x: torch.Tensor
    tau: torch.Tensor
    fmap: torch.Tensor
    deformed_x: torch.Tensor = field(repr=False)
    aligned_x: torch.Tensor = field(repr=False)
    rotation: torch.Tensor
    translation: torch.Tensor
    k_array: tuple[int, ...]
    level_objectives: torch.Tensor
    mcmc_scores: torch.Tensor | None = None
    rigid_scores: list = field(default_factory=list)


def basis_features(x: ShellsShape, y: ShellsShape) -> tuple[torch.Tensor, torch.Tensor]:
    """Spectral coefficients of [SHOT, HKS], normalized as in the original (module docstring, step 1).

    HKS: :func:`shapecorr.geometry.descriptors.hks` with 200 eigenpairs (the constant skipped) and 100 times
    log-spaced in [0.002, 0.05] of the original eigenvalue scale (ours times ``ORIGINAL_EIGENVALUE_FACTOR``).

    Returns
    -------
    feat_x : (K_x, c + 100) float
    feat_y : (K_y, c + 100) float
        Truncated to the common ``K = min(K_x, K_y)`` rows.
    """
    if x.shot is None or y.shot is None:
        raise ConfigError(f"basis features need SHOT on both shapes ({x.name}, {y.name}); set lambda_feat=0 "
                          "or compute the 'shot' descriptor")
    blocks_x, blocks_y = [], []
    k = min(x.spectral.n_eigs, y.spectral.n_eigs)
    for desc_x, desc_y in ((x.shot, y.shot), (_hks(x), _hks(y))):
        cx = spectral_coefficients(x.spectral.evecs[:, :k], x.spectral.mass, desc_x).to(torch.float64)
        cy = spectral_coefficients(y.spectral.evecs[:, :k], y.spectral.mass, desc_y).to(torch.float64)
        norm = torch.sqrt(cx.square().sum() + cy.square().sum())
        if not norm > 0:
            which = "SHOT" if desc_x is x.shot else "HKS"
            hint = (" (SHOT support radius too small for this mesh resolution? raise "
                    "data.operators.params.shot.radius_factor, e.g. to 0.25 on a few hundred vertices)"
                    if which == "SHOT" else "")
            raise NumericalError(f"basis features of {x.name}, {y.name}: the {which} descriptor is zero on both "
                                 f"shapes{hint}; or set model.lambda_feat=0 to match without features")
        blocks_x.append(cx / norm)
        blocks_y.append(cy / norm)
    fx, fy = torch.cat(blocks_x, 1), torch.cat(blocks_y, 1)
    row = 0.5 * (fx.norm(dim=1) + fy.norm(dim=1))
    row = torch.where(row > 0, row, torch.ones_like(row))
    return (fx / row[:, None]).to(x.spectral.evecs.dtype), (fy / row[:, None]).to(y.spectral.evecs.dtype)


def _hks(s: ShellsShape) -> torch.Tensor:
    k = min(HKS_NUM_EIGS, s.spectral.n_eigs)
    evals = ORIGINAL_EIGENVALUE_FACTOR * s.evals[:k].detach().cpu().double().clamp_min(0).numpy()
    values = hks(evals, s.spectral.evecs[:, :k].detach().cpu().double().numpy(), t_min=HKS_T_MIN, t_max=HKS_T_MAX,
                 n_times=HKS_NUM_TIMES, normalize="none")
    return torch.from_numpy(values).to(device=s.spectral.evecs.device, dtype=s.spectral.evecs.dtype)
