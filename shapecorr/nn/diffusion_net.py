"""DiffusionNet and its backbone.

Sharp, Attaiki, Crane & Ovsjanikov, "DiffusionNet: Discretization Agnostic Learning on Surfaces", ACM ToG
2022.

The network maps per-vertex input features ``x (n, C_in)`` to per-vertex features ``(n, C_out)``:

1. ``x <- x W_in + b`` (width ``W``);
2. ``n_blocks`` times ``x <- x + MLP([x, h, g])`` with
   - ``h = Phi diag(exp(-lambda t_c)) Phi^T M x_c``: spectral heat diffusion of each channel ``c`` for its own
     learned time ``t_c >= 0`` (paper §3.2; ``Phi (n, k)`` mass-orthonormal eigenfunctions, ``lambda (k,)``,
     ``M`` the lumped mass);
   - ``g``: spatial gradient features (paper §3.3). The gradient of every diffused channel in the vertex tangent
     frames is a complex number ``z_c = (G_x h)_c + i (G_y h)_c``; a learned complex-linear map mixes the
     channels, ``w = A z`` (``A = A_re + i A_im``, no bias: each entry scales *and rotates* a gradient, the
     "with gradient rotations" variant), and the feature is ``tanh(Re(conj(z_c) w_c))``, the dot product of the
     gradient with its transformed version. A rotation of vertex ``i``'s tangent frame multiplies all
     ``z_c(i)`` and ``w_c(i)`` by the same unit complex number, which cancels in ``conj(z) w``: the output does
     not depend on how the frames' first axes are chosen (nor, with intrinsic inputs such as HKS/WKS, on the
     shape's orientation in space). Without rotations ``A`` is real;
   - MLP: ``Linear(3W, W) - ReLU - Dropout - Linear(W, W) - ReLU - Dropout - Linear(W, W)`` (hidden sizes
     configurable);
3. ``x W_out + b`` (optionally followed by a last activation; G-MSM uses none).

The diffusion times are initialized at 0 (the identity on the span of the basis) and kept non-negative by
projection: before a forward pass uses them, negative entries (after an optimizer step) are set to 0 in place
(the reference implementation clamps at 1e-8 in the same way). Projection instead of a functional clamp keeps
the gradient of a time at the boundary alive.

The per-shape operators come from the operator registry (:mod:`shapecorr.data.operators`), computed by
:mod:`shapecorr.geometry.laplace_beltrami` (``eigenbasis``) and :mod:`shapecorr.geometry.diffusion_operators`
(``diffusion_gradients``); see ``docs/gmsm.md`` for the published settings. The gradient operators are applied as
CSR matrices (:func:`gradient_operators`, transposes kept for the backward pass) and the dropout layers are
:class:`~shapecorr.nn.dropout.RowDropout` (torch's dropout, its masks drawn faster): both give bitwise the values
and gradients of the plain sparse products and ``nn.Dropout`` (docs/speed.md §4).
"""

from __future__ import annotations

import itertools
import warnings
import weakref
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import nn
from torch.autograd.function import once_differentiable

from shapecorr.errors import ConfigError, NumericalError
from shapecorr.geometry.finiteness import all_finite
from shapecorr.nn.backbone import Backbone
from shapecorr.nn.dropout import RowDropout

#: Published DiffusionNet setting of G-MSM (Eisenberger et al., CVPR 2023, with the DiffusionNet defaults of
#: Sharp et al. 2022): width, blocks, output channels, eigenpairs, dropout probability (docs/gmsm.md).
DEFAULT_WIDTH = 128
DEFAULT_BLOCKS = 4
DEFAULT_OUT_CHANNELS = 128
DEFAULT_K_EIG = 128
DEFAULT_DROPOUT = 0.5
#: Initial diffusion time of every channel (Sharp et al. 2022: zero, i.e. no diffusion).
INITIAL_DIFFUSION_TIME = 0.0

LAST_ACTIVATIONS = {None: None, "none": None, "relu": nn.ReLU, "sigmoid": nn.Sigmoid, "tanh": nn.Tanh}
#: Inputs a DiffusionNetBackbone reads from the sample directly (anything else names a descriptor operator).
XYZ_INPUT = "xyz"


def spectral_diffusion(
    x: torch.Tensor, evals: torch.Tensor, evecs: torch.Tensor, mass: torch.Tensor, times: torch.Tensor
) -> torch.Tensor:
    """Heat diffusion of each channel for its own time, in a truncated eigenbasis.

    ``Phi diag(exp(-lambda t_c)) Phi^T M x_c`` for every channel ``c``: at ``t = 0`` the mass-orthogonal
    projection onto the span of ``Phi`` (the identity on that span); for ``t -> inf`` only the constant
    eigenfunction survives and every value tends to the mass-weighted mean ``sum_i m_i x_i / sum_i m_i``.

    Parameters
    ----------
    x : (n, C) float
    evals : (k,) float
        Eigenvalues ``>= 0`` (of ``L phi = lambda M phi``).
    evecs : (n, k) float
        Mass-orthonormal eigenfunctions ``Phi^T M Phi = I``.
    mass : (n,) float
        Lumped vertex areas.
    times : (C,) float
        Diffusion times ``>= 0``.

    Returns
    -------
    (n, C) float
    """
    coeffs = evecs.transpose(0, 1) @ (mass[:, None] * x)  # (k, C)
    coeffs = coeffs * torch.exp(-evals[:, None] * times[None, :])
    return evecs @ coeffs


class GradientOperators:
    """The tangent gradient operators ``G_x, G_y (n, n)`` of one shape as CSR matrices.

    Applying a CSR matrix costs about half of applying the coalesced COO tensor the data pipeline hands over,
    with the same sums per row (bitwise equal products); the backward pass applies the transposes, built as CSR
    on first use (a CSC conversion read as CSR) and kept. :func:`gradient_operators` caches one per operator
    tensor.

    Parameters
    ----------
    grad_x, grad_y : (n, n) torch sparse float
        COO or CSR.
    """

    def __init__(self, grad_x: torch.Tensor, grad_y: torch.Tensor):
        with warnings.catch_warnings():  # "sparse CSR support is in beta": the two products used here are not
            warnings.simplefilter("ignore", UserWarning)
            self.x, self.y = (g if g.layout == torch.sparse_csr else g.to_sparse_csr() for g in (grad_x, grad_y))
        self._transposed: tuple[torch.Tensor, torch.Tensor] | None = None

    def transposed(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(G_x^T, G_y^T)`` as CSR matrices."""
        if self._transposed is None:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                self._transposed = tuple(  # type: ignore[assignment]
                    torch.sparse_csr_tensor(c.ccol_indices(), c.row_indices(), c.values(), c.shape[::-1])
                    for c in (self.x.to_sparse_csc(), self.y.to_sparse_csc()))
        return self._transposed  # type: ignore[return-value]

    def apply(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(G_x h, G_y h)`` for ``h (n, C)``, differentiable in ``h``.

        Two autograd nodes, as two sparse products would be, so that autograd sums the gradient of ``h`` in
        the same order.
        """
        return _SparseProduct.apply(h, self, 0), _SparseProduct.apply(h, self, 1)


class _SparseProduct(torch.autograd.Function):
    """``ops.x @ h`` (``which`` 0) or ``ops.y @ h`` (1); backward by the kept transpose."""

    @staticmethod
    def forward(ctx, h, ops, which):
        ctx.ops, ctx.which = ops, which
        return (ops.x, ops.y)[which] @ h

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        return ctx.ops.transposed()[ctx.which] @ grad, None, None


#: id(grad_x) -> (weak reference to grad_x, weak reference to grad_y, their GradientOperators); an entry is
#: dropped when grad_x is garbage collected (tensors compare elementwise, so they cannot be dictionary keys).
_GRADIENT_OPERATORS: dict[int, tuple[weakref.ref, weakref.ref, GradientOperators]] = {}


def gradient_operators(grad_x: torch.Tensor, grad_y: torch.Tensor) -> GradientOperators:
    """:class:`GradientOperators` of ``grad_x, grad_y (n, n)``, cached while the two tensors live (by identity)."""
    key = id(grad_x)
    entry = _GRADIENT_OPERATORS.get(key)
    if entry is None or entry[0]() is not grad_x or entry[1]() is not grad_y:
        ops = GradientOperators(grad_x, grad_y)
        entry = (weakref.ref(grad_x, lambda _, key=key: _GRADIENT_OPERATORS.pop(key, None)), weakref.ref(grad_y),
                 ops)
        _GRADIENT_OPERATORS[key] = entry
    return entry[2]


class LearnedTimeDiffusion(nn.Module):
    """Spectral diffusion with a learned, non-negative time per channel (see the module docstring).

    Parameters
    ----------
    channels : int
    init_time : float
        Initial time of every channel.
    """

    def __init__(self, channels: int, init_time: float = INITIAL_DIFFUSION_TIME):
        super().__init__()
        self.times = nn.Parameter(torch.full((channels,), float(init_time)))

    def project_times(self) -> None:
        """Set negative times to 0 in place (only when there is one, so no version bump otherwise)."""
        if bool((self.times < 0).any()):
            with torch.no_grad():
                self.times.clamp_(min=0.0)

    def forward(self, x: torch.Tensor, evals: torch.Tensor, evecs: torch.Tensor, mass: torch.Tensor) -> torch.Tensor:
        """``x (n, C)`` diffused: ``(n, C)``."""
        self.project_times()
        return spectral_diffusion(x, evals, evecs, mass, self.times)


class GradientFeatures(nn.Module):
    """Frame-independent features of per-channel tangent gradients (paper §3.3).

    Parameters
    ----------
    channels : int
    with_rotations : bool
        Complex-linear mixing (scales and rotates gradients; the published variant) or a real linear map.
    """

    def __init__(self, channels: int, with_rotations: bool = True):
        super().__init__()
        self.with_rotations = with_rotations
        self.a_re = nn.Linear(channels, channels, bias=False)
        self.a_im = nn.Linear(channels, channels, bias=False) if with_rotations else None

    def forward(self, grad_re: torch.Tensor, grad_im: torch.Tensor) -> torch.Tensor:
        """Features ``(n, C)`` from the gradient components ``grad_re, grad_im (n, C)`` (along x and y axes)."""
        if self.with_rotations:
            w_re = self.a_re(grad_re) - self.a_im(grad_im)
            w_im = self.a_re(grad_im) + self.a_im(grad_re)
        else:
            w_re, w_im = self.a_re(grad_re), self.a_re(grad_im)
        return torch.tanh(grad_re * w_re + grad_im * w_im)


def _mlp(sizes: Sequence[int], dropout: float) -> nn.Sequential:
    """Linear layers with ReLU and dropout between them (none after the last)."""
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(itertools.pairwise(sizes)):
        layers.append(nn.Linear(a, b))
        if i < len(sizes) - 2:
            layers.append(nn.ReLU())
            if dropout > 0:
                layers.append(RowDropout(dropout))
    return nn.Sequential(*layers)


def _mlp_at_rows(mlp: nn.Sequential, x: torch.Tensor, rows: torch.Tensor | None, full_rows: int) -> torch.Tensor:
    """``mlp`` of ``x``: rows ``rows`` of a ``(full_rows, .)`` input, with the full input's dropout masks."""
    for layer in mlp:
        x = layer(x, rows, full_rows) if isinstance(layer, RowDropout) and rows is not None else layer(x)
    return x


class DiffusionNetBlock(nn.Module):
    """One residual DiffusionNet block: diffusion, gradient features, per-vertex MLP (module docstring).

    Parameters
    ----------
    width : int
    mlp_hidden : sequence of int
        Hidden sizes of the MLP (published: ``[width, width]``).
    dropout : float
        Dropout probability after each hidden layer (0 disables).
    with_gradient_features, with_gradient_rotations : bool
    """

    def __init__(
        self,
        width: int,
        mlp_hidden: Sequence[int],
        dropout: float = DEFAULT_DROPOUT,
        with_gradient_features: bool = True,
        with_gradient_rotations: bool = True,
    ):
        super().__init__()
        self.diffusion = LearnedTimeDiffusion(width)
        self.gradient = GradientFeatures(width, with_gradient_rotations) if with_gradient_features else None
        n_in = 3 * width if with_gradient_features else 2 * width
        self.mlp = _mlp([n_in, *mlp_hidden, width], dropout)

    def forward(self, x, evals, evecs, mass, grads: GradientOperators, rows: torch.Tensor | None = None
                ) -> torch.Tensor:
        """``x (n, W)`` -> ``(n, W)``, or ``(len(rows), W)`` at the vertices ``rows``.

        Operators as in :meth:`DiffusionNet.forward` (``grads``: the gradient operators,
        :func:`gradient_operators`). The diffusion and the gradients need every vertex; the per-vertex layers
        after them (gradient features, MLP) run at ``rows`` only, with the values they have there in the full
        computation (the dropout masks of the full computation, :class:`~shapecorr.nn.dropout.RowDropout`).
        """
        n = x.shape[0]
        h = self.diffusion(x, evals, evecs, mass)
        g = grads.apply(h) if self.gradient is not None else None
        if rows is not None:
            x, h = x[rows], h[rows]
            g = None if g is None else (g[0][rows], g[1][rows])
        parts = [x, h]
        if g is not None:
            parts.append(self.gradient(*g))
        return x + _mlp_at_rows(self.mlp, torch.cat(parts, dim=1), rows, n)

    def dropout_draws_apart(self, device) -> bool:
        """Whether this block's dropout masks can be drawn apart from the values on ``device`` (rows allowed)."""
        return all(m.draws_apart(device) for m in self.mlp if isinstance(m, RowDropout))


class DiffusionNet(nn.Module):
    """DiffusionNet on per-vertex features (module docstring), outputs at the vertices.

    Parameters
    ----------
    in_channels, out_channels : int
    width : int
        Channels inside the blocks (published 128).
    n_blocks : int
        Number of residual blocks (published 4).
    mlp_hidden : sequence of int, optional
        Hidden sizes of each block's MLP; default ``[width, width]`` (published).
    dropout : float
        Dropout probability in the MLPs (published: dropout on, p = 0.5; 0 disables).
    with_gradient_features, with_gradient_rotations : bool
        Published: both on.
    last_activation : {None, "relu", "sigmoid", "tanh"}
        Applied to the output (G-MSM: none).
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int = DEFAULT_OUT_CHANNELS,
        width: int = DEFAULT_WIDTH,
        n_blocks: int = DEFAULT_BLOCKS,
        mlp_hidden: Sequence[int] | None = None,
        dropout: float = DEFAULT_DROPOUT,
        with_gradient_features: bool = True,
        with_gradient_rotations: bool = True,
        last_activation: str | None = None,
    ):
        super().__init__()
        if min(in_channels, out_channels, width) < 1 or n_blocks < 0:
            raise ConfigError(
                f"DiffusionNet needs positive in/out channels and width and n_blocks >= 0, got in={in_channels}, "
                f"out={out_channels}, width={width}, n_blocks={n_blocks}"
            )
        if not 0.0 <= dropout < 1.0:
            raise ConfigError(f"DiffusionNet dropout must be a probability in [0, 1), got {dropout}")
        if last_activation not in LAST_ACTIVATIONS:
            raise ConfigError(f"last_activation must be one of {list(LAST_ACTIVATIONS)}, got {last_activation!r}")
        hidden = [width, width] if mlp_hidden is None else [int(h) for h in mlp_hidden]
        self.in_channels, self.out_channels, self.width = int(in_channels), int(out_channels), int(width)
        self.first_lin = nn.Linear(in_channels, width)
        self.blocks = nn.ModuleList(
            DiffusionNetBlock(width, hidden, dropout, with_gradient_features, with_gradient_rotations)
            for _ in range(n_blocks)
        )
        self.last_lin = nn.Linear(width, out_channels)
        act = LAST_ACTIVATIONS[last_activation]
        self.last_activation = act() if act is not None else None

    def forward(
        self,
        x: torch.Tensor,
        evals: torch.Tensor,
        evecs: torch.Tensor,
        mass: torch.Tensor,
        grad_x: torch.Tensor,
        grad_y: torch.Tensor,
        rows: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Per-vertex features, at every vertex or at ``rows``.

        Parameters
        ----------
        x : (n, C_in) float
        evals : (k,) float
        evecs : (n, k) float
            Mass-orthonormal eigenbasis.
        mass : (n,) float
        grad_x, grad_y : (n, n) torch sparse float
            Tangent-frame gradient operators (:func:`shapecorr.geometry.diffusion_operators.spatial_gradient`),
            COO or CSR; applied as CSR matrices (:func:`gradient_operators`, cached per tensor).
        rows : (r,) int64, optional
            Vertices whose features are wanted (repetitions allowed). Without gradients (queries), the last
            block's per-vertex layers (gradient features, MLP) and the output layer run at the distinct rows only,
            with the values of the full computation there: the same products per row and, with an active dropout
            (``dropout_at_test``), the masks drawn for every vertex (:class:`~shapecorr.nn.dropout.RowDropout`;
            the random stream advances as in the full computation), except on a GPU, whose dropout kernel draws
            the masks with the values. With gradients (training) every vertex is computed and the rows are
            selected at the end, so that the parameters' gradients are the sums of the full computation, in the
            same order.

        Returns
        -------
        (n, C_out) or (r, C_out) float
        """
        n = x.shape[0]
        if x.ndim != 2 or x.shape[1] != self.in_channels:
            raise ConfigError(f"DiffusionNet expects input of shape (n, {self.in_channels}), got {tuple(x.shape)}")
        if evecs.shape[0] != n or mass.shape != (n,) or evals.shape != (evecs.shape[1],):
            raise ConfigError(
                f"DiffusionNet operators do not fit the input with {n} vertices: evals {tuple(evals.shape)}, "
                f"evecs {tuple(evecs.shape)}, mass {tuple(mass.shape)}"
            )
        if tuple(grad_x.shape) != (n, n) or tuple(grad_y.shape) != (n, n):
            raise ConfigError(f"gradient operators must be ({n}, {n}), "
                              f"got {tuple(grad_x.shape)}, {tuple(grad_y.shape)}")
        grads = gradient_operators(grad_x, grad_y)
        h = self.first_lin(x)
        # Without gradients (queries) the last block's per-vertex layers and the output layer run at the distinct
        # rows only: per row the same products, the full computation's dropout masks (dropout_at_test).
        at_rows = (rows is not None and len(self.blocks) > 0 and not torch.is_grad_enabled()
                   and self.blocks[-1].dropout_draws_apart(x.device))
        last_rows = inverse = None
        if at_rows:
            last_rows, inverse = torch.unique(rows, return_inverse=True)
        for i, block in enumerate(self.blocks):
            h = block(h, evals, evecs, mass, grads, last_rows if i == len(self.blocks) - 1 else None)
        out = self.last_lin(h)
        if self.last_activation is not None:
            out = self.last_activation(out)
        if rows is None:
            return out
        return out[inverse] if at_rows else out[rows]


class DiffusionNetBackbone(Backbone):
    """DiffusionNet as a backbone (:mod:`shapecorr.nn.backbone`): features of a sample at its vertices.

    Reads ``sample.operators["eigenbasis"]`` (``evals``, ``evecs``, ``mass``; the first ``k_eig`` pairs are used),
    ``sample.operators["diffusion_gradients"]`` (``grad_x``, ``grad_y``, torch sparse) and the input: the
    vertex positions ``sample.verts`` (``input_features="xyz"``, G-MSM's setting) or a descriptor
    ``sample.operators[name][name]`` (e.g. ``"hks"``, ``"wks"``; ``in_channels`` must then be its length).

    Parameters
    ----------
    input_features : str
        ``"xyz"`` or the name of a descriptor operator.
    in_channels : int, optional
        Input channels; 3 for xyz (default), required for a descriptor.
    descriptor_params : mapping, optional
        Parameters of the descriptor operator request (e.g. ``{"count": 16}``).
    k_eig : int
        Eigenpairs used by the diffusion (published 128).
    out_channels, width, n_blocks, mlp_hidden, dropout, with_gradient_features, with_gradient_rotations,
    last_activation
        See :class:`DiffusionNet`.
    """

    def __init__(
        self,
        input_features: str = XYZ_INPUT,
        in_channels: int | None = None,
        descriptor_params: Mapping[str, Any] | None = None,
        k_eig: int = DEFAULT_K_EIG,
        out_channels: int = DEFAULT_OUT_CHANNELS,
        width: int = DEFAULT_WIDTH,
        n_blocks: int = DEFAULT_BLOCKS,
        mlp_hidden: Sequence[int] | None = None,
        dropout: float = DEFAULT_DROPOUT,
        with_gradient_features: bool = True,
        with_gradient_rotations: bool = True,
        last_activation: str | None = None,
    ):
        super().__init__()
        if input_features == XYZ_INPUT:
            in_channels = 3 if in_channels is None else in_channels
            if in_channels != 3:
                raise ConfigError(f"xyz input has 3 channels, got in_channels={in_channels}")
        elif in_channels is None:
            raise ConfigError(
                f"DiffusionNet backbone with descriptor input {input_features!r} needs in_channels (the descriptor "
                "length): set model.backbone.in_channels"
            )
        if k_eig < 1:
            raise ConfigError(f"k_eig must be >= 1, got {k_eig}")
        self.input_features = str(input_features)
        self.k_eig = int(k_eig)
        self.out_channels = int(out_channels)
        self.net = DiffusionNet(
            int(in_channels), out_channels, width, n_blocks, mlp_hidden, dropout,
            with_gradient_features, with_gradient_rotations, last_activation,
        )
        request: dict[str, dict[str, Any]] = {"eigenbasis": {"k": self.k_eig}, "diffusion_gradients": {}}
        if self.input_features != XYZ_INPUT:
            request[self.input_features] = dict(descriptor_params or {})
        self.required_operators = request

    def _input(self, sample, dtype, device) -> torch.Tensor:
        if self.input_features == XYZ_INPUT:
            x = sample.verts
        else:
            x = sample.operators[self.input_features][self.input_features]
        return torch.as_tensor(x, dtype=dtype, device=device)

    def forward(self, sample, rows: torch.Tensor | None = None) -> torch.Tensor:
        """Features ``(n, C)`` at every vertex, or ``(len(rows), C)`` at the vertices ``rows (r,)`` int64."""
        p = self.net.first_lin.weight
        dtype, device = p.dtype, p.device
        eig = sample.operators["eigenbasis"]
        grads = sample.operators["diffusion_gradients"]
        evals = torch.as_tensor(eig["evals"], dtype=dtype, device=device)
        evecs = torch.as_tensor(eig["evecs"], dtype=dtype, device=device)
        if evals.shape[0] < self.k_eig or evecs.shape[1] < self.k_eig:
            raise ConfigError(
                f"DiffusionNet backbone needs {self.k_eig} eigenpairs but the sample has {evecs.shape[1]}: request "
                f"eigenbasis k >= {self.k_eig} (the backbone's required_operators) or lower model.backbone.k_eig"
            )
        evals, evecs = evals[: self.k_eig], evecs[:, : self.k_eig]
        mass = torch.as_tensor(eig["mass"], dtype=dtype, device=device)
        grad_x = grads["grad_x"].to(device=device, dtype=dtype)
        grad_y = grads["grad_y"].to(device=device, dtype=dtype)
        out = self.net(self._input(sample, dtype, device), evals, evecs, mass, grad_x, grad_y, rows)
        if not all_finite(out):
            raise NumericalError("DiffusionNet produced NaN/Inf features (check the operators and the input)")
        return out


__all__ = [
    "DiffusionNet",
    "DiffusionNetBackbone",
    "DiffusionNetBlock",
    "GradientFeatures",
    "LearnedTimeDiffusion",
    "spectral_diffusion",
]
