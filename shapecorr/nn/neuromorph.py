"""The two networks of NeuroMorph (Eisenberger et al., CVPR 2021; docs/neuromorph.md §3), built on ResnetEC.

* :class:`NeuroMorphFeatureNet`: per-vertex input ``[xyz, vertex normal]`` (6 channels), 128-D output,
  L2-normalized per vertex (the features of the softmax correspondence, :mod:`shapecorr.matching.softmax`).
* :class:`NeuroMorphInterpolator`: per-vertex input ``[x, Pi y - x, t]`` (7 channels), output a displacement
  ``d``; the interpolation is ``X(t) = x + t d(x, Pi y - x, t)``. All time steps run as one batch, whose
  elements differ only in the vertex-constant channel t: the t-independent work runs once
  (:meth:`shapecorr.nn.edgeconv.ResnetEC.forward_separable`).

Time steps (docs/neuromorph.md §5): with T intermediate steps, ``t_i = i / (T + 1)`` for ``i = 1 .. T + 1``, so
the last one is t = 1 (:func:`interpolation_times`).

Both networks take the mesh edges explicitly (``shapecorr.geometry.mesh_graph.undirected_edges``) and hold
no mesh state; they run on the device of their inputs.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from shapecorr.errors import ConfigError, NumericalError
from shapecorr.geometry.normals import vertex_normals
from shapecorr.nn.edgeconv import DEFAULT_HIDDEN, DEFAULT_N_BLOCKS, ResnetEC

#: Feature dimension of the NeuroMorph feature network (NeuroMorph code: 128).
DEFAULT_FEATURE_DIM = 128
#: Norm floor of the feature normalization (only reached by an all-zero feature vector).
FEATURE_NORM_EPS = 1e-12
#: Input channels: xyz + normal (feature net); x, Pi y - x, t (interpolator).
FEATURE_NET_IN = 6
INTERPOLATOR_IN = 7


def _check_finite(t: torch.Tensor, what: str) -> None:
    if not bool(torch.isfinite(t).all()):
        raise NumericalError(f"{what} contains NaN or Inf")


def interpolation_times(
    n_intermediate: int, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
) -> torch.Tensor:
    """Times of the NeuroMorph interpolation: ``i / (T + 1)`` for ``i = 1 .. T + 1``.

    Parameters
    ----------
    n_intermediate : int
        Number T >= 0 of intermediate steps (NeuroMorph schedule: 0, 1, 3, 7).

    Returns
    -------
    (T + 1,) float
        Increasing times in (0, 1], the last equal to 1.
    """
    if n_intermediate < 0:
        raise ConfigError(f"the number of intermediate time steps must be >= 0, got {n_intermediate}")
    steps = n_intermediate + 1
    return torch.arange(1, steps + 1, dtype=dtype, device=device) / steps


class NeuroMorphFeatureNet(nn.Module):
    """Per-vertex features from positions and normals; unit-length rows.

    Parameters
    ----------
    out_channels : int
        Feature dimension (NeuroMorph: 128).
    hidden_channels, n_blocks, pool, residual_init
        See :class:`shapecorr.nn.edgeconv.ResnetEC` (pool "global" by default; "channel" is the original's;
        residual_init "zero" by default, "original" the original's).
    """

    def __init__(
        self,
        out_channels: int = DEFAULT_FEATURE_DIM,
        hidden_channels: int = DEFAULT_HIDDEN,
        n_blocks: int = DEFAULT_N_BLOCKS,
        pool: str = "global",
        residual_init: str = "zero",
    ):
        super().__init__()
        self.net = ResnetEC(FEATURE_NET_IN, out_channels, hidden_channels, n_blocks, pool, residual_init)

    def forward(
        self, verts: torch.Tensor, faces: torch.Tensor, edges: torch.Tensor, fast: bool = True
    ) -> torch.Tensor:
        """Features of one shape.

        Parameters
        ----------
        verts : (n, 3) float
        faces : (f, 3) int64
            For the vertex normals (area-weighted, :func:`shapecorr.geometry.normals.vertex_normals`).
        edges : (E, 2) int64
            Undirected mesh edges.
        fast : bool
            Restructured EdgeConv (default) or the per-edge reference.

        Returns
        -------
        (n, out_channels) float
            L2-normalized rows.
        """
        if verts.ndim != 2 or verts.shape[1] != 3:
            raise ConfigError(f"verts must be (n, 3), got {tuple(verts.shape)}")
        _check_finite(verts, "feature net input vertices")
        inputs = torch.cat((verts, vertex_normals(verts, faces)), dim=-1)
        feat = self.net(inputs, edges, fast=fast)
        _check_finite(feat, "feature net output (diverged weights?)")
        return F.normalize(feat, dim=-1, eps=FEATURE_NORM_EPS)


class NeuroMorphInterpolator(nn.Module):
    """Displacement field of x towards its (soft) image on y, for several times at once.

    Parameters
    ----------
    hidden_channels, n_blocks, pool, residual_init
        See :class:`shapecorr.nn.edgeconv.ResnetEC`.
    """

    def __init__(
        self,
        hidden_channels: int = DEFAULT_HIDDEN,
        n_blocks: int = DEFAULT_N_BLOCKS,
        pool: str = "global",
        residual_init: str = "zero",
    ):
        super().__init__()
        self.net = ResnetEC(INTERPOLATOR_IN, 3, hidden_channels, n_blocks, pool, residual_init)

    def forward(
        self,
        verts_x: torch.Tensor,
        target_x: torch.Tensor,
        edges: torch.Tensor,
        times: torch.Tensor,
        fast: bool = True,
    ) -> torch.Tensor:
        """Displacements ``d(x, target - x, t)`` for every time.

        Parameters
        ----------
        verts_x : (n, 3) float
        target_x : (n, 3) float
            Where each vertex of x should go, e.g. ``Pi_x_to_y @ verts_y``.
        edges : (E, 2) int64
            Undirected edges of x.
        times : (T,) float
        fast : bool
            Restructured EdgeConv (default) or the per-edge reference.

        Returns
        -------
        (T, n, 3) float
        """
        if verts_x.ndim != 2 or verts_x.shape[1] != 3 or target_x.shape != verts_x.shape:
            raise ConfigError(
                f"verts_x and target_x must both be (n, 3), got {tuple(verts_x.shape)} and {tuple(target_x.shape)}"
            )
        if times.ndim != 1 or times.numel() == 0:
            raise ConfigError(f"times must be a non-empty 1-D tensor, got shape {tuple(times.shape)}")
        _check_finite(verts_x, "interpolator input vertices")
        _check_finite(target_x, "interpolator target positions")
        # The inputs of the time steps differ only in the t channel: the network runs the t-independent work
        # once (ResnetEC.forward_separable).
        per_vertex = torch.cat((verts_x, target_x - verts_x), dim=-1)
        disp = self.net.forward_separable(per_vertex, times.to(verts_x).unsqueeze(1), edges, fast=fast)
        _check_finite(disp, "interpolator output (diverged weights?)")
        return disp

    def interpolate(
        self,
        verts_x: torch.Tensor,
        target_x: torch.Tensor,
        edges: torch.Tensor,
        times: torch.Tensor,
        fast: bool = True,
    ) -> torch.Tensor:
        """The interpolation ``X(t) = x + t d(x, target - x, t)`` at the given times.

        Parameters
        ----------
        verts_x, target_x : (n, 3) float
        edges : (E, 2) int64
        times : (T,) float
        fast : bool

        Returns
        -------
        (T, n, 3) float
            Positions of x's vertices at each time (frame ``k`` at ``times[k]``).
        """
        disp = self.forward(verts_x, target_x, edges, times, fast=fast)
        return verts_x + times.to(verts_x).view(-1, 1, 1) * disp
