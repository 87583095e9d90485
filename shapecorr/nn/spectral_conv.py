"""Smooth spectral filter bank: the Deep Shells feature extractor.

A layer maps per-vertex input channels ``f_c`` to output channels ``g_j`` by filtering in the Laplace-Beltrami
eigenbasis (Deep Shells, Eisenberger et al. NeurIPS 2020, §4; docs/deep_shells.md §3):

    g_j = Phi diag-sum_c h_{c,j}(lambda) Phi^T A f_c,        h_{c,j}(lambda) = sum_m a_{c,j,m} B_m(lambda) + b_{c,j}

with a smooth cosine basis on the eigenvalue axis, ``B_m(lambda) = cos(m pi lambda / T)``, ``m = 0..M-1``.
``Phi`` are the first ``num_eigs`` mass-orthonormal eigenfunctions, ``A`` the lumped mass. The filters are
smooth functions of the eigenvalue, so the layer is (approximately) invariant to the eigenbasis of the shape
it runs on: the same weights apply to any mesh. Without nonlinearity the layer is linear in the features.

Eigenvalue convention. shapecorr's Laplacian uses the standard ``1/2 (cot a + cot b)`` weights; the original
MATLAB preprocessing used ``cot a + cot b``, so its eigenvalues are twice ours (docs/deep_shells.md §2), and the
published filter scale ``T = 5e4`` refers to those. In shapecorr's convention the same filters need
``max_frequency = T / 2 = 2.5e4`` (:data:`DEFAULT_MAX_FREQUENCY`). Eigenvalues also scale with 1/area: the
default assumes the Deep Shells normalization to total area 0.44 (shapecorr's default (2/3)^2 = 0.444 is
within 1 %); rescale ``max_frequency`` by ``0.44 / area`` for other normalizations.

Cost. The input is projected once (``Phi^T A f``: ``(K, c_in)``), filtered per eigenvalue in the spectral
domain, where the ``M`` cosine responses are contracted with the weights by one ``(K, c_in) x (c_in, M c_out)``
product (the ``(K, c_in, c_out)`` filter tensor is never needed), and projected back only at the requested rows.
Nothing of size ``n x c_in x c_out`` is ever formed.
"""

from __future__ import annotations

import math
from os import PathLike
from pathlib import Path

import torch
from torch import nn

from shapecorr.errors import ConfigError
from shapecorr.nn.backbone import Backbone, sample_descriptor

#: Deep Shells ``filter_scale`` (param.py ``Param``), in the original doubled-eigenvalue convention.
ORIGINAL_FILTER_SCALE = 5e4
#: Ratio of the original MATLAB eigenvalues to shapecorr's (full vs half cotangent weights, docs/deep_shells.md §2).
ORIGINAL_EIGENVALUE_FACTOR = 2.0
#: Cosine period parameter T in shapecorr's eigenvalue convention (= 5e4 / 2).
DEFAULT_MAX_FREQUENCY = ORIGINAL_FILTER_SCALE / ORIGINAL_EIGENVALUE_FACTOR
#: Deep Shells ``SpecConvModule(num_basis_fcts=16)``.
DEFAULT_NUM_BASIS = 16
#: Deep Shells ``SpecConvModule(num_evecs=200)``.
DEFAULT_NUM_EIGS = 200
#: SHOT descriptor length used as input by Deep Shells (10 bins x 32 sectors + 32 = 352).
DEFAULT_IN_CHANNELS = 352
#: Deep Shells ``num_hidden_layers = 120`` (the number of output features).
DEFAULT_OUT_CHANNELS = 120
#: Input descriptor of the published network (SHOT, Deep Shells §4).
DEFAULT_DESCRIPTOR = "shot"

_ACTIVATIONS = {
    "relu": nn.ReLU,
    "leaky_relu": nn.LeakyReLU,
    "gelu": nn.GELU,
    "tanh": nn.Tanh,
}

#: Parameter names of the original checkpoint's feature module (``feat_mod`` in ``ckpt_*.pth``).
_ORIGINAL_WEIGHT_KEY = "conv.a.0.weight"
_ORIGINAL_BIAS_KEY = "conv.a.0.bias"


def cosine_filter_basis(evals: torch.Tensor, num_basis: int, max_frequency: float) -> torch.Tensor:
    """Cosine basis functions evaluated at the eigenvalues: ``B[i, m] = cos(m pi lambda_i / T)``.

    Parameters
    ----------
    evals : (K,) float
        Eigenvalues (shapecorr convention).
    num_basis : int
        Number ``M`` of basis functions (``m = 0..M-1``).
    max_frequency : float
        ``T``; see the module docstring for its convention.

    Returns
    -------
    (K, M) float
    """
    m = torch.arange(num_basis, dtype=evals.dtype, device=evals.device)
    return torch.cos(evals[:, None] * m[None, :] * (math.pi / max_frequency))


class SpectralConv(nn.Module):
    """One spectral filter-bank layer, ``c_in -> c_out`` channels (no nonlinearity).

    Parameters
    ----------
    in_channels, out_channels : int
    num_basis : int
        Number of cosine basis functions per filter.
    num_eigs : int
        Number of eigenpairs used (the first ``num_eigs`` columns of ``evecs``).
    max_frequency : float
        Cosine scale ``T`` in shapecorr's eigenvalue convention.

    Attributes
    ----------
    weight : (num_basis, in_channels, out_channels) Parameter
        ``a[m, c, j]``.
    bias : (in_channels, out_channels) Parameter
        ``b[c, j]``, the constant part of each filter.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        num_basis: int = DEFAULT_NUM_BASIS,
        num_eigs: int = DEFAULT_NUM_EIGS,
        max_frequency: float = DEFAULT_MAX_FREQUENCY,
    ):
        super().__init__()
        for name, value in (("in_channels", in_channels), ("out_channels", out_channels),
                            ("num_basis", num_basis), ("num_eigs", num_eigs)):
            if int(value) < 1:
                raise ConfigError(f"spectral_conv: {name} must be >= 1, got {value}")
        if not max_frequency > 0:
            raise ConfigError(f"spectral_conv: max_frequency must be positive, got {max_frequency}")
        self.in_channels = int(in_channels)
        self.out_channels = int(out_channels)
        self.num_basis = int(num_basis)
        self.num_eigs = int(num_eigs)
        self.max_frequency = float(max_frequency)
        self.weight = nn.Parameter(torch.empty(self.num_basis, self.in_channels, self.out_channels))
        self.bias = nn.Parameter(torch.empty(self.in_channels, self.out_channels))
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """The original initialization: that of ``nn.Linear(num_basis, c_in * c_out)``."""
        bound = 1.0 / math.sqrt(self.num_basis)
        nn.init.uniform_(self.weight, -bound, bound)
        nn.init.uniform_(self.bias, -bound, bound)

    def filters(self, evals: torch.Tensor) -> torch.Tensor:
        """The filter responses ``h[i, c, j] = h_{c,j}(lambda_i)`` (for inspection and tests).

        Parameters
        ----------
        evals : (K,) float

        Returns
        -------
        (K, in_channels, out_channels) float
        """
        basis = cosine_filter_basis(evals, self.num_basis, self.max_frequency)
        return torch.einsum("km,mco->kco", basis, self.weight) + self.bias

    def filter_coefficients(self, coeffs: torch.Tensor, evals: torch.Tensor) -> torch.Tensor:
        """Apply the filters in the spectral domain.

        Parameters
        ----------
        coeffs : (K, in_channels) float
            Spectral coefficients ``Phi^T A f``.
        evals : (K,) float

        Returns
        -------
        (K, out_channels) float
            ``G[i, j] = sum_c h_{c,j}(lambda_i) coeffs[i, c]``.
        """
        k = coeffs.shape[0]
        basis = cosine_filter_basis(evals, self.num_basis, self.max_frequency)  # (K, M)
        # sum_c coeffs[i, c] a[m, c, j] for all (m, j) at once: (K, c_in) x (c_in, M * c_out).
        w = self.weight.permute(1, 0, 2).reshape(self.in_channels, self.num_basis * self.out_channels)
        per_basis = (coeffs @ w).view(k, self.num_basis, self.out_channels)
        return torch.einsum("km,kmo->ko", basis, per_basis) + coeffs @ self.bias

    def forward(
        self,
        features: torch.Tensor,
        evecs: torch.Tensor,
        evals: torch.Tensor,
        mass: torch.Tensor,
        rows: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Filter per-vertex features.

        Parameters
        ----------
        features : (n, in_channels) float
        evecs : (n, K) float
            Mass-orthonormal eigenfunctions, ``K >= num_eigs``, ascending eigenvalues.
        evals : (K,) float
            Eigenvalues in shapecorr's convention.
        mass : (n,) float
            Lumped vertex areas.
        rows : (r,) int64, optional
            Only return these vertices (e.g. the training samples); default all.

        Returns
        -------
        (n, out_channels) or (r, out_channels) float
        """
        _check_operator_shapes(features, evecs, evals, mass, self.in_channels, self.num_eigs)
        phi = evecs[:, : self.num_eigs]
        coeffs = phi.transpose(0, 1) @ (mass[:, None] * features)  # (K, c_in)
        spec = self.filter_coefficients(coeffs, evals[: self.num_eigs])  # (K, c_out)
        out_phi = phi if rows is None else phi[rows]
        return out_phi @ spec


def _check_operator_shapes(features, evecs, evals, mass, in_channels, num_eigs) -> None:
    if features.dim() != 2 or features.shape[1] != in_channels:
        raise ConfigError(
            f"spectral_conv: expected features of shape (n, {in_channels}), got {tuple(features.shape)}"
        )
    n = features.shape[0]
    if evecs.dim() != 2 or evecs.shape[0] != n or mass.shape != (n,):
        raise ConfigError(
            f"spectral_conv: operators do not match the {n} feature rows: evecs {tuple(evecs.shape)}, "
            f"mass {tuple(mass.shape)}"
        )
    if evecs.shape[1] < num_eigs or evals.shape[0] < num_eigs:
        raise ConfigError(
            f"spectral_conv: needs {num_eigs} eigenpairs (num_eigs), got evecs {tuple(evecs.shape)} and "
            f"evals {tuple(evals.shape)}"
        )


class SpectralFilterBank(nn.Module):
    """A stack of :class:`SpectralConv` layers with a nonlinearity in between.

    The default is the published Deep Shells feature extractor: a single linear layer, 352 SHOT channels to
    120 features, 16 cosine basis functions on the first 200 eigenvalues.

    Parameters
    ----------
    in_channels : int
    out_channels : int
    hidden_channels : sequence of int
        Widths of intermediate layers (default none: a single layer).
    num_basis, num_eigs, max_frequency
        See :class:`SpectralConv` (shared by all layers).
    activation : {"relu", "leaky_relu", "gelu", "tanh"}
        Nonlinearity applied per vertex between layers (not after the last one).
    """

    def __init__(
        self,
        in_channels: int = DEFAULT_IN_CHANNELS,
        out_channels: int = DEFAULT_OUT_CHANNELS,
        hidden_channels: tuple[int, ...] | list[int] = (),
        num_basis: int = DEFAULT_NUM_BASIS,
        num_eigs: int = DEFAULT_NUM_EIGS,
        max_frequency: float = DEFAULT_MAX_FREQUENCY,
        activation: str = "relu",
    ):
        super().__init__()
        if activation not in _ACTIVATIONS:
            raise ConfigError(f"spectral_conv: activation must be one of {sorted(_ACTIVATIONS)}, got {activation!r}")
        widths = [int(in_channels), *[int(h) for h in hidden_channels], int(out_channels)]
        self.in_channels = widths[0]
        self.out_channels = widths[-1]
        self.num_eigs = int(num_eigs)
        self.max_frequency = float(max_frequency)
        self.layers = nn.ModuleList(
            SpectralConv(c_in, c_out, num_basis, num_eigs, max_frequency)
            for c_in, c_out in zip(widths[:-1], widths[1:])
        )
        self.activation = _ACTIVATIONS[activation]()

    def forward(
        self,
        features: torch.Tensor,
        evecs: torch.Tensor,
        evals: torch.Tensor,
        mass: torch.Tensor,
        rows: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Per-vertex output features.

        Parameters
        ----------
        features : (n, in_channels) float
        evecs : (n, K) float
        evals : (K,) float
            shapecorr convention (see the module docstring).
        mass : (n,) float
        rows : (r,) int64, optional
            Vertices at which the output is wanted; intermediate layers always run at all vertices.

        Returns
        -------
        (n, out_channels) or (r, out_channels) float
        """
        x = features
        last = len(self.layers) - 1
        for i, layer in enumerate(self.layers):
            x = layer(x, evecs, evals, mass, rows=rows if i == last else None)
            if i != last:
                x = self.activation(x)
        return x


class SpectralBackbone(Backbone, SpectralFilterBank):
    """The Deep Shells feature extractor as a backbone: a :class:`SpectralFilterBank` on a per-vertex descriptor.

    Reads ``sample.operators[descriptor]`` and the eigenbasis (``evals``, ``evecs``, ``mass``) of a
    :class:`~shapecorr.data.datasets.ShapeSample`; declares ``{"eigenbasis": {"k": num_eigs}, descriptor: {}}``.
    Its parameters (``layers.*``) are those of the filter bank, so state dicts and the original's released weights
    (:func:`load_original_deep_shells_weights`) load unchanged. Config: ``configs/model/backbone/spectral_conv.yaml``.

    Parameters
    ----------
    descriptor : str
        Input descriptor operator (published: ``shot``, 352 channels).
    in_channels, out_channels, hidden_channels, num_basis, num_eigs, max_frequency, activation
        :class:`SpectralFilterBank` options (published: 352 -> 120, 16 cosines, 200 eigenpairs, T = 2.5e4 in
        shapecorr's eigenvalue convention, no hidden layer).
    """

    def __init__(
        self,
        descriptor: str = DEFAULT_DESCRIPTOR,
        in_channels: int = DEFAULT_IN_CHANNELS,
        out_channels: int = DEFAULT_OUT_CHANNELS,
        hidden_channels: tuple[int, ...] | list[int] = (),
        num_basis: int = DEFAULT_NUM_BASIS,
        num_eigs: int = DEFAULT_NUM_EIGS,
        max_frequency: float = DEFAULT_MAX_FREQUENCY,
        activation: str = "relu",
    ):
        SpectralFilterBank.__init__(self, in_channels, out_channels, tuple(hidden_channels), num_basis, num_eigs,
                                    max_frequency, activation)
        self.descriptor = str(descriptor)

    @property
    def required_operators(self) -> dict:  # type: ignore[override]
        """``{"eigenbasis": {"k": num_eigs}, descriptor: {}}``."""
        return {"eigenbasis": {"k": self.num_eigs}, self.descriptor: {}}

    def forward(self, sample, rows: torch.Tensor | None = None) -> torch.Tensor:  # type: ignore[override]
        """Filtered features ``(n, out_channels)`` or ``(len(rows), out_channels)`` of a ShapeSample."""
        features = sample_descriptor(sample, self.descriptor, "the spectral_conv backbone")
        return SpectralFilterBank.forward(self, features, sample.evecs, sample.evals, sample.mass, rows=rows)


def load_original_deep_shells_weights(module: SpectralFilterBank, path: str | PathLike) -> dict:
    """Load the published Deep Shells feature-module weights into a :class:`SpectralFilterBank`.

    The original stores one ``nn.Linear(16, c_in * c_out)`` (``conv.a.0.weight (c_in*c_out, M)``,
    ``conv.a.0.bias (c_in*c_out,)``) whose output index is ``c * c_out + j``; here it becomes
    ``weight[m, c, j]`` and ``bias[c, j]``. The checkpoint's filter scale must match ``module.max_frequency``
    in the doubled eigenvalue convention (``T_original = 2 * max_frequency``).

    Parameters
    ----------
    module : SpectralFilterBank
        A single-layer bank with matching sizes (the defaults for the published checkpoint).
    path : path-like
        ``ckpt_*.pth`` of the original (a dict with ``feat_mod`` and ``par``) or a bare state dict.

    Returns
    -------
    dict
        The checkpoint's hyperparameters (``par``), empty if absent.

    Raises
    ------
    ConfigError
        If the file is missing or unreadable, is not a Deep Shells checkpoint, or does not fit the module.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError("Deep Shells checkpoint not found", path=path)
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several unrelated types for unreadable/unsafe pickles
        raise ConfigError(f"not a readable torch checkpoint ({type(exc).__name__}: {exc})", path=path) from exc
    if not isinstance(ckpt, dict):
        raise ConfigError("not a Deep Shells checkpoint (expected a dict)", path=path)
    state = ckpt.get("feat_mod", ckpt)
    if not isinstance(state, dict) or _ORIGINAL_WEIGHT_KEY not in state or _ORIGINAL_BIAS_KEY not in state:
        raise ConfigError(
            f"not a Deep Shells checkpoint: missing {_ORIGINAL_WEIGHT_KEY!r} / {_ORIGINAL_BIAS_KEY!r}", path=path
        )
    params = ckpt.get("par", {}) if isinstance(ckpt.get("par", {}), dict) else {}
    if len(module.layers) != 1:
        raise ConfigError(
            f"the original weights are a single layer; the module has {len(module.layers)} layers", path=path
        )
    layer = module.layers[0]
    weight, bias = state[_ORIGINAL_WEIGHT_KEY], state[_ORIGINAL_BIAS_KEY]
    expected = (layer.in_channels * layer.out_channels, layer.num_basis)
    if tuple(weight.shape) != expected or tuple(bias.shape) != (expected[0],):
        raise ConfigError(
            f"weights {tuple(weight.shape)} / bias {tuple(bias.shape)} do not fit a {layer.in_channels}->"
            f"{layer.out_channels} layer with {layer.num_basis} basis functions (expected {expected})",
            path=path,
        )
    scale = params.get("filter_scale")
    if scale is not None and not math.isclose(float(scale), ORIGINAL_EIGENVALUE_FACTOR * layer.max_frequency,
                                              rel_tol=1e-6):
        raise ConfigError(
            f"checkpoint filter_scale {scale} (doubled eigenvalues) does not match max_frequency "
            f"{layer.max_frequency} (= {scale} / {ORIGINAL_EIGENVALUE_FACTOR} expected)",
            path=path,
        )
    num_eigs = params.get("num_evecs")
    if num_eigs is not None and int(num_eigs) != layer.num_eigs:
        raise ConfigError(f"checkpoint uses {num_eigs} eigenpairs, the module {layer.num_eigs}", path=path)
    with torch.no_grad():
        w = weight.to(layer.weight.dtype).t().reshape(layer.num_basis, layer.in_channels, layer.out_channels)
        layer.weight.copy_(w)
        layer.bias.copy_(bias.to(layer.bias.dtype).reshape(layer.in_channels, layer.out_channels))
    return dict(params)
