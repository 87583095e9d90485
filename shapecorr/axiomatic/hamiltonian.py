"""Hamiltonian shape interpolation (Eisenberger & Cremers, ECCV 2020; docs/hamiltonian.md).

x is moved towards the target positions of its vertices (given by a map to y) by a time-discrete physical
simulation: velocities live in the divergence-free basis of :mod:`shapecorr.geometry.divergence_free`, so every
in-between keeps the volume, and each step balances inertia against an anisotropic as-rigid-as-possible force.
The free variables (initial field coefficients ``a``, per-sample 3x3 anisotropy matrices ``A_i``, the log of the
inertia weight) are optimized with Adam through the whole simulation (autograd).

One step (docs/hamiltonian.md §2), on ``n`` farthest-point samples with a kNN graph of undirected edges ``(a, b)``
weighted by their multiplicity ``c_e`` in the directed neighbour list, ``e(x) = x_b - x_a``, step ``h = 1 / N``:

1. predicted velocity ``v* = 2 v_t - v_{t-1}`` (``extrapolate_velocity``; otherwise ``v* = v_t``);
2. rotations ``R_i`` fitted from the rest edges to the edges of the predicted pose ``x_t + h v*`` (exact ARAP
   rotations, :func:`shapecorr.losses.arap.arap_rotations`); edge residuals ``r_e = e(x_t) - (R_a + R_b)/2
   e(x_0)``; anisotropic frames ``R'_i = R_i A_i^T``; force ``f_i = R'_i sum_e ±c_e ((R'_a + R'_b)/2)^T r_e``
   (``+`` at a, ``-`` at b: the negative gradient of ``|r_e|^2 / 2``);
3. basis ``Psi (n, F, 3)`` at the midpoint ``x_t + h/2 v*``, ``Q_i = R'_i^T Psi_i``, graph Laplacian ``H`` of the
   weighted edges, ``lambda' = exp(log_lambda) h``; solve (float64)
   ``(1e-3 I + lambda' Psi^T Psi + h^2 Q^T H Q) xi = Psi^T (lambda' v* + h/2 f)``;
4. ``v_{t+1} = Psi xi``, ``x_{t+1} = x_t + h v_{t+1}``;
5. energy ``E_arap += sum_e c_e |e(x_{t+1}) - (R_a + R_b)/2 e(x_0)|^2 / (n N 25 / k)``.

Initial velocity ``v_0 = v_{-1} = h sum_f a_f v_f(x_0)``. Loss ``E = MSE(x_N, y) + lambda_reg E_arap``, the mean
squared error over the samples whose target is known (``mask``; partial targets) and the three coordinates.

Replay (full resolution, chunked): the per-step coefficients ``xi_t`` define the velocity of any point, so every
vertex of x runs the same recursion (steps 1 and 4, with ``v_{t+1} = velocity(x_t + h/2 v*, xi_t)``); on the
samples it reproduces the optimized trajectory. Extrapolation (t > 1): the simulation continues on the samples
past step N with the optimized parameters (no optimization), and the new ``xi_t`` are replayed the same way.
Frames between steps are linear in time (the step moves each point on a straight line).

Pure torch (CPU or GPU); written by hand: no library implements this scheme.
"""

from __future__ import annotations

import functools
import math
import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import torch

from shapecorr.axiomatic.divfree import ARAP_NORMALIZATION, PUBLISHED_KNN, PUBLISHED_LAMBDA_REG, knn_graph_edges
from shapecorr.errors import ConfigError, NumericalError
from shapecorr.geometry import divergence_free as df
from shapecorr.geometry.sampling import farthest_point_sampling
from shapecorr.losses.arap import edge_vectors, rotations_from_covariances
from shapecorr.matching.baselines import LinearBlend
from shapecorr.matching.result import MatchResult

#: Adam step size (original code ``DivFreeParam.lr``).
PUBLISHED_LR = 0.02
#: Adam iterations (original code ``DivFreeParam.num_it``).
PUBLISHED_ITERATIONS = 100
#: Farthest-point samples of x (original code ``DivFreeParam.num_vert``).
PUBLISHED_SAMPLES = 2000
#: Initial inertia weight, optimized as a log (original code ``DivFreeParam.lambda_inertia``).
PUBLISHED_LAMBDA_INERTIA = 0.3
#: Ridge of the per-step linear system (original code: ``1e-3 * I``).
PUBLISHED_RIDGE = 1e-3
#: Default frames of :meth:`Hamiltonian.match` (as LinearBlend: 0, 1/4, ..., 1).
HAMILTONIAN_TIMES = (0.0, 0.25, 0.5, 0.75, 1.0)
#: Alignment MSE (box units^2, RMS 1e-5) below which the pair counts as aligned and Adam stops (project choice).
ALIGN_TOLERANCE = 1e-10
#: Frame times are matched to the step grid within this tolerance (in steps).
STEP_ATOL = 1e-6


@dataclass(frozen=True)
class HamiltonianConfig:
    """Parameters of :func:`hamiltonian_interpolation` (defaults: the published ones, docs/hamiltonian.md §5).

    Attributes
    ----------
    lr, iterations : float, int
        Adam step size and iterations.
    n_steps : int
        Time steps N from t = 0 to t = 1 (h = 1 / N).
    lambda_reg : float
        Weight of the ARAP energy.
    lambda_inertia : float
        Initial inertia weight (optimized as its log).
    samples, knn : int
        Farthest-point samples of x (clipped to the vertex count) and neighbours of their graph.
    n_modes : int
        Modes per axis K of the basis (3 K^3 fields).
    extrapolate_velocity : bool
        Predict ``v* = 2 v_t - v_{t-1}`` (True) or ``v* = v_t``.
    ridge : float
        Ridge of the per-step system.
    margin : float
        Box margin of the pair normalization.
    convention : {"published", "original_code"}
        Basis convention.
    learn_anisotropy, learn_inertia : bool
        Optimize the anisotropy matrices / the inertia weight (published: both).
    align_tolerance : float
        The optimization stops once the alignment MSE (box units^2) is below it: Adam normalizes the gradient,
        so round-off gradients of an already aligned pair would otherwise take full steps (project choice).
    chunk_size : int
        Vertices per chunk of the full-resolution replay.
    seed : int
        Start vertex of the farthest-point sampling.
    """

    lr: float = PUBLISHED_LR
    iterations: int = PUBLISHED_ITERATIONS
    n_steps: int = df.PUBLISHED_N_STEPS
    lambda_reg: float = PUBLISHED_LAMBDA_REG
    lambda_inertia: float = PUBLISHED_LAMBDA_INERTIA
    samples: int = PUBLISHED_SAMPLES
    knn: int = PUBLISHED_KNN
    n_modes: int = df.PUBLISHED_N_MODES
    extrapolate_velocity: bool = True
    ridge: float = PUBLISHED_RIDGE
    margin: float = df.BOX_MARGIN
    convention: str = "original_code"
    learn_anisotropy: bool = True
    learn_inertia: bool = True
    align_tolerance: float = ALIGN_TOLERANCE
    chunk_size: int = 1000
    seed: int = 0

    def __post_init__(self):
        if not (self.lr > 0 and self.lambda_inertia > 0 and self.ridge > 0 and self.lambda_reg >= 0):
            raise ConfigError("hamiltonian: lr, lambda_inertia and ridge must be positive, lambda_reg >= 0")
        for name in ("n_steps", "samples", "knn", "n_modes", "chunk_size"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"hamiltonian: {name} must be >= 1, got {getattr(self, name)}")
        if int(self.iterations) < 0:
            raise ConfigError(f"hamiltonian: iterations must be >= 0, got {self.iterations}")
        if self.convention not in df.CONVENTIONS:
            raise ConfigError(f"hamiltonian: convention must be one of {df.CONVENTIONS}, got {self.convention!r}")


@dataclass
class HamiltonianFit:
    """The optimized simulation of one pair (output of :func:`hamiltonian_interpolation`).

    Attributes
    ----------
    frames : (T, n_x, 3) float
        Positions of all vertices of x at ``times``, in the input units of ``verts_x``; the translation between
        the two box centres is added linearly in t (docs/hamiltonian.md §4).
    times : (T,) float
    coeffs : (3 K^3,) float
        Initial field coefficients ``a``.
    xi : (S, 3 K^3) float
        Per-step coefficients ``xi_t`` (S >= N steps, more when extrapolating).
    anisotropy : (n, 3, 3) float
        The optimized ``A_i`` of the samples.
    lambda_inertia : float
    samples : (n,) int64
        Indices of the samples in x.
    energies : dict
        ``align``, ``arap`` and ``loss`` of the final parameters.
    history : list of (float, float)
        ``(align, arap)`` of every Adam iteration (before its step).
    seconds : float
        Wall time of the whole call.
    """

    frames: torch.Tensor
    times: torch.Tensor
    coeffs: torch.Tensor
    xi: torch.Tensor
    anisotropy: torch.Tensor
    lambda_inertia: float
    samples: torch.Tensor
    energies: dict = field(default_factory=dict)
    history: list = field(default_factory=list)
    seconds: float = 0.0


# ----------------------------------------------------------------------------------------------------------
# The simulation
# ----------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Graph:
    """kNN graph of the samples: undirected edges (a, b), multiplicities, rest edge vectors."""

    edges: torch.Tensor  # (E, 2) int64
    weights: torch.Tensor  # (E,) float
    rest: torch.Tensor  # (E, 3) x_0[b] - x_0[a]
    #: Sparsity pattern of the block matrix of :func:`_dynamics_operator` and the degrees, per sample count (built
    #: once).
    patterns: dict = field(default_factory=dict, compare=False, repr=False)

    def degree(self, n: int) -> torch.Tensor:
        """Weighted degree ``d_i = sum_{e ∋ i} c_e`` of the n samples (n,), built once."""
        if ("degree", n) not in self.patterns:
            w = self.weights
            self.patterns[("degree", n)] = w.new_zeros(n).index_add(0, self.edges[:, 0], w).index_add(
                0, self.edges[:, 1], w)
        return self.patterns[("degree", n)]

    @functools.cached_property
    def weighted_rest(self) -> torch.Tensor:
        """``c_e e(x_0)`` (E, 3): the rest edges weighted for the ARAP covariances."""
        return self.rest * self.weights.to(self.rest).unsqueeze(-1)

    def block_pattern(self, n: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """CSR layout of a ``(3n, 3n)`` matrix of 3x3 blocks on the diagonal and at ``(a, b)``, ``(b, a)``.

        Returns ``crow (3n + 1,)``, ``col (9 m,)`` and ``perm (9 m,)``: the CSR values are
        ``blocks.reshape(-1)[perm]`` for the ``m = n + 2E`` blocks in the order diagonal, ``(a, b)``, ``(b, a)``.
        """
        if n not in self.patterns:
            device = self.edges.device
            idx = torch.arange(n, device=device)
            a, b = self.edges[:, 0], self.edges[:, 1]
            block_row, block_col = torch.cat([idx, a, b]), torch.cat([idx, b, a])
            three = torch.arange(3, device=device)
            row = (3 * block_row[:, None, None] + three[None, :, None]).expand(-1, 3, 3).reshape(-1)
            col = (3 * block_col[:, None, None] + three[None, None, :]).expand(-1, 3, 3).reshape(-1)
            perm = torch.argsort(row * (3 * n) + col)
            crow = torch.zeros(3 * n + 1, dtype=torch.int64, device=device)
            crow[1:] = torch.bincount(row, minlength=3 * n).cumsum(0)
            self.patterns[n] = (crow, col[perm], perm)
        return self.patterns[n]


def _laplacian_apply(q: torch.Tensor, graph: _Graph) -> torch.Tensor:
    """``H q`` for the weighted graph Laplacian H (``(H q)_a = sum_e c_e (q_a - q_b)``) of ``q (n, ...)``."""
    a, b = graph.edges[:, 0], graph.edges[:, 1]
    w = graph.weights.view(-1, *([1] * (q.ndim - 1))).to(q)
    diff = w * (q.index_select(0, a) - q.index_select(0, b))
    return torch.zeros_like(q).index_add(0, a, diff).index_add(0, b, -diff)


def _force(x: torch.Tensor, x_pred: torch.Tensor, x0: torch.Tensor, graph: _Graph, aniso: torch.Tensor):
    """Anisotropic ARAP force at ``x`` with rotations of the predicted pose (module docstring, step 2).

    The rotations are those of :func:`shapecorr.losses.arap.arap_rotations` (the same covariances, bitwise: the
    weights are edge multiplicities, 1 or 2, so weighting the rest edges first is exact), without its checks of
    the fixed graph at every step.

    Returns
    -------
    force : (n, 3)
    rest_rotated : (E, 3)
        ``(R_a + R_b)/2 e(x_0)`` (for the energy after the step).
    frames : (n, 3, 3)
        ``R'_i = R_i A_i^T``.
    """
    n, a, b = x.shape[0], graph.edges[:, 0], graph.edges[:, 1]
    edge_pred = x_pred.index_select(0, b) - x_pred.index_select(0, a)
    outer = (edge_pred.unsqueeze(-1) * graph.weighted_rest.unsqueeze(-2)).reshape(-1, 9)
    cov = x.new_zeros(n, 9).index_add(0, a, outer).index_add(0, b, outer)
    rot = rotations_from_covariances(cov.reshape(n, 3, 3), differentiable=True)
    return _ForceFromRotations.apply(x, rot, aniso, graph)


class _ForceFromRotations(torch.autograd.Function):
    """The force of :func:`_force` from the rotations ``R (n, 3, 3)``, with a hand-written backward.

    Forward: ``r_e = e(x) - (R_a + R_b)/2 e(x_0)``, ``R'_i = R_i A_i^T``, ``s_e = c_e ((R'_a + R'_b)/2)^T r_e``,
    ``f_i = R'_i sum_e ±s_e``; returns ``f (n, 3)``, ``(R_a + R_b)/2 e(x_0) (E, 3)`` and ``R' (n, 3, 3)``.
    Backward: the chain rule through these linear and bilinear maps (one scatter per edge list and gradient,
    instead of autograd's node per gather, product and transpose).
    """

    @staticmethod
    def forward(ctx, x, rot, aniso, graph):
        a, b = graph.edges[:, 0], graph.edges[:, 1]
        rot_edge = 0.5 * (rot.index_select(0, a) + rot.index_select(0, b))
        rest_rotated = (rot_edge @ graph.rest.unsqueeze(-1)).squeeze(-1)
        residual = edge_vectors(x, graph.edges) - rest_rotated
        frames = rot @ aniso.transpose(1, 2)
        frame_edge = 0.5 * (frames.index_select(0, a) + frames.index_select(0, b))
        back = (frame_edge.transpose(1, 2) @ residual.unsqueeze(-1)).squeeze(-1) * graph.weights.unsqueeze(-1)
        summed = torch.zeros_like(x).index_add(0, a, back).index_add(0, b, -back)
        force = (frames @ summed.unsqueeze(-1)).squeeze(-1)
        ctx.save_for_backward(rot, aniso, residual, frames, frame_edge, summed)
        ctx.graph = graph
        return force, rest_rotated, frames

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_force, grad_rest_rotated, grad_frames):
        rot, aniso, residual, frames, frame_edge, summed = ctx.saved_tensors
        graph = ctx.graph
        a, b = graph.edges[:, 0], graph.edges[:, 1]
        g_frames = torch.zeros_like(frames) if grad_frames is None else grad_frames.clone()
        g_residual = torch.zeros_like(residual)
        if grad_force is not None:
            g_summed = (frames.transpose(1, 2) @ grad_force.unsqueeze(-1)).squeeze(-1)
            g_frames += grad_force.unsqueeze(-1) * summed.unsqueeze(-2)
            g_back = (g_summed.index_select(0, a) - g_summed.index_select(0, b)) * graph.weights.unsqueeze(-1)
            g_frame_edge = 0.5 * (residual.unsqueeze(-1) * g_back.unsqueeze(-2))
            g_frames.index_add_(0, a, g_frame_edge).index_add_(0, b, g_frame_edge)
            g_residual = (frame_edge @ g_back.unsqueeze(-1)).squeeze(-1)
        g_x = torch.zeros_like(summed).index_add_(0, b, g_residual).index_add_(0, a, -g_residual)
        g_rest_rotated = -g_residual if grad_rest_rotated is None else grad_rest_rotated - g_residual
        g_rot_edge = 0.5 * (g_rest_rotated.unsqueeze(-1) * graph.rest.unsqueeze(-2))
        g_rot = (g_frames @ aniso).index_add_(0, a, g_rot_edge).index_add_(0, b, g_rot_edge)
        g_aniso = g_frames.transpose(1, 2) @ rot
        return g_x, g_rot, g_aniso, None


def _dynamics_operator(frames: torch.Tensor, lam: torch.Tensor, h: float, graph: _Graph) -> torch.Tensor:
    """``G = lambda' I + h^2 B^T (H x I_3) B`` as a sparse ``(3n, 3n)`` CSR matrix (``B = diag(R'_i^T)``).

    Its 3x3 blocks: ``lambda' I + h^2 d_i R'_i R'_i^T`` on the diagonal (``d_i`` the weighted degree) and
    ``-h^2 c_e R'_a R'_b^T`` at ``(a, b)`` (transposed at ``(b, a)``), so that ``Psi^T G Psi`` is the matrix of
    step 3 and ``(G v)_i = lambda' v_i + h^2 R'_i (H (R'^T v))_i`` for ``v (n, 3)``.
    """
    n = frames.shape[0]
    weights, degree = graph.weights.to(frames), graph.degree(n).to(frames)
    h2 = h * h
    eye = torch.eye(3, dtype=frames.dtype, device=frames.device)
    diag = lam * eye + (h2 * degree)[:, None, None] * (frames @ frames.transpose(1, 2))
    off = (-h2 * weights)[:, None, None] * (frames.index_select(0, graph.edges[:, 0])
                                            @ frames.index_select(0, graph.edges[:, 1]).transpose(1, 2))
    crow, col, perm = graph.block_pattern(n)
    values = torch.cat([diag, off, off.transpose(1, 2)]).reshape(-1).index_select(0, perm)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta state")
        return torch.sparse_csr_tensor(crow, col, values, (3 * n, 3 * n), check_invariants=False)


def _system_product(psi: torch.Tensor, product: torch.Tensor, k: int) -> torch.Tensor:
    """``psi^T product (F, F)`` for direction-major ``(n, 3, F)`` matrices whose product is symmetric.

    ``psi`` is the basis of :func:`_direction_major_basis` (rows ``(i, d)``, columns ``(e, abc)``), which is
    zero where ``d = e``: block row e of the product sums over the two rows ``d != e`` only, and only the blocks
    on and below the diagonal are multiplied (2/3 of the full product's work times 2/3); the others are their
    transposes. (The diagonal blocks are symmetric up to round-off; the Cholesky factorization reads the lower
    triangle.)
    """
    m = k ** 3
    out = psi.new_empty(3 * m, 3 * m)
    for e in range(3):
        rows, cols = slice(e * m, (e + 1) * m), slice(0, (e + 1) * m)
        d1, d2 = [d for d in range(3) if d != e]
        block = psi[:, d1, rows].T @ product[:, d1, cols]
        out[rows, cols] = block.addmm_(psi[:, d2, rows].T, product[:, d2, cols])
        for e2 in range(e):
            out[e2 * m:(e2 + 1) * m, rows] = out[rows, e2 * m:(e2 + 1) * m].T
    return out


def _levi_civita() -> torch.Tensor:
    """``(3, 3, 3)``: ``eps[i, j, d] = eps_ijd`` (+1 for the cyclic orders, -1 for the others, 0 else)."""
    eps = torch.zeros(3, 3, 3)
    for i, j, d in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        eps[i, j, d], eps[i, d, j] = 1.0, -1.0
    return eps


#: Levi-Civita symbol: ``v_i = sum_jd eps_ijd d_j Phi_d`` (the curl of the potentials).
_EPS = _levi_civita()
#: Order (0 or 1) of the factor of axis m in the first derivative ``d_j psi``: ``_ORDER_AXIS[m][j] = (j == m)``.
_ORDER_AXIS = torch.eye(3, dtype=torch.int64)


def _gradient_factors(factors: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The factors of ``d_j psi_abc`` for j = 0, 1, 2 along x, y and z, each ``(n, 3 j, K)``."""
    orders = _ORDER_AXIS.to(factors.device)
    return tuple(factors[:, :, m].index_select(1, orders[m]) for m in range(3))


def _field_factors(points: torch.Tensor, n_modes: int) -> torch.Tensor:
    """Per-coordinate factors of the potentials and their derivatives, ``(n, 3 orders, 3 axes, K)``.

    Order 0, 1, 2 of axis m: ``sin(a pi x_m)``, ``a cos(a pi x_m)``, ``-a^2 sin(a pi x_m)`` (each derivative
    without its factor pi, as :mod:`shapecorr.geometry.divergence_free` writes the fields).
    """
    k = torch.arange(1, n_modes + 1, dtype=points.dtype, device=points.device)
    arg = points.unsqueeze(-1) * (math.pi * k)
    sin = torch.sin(arg)
    return torch.stack((sin, torch.cos(arg) * k, -sin * k**2), dim=1)


def _potential_derivatives(factors: torch.Tensor, pot: torch.Tensor) -> torch.Tensor:
    """Every mixed derivative of order <= 2 per axis of the potentials ``pot (S, 3, K, K, K)`` at the points.

    Returns ``(n, 3 o_y, 3 o_z, S, 3 d, 3 o_x)``, flattened to ``(n, 81 S)``: ``sum_abc pot[s, d, a, b, c]
    X^{o_x}_a Y^{o_y}_b Z^{o_z}_c`` with the factors of :func:`_field_factors` (the derivative of ``Phi_d / pi``
    of orders ``(o_x, o_y, o_z)``, up to one factor pi per order above the first). Three batched products, one
    axis each, laid out so that no intermediate is copied; :func:`_derivative_index` picks entries.
    """
    n, k, s = factors.shape[0], factors.shape[-1], pot.shape[0]
    t = factors[:, :, 2] @ pot.reshape(s * 3 * k * k, k).T  # (n, o_z, s d a b)
    t = factors[:, :, 1] @ t.reshape(n, 3 * s * 3 * k, k).transpose(1, 2)  # (n, o_y, o_z s d a)
    t = t.reshape(n, 3 * 3 * s * 3, k) @ factors[:, :, 0].transpose(1, 2)  # (n, o_y o_z s d, o_x)
    return t.reshape(n, -1)


@functools.lru_cache(maxsize=8)
def _derivative_index(s: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """Positions in the output of :func:`_potential_derivatives` (S fields) of the derivatives a step needs.

    Returns ``grad (9,)``: ``d_j Phi_d`` of field 0 in the order ``(d, j)``, and ``hess (27 S,)``: ``d_l d_j Phi_d``
    of every field in the order ``(s, d, j, l)``.
    """
    def flat(orders, field, d):
        o_x, o_y, o_z = orders
        return (((o_y * 3 + o_z) * s + field) * 3 + d) * 3 + o_x

    unit = [tuple(int(m == j) for m in range(3)) for j in range(3)]
    grad = [flat(unit[j], 0, d) for d in range(3) for j in range(3)]
    hess = [flat(tuple(p + q for p, q in zip(unit[j], unit[m])), field, d)
            for field in range(s) for d in range(3) for j in range(3) for m in range(3)]
    return torch.tensor(grad, device=device), torch.tensor(hess, device=device)


def _basis_transpose(factors: torch.Tensor, w: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """``Psi^T w (F,)`` for per-point vectors ``w (n, 3)``, without the basis: ``sum_i w_i . v_f(x_i)``.

    Fields direction-major (``scales`` of :func:`_direction_major_scales`).

    With ``v_f = s_f curl(psi_abc e_d)``: ``s_f sum_{i, j} (sum_c w_ic eps_cjd) d_j psi_abc(x_i)``, one product
    over the points for the three derivative directions j.
    """
    n, k = factors.shape[0], factors.shape[-1]
    skew = (w @ _EPS.to(w).reshape(3, 9)).reshape(n, 3, 3, 1)  # (n, j, d): sum_c w_c eps_cjd
    # factors of d_j psi: order 1 along axis j, 0 along the others
    fx, fy, fz = _gradient_factors(factors)  # (n, j, K)
    t = (skew * fx.unsqueeze(2)).unsqueeze(-1) * fy[:, :, None, None, :]  # (n, j, d, a, b)
    t = t.reshape(n * 3, 3 * k * k).T @ fz.reshape(n * 3, k)  # (d a b, c)
    return t.reshape(-1) * scales


#: Per row ``(d, e)`` of the direction-major basis: the derivative direction j of ``eps_dje`` (the third index; j = d
#: on the zero rows d = e).
_THIRD = tuple((3 - d - e) % 3 for d in range(3) for e in range(3))


@functools.lru_cache(maxsize=8)
def _direction_major_scales(k: int, convention: str, dtype: torch.dtype, device: torch.device):
    """Scales of the fields in direction-major order and the signed table of the basis assembly.

    Returns ``scales (3 K^3,)`` (field ``(e, abc)``: ``s_{abc, e}``) and ``signed (9, K^3)`` (row ``(d, e)``:
    ``eps_dje s_{abc, e}`` with j = ``_THIRD[3 d + e]``, 0 where d = e).
    """
    scales = df.basis_scales(k, convention, dtype=dtype, device=device).reshape(k ** 3, 3).T.contiguous()
    eps = _EPS.to(dtype=dtype, device=device)
    sign = torch.stack([eps[d, _THIRD[3 * d + e], e] for d in range(3) for e in range(3)])
    return scales.reshape(-1), sign[:, None] * scales.repeat(3, 1)


def _direction_major_basis(factors: torch.Tensor, k: int, convention: str) -> torch.Tensor:
    """The basis at the points of ``factors`` (:func:`_field_factors`), ``(n, 3 d, 3 K^3)``, fields direction-major.

    Entry ``(i, d, (e, abc))`` is component d of the field ``(abc, e)`` (field ``abc * 3 + e`` of
    :func:`shapecorr.geometry.divergence_free.basis_fields`, the same products, bitwise): ``eps_dje s_{abc,e}
    d_j psi_abc(x_i)``, zero for ``d = e``. Each of the nine ``(n, K^3)`` blocks is written in place.
    """
    n = factors.shape[0]
    _, signed = _direction_major_scales(k, convention, factors.dtype, factors.device)
    fx, fy, fz = _gradient_factors(factors)  # (n, j, K)
    grad = ((fx[:, :, :, None] * fy[:, :, None, :]).reshape(n, 3, k * k, 1) * fz[:, :, None, :]).reshape(n, 3, -1)
    out = factors.new_empty(n, 9, k ** 3)
    for row, j in enumerate(_THIRD):  # rows d = e: signed is 0 there
        torch.mul(grad[:, j], signed[row], out=out[:, row])
    return out.reshape(n, 3, 3 * k ** 3)


def _to_direction_major(coeffs: torch.Tensor, k: int) -> torch.Tensor:
    """Field order ``abc * 3 + e`` -> direction-major ``e * K^3 + abc`` (``(..., 3 K^3)``)."""
    return coeffs.reshape(*coeffs.shape[:-1], k ** 3, 3).transpose(-1, -2).reshape(*coeffs.shape[:-1], -1)


def _to_field_order(coeffs: torch.Tensor, k: int) -> torch.Tensor:
    """Direction-major -> the field order of :mod:`shapecorr.geometry.divergence_free`."""
    return coeffs.reshape(*coeffs.shape[:-1], 3, k ** 3).transpose(-1, -2).reshape(*coeffs.shape[:-1], -1)


class _StepSolve(torch.autograd.Function):
    """Step 3-4 of the module docstring with a hand-written backward.

    Forward: the basis ``Psi (3n, F)`` at ``mid`` (fields direction-major, :func:`_direction_major_basis`),
    ``W = G Psi`` with ``G = lambda' I + h^2 B^T H B`` (``B`` the block diagonal of ``R'_i^T``, so that
    ``Q = B Psi``), the system ``S = Psi^T W + ridge I`` (:func:`_system_product`; symmetric positive definite:
    Cholesky in float64), ``xi = S^-1 Psi^T b`` (returned in the field order of
    :mod:`shapecorr.geometry.divergence_free`) and ``v = Psi xi``.

    Backward: the gradient of ``xi = S^-1 r`` with respect to S is the outer product ``-u xi^T`` (``u = S^-1 g``),
    so every gradient of the F x F system reduces to products of ``Psi`` with the two vectors ``u`` and ``xi``:
    the cotangent of ``Psi_i`` is ``alpha_i u^T + beta_i xi^T`` (``alpha, beta (n, 3)``), whose pull-back to
    ``mid`` is ``J_u(mid_i)^T alpha_i + J_xi(mid_i)^T beta_i`` with ``J_c`` the Jacobian of the field of
    coefficients c: the second derivatives of the potentials, evaluated from the per-coordinate factors
    (:func:`_potential_derivatives`), as are ``Psi^T grad_v`` and ``Psi u`` (:func:`_basis_transpose`). Nothing
    of size ``n x F`` is kept between forward and backward (only the Cholesky factor), and the backward costs
    no ``n F^2`` product.
    """

    @staticmethod
    def forward(ctx, mid, frames, lam, rhs, graph, h, cfg):
        n, k = mid.shape[0], cfg.n_modes
        factors = _field_factors(mid, k)
        psi = _direction_major_basis(factors, k, cfg.convention)  # (n, 3, F), rows (i, d)
        operator = _dynamics_operator(frames, lam, h, graph)
        # G Psi into a fresh buffer: beta = 0 ignores its contents (the plain sparse product zero-fills a
        # temporary and copies it, three times the work at these sizes)
        product = psi.new_empty(3 * n, psi.shape[-1])
        torch.addmm(product, operator, psi.reshape(3 * n, -1), beta=0, out=product)
        system = _system_product(psi, product.reshape(n, 3, -1), k).double()
        del product  # 3 n F floats: not kept through the factorization
        system.diagonal().add_(cfg.ridge)
        factor, info = torch.linalg.cholesky_ex(system)
        del system
        if int(info) != 0:
            raise NumericalError("hamiltonian: the per-step system is not positive definite; lower lr or check "
                                 "the inputs")
        psi = psi.reshape(3 * n, -1)
        r = psi.T @ rhs.reshape(3 * n)
        xi = torch.cholesky_solve(r.double().unsqueeze(-1), factor).squeeze(-1).to(mid.dtype)  # direction-major
        if not bool(torch.isfinite(xi).all()):
            raise NumericalError("hamiltonian: the per-step linear solve gave NaN/Inf; lower lr or check the inputs")
        v = (psi @ xi).reshape(n, 3)
        ctx.save_for_backward(frames, rhs, xi, v, factor, factors)
        ctx.graph, ctx.h, ctx.cfg, ctx.operator = graph, h, cfg, operator
        return _to_field_order(xi, k), v

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_xi, grad_v):
        frames, rhs, xi, v, factor, factors = ctx.saved_tensors
        graph, h, cfg, operator = ctx.graph, ctx.h, ctx.cfg, ctx.operator
        n, k = v.shape[0], cfg.n_modes
        scales = _direction_major_scales(k, cfg.convention, v.dtype, v.device)[0]
        g = _to_direction_major(grad_xi, k) if grad_xi is not None else torch.zeros_like(xi)
        if grad_v is not None:
            g = g + _basis_transpose(factors, grad_v, scales)  # Psi^T grad_v
        else:
            grad_v = torch.zeros_like(v)
        u = torch.cholesky_solve(g.double().unsqueeze(-1), factor).squeeze(-1).to(xi.dtype)
        # potentials of the two fields Psi u and Psi xi: (2, 3 d, K, K, K)
        pot = (torch.stack((u, xi)) * scales).reshape(2, 3, k, k, k)
        deriv = _potential_derivatives(factors, pot)
        at_grad, at_hess = _derivative_index(2, v.device)
        eps_dj = _EPS.to(v).permute(0, 2, 1).reshape(3, 9)  # [i, (d, j)]
        # Psi u: the curl of the gradient
        p_u = deriv.index_select(1, at_grad) @ eps_dj.T
        # cotangent of Psi_i: alpha_i u^T + beta_i xi^T with alpha = rhs - G Psi xi, beta = grad_v - G Psi u
        both = (operator @ torch.stack((v, p_u), dim=-1).reshape(3 * n, 2)).reshape(n, 3, 2)
        weights = torch.stack((rhs - both[..., 0], grad_v - both[..., 1]), dim=1)  # (n, 2, 3)
        grad_mid = None
        if ctx.needs_input_grad[0]:
            # sum_i w_i d_l v_i = pi sum_{j, d} (sum_i w_i eps_ijd) d_l d_j Phi_d, both fields at once
            skew = (weights @ eps_dj).reshape(n, 1, 18)  # (s, d, j)
            hess = deriv.index_select(1, at_hess).reshape(n, 18, 3)  # (s, d, j), l
            grad_mid = math.pi * (skew @ hess).reshape(n, 3)
        rotated = frames.transpose(1, 2) @ torch.stack((v, p_u), dim=-1)  # (n, 3, 2): R'^T v, R'^T Psi u
        lap = _laplacian_apply(rotated, graph)
        grad_frames = (-h * h) * (torch.stack((p_u, v), dim=-1) @ lap.transpose(1, 2))
        grad_lam = -(p_u * v).sum()
        return grad_mid, grad_frames, grad_lam, p_u, None, None, None


def _solve_step(mid: torch.Tensor, v_pred: torch.Tensor, force: torch.Tensor, frames: torch.Tensor, graph: _Graph,
                lam: torch.Tensor, h: float, cfg: HamiltonianConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Coefficients ``xi`` of the new velocity and the velocity at the samples (module docstring, step 3-4)."""
    return _StepSolve.apply(mid, frames, lam, lam * v_pred + 0.5 * h * force, graph, h, cfg)


def _simulate(x0: torch.Tensor, coeffs: torch.Tensor, aniso: torch.Tensor, log_lam: torch.Tensor, graph: _Graph,
              n_total: int, cfg: HamiltonianConfig):
    """Run ``n_total`` steps on the samples; positions after step N, the ARAP energy and every ``xi_t``."""
    h = 1.0 / cfg.n_steps
    lam = torch.exp(log_lam) * h
    scale = x0.shape[0] * cfg.n_steps * ARAP_NORMALIZATION / cfg.knn
    v = h * df.velocity(x0, coeffs, cfg.convention)
    v_prev = v
    x = x0
    energy = x0.new_zeros(())
    x_end = x0
    xis = []
    for step in range(n_total):
        v_pred = 2.0 * v - v_prev if cfg.extrapolate_velocity else v
        v_prev = v
        force, rest_rotated, frames = _force(x, x + h * v_pred, x0, graph, aniso)
        xi, v = _solve_step(x + 0.5 * h * v_pred, v_pred, force, frames, graph, lam, h, cfg)
        x = x + h * v
        xis.append(xi)
        if step < cfg.n_steps:
            residual = edge_vectors(x, graph.edges) - rest_rotated
            energy = energy + (graph.weights * residual.square().sum(-1)).sum() / scale
        if step == cfg.n_steps - 1:
            x_end = x
    return x_end, energy, xis


def _replay(points: torch.Tensor, coeffs: torch.Tensor, xis, cfg: HamiltonianConfig) -> torch.Tensor:
    """Positions of any points after each step (``(S + 1, m, 3)``, including the start), chunked."""
    h = 1.0 / cfg.n_steps
    out = []
    for start in range(0, points.shape[0], cfg.chunk_size):
        x = points[start:start + cfg.chunk_size]
        v = h * df.velocity(x, coeffs, cfg.convention)
        v_prev = v
        path = [x]
        for xi in xis:
            v_pred = 2.0 * v - v_prev if cfg.extrapolate_velocity else v
            v_prev = v
            v = df.velocity(x + 0.5 * h * v_pred, xi, cfg.convention)
            x = x + h * v
            path.append(x)
        out.append(torch.stack(path, dim=0))
    return torch.cat(out, dim=1)


def _frames_at(path: torch.Tensor, times: torch.Tensor, n_steps: int) -> torch.Tensor:
    """Piecewise-linear positions at ``times`` from the per-step path ``(S + 1, m, 3)``."""
    frames = []
    for t in times.tolist():
        s = t * n_steps
        k = min(int(math.floor(s + STEP_ATOL)), path.shape[0] - 1)
        frac = s - k
        if frac <= STEP_ATOL or k == path.shape[0] - 1:
            frames.append(path[k])
        else:
            frames.append(path[k] + frac * (path[k + 1] - path[k]))
    return torch.stack(frames, dim=0)


def _check_inputs(verts_x, faces_x, verts_y_matched, mask, times) -> tuple[torch.Tensor, torch.Tensor]:
    for name, v in (("verts_x", verts_x), ("verts_y_matched", verts_y_matched)):
        if not isinstance(v, torch.Tensor) or v.ndim != 2 or v.shape[1] != 3 or not v.dtype.is_floating_point:
            raise ConfigError(f"hamiltonian: {name} must be an (n, 3) float tensor")
        if not bool(torch.isfinite(v).all()):
            raise NumericalError(f"hamiltonian: {name} contains NaN or Inf")
    if verts_y_matched.shape != verts_x.shape:
        raise ConfigError(f"hamiltonian: verts_y_matched must be (n_x, 3) = {tuple(verts_x.shape)} (the image of "
                          f"every vertex of x under the map), got {tuple(verts_y_matched.shape)}")
    if faces_x is not None and (faces_x.ndim != 2 or faces_x.shape[1] != 3):
        raise ConfigError(f"hamiltonian: faces_x must be (f, 3), got {tuple(faces_x.shape)}")
    if mask is None:
        mask = torch.ones(verts_x.shape[0], dtype=torch.bool, device=verts_x.device)
    mask = torch.as_tensor(mask, device=verts_x.device)
    if mask.shape != (verts_x.shape[0],) or mask.dtype != torch.bool:
        raise ConfigError(f"hamiltonian: mask must be a (n_x,) bool tensor, got {tuple(mask.shape)} {mask.dtype}")
    if not bool(mask.any()):
        raise ConfigError("hamiltonian: the mask marks no vertex of x with a known target")
    times = torch.as_tensor(times, dtype=torch.float32).reshape(-1)
    if times.numel() == 0 or not bool(torch.isfinite(times).all()) or bool((times < 0).any()):
        raise ConfigError(f"hamiltonian: times must be finite and >= 0 (the simulation runs forward), got "
                          f"{times.tolist()}")
    return mask, times


def hamiltonian_interpolation(verts_x: torch.Tensor, faces_x: torch.Tensor | None, verts_y_matched: torch.Tensor,
                              config: HamiltonianConfig | dict | None = None, times=HAMILTONIAN_TIMES,
                              mask: torch.Tensor | None = None) -> HamiltonianFit:
    """Optimize the Hamiltonian simulation moving x onto its targets and return its frames (module docstring).

    Parameters
    ----------
    verts_x : (n_x, 3) float
        The shape x (any units; the pair is placed in the unit box internally).
    faces_x : (f, 3) int64 or None
        Triangles of x (only checked; the simulation runs on a kNN graph of samples, as the original).
    verts_y_matched : (n_x, 3) float
        Target position of every vertex of x (``verts_y[p2p]`` for a map x -> y); rows outside ``mask`` are
        ignored.
    config : HamiltonianConfig or dict, optional
        Parameters (default: the published ones).
    times : sequence of float
        Frame times, >= 0 (t > 1 continues the simulation past step N).
    mask : (n_x,) bool, optional
        Vertices of x whose target is known (partial targets); default all. The alignment term is the mean
        squared error over the masked samples only; the ARAP energy and the dynamics cover every sample.

    Returns
    -------
    HamiltonianFit
    """
    start_time = time.perf_counter()
    cfg = config if isinstance(config, HamiltonianConfig) else HamiltonianConfig(**(config or {}))
    mask, times = _check_inputs(verts_x, faces_x, verts_y_matched, mask, times)
    vx = verts_x.detach().to(torch.float32)
    vy = verts_y_matched.detach().to(device=vx.device, dtype=torch.float32)
    box_x, box_y = df.box_normalization(vx, vy[mask], cfg.margin)
    bx, by = box_x.to_box(vx), box_y.to_box(vy)
    n_samples = min(int(cfg.samples), bx.shape[0])
    rng = np.random.default_rng(cfg.seed)
    samples = torch.from_numpy(farthest_point_sampling(bx.cpu(), n_samples, start=int(rng.integers(bx.shape[0]))))
    samples = samples.to(vx.device)
    x0 = bx[samples]
    knn = min(int(cfg.knn), n_samples - 1)
    if knn < 1:
        raise ConfigError("hamiltonian: x needs at least 2 vertices")
    edges, counts = knn_graph_edges(x0, knn)
    graph = _Graph(edges, counts, edge_vectors(x0, edges))
    keep = mask[samples]
    if not bool(keep.any()):
        raise ConfigError("hamiltonian: no farthest-point sample of x has a known target; raise model.samples")
    target = by[samples][keep]

    coeffs = torch.zeros(df.n_fields(cfg.n_modes), device=vx.device, requires_grad=True)
    aniso = torch.eye(3, device=vx.device).repeat(n_samples, 1, 1).requires_grad_(cfg.learn_anisotropy)
    log_lam = torch.tensor(math.log(cfg.lambda_inertia), device=vx.device).requires_grad_(cfg.learn_inertia)
    params = [p for p in (coeffs, aniso, log_lam) if p.requires_grad]
    optimizer = torch.optim.Adam(params, lr=cfg.lr)
    history = []
    with torch.enable_grad():
        for _ in range(int(cfg.iterations)):
            optimizer.zero_grad(set_to_none=True)
            x_end, e_arap, _ = _simulate(x0, coeffs, aniso, log_lam, graph, cfg.n_steps, cfg)
            e_align = torch.nn.functional.mse_loss(x_end[keep], target)
            loss = e_align + cfg.lambda_reg * e_arap
            if not bool(torch.isfinite(loss.detach())):
                raise NumericalError("hamiltonian: the energy became non-finite; lower model.lr")
            if float(e_align.detach()) < cfg.align_tolerance:
                break
            loss.backward()
            optimizer.step()
            history.append((float(e_align.detach()), float(e_arap.detach())))

    n_total = max(cfg.n_steps, int(math.ceil(float(times.max()) * cfg.n_steps - STEP_ATOL)))
    with torch.no_grad():
        x_end, e_arap, xis = _simulate(x0, coeffs.detach(), aniso.detach(), log_lam.detach(), graph, n_total, cfg)
        e_align = torch.nn.functional.mse_loss(x_end[keep], target)
        energies = {"align": float(e_align), "arap": float(e_arap), "loss": float(e_align + cfg.lambda_reg * e_arap)}
        path = _replay(bx, coeffs.detach(), xis, cfg)
        if not bool(torch.isfinite(path).all()):
            raise NumericalError("hamiltonian: the full-resolution replay diverged (NaN/Inf)")
        frames = _frames_at(path, times, cfg.n_steps)
        shift = (box_y.center - box_x.center).to(frames)
        frames = box_x.from_box(frames) + times.to(frames).reshape(-1, 1, 1) * shift
    return HamiltonianFit(
        frames=frames.to(verts_x.dtype), times=times, coeffs=coeffs.detach(), xi=torch.stack(xis, dim=0),
        anisotropy=aniso.detach(), lambda_inertia=float(torch.exp(log_lam.detach())), samples=samples,
        energies=energies, history=history, seconds=time.perf_counter() - start_time,
    )


# ----------------------------------------------------------------------------------------------------------
# The matcher
# ----------------------------------------------------------------------------------------------------------
class Hamiltonian(LinearBlend):
    """Hamiltonian interpolation around any matcher (configs/model/hamiltonian.yaml).

    The maps are those of the wrapped matcher; the frames are the optimized simulation moving every vertex of
    x towards its image ``y[p2p]`` (:func:`hamiltonian_interpolation`). It reuses LinearBlend's wrapping (the
    matcher's ``required_operators`` / ``needs_ground_truth``, ``match`` at ``interp_times``, a
    ``torch.nn.Module`` so that ``.eval()`` / ``.to()`` reach a wrapped learned model) and replaces the
    straight lines by the simulation.

    Parameters
    ----------
    matcher : Matcher
        Anything with ``match(x, y) -> MatchResult`` (default in the config: ``identity_gt``).
    interp_times : sequence of float
        Frames of :meth:`match`, >= 0; :meth:`interpolate` takes any times >= 0.
    **config
        Fields of :class:`HamiltonianConfig`.
    """

    def __init__(self, matcher, interp_times=HAMILTONIAN_TIMES, **config):
        super().__init__(matcher, interp_times)
        if min(self.interp_times) < 0:
            raise ConfigError(f"Hamiltonian interp_times must be >= 0, got {list(self.interp_times)}")
        unknown = set(config) - set(HamiltonianConfig.__dataclass_fields__)
        if unknown:
            raise ConfigError(f"Hamiltonian: unknown options {sorted(unknown)} (configs/model/hamiltonian.yaml)")
        self.config = HamiltonianConfig(**config)

    def interpolate(self, x, y, times) -> MatchResult:
        """The wrapped matcher's maps and the Hamiltonian frames at ``times (T,)`` (values >= 0)."""
        result = self.matcher.match(x, y)
        p2p = result.p2p.to(x.verts.device)
        target = y.verts.detach().to(x.verts)[p2p]
        fit = hamiltonian_interpolation(x.verts, x.faces, target, self.config, times)
        extras = dict(result.extras)
        extras.update({"energies": fit.energies, "fit_seconds": fit.seconds, "lambda_inertia": fit.lambda_inertia})
        return MatchResult(p2p=result.p2p, p2p_inv=result.p2p_inv, deformation=fit.frames,
                           times=fit.times.to(fit.frames.device), extras=extras)
