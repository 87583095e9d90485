"""Soft correspondences from per-vertex features by a row softmax of cosine similarities (NeuroMorph).

NeuroMorph (Eisenberger et al., CVPR 2021, §3.2; docs/neuromorph.md §4) matches two shapes through their
L2-normalized features: with ``S = F_x F_y^T`` (cosine similarities, in [-1, 1])

    Pi     = softmax_rows(sigma * S)        (n_x, n_y), row-stochastic: soft map x -> y
    Pi_inv = softmax_rows(sigma * S^T)      (n_y, n_x), row-stochastic: soft map y -> x

with ``sigma = 100`` hard-coded in the original code. ``sigma`` multiplies the similarities, i.e. it is an
*inverse* temperature: larger is sharper. Hard maps are the row-wise argmax of ``Pi`` and of ``Pi_inv``;
since the softmax is monotone they are the argmax of ``S`` by rows and by columns, so
:func:`hard_maps` never forms the softmax and works in chunks.

Both maps from one exponential. ``Pi`` normalizes ``exp(sigma S)`` by rows, ``Pi_inv^T`` by columns, so with
one global shift ``m = max(sigma S)`` a single ``E = exp(sigma S - m)`` serves both: ``Pi = E / rowsum(E)``,
``Pi_inv = (E / colsum(E))^T``. ``Pi_inv`` is returned as that transposed view (strides ``(1, n_y)``), which
matrix products read for free; the hand-written backward never forms a transposed copy either (plain
autograd adds the two gradients of S through a transposed n^2 copy). Mathematically this is the softmax
(any shift cancels); numerically it needs every row and column to keep a non-negligible mass under the
global shift: when a row or column sum of E falls below ``n * tiny / eps`` of the dtype (its entries would
lose precision to underflow), the two maps are computed as two separately shifted softmaxes instead.

Memory. :func:`softmax_soft_maps` holds ``Pi`` and ``Pi_inv``: two ``n_x * n_y`` matrices (16 MB each in
float32 at 2000 x 2000, 400 MB each at 10k x 10k), kept for the backward pass. :func:`hard_maps` needs only
``chunk_size * n_y``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from shapecorr.errors import ConfigError, NumericalError

#: Inverse temperature of the softmax on cosine similarities (NeuroMorph code, hard-coded factor 100).
DEFAULT_SIGMA = 100.0
#: Rows of X processed at once by :func:`hard_maps` (bounds the memory to chunk_size * n_y similarities).
DEFAULT_CHUNK_SIZE = 4096
#: Norm floor of the feature normalization (only reached by all-zero feature vectors).
FEATURE_NORM_EPS = 1e-12


def _check_features(feat_x: torch.Tensor, feat_y: torch.Tensor) -> None:
    if feat_x.ndim != 2 or feat_y.ndim != 2 or feat_x.shape[1] != feat_y.shape[1]:
        raise ConfigError(
            f"features must be (n_x, d) and (n_y, d) with the same d, got {tuple(feat_x.shape)} and "
            f"{tuple(feat_y.shape)}"
        )
    if feat_x.shape[0] == 0 or feat_y.shape[0] == 0:
        raise ConfigError("features of an empty shape cannot be matched")
    for name, feat in (("feat_x", feat_x), ("feat_y", feat_y)):
        if not bool(torch.isfinite(feat).all()):
            raise NumericalError(f"{name} contains NaN or Inf values; cannot compute a soft correspondence")


def cosine_similarity(feat_x: torch.Tensor, feat_y: torch.Tensor, normalize: bool = True) -> torch.Tensor:
    """Cosine similarities of all pairs of feature vectors.

    Parameters
    ----------
    feat_x : (n_x, d) float
    feat_y : (n_y, d) float
    normalize : bool
        L2-normalize the rows first; pass False when the features are already unit vectors.

    Returns
    -------
    (n_x, n_y) float
    """
    _check_features(feat_x, feat_y)
    if normalize:
        feat_x = F.normalize(feat_x, dim=-1, eps=FEATURE_NORM_EPS)
        feat_y = F.normalize(feat_y, dim=-1, eps=FEATURE_NORM_EPS)
    return feat_x @ feat_y.T


def softmax_soft_maps(
    feat_x: torch.Tensor,
    feat_y: torch.Tensor,
    sigma: float = DEFAULT_SIGMA,
    normalize: bool = True,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Soft maps both ways from a softmax of scaled cosine similarities (NeuroMorph eq. 3).

    Parameters
    ----------
    feat_x : (n_x, d) float
    feat_y : (n_y, d) float
    sigma : float
        Inverse temperature (NeuroMorph: 100); must be positive.
    normalize : bool
        L2-normalize the features first (cosine similarity). NeuroMorph's feature network already outputs
        unit vectors, for which this is a no-op.

    Returns
    -------
    pi_x_to_y : (n_x, n_y) float
        Row-stochastic soft map x -> y.
    pi_y_to_x : (n_y, n_x) float
        Row-stochastic soft map y -> x; usually a transposed view of an ``(n_x, n_y)`` buffer (module
        docstring): call ``.contiguous()`` before ``.view()``.
    """
    if not sigma > 0:
        raise ConfigError(f"softmax sigma must be positive, got {sigma}")
    _check_features(feat_x, feat_y)
    if normalize:
        feat_x = F.normalize(feat_x, dim=-1, eps=FEATURE_NORM_EPS)
        feat_y = F.normalize(feat_y, dim=-1, eps=FEATURE_NORM_EPS)
    maps = _SoftmaxBothWays.apply(feat_x, feat_y, float(sigma))
    if maps is not None:
        return maps
    # A row or a column would underflow under the global shift: two separately shifted softmaxes.
    scores = (sigma * feat_x) @ feat_y.T
    pi_x_to_y = torch.softmax(scores, dim=1)
    # Row softmax of S^T (a column softmax of S, then .T, is ~2x slower on CPU: strided reductions).
    pi_y_to_x = torch.softmax(scores.T, dim=1)
    return pi_x_to_y, pi_y_to_x


def _min_safe_sum(n: int, dtype: torch.dtype) -> float:
    """Smallest row/column sum of ``E`` for which the shared-shift softmax keeps full precision.

    See the module docstring: the largest entry is then at least ``tiny / eps``, so entries down to ``eps``
    times it are normal numbers.
    """
    info = torch.finfo(dtype)
    return n * info.tiny / info.eps


class _SoftmaxBothWays(torch.autograd.Function):
    """``Pi`` and ``Pi_inv`` from one exponential (module docstring).

    ``Pi = softmax_rows(sigma F_x F_y^T)`` and ``Pi_inv = softmax_rows(sigma F_y F_x^T)``; returns None (nothing
    to differentiate) when the shared shift would underflow a row or a column.

    Backward, with ``Q = Pi_inv^T`` and upstream gradients ``G1 (n_x, n_y)``, ``G2 (n_y, n_x)``:
    ``dL/d(sigma S) = Pi * (G1 - rowdot(G1, Pi)) + Q * (G2^T - coldot(G2^T, Q))``, then
    ``dL/dF_x = sigma (dL/d(sigma S)) F_y`` and ``dL/dF_y = sigma (dL/d(sigma S))^T F_x``.
    """

    @staticmethod
    def forward(ctx, feat_x, feat_y, sigma):
        ctx.set_materialize_grads(False)
        expo = (sigma * feat_x) @ feat_y.T
        expo.sub_(expo.max()).exp_()
        row_sum, col_sum = expo.sum(dim=1, keepdim=True), expo.sum(dim=0, keepdim=True)
        n_x, n_y = expo.shape
        if (float(row_sum.min()) < _min_safe_sum(n_y, expo.dtype)
                or float(col_sum.min()) < _min_safe_sum(n_x, expo.dtype)):
            return None
        pi = expo / row_sum
        q = expo.div_(col_sum)  # Pi_inv^T, column-stochastic
        ctx.save_for_backward(feat_x, feat_y, pi, q)
        ctx.sigma = sigma
        return pi, q.T

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_pi, grad_pi_inv):
        feat_x, feat_y, pi, q = ctx.saved_tensors
        grad_scores = None
        if grad_pi is not None:
            # Pi * (G1 - rowdot(G1, Pi)) = Pi * G1 - Pi * rowsum(Pi * G1)
            grad_scores = grad_pi * pi
            grad_scores.addcmul_(pi, grad_scores.sum(dim=1, keepdim=True), value=-1.0)
        if grad_pi_inv is not None:
            g2 = grad_pi_inv.T  # (n_x, n_y); contiguous when it comes from a product with the transposed view
            part = g2 * q
            col_dot = part.sum(dim=0, keepdim=True)
            grad_scores = part if grad_scores is None else grad_scores.add_(part)
            grad_scores.addcmul_(q, col_dot, value=-1.0)
        if grad_scores is None:
            return None, None, None
        grad_x = grad_y = None
        if ctx.needs_input_grad[0]:
            grad_x = (grad_scores @ feat_y).mul_(ctx.sigma)
        if ctx.needs_input_grad[1]:
            grad_y = (grad_scores.T @ feat_x).mul_(ctx.sigma)
        return grad_x, grad_y, None


def soft_map_to_p2p(soft_map: torch.Tensor) -> torch.Tensor:
    """Point-to-point map from a soft map: the argmax of every row.

    Parameters
    ----------
    soft_map : (n, m) float
        Soft map from a shape with n vertices to one with m vertices.

    Returns
    -------
    (n,) int64
        For each source vertex, the target vertex with the largest weight.
    """
    if soft_map.ndim != 2 or soft_map.shape[1] == 0:
        raise ConfigError(f"soft map must be a non-empty (n, m) matrix, got {tuple(soft_map.shape)}")
    return soft_map.argmax(dim=1)


@torch.no_grad()
def hard_maps(
    feat_x: torch.Tensor,
    feat_y: torch.Tensor,
    normalize: bool = True,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Point-to-point maps both ways, equal to the row argmax of the soft maps, without forming them.

    Parameters
    ----------
    feat_x : (n_x, d) float
    feat_y : (n_y, d) float
    normalize : bool
        L2-normalize the features first (as :func:`softmax_soft_maps`; the argmax does not depend on
        sigma).
    chunk_size : int
        Rows of ``feat_x`` per block; memory is ``chunk_size * n_y`` similarities.

    Returns
    -------
    p2p_x_to_y : (n_x,) int64
        For each vertex of x, its most similar vertex of y.
    p2p_y_to_x : (n_y,) int64
        For each vertex of y, its most similar vertex of x.
    """
    if chunk_size < 1:
        raise ConfigError(f"chunk_size must be >= 1, got {chunk_size}")
    _check_features(feat_x, feat_y)
    if normalize:
        feat_x = F.normalize(feat_x, dim=-1, eps=FEATURE_NORM_EPS)
        feat_y = F.normalize(feat_y, dim=-1, eps=FEATURE_NORM_EPS)
    n_y = feat_y.shape[0]
    p2p_x_to_y = torch.empty(feat_x.shape[0], dtype=torch.int64, device=feat_x.device)
    best_y = torch.full((n_y,), -float("inf"), dtype=feat_x.dtype, device=feat_x.device)
    p2p_y_to_x = torch.zeros(n_y, dtype=torch.int64, device=feat_x.device)
    for start in range(0, feat_x.shape[0], chunk_size):
        block = feat_x[start : start + chunk_size] @ feat_y.T
        p2p_x_to_y[start : start + block.shape[0]] = block.argmax(dim=1)
        col_best, col_arg = block.max(dim=0)
        # Strictly greater: on ties the first (smallest) x index wins, as in a full argmax.
        better = col_best > best_y
        best_y = torch.where(better, col_best, best_y)
        p2p_y_to_x = torch.where(better, col_arg + start, p2p_y_to_x)
    return p2p_x_to_y, p2p_y_to_x
