"""Deep Shells: the differentiable hierarchical matching layer and its test-time refinement.

Eisenberger, Toker, Leal-Taixé, Cremers, "Deep Shells: Unsupervised Shape Correspondence with Optimal
Transport", NeurIPS 2020 (docs/deep_shells.md §6, §8). Pure functions on tensors; the LightningModule that
wraps them lives in ``shapecorr.models``.

Training layer (:func:`deep_shells_layer`), for a pair (X, Y) and features at sampled vertices:

1. soft correspondences ``P (n_s, m_s)``, ``P_adj (m_s, n_s)`` = Sinkhorn of the feature distances;
2. for each shell size ``k`` of the schedule (coarse to fine):

   a. smooth shells ``X_k``, ``Y_k`` (low-pass reconstructions of the coordinates, :mod:`shapecorr.geometry.shells`);
   b. closed-form fit, from the current soft correspondences, of a functional map ``C (k, k)`` and a spectral
      deformation ``tau (k, 3)``: least squares on the stacked two-sided correspondences
      ``[Phi_X; P_adj Phi_X] C ~ [P Phi_Y; Phi_Y]`` and ``[Phi_X; P_adj Phi_X] tau ~ [P Y_k - X_k; Y_k - P_adj X_k]``
      (float64 normal equations with a tiny ridge, :mod:`shapecorr.matching.least_squares`);
   c. product-space embedding of the deformed shell ``X* = X_k + Phi_X tau`` and of ``Y_k``:
      ``[X*, a_s Phi_X C, a_n n(X*)]`` vs ``[Y_k, a_s Phi_Y, a_n n(Y_k)]`` with ``a_s = fac_spec |Y_k| / |Phi_Y|``
      and ``a_n = fac_norm |Y_k| / |n(Y_k)|`` (Frobenius norms);
   d. new ``P, P_adj`` = Sinkhorn of the embedding distances; level energy
      ``E_k = sum |X* - P Y_k|^2 + sum |P_adj X* - Y_k|^2`` over the samples (a sum, as in the original);

3. loss = mean of the ``E_k``. Gradients flow through every Sinkhorn and every solve into the features.

Only what the samples need is computed: ``Phi`` rows and shells at the samples, the deformed shell on the
samples' one-ring (for their normals); ``Y_k`` (feature independent) at full resolution for its norms. All
feature-independent quantities of every level are prepared before the first Sinkhorn. The plans are never
formed: each enters only through one product with thin matrices (energy of its level and right-hand sides of
the next level's solve together), which :func:`~shapecorr.matching.sinkhorn.sinkhorn_sq_euclidean_products`
computes from the Gibbs kernel and the potentials, with a low-rank backward; autograd keeps one
``n_s x m_s`` kernel per level.

Test time (:func:`deep_shells_query`): feature Sinkhorn and one OT level at ``k_array[0]`` (no gradients),
then at full resolution a bidirectional nearest-neighbour matching in that level's embedding
(:func:`product_embedding_maps`, also usable on the last training level as G-MSM does), followed by the
axiomatic refinement :func:`refine_deep_shells`: 40 log-spaced shell sizes from 6 to 499, each fitting
``(C, tau)`` by least squares on the current two-sided nearest-neighbour pairs and re-matching (exact
nearest neighbours, :mod:`shapecorr.matching.nearest_neighbors`). Unlike the original, the OT level's
second Sinkhorn (whose plan the original computes and discards) is skipped.

Deviations from the original code (docs/deep_shells.md §9; ``DeepShellsConfig.original()`` restores all of the
original Python behaviour, and is what the parity test uses):

- Shell of X (``smooth_x``): the Deep Shells code truncates X hard at ``k`` but smooths Y with the sigmoid
  weights, so ``Y_k`` keeps frequencies up to ``k + 8`` that ``X* = X_k + Phi_X[:, :k] tau`` cannot represent.
  Default ``"sigmoid"``: both shells are sigmoid smoothed, as in the paper and the MATLAB Smooth Shells.
  Original: ``"hard"``.
- Sigmoid length (``sigmoid_inclusive``): MATLAB uses ``k+9`` weights (the last equals the truncation threshold
  0.01), the Python port ``k+8``. Default ``True`` (MATLAB, the designed range); original ``False``.
- Normal weight (``normal_norm``): the original divides by the norm of Y's normals **at the samples** but by
  the norm of ``Y_k`` over **all** vertices, so the normal weight grows with ``sqrt(n / n_samples)`` and differs
  between training (2000 samples) and test (all vertices). Default ``"all"``: both norms over all vertices,
  so training and test embeddings agree. Original: ``"samples"``. At full resolution both coincide.
- Scale factors: the MATLAB Smooth Shells scales X's embedding with Y's factors and vice versa; Deep Shells
  uses one pair of factors, computed from Y, for both sides, which is what a distance between the two
  embeddings needs. Kept (there is no swap here to reproduce).
- Solves: float64 normal equations with a relative ridge of ``ridge`` (default 1e-8) instead of float32
  unregularized ``torch.solve``; differences are far below float32 resolution on well-posed problems.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch

from shapecorr.errors import ConfigError, NumericalError
from shapecorr.geometry.normals import vertex_normals
from shapecorr.geometry.sampling import farthest_point_sampling
from shapecorr.geometry.shells import sigmoid_shell_weights, smooth_shell
from shapecorr.geometry.spectral_shape import SpectralShape, reorder_vertices
from shapecorr.geometry.finiteness import all_finite
from shapecorr.matching.least_squares import DEFAULT_RIDGE, normal_equations, solve_normal_equations
from shapecorr.matching.nearest_neighbors import bidirectional_nearest_neighbors, resolved_backend, spatial_order
from shapecorr.matching.sinkhorn import (
    DEFAULT_NUM_ITERS,
    DEFAULT_SIGMA,
    pairwise_sq_dists,
    sinkhorn_log_reference,
    sinkhorn_sq_euclidean_products,
)

#: Training shell sizes: DeepParam k_min=6, k_max=21, k_array_len=8, log-spaced and int-truncated
#: (stored in the released checkpoint's ``par.k_array``).
DEFAULT_K_ARRAY = (6, 7, 8, 10, 12, 14, 17, 21)
#: DeepParam ``fac_spec``: weight of the spectral block of the training embedding.
DEFAULT_FAC_SPEC = 0.3
#: DeepParam ``fac_norm``: weight of the normals in the training embedding.
DEFAULT_FAC_NORM = 0.025
#: Param() defaults used by the test-time refinement (AssSmoothShells): fac_spec 0.25, fac_norm 0.04.
DEFAULT_REFINE_FAC_SPEC = 0.25
DEFAULT_REFINE_FAC_NORM = 0.04
#: Param() k schedule of the refinement: 40 log-spaced sizes from 6 to 500, int-truncated (6, 6, 7, ..., 446, 499).
DEFAULT_REFINE_K_MIN = 6
DEFAULT_REFINE_K_MAX = 500
DEFAULT_REFINE_LEVELS = 40
#: DeepParam ``subsample_num``: random samples per shape and training step (drawn with replacement).
DEFAULT_NUM_SAMPLES = 2000
#: test_model ``max_vert``: larger shapes are farthest-point subsampled to this many points for the OT part.
DEFAULT_MAX_QUERY_POINTS = 6000

#: Rows per block of the refinement's float64 products ``Phi^T (w Phi)`` of float32 bases: larger shapes are
#: summed over row blocks, so no float64 copy of a whole (n, k) basis exists (meshes up to this size: one block).
REFINE_ROW_BLOCK = 32768
#: Shapes with at least this many vertices are refined with their vertices in a spatial order when the search runs
#: on k-d trees (:func:`~shapecorr.matching.nearest_neighbors.spatial_order`; the maps are returned in the
#: original numbering): large trees do not fit the CPU caches. Below it the order made no difference (5k vertices).
SPATIAL_ORDER_MIN_VERTS = 20000
_SHELL_MODES = ("sigmoid", "hard")
_NORMAL_NORMS = ("all", "samples")
_SINKHORN_IMPLS = ("fast", "reference")
_NN_BACKENDS = ("auto", "kdtree", "brute")


def log_spaced_k(k_min: int, k_max: int, num: int) -> tuple[int, ...]:
    """Shell sizes ``int(exp(linspace(log k_min, log k_max, num)))`` (the originals' schedule rule).

    The truncation is kept on purpose: ``log_spaced_k(6, 500, 40)`` ends with 499 and starts with 6, 6.

    Returns
    -------
    tuple of int, non-decreasing
    """
    if k_min < 1 or k_max < k_min or num < 1:
        raise ConfigError(f"invalid k schedule: k_min={k_min}, k_max={k_max}, num={num}")
    values = np.exp(np.linspace(np.log(k_min), np.log(k_max), num))
    return tuple(max(1, int(v)) for v in values)


@dataclass(frozen=True)
class DeepShellsConfig:
    """Hyperparameters of the Deep Shells matching layer and test-time refinement.

    Defaults are the published values (released checkpoint ``par`` and ``param.py``), except for the
    deviations from the original code (docs/deep_shells.md §9, module docstring); :meth:`original` gives the
    original behaviour.

    Attributes
    ----------
    k_array : tuple of int
        Training shell sizes (coarse to fine). The test-time OT level uses ``k_array[0]``.
    sigma : float
        Sinkhorn temperature (``sigma_sink``).
    num_sinkhorn : int
        Sinkhorn normalization rounds (``num_sink``).
    fac_spec, fac_norm : float
        Weights of the spectral block and the normals in the training / OT embedding.
    refine_fac_spec, refine_fac_norm : float
        The same for the test-time refinement.
    refine_k_min, refine_k_max, refine_levels : int
        Refinement schedule, :func:`log_spaced_k` (6, 500, 40 -> 6, 6, 7, ..., 446, 499).
    num_samples : int
        Random vertices per shape and training step (used by the training module, not by the layer).
    max_query_points : int
        Test time: above this many vertices the OT part runs on farthest-point samples.
    smooth_x : {"sigmoid", "hard"}
        Shell of X; the original truncates hard (deviation from the original code, docs/deep_shells.md §9).
    sigmoid_inclusive : bool
        Sigmoid weight count k+9 (True, MATLAB) or k+8 (False, original Python port).
    normal_norm : {"all", "samples"}
        Vertices over which Y's normals are normed for their weight; the original uses the samples.
    ridge : float
        Relative ridge of the (C, tau) normal equations.
    sinkhorn_impl : {"fast", "reference"}
        :func:`~shapecorr.matching.sinkhorn.sinkhorn_sq_euclidean_products` (plans never formed) or the
        op-by-op log-domain version (plans formed, autograd).
    nn_backend : {"auto", "kdtree", "brute"}
        Nearest-neighbour search at test time (:mod:`shapecorr.matching.nearest_neighbors`).
    """

    k_array: tuple[int, ...] = DEFAULT_K_ARRAY
    sigma: float = DEFAULT_SIGMA
    num_sinkhorn: int = DEFAULT_NUM_ITERS
    fac_spec: float = DEFAULT_FAC_SPEC
    fac_norm: float = DEFAULT_FAC_NORM
    refine_fac_spec: float = DEFAULT_REFINE_FAC_SPEC
    refine_fac_norm: float = DEFAULT_REFINE_FAC_NORM
    refine_k_min: int = DEFAULT_REFINE_K_MIN
    refine_k_max: int = DEFAULT_REFINE_K_MAX
    refine_levels: int = DEFAULT_REFINE_LEVELS
    num_samples: int = DEFAULT_NUM_SAMPLES
    max_query_points: int = DEFAULT_MAX_QUERY_POINTS
    smooth_x: str = "sigmoid"
    sigmoid_inclusive: bool = True
    normal_norm: str = "all"
    ridge: float = DEFAULT_RIDGE
    sinkhorn_impl: str = "fast"
    nn_backend: str = "auto"

    def __post_init__(self):
        object.__setattr__(self, "k_array", tuple(int(k) for k in self.k_array))
        if not self.k_array or min(self.k_array) < 1:
            raise ConfigError(f"deep_shells.k_array must be a non-empty list of sizes >= 1, got {self.k_array}")
        if not self.sigma > 0:
            raise ConfigError(f"deep_shells.sigma must be positive, got {self.sigma}")
        if self.num_sinkhorn < 0:
            raise ConfigError(f"deep_shells.num_sinkhorn must be >= 0, got {self.num_sinkhorn}")
        for name in ("fac_spec", "fac_norm", "refine_fac_spec", "refine_fac_norm", "ridge"):
            if getattr(self, name) < 0:
                raise ConfigError(f"deep_shells.{name} must be >= 0, got {getattr(self, name)}")
        log_spaced_k(self.refine_k_min, self.refine_k_max, self.refine_levels)  # validates
        if self.num_samples < 1 or self.max_query_points < 2:
            raise ConfigError(
                f"deep_shells.num_samples must be >= 1 and max_query_points >= 2, got {self.num_samples}, "
                f"{self.max_query_points}"
            )
        for name, allowed in (("smooth_x", _SHELL_MODES), ("normal_norm", _NORMAL_NORMS),
                              ("sinkhorn_impl", _SINKHORN_IMPLS), ("nn_backend", _NN_BACKENDS)):
            if getattr(self, name) not in allowed:
                raise ConfigError(f"deep_shells.{name} must be one of {allowed}, got {getattr(self, name)!r}")

    @classmethod
    def original(cls, **overrides) -> "DeepShellsConfig":
        """The original code's behaviour on every deviation (docs/deep_shells.md §9; parity, published weights)."""
        return replace(cls(smooth_x="hard", sigmoid_inclusive=False, normal_norm="samples"), **overrides)

    @property
    def refine_k_array(self) -> tuple[int, ...]:
        """Shell sizes of the test-time refinement."""
        return log_spaced_k(self.refine_k_min, self.refine_k_max, self.refine_levels)


@dataclass(frozen=True, eq=False)
class DeepShellsOutput:
    """Result of the training layer.

    Attributes
    ----------
    loss : () float
        Mean of the level energies.
    level_energies : (L,) float
        ``E_k`` per shell size of ``k_array``.
    plan : (n_s, m_s) float or None
        Final soft map X -> Y on the samples (rows sum to 1), detached; None if not requested.
    plan_adj : (m_s, n_s) float or None
        Final soft map Y -> X (rows sum to 1), detached; None if not requested.
    fmap : (k, k) float
        Functional map of the last level (``Phi_X C ~ Phi_Y``).
    tau : (k, 3) float
        Spectral deformation of the last level.
    deformed_x : (n_s, 3) float
        ``X* = X_k + Phi_X tau`` at the samples, last level.
    shell_y : (m_s, 3) float
        ``Y_k`` at the samples, last level.
    """

    loss: torch.Tensor
    level_energies: torch.Tensor
    plan: torch.Tensor | None
    plan_adj: torch.Tensor | None
    fmap: torch.Tensor
    tau: torch.Tensor
    deformed_x: torch.Tensor
    shell_y: torch.Tensor


@dataclass(frozen=True, eq=False)
class DeepShellsMatch:
    """Result of the test-time pipeline / refinement (point-to-point maps at full resolution).

    Attributes
    ----------
    map_x_to_y : (n_x,) int64
        For each vertex of X its matched vertex of Y.
    map_y_to_x : (n_y,) int64
        For each vertex of Y its matched vertex of X.
    fmap : (k, k) float
        Functional map of the last refinement level.
    tau : (k, 3) float
        Spectral deformation of the last level.
    deformed_x : (n_x, 3) float
        ``X* = X_k + Phi_X tau`` of the last level.
    """

    map_x_to_y: torch.Tensor
    map_y_to_x: torch.Tensor
    fmap: torch.Tensor
    tau: torch.Tensor
    deformed_x: torch.Tensor = field(repr=False)


# ----------------------------------------------------------------------------------------------------------
# building blocks


def shell_size(k: int, mode: str, inclusive: bool) -> int:
    """Number of eigenfunctions a shell of size ``k`` uses (``k`` for hard truncation)."""
    if mode == "hard":
        return k
    return int(sigmoid_shell_weights(k, inclusive=inclusive).shape[0])


def _shell(shape: SpectralShape, k: int, mode: str, inclusive: bool, rows: torch.Tensor | None = None):
    """Smooth shell of ``shape`` at all vertices or at ``rows``: ``(n or r, 3)``."""
    if rows is None:
        return smooth_shell(shape.evecs, shape.mass, shape.verts, k, mode=mode, inclusive=inclusive,
                            coefficients=shape.coeffs)
    if mode == "hard":
        return shape.evecs[rows, :k] @ shape.coeffs[:k]
    w = sigmoid_shell_weights(k, inclusive=inclusive, dtype=shape.evecs.dtype, device=shape.evecs.device)
    kk = w.shape[0]
    return shape.evecs[rows, :kk] @ (w[:, None] * shape.coeffs[:kk])


class _Stencil:
    """The faces around a set of vertices, relabelled: normals at the samples without the whole mesh."""

    def __init__(self, faces: torch.Tensor, rows: torch.Tensor, n_verts: int):
        in_rows = torch.zeros(n_verts, dtype=torch.bool, device=faces.device)
        in_rows[rows] = True
        sub_faces = faces[in_rows[faces].any(1)]
        self.verts = torch.unique(torch.cat([sub_faces.reshape(-1), rows]))  # sorted
        self.faces = torch.searchsorted(self.verts, sub_faces)
        self.rows = torch.searchsorted(self.verts, rows)

    def normals(self, local_verts: torch.Tensor) -> torch.Tensor:
        """Unit area-weighted normals at the rows, given positions ``(len(self.verts), 3)``."""
        return vertex_normals(local_verts, self.faces)[self.rows]


class _Level:
    """Feature-independent quantities of one training level (shell size ``k``) at the samples."""

    def __init__(self, shape_x, shape_y, samples_x, samples_y, stencil, k, config):
        incl = config.sigmoid_inclusive
        self.stencil_phi_x = shape_x.evecs[stencil.verts, :k]
        self.stencil_shell_x = _shell(shape_x, k, config.smooth_x, incl, rows=stencil.verts)
        self.phi_x = self.stencil_phi_x[stencil.rows]
        self.shell_x = self.stencil_shell_x[stencil.rows]
        self.phi_y = shape_y.evecs[samples_y, :k]
        shell_y_full = _shell(shape_y, k, "sigmoid", incl)
        self.shell_y = shell_y_full[samples_y]
        normals_y_full = vertex_normals(shell_y_full, shape_y.faces)
        self.normals_y = normals_y_full[samples_y]
        self.fac_spec, self.fac_norm = _embedding_scales(
            shell_y_full, shape_y.evecs[:, :k], normals_y_full if config.normal_norm == "all" else self.normals_y,
            config.fac_spec, config.fac_norm,
        )


def _check_eigs(shape: SpectralShape, ks, config: DeepShellsConfig) -> None:
    need = max(max(shell_size(k, config.smooth_x, config.sigmoid_inclusive),
                   shell_size(k, "sigmoid", config.sigmoid_inclusive)) for k in ks)
    if shape.n_eigs < need:
        raise ConfigError(
            f"{shape.name}: the shell schedule up to k={max(ks)} needs {need} eigenfunctions, the shape has "
            f"{shape.n_eigs}; compute more eigenpairs or shorten the schedule"
        )


def _embedding_scales(shell_y_full, evecs_y_k, normals_y_for_norm, fac_spec, fac_norm):
    """Weights of the spectral block and of the normals (from Y, shared by both sides)."""
    y_norm = shell_y_full.norm()
    phi_norm = evecs_y_k.norm()
    n_norm = normals_y_for_norm.norm()
    if float(phi_norm) == 0.0 or float(n_norm) == 0.0:
        raise NumericalError("deep shells: zero eigenfunction or normal norm; cannot scale the embedding")
    return fac_spec * y_norm / phi_norm, fac_norm * y_norm / n_norm


def _transport(config: DeepShellsConfig, emb_x, emb_y, values_y, values_x, return_plans: bool = False):
    """Sinkhorn soft maps of two embeddings applied to values: ``(P values_y, P_adj values_x, P, P_adj)``.

    The fast implementation never forms the plans unless ``return_plans`` (then detached); the reference one
    forms them (with gradients) and multiplies.
    """
    if config.sinkhorn_impl == "reference":
        plans = sinkhorn_log_reference(pairwise_sq_dists(emb_x, emb_y), config.sigma, config.num_sinkhorn)
        return plans.plan @ values_y, plans.plan_adj @ values_x, plans.plan, plans.plan_adj
    return sinkhorn_sq_euclidean_products(emb_x, emb_y, values_y, values_x, config.sigma, config.num_sinkhorn,
                                          return_plans=return_plans)


def deformation_from_plans(
    plan: torch.Tensor,
    plan_adj: torch.Tensor,
    phi_x: torch.Tensor,
    phi_y: torch.Tensor,
    shell_x: torch.Tensor,
    shell_y: torch.Tensor,
    ridge: float = DEFAULT_RIDGE,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Closed-form functional map and deformation from soft correspondences (Deep Shells eq. for C, tau).

    Least squares over the stacked two-sided correspondences (rows: X samples through ``plan``, then Y samples
    through ``plan_adj``): ``A = [Phi_X; P_adj Phi_X]``, ``A C ~ [P Phi_Y; Phi_Y]``,
    ``A tau ~ [P Y_k - X_k; Y_k - P_adj X_k]``, solved in float64.

    Parameters
    ----------
    plan : (n, m) float
        Soft map X -> Y (rows sum to 1).
    plan_adj : (m, n) float
        Soft map Y -> X.
    phi_x : (n, k) float
        Eigenfunctions of X at its samples.
    phi_y : (m, k) float
        Eigenfunctions of Y at its samples.
    shell_x : (n, 3) float
        ``X_k`` at the samples.
    shell_y : (m, 3) float
        ``Y_k`` at the samples.
    ridge : float
        Relative ridge, :func:`~shapecorr.matching.least_squares.solve_normal_equations`.

    Returns
    -------
    fmap : (k, k) float
    tau : (k, 3) float
    """
    py = plan @ torch.cat([phi_y, shell_y], 1)  # (n, k + 3)
    qx = plan_adj @ torch.cat([phi_x, shell_x], 1)  # (m, k + 3)
    return deformation_from_products(py, qx, phi_x, phi_y, shell_x, shell_y, ridge)


def deformation_from_products(
    py: torch.Tensor,
    qx: torch.Tensor,
    phi_x: torch.Tensor,
    phi_y: torch.Tensor,
    shell_x: torch.Tensor,
    shell_y: torch.Tensor,
    ridge: float = DEFAULT_RIDGE,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`deformation_from_plans` given the plans' products instead of the plans.

    Parameters
    ----------
    py : (n, k + 3) float
        ``plan @ [Phi_Y, Y_k]`` (e.g. from :func:`~shapecorr.matching.sinkhorn.sinkhorn_sq_euclidean_products`).
    qx : (m, k + 3) float
        ``plan_adj @ [Phi_X, X_k]``.
    phi_x, phi_y, shell_x, shell_y, ridge
        See :func:`deformation_from_plans`.

    Returns
    -------
    fmap : (k, k) float
    tau : (k, 3) float
    """
    k = phi_x.shape[1]
    design = torch.cat([phi_x, qx[:, :k]], 0)
    target = torch.cat([
        torch.cat([py[:, :k], py[:, k:] - shell_x], 1),
        torch.cat([phi_y, shell_y - qx[:, k:]], 1),
    ], 0)
    gram, rhs = normal_equations(design, target)
    sol = solve_normal_equations(gram, rhs, ridge=ridge, what=f"Deep Shells (C, tau) solve at k={k}")
    sol = sol.to(phi_x.dtype)
    return sol[:, :k], sol[:, k:]


def deformation_from_pairs(
    phi_x: torch.Tensor,
    phi_y: torch.Tensor,
    shell_x: torch.Tensor,
    shell_y: torch.Tensor,
    map_x_to_y: torch.Tensor,
    map_y_to_x: torch.Tensor,
    ridge: float = DEFAULT_RIDGE,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Functional map and deformation from two-sided hard correspondences (the refinement's solve).

    The pairs are ``(i, map_x_to_y[i])`` for all vertices i of X and ``(map_y_to_x[j], j)`` for all j of Y;
    ``Phi_X[px] C ~ Phi_Y[py]`` and ``Phi_X[px] tau ~ Y_k[py] - X_k[px]`` in the least-squares sense. The
    normal equations are accumulated per vertex of X (multiplicities and scatter-adds) instead of over the
    ``n_x + n_y`` stacked rows.

    Parameters
    ----------
    phi_x : (n_x, k) float
        Eigenfunctions of X (float64 recommended for large k).
    phi_y : (n_y, k) float
    shell_x : (n_x, 3) float
    shell_y : (n_y, 3) float
    map_x_to_y : (n_x,) int64
    map_y_to_x : (n_y,) int64
    ridge : float

    Returns
    -------
    fmap : (k, k) float64
    tau : (k, 3) float64
    """
    n_x, k = phi_x.shape
    f64 = torch.float64
    phi_y64 = phi_y.to(f64)
    sx, sy = shell_x.to(f64), shell_y.to(f64)
    extra = torch.bincount(map_y_to_x, minlength=n_x).to(f64)  # how often each X vertex is a Y -> X image
    target = torch.cat([phi_y64[map_x_to_y], sy[map_x_to_y] - sx], 1)
    target.index_add_(0, map_y_to_x, torch.cat([phi_y64, sy], 1))
    target[:, k:] -= extra[:, None] * sx
    phi_x64 = phi_x.to(f64)
    # sum over pairs of Phi_X[px]^T Phi_X[px] = Phi_X^T diag(multiplicity) Phi_X; the right-hand side sums
    # are already accumulated per X vertex in `target`.
    gram = phi_x64.transpose(0, 1) @ ((1.0 + extra)[:, None] * phi_x64)
    rhs = phi_x64.transpose(0, 1) @ target
    sol = solve_normal_equations(gram, rhs, ridge=ridge, what=f"Deep Shells refinement solve at k={k}")
    return sol[:, :k], sol[:, k:]


def _blocked_gram(a: torch.Tensor, b: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
    """``a^T diag(weights) b`` in float64, summed over blocks of ``REFINE_ROW_BLOCK`` rows.

    a : (n, p) float, b : (n, q) float, weights : (n,) float or None -> (p, q) float64. Each block is converted
    to float64 when used (exact), so only ``REFINE_ROW_BLOCK`` rows exist in float64 at a time.
    """
    f64 = torch.float64
    out = None
    for start in range(0, a.shape[0], REFINE_ROW_BLOCK):
        rows = slice(start, start + REFINE_ROW_BLOCK)
        right = b[rows].to(f64)
        if weights is not None:
            right = weights[rows, None].to(f64) * right
        part = a[rows].to(f64).transpose(0, 1) @ right
        out = part if out is None else out.add_(part)
    return out


class _PairNormalEquations:
    """The normal equations of :func:`deformation_from_pairs`, carried from one refinement level to the next.

    Rebuilding ``Phi_X^T W Phi_X`` and ``Phi_X^T T_C`` (``T_C``: the partners' ``Phi_Y`` rows summed per
    vertex of X) costs ``4 n k^2`` flops per level. Between consecutive levels ``k`` grows by ~12 % and, at
    large ``k``, the pairs of only a few percent of the vertices change, so the previous matrices are updated
    on the rows whose pairs changed and extended by the new columns; a full rebuild is used when that is not
    cheaper. The deformation part of the right-hand side (3 columns, shells change with ``k``) is rebuilt.
    Everything is computed in float64 (buffers sized for the largest ``k``); the result equals
    :func:`deformation_from_pairs` up to rounding (~1e-14 relative; in the float32 the solution is used in,
    a few entries differ by one unit in the last place). A basis of at most ``REFINE_ROW_BLOCK`` rows is
    converted to float64 once (20 MB for 5000 vertices and 500 eigenfunctions; every level's products would
    convert all of its rows anyway). Larger bases are kept in their own dtype and the blocks a product needs
    are converted when used (exact), so float32 bases are not copied to float64 whole (1.2 GB for two
    150k-vertex shapes with 500 eigenfunctions).
    """

    def __init__(self, phi_x: torch.Tensor, phi_y: torch.Tensor):
        # (n_x, K), (n_y, K) float: float64 up to one row block, else their own dtype (float32 or float64)
        self.phi_x, self.phi_y = (p.to(torch.float64) if p.shape[0] <= REFINE_ROW_BLOCK else p for p in (phi_x, phi_y))
        n, kmax = phi_x.shape
        self.k = 0
        self.map_x_to_y = self.map_y_to_x = self.weights = None
        f64 = dict(dtype=torch.float64, device=phi_x.device)
        self.target = torch.empty(n, kmax, **f64)  # T_C, columns :k valid
        self.gram = torch.empty(kmax, kmax, **f64)  # [:k, :k] valid
        self.rhs = torch.empty(kmax, kmax, **f64)

    def _fill_target(self, map_x_to_y, map_y_to_x, start, stop):
        """Columns ``start:stop`` of ``T_C``: ``Phi_Y[map_x_to_y] + sum over j with map_y_to_x[j] = i of Phi_Y[j]``."""
        target = self.target[:, start:stop]
        target.copy_(self.phi_y[map_x_to_y, start:stop])
        for first in range(0, self.phi_y.shape[0], REFINE_ROW_BLOCK):
            rows = slice(first, first + REFINE_ROW_BLOCK)
            target.index_add_(0, map_y_to_x[rows], self.phi_y[rows, start:stop].to(torch.float64))

    def _rebuild(self, k, map_x_to_y, map_y_to_x, weights):
        px = self.phi_x[:, :k]
        self._fill_target(map_x_to_y, map_y_to_x, 0, k)
        self.gram[:k, :k] = _blocked_gram(px, px, weights)
        self.rhs[:k, :k] = _blocked_gram(px, self.target[:, :k])

    def _update(self, map_x_to_y, map_y_to_x, weights, rows, changed_x, changed_y):
        """Add the changes of the pairs (all on ``rows``) to ``gram``, ``rhs`` and ``target`` at the current k."""
        k = self.k
        local = torch.full((self.phi_x.shape[0],), -1, dtype=torch.int64, device=rows.device)
        local[rows] = torch.arange(rows.numel(), device=rows.device)
        delta = self.target.new_zeros(rows.numel(), k)
        new_y, old_y = map_x_to_y[changed_x], self.map_x_to_y[changed_x]
        delta.index_add_(0, local[changed_x], self.phi_y[new_y, :k].to(torch.float64)
                         - self.phi_y[old_y, :k].to(torch.float64))
        phi_changed = self.phi_y[changed_y, :k].to(torch.float64)
        delta.index_add_(0, local[map_y_to_x[changed_y]], phi_changed)
        delta.index_add_(0, local[self.map_y_to_x[changed_y]], phi_changed, alpha=-1.0)
        pr = self.phi_x[rows, :k].to(torch.float64)
        self.rhs[:k, :k] += pr.transpose(0, 1) @ delta
        self.target[rows, :k] += delta
        dw = weights[rows] - self.weights[rows]
        moved = dw.nonzero().flatten()  # rows whose multiplicity changed
        if moved.numel():
            pw = pr[moved]
            self.gram[:k, :k] += pw.transpose(0, 1) @ (dw[moved, None] * pw)

    def _extend(self, k, map_x_to_y, map_y_to_x, weights):
        """Grow ``gram``, ``rhs``, ``target`` from the current size to ``k`` (same pairs)."""
        kp = self.k
        px, pn = self.phi_x[:, :k], self.phi_x[:, kp:k]
        self._fill_target(map_x_to_y, map_y_to_x, kp, k)
        cross = _blocked_gram(px, pn, weights)  # (k, k - kp)
        self.gram[:k, kp:k] = cross
        self.gram[kp:k, :kp] = cross[:kp].transpose(0, 1)
        self.rhs[:k, kp:k] = _blocked_gram(px, self.target[:, kp:k])
        self.rhs[kp:k, :kp] = _blocked_gram(pn, self.target[:, :kp])

    def solve(self, k, shell_x, shell_y, map_x_to_y, map_y_to_x, ridge):
        """:func:`deformation_from_pairs` with ``phi_x[:, :k]``, ``phi_y[:, :k]``: ``(fmap, tau)`` float64."""
        n, kmax = self.phi_x.shape
        if k > kmax:
            raise ConfigError(f"refinement solve: k={k} exceeds the {kmax} prepared eigenfunctions")
        extra = torch.bincount(map_y_to_x, minlength=n).to(torch.float64)
        weights = 1.0 + extra
        rebuild = self.k == 0 or k < self.k
        if not rebuild:
            changed_x = (map_x_to_y != self.map_x_to_y).nonzero().flatten()
            changed_y = (map_y_to_x != self.map_y_to_x).nonzero().flatten()
            rows = torch.unique(torch.cat([changed_x, map_y_to_x[changed_y], self.map_y_to_x[changed_y]]))
            kp = self.k
            # flops: update <= 4 r kp^2, extension ~6 n k (k - kp); rebuild 4 n k^2
            rebuild = 4 * rows.numel() * kp * kp + 6 * n * k * (k - kp) >= 4 * n * k * k
        if rebuild:
            self._rebuild(k, map_x_to_y, map_y_to_x, weights)
        else:
            if rows.numel():
                self._update(map_x_to_y, map_y_to_x, weights, rows, changed_x, changed_y)
            if k > self.k:
                self._extend(k, map_x_to_y, map_y_to_x, weights)
        self.k, self.map_x_to_y, self.map_y_to_x, self.weights = k, map_x_to_y, map_y_to_x, weights
        sx, sy = shell_x.to(torch.float64), shell_y.to(torch.float64)
        target_tau = sy[map_x_to_y] - sx
        target_tau.index_add_(0, map_y_to_x, sy)
        target_tau -= extra[:, None] * sx
        rhs = torch.cat([self.rhs[:k, :k], _blocked_gram(self.phi_x[:, :k], target_tau)], 1)
        sol = solve_normal_equations(self.gram[:k, :k], rhs, ridge=ridge,
                                     what=f"Deep Shells refinement solve at k={k}")
        return sol[:, :k], sol[:, k:]


def _product_embedding(deformed_x, spec_x, normals_x, shell_y, spec_y, normals_y, fac_s, fac_n):
    emb_x = torch.cat([deformed_x, fac_s * spec_x, fac_n * normals_x], 1)
    emb_y = torch.cat([shell_y, fac_s * spec_y, fac_n * normals_y], 1)
    return emb_x, emb_y


def random_samples(n: int, num: int, generator: torch.Generator | None = None, device=None) -> torch.Tensor:
    """``num`` vertex indices drawn uniformly **with replacement** (the Deep Shells training subsampling).

    Returns
    -------
    (num,) int64
    """
    return torch.randint(0, n, (num,), generator=generator, device=device)


# ----------------------------------------------------------------------------------------------------------
# the training layer


def _check_samples(shape: SpectralShape, samples: torch.Tensor, feats: torch.Tensor, side: str) -> None:
    if samples.dim() != 1 or samples.dtype != torch.int64:
        raise ConfigError(f"deep shells: samples_{side} must be a 1-D int64 tensor")
    if samples.numel() == 0 or int(samples.min()) < 0 or int(samples.max()) >= shape.n_verts:
        raise ConfigError(f"deep shells: samples_{side} out of range for {shape.name} ({shape.n_verts} vertices)")
    if feats.dim() != 2 or feats.shape[0] != samples.shape[0]:
        raise ConfigError(
            f"deep shells: feat_{side} must have one row per sample ({samples.shape[0]}), got {tuple(feats.shape)}"
        )
    if not all_finite(feats):
        raise NumericalError(f"deep shells: feat_{side} ({shape.name}) contains NaN or Inf")


def deep_shells_layer(
    feat_x: torch.Tensor,
    feat_y: torch.Tensor,
    shape_x: SpectralShape,
    shape_y: SpectralShape,
    samples_x: torch.Tensor,
    samples_y: torch.Tensor,
    config: DeepShellsConfig = DeepShellsConfig(),
    return_plans: bool = True,
) -> DeepShellsOutput:
    """The differentiable hierarchical OT matching layer (training forward).

    Parameters
    ----------
    feat_x : (n_s, c) float
        Features of X at its sampled vertices (any ``c``: learned features or raw descriptors).
    feat_y : (m_s, c) float
        Features of Y at its samples.
    shape_x, shape_y : SpectralShape
        Full-resolution vertices, faces, eigenfunctions, mass.
    samples_x : (n_s,) int64
        Sampled vertex indices of X (repetitions allowed).
    samples_y : (m_s,) int64
    config : DeepShellsConfig
    return_plans : bool
        Form the last level's soft maps for the output (two ``n_s x m_s`` buffers; the loss never needs them:
        every plan enters only through its products with thin matrices). ``False`` saves ~1-2 % of a step.

    Returns
    -------
    DeepShellsOutput
        Total loss (mean of the per-level energies), the energies, the final soft maps (``None`` unless
        ``return_plans``), the last ``C``, ``tau`` and the last deformed / target shells at the samples.

    Raises
    ------
    ConfigError
        On inconsistent inputs (sample counts, feature widths, too few eigenpairs).
    NumericalError
        If a solve fails or NaN/Inf appears.
    """
    _check_samples(shape_x, samples_x, feat_x, "x")
    _check_samples(shape_y, samples_y, feat_y, "y")
    if feat_x.shape[1] != feat_y.shape[1]:
        raise ConfigError(f"deep shells: feature widths differ ({feat_x.shape[1]} vs {feat_y.shape[1]})")
    _check_eigs(shape_x, config.k_array, config)
    _check_eigs(shape_y, config.k_array, config)
    stencil = _Stencil(shape_x.faces, samples_x, shape_x.n_verts)
    levels = [_Level(shape_x, shape_y, samples_x, samples_y, stencil, k, config) for k in config.k_array]

    first = levels[0]
    py, qx, plan, plan_adj = _transport(config, feat_x, feat_y, torch.cat([first.phi_y, first.shell_y], 1),
                                        torch.cat([first.phi_x, first.shell_x], 1))
    energies = []
    for i, lv in enumerate(levels):
        fmap, tau = deformation_from_products(py, qx, lv.phi_x, lv.phi_y, lv.shell_x, lv.shell_y, config.ridge)
        deformed = lv.stencil_shell_x + lv.stencil_phi_x @ tau  # X* on the samples' one-ring
        deformed_s = deformed[stencil.rows]
        emb_x, emb_y = _product_embedding(deformed_s, lv.phi_x @ fmap, stencil.normals(deformed), lv.shell_y,
                                          lv.phi_y, lv.normals_y, lv.fac_spec, lv.fac_norm)
        # The plans only enter through their products with the energy's and the next level's values.
        nxt = levels[i + 1] if i + 1 < len(levels) else None
        py, qx, plan, plan_adj = _transport(
            config, emb_x, emb_y, torch.cat([lv.shell_y] + ([nxt.phi_y, nxt.shell_y] if nxt else []), 1),
            torch.cat([deformed_s] + ([nxt.phi_x, nxt.shell_x] if nxt else []), 1),
            return_plans=return_plans and nxt is None,
        )
        energies.append((deformed_s - py[:, :3]).square().sum() + (qx[:, :3] - lv.shell_y).square().sum())
        py, qx = py[:, 3:], qx[:, 3:]
    level_energies = torch.stack(energies)
    loss = level_energies.mean()
    if not torch.isfinite(loss):
        raise NumericalError("deep shells: the loss is NaN or Inf")
    if return_plans:
        plan, plan_adj = plan.detach(), plan_adj.detach()
    else:
        plan = plan_adj = None
    return DeepShellsOutput(loss=loss, level_energies=level_energies, plan=plan, plan_adj=plan_adj,
                            fmap=fmap, tau=tau, deformed_x=deformed_s, shell_y=lv.shell_y)


# ----------------------------------------------------------------------------------------------------------
# test time


class _EmbeddingBuffers:
    """float64 storage of the full-resolution embeddings of every refinement level (the k-d trees' input).

    Each level's embeddings are formed in the bases' dtype, with the values of :func:`_product_embedding`
    (the same products and scalings), and converted once into these buffers, sized for the largest level; the
    nearest-neighbour search reads them without a copy. A level allocates neither its ``(n, 3 + k + 3)``
    embeddings nor their float64 copies.
    """

    def __init__(self, n_x: int, n_y: int, k_max: int, like: torch.Tensor):
        width = k_max + 6
        self.x = like.new_empty(n_x * width, dtype=torch.float64)
        self.y = like.new_empty(n_y * width, dtype=torch.float64)
        self.spec = like.new_empty(max(n_x, n_y) * k_max)  # one spectral block at a time, bases' dtype

    def fill(self, deformed_x, phi_x, fmap, normals_x, shell_y, phi_y, normals_y, fac_s, fac_n):
        """``(emb_x (n_x, k + 6), emb_y (n_y, k + 6))`` float64 views of the buffers."""
        (n_x, k), n_y = phi_x.shape, phi_y.shape[0]
        spec_x = torch.mm(phi_x, fmap, out=self.spec[: n_x * k].view(n_x, k)).mul_(fac_s)  # fac_s * (Phi_X C)
        emb_x = self._write(self.x, deformed_x, spec_x, fac_n * normals_x)  # before spec_y reuses the storage
        spec_y = torch.mul(phi_y, fac_s, out=self.spec[: n_y * k].view(n_y, k))
        return emb_x, self._write(self.y, shell_y, spec_y, fac_n * normals_y)

    @staticmethod
    def _write(buf, first, spec, last):
        n, k = spec.shape
        emb = buf[: n * (k + 6)].view(n, k + 6)
        emb[:, :3].copy_(first)
        emb[:, 3:3 + k].copy_(spec)
        emb[:, 3 + k:].copy_(last)
        return emb


def _full_embedding(shape_x, shape_y, k, fmap, tau, fac_spec, fac_norm, config, shell_x=None, shell_y=None,
                    buffers=None):
    """Full-resolution product embedding for shell size ``k`` and a fitted ``(C, tau)``.

    With ``buffers`` (:class:`_EmbeddingBuffers`), float64 views of them holding the same values.
    """
    incl = config.sigmoid_inclusive
    if shell_x is None:
        shell_x = _shell(shape_x, k, config.smooth_x, incl)
    if shell_y is None:
        shell_y = _shell(shape_y, k, "sigmoid", incl)
    phi_x, phi_y = shape_x.evecs[:, :k], shape_y.evecs[:, :k]
    deformed = shell_x + phi_x @ tau
    normals_x = vertex_normals(deformed, shape_x.faces)
    normals_y = vertex_normals(shell_y, shape_y.faces)
    fac_s, fac_n = _embedding_scales(shell_y, phi_y, normals_y, fac_spec, fac_norm)
    if buffers is None:
        emb_x, emb_y = _product_embedding(deformed, phi_x @ fmap, normals_x, shell_y, phi_y, normals_y, fac_s, fac_n)
    else:
        emb_x, emb_y = buffers.fill(deformed, phi_x, fmap, normals_x, shell_y, phi_y, normals_y, fac_s, fac_n)
    return emb_x, emb_y, deformed


def product_embedding_maps(
    shape_x: SpectralShape,
    shape_y: SpectralShape,
    fmap: torch.Tensor,
    tau: torch.Tensor,
    config: DeepShellsConfig = DeepShellsConfig(),
    fac_spec: float | None = None,
    fac_norm: float | None = None,
) -> DeepShellsMatch:
    """Hard maps by bidirectional nearest neighbours in the full-resolution product embedding of a level.

    The shell size is ``k = fmap.shape[0]``; e.g. ``fmap``, ``tau`` of :class:`DeepShellsOutput` give the
    hard maps of the last training level (what G-MSM queries use), those of the first OT level the initial
    maps of the Deep Shells test pipeline.

    Parameters
    ----------
    shape_x, shape_y : SpectralShape
    fmap : (k, k) float
    tau : (k, 3) float
    config : DeepShellsConfig
        Shell conventions and nearest-neighbour backend.
    fac_spec, fac_norm : float, optional
        Embedding weights; default ``config.fac_spec``, ``config.fac_norm`` (the training ones).

    Returns
    -------
    DeepShellsMatch
    """
    k = int(fmap.shape[0])
    if fmap.shape != (k, k) or tau.shape != (k, 3):
        raise ConfigError(f"product_embedding_maps: need fmap (k, k) and tau (k, 3), got {tuple(fmap.shape)}, "
                          f"{tuple(tau.shape)}")
    _check_eigs(shape_x, (k,), config)
    _check_eigs(shape_y, (k,), config)
    fac_spec = config.fac_spec if fac_spec is None else fac_spec
    fac_norm = config.fac_norm if fac_norm is None else fac_norm
    with torch.no_grad():
        fmap, tau = fmap.detach().to(shape_x.evecs.dtype), tau.detach().to(shape_x.evecs.dtype)
        emb_x, emb_y, deformed = _full_embedding(shape_x, shape_y, k, fmap, tau, fac_spec, fac_norm, config)
        map_x_to_y, map_y_to_x = bidirectional_nearest_neighbors(emb_x, emb_y, backend=config.nn_backend,
                                                                workers=torch.get_num_threads())
    return DeepShellsMatch(map_x_to_y=map_x_to_y, map_y_to_x=map_y_to_x, fmap=fmap, tau=tau, deformed_x=deformed)


def refine_deep_shells(
    shape_x: SpectralShape,
    shape_y: SpectralShape,
    map_x_to_y: torch.Tensor,
    map_y_to_x: torch.Tensor,
    config: DeepShellsConfig = DeepShellsConfig(),
) -> DeepShellsMatch:
    """Axiomatic full-resolution shell refinement (the original test-time ``AssSmoothShells``).

    For each ``k`` of ``config.refine_k_array``: smooth shells, least-squares ``(C, tau)`` on the current
    two-sided pairs (:func:`deformation_from_pairs`; its float64 normal equations are carried from level to
    level and updated only where pairs changed, equal up to rounding), product embedding with
    ``(refine_fac_spec, refine_fac_norm)``, bidirectional nearest neighbours -> new pairs. Shapes of at least
    ``SPATIAL_ORDER_MIN_VERTS`` vertices are refined in a spatial vertex order on CPU (faster search; the sums of
    the normal equations then run in another order, equal up to rounding).

    Parameters
    ----------
    shape_x, shape_y : SpectralShape
    map_x_to_y : (n_x,) int64
        Initial map X -> Y.
    map_y_to_x : (n_y,) int64
        Initial map Y -> X.
    config : DeepShellsConfig

    Returns
    -------
    DeepShellsMatch
    """
    ks = config.refine_k_array
    _check_eigs(shape_x, ks, config)
    _check_eigs(shape_y, ks, config)
    if map_x_to_y.shape != (shape_x.n_verts,) or map_y_to_x.shape != (shape_y.n_verts,):
        raise ConfigError("refine_deep_shells: the initial maps must have one entry per vertex of X and of Y")
    kdtree = resolved_backend(config.nn_backend, shape_x.evecs.device) == "kdtree"
    if not kdtree or max(shape_x.n_verts, shape_y.n_verts) < SPATIAL_ORDER_MIN_VERTS:
        return _refine_levels(shape_x, shape_y, map_x_to_y, map_y_to_x, config)
    with torch.no_grad():
        order_x, order_y = spatial_order(shape_x.verts), spatial_order(shape_y.verts)
        rank_x, rank_y = torch.argsort(order_x), torch.argsort(order_y)  # old vertex -> new number
        sorted_x, sorted_y = reorder_vertices(shape_x, order_x), reorder_vertices(shape_y, order_y)  # every column:
        # the sigmoid shells weigh eigenfunctions beyond k as well
        result = _refine_levels(sorted_x, sorted_y, rank_y[map_x_to_y[order_x]], rank_x[map_y_to_x[order_y]], config)
        map_x_to_y, map_y_to_x = torch.empty_like(map_x_to_y), torch.empty_like(map_y_to_x)
        deformed = torch.empty_like(result.deformed_x)
        map_x_to_y[order_x] = order_y[result.map_x_to_y]
        map_y_to_x[order_y] = order_x[result.map_y_to_x]
        deformed[order_x] = result.deformed_x
    return replace(result, map_x_to_y=map_x_to_y, map_y_to_x=map_y_to_x, deformed_x=deformed)


def _refine_levels(shape_x, shape_y, map_x_to_y, map_y_to_x, config):
    """The levels of :func:`refine_deep_shells` on the shapes as numbered."""
    ks = config.refine_k_array
    incl = config.sigmoid_inclusive
    with torch.no_grad():
        # normal equations carried from level to level (float64 products of the bases' blocks)
        system = _PairNormalEquations(shape_x.evecs[:, : max(ks)], shape_y.evecs[:, : max(ks)])
        buffers = _EmbeddingBuffers(shape_x.n_verts, shape_y.n_verts, max(ks), shape_x.evecs)
        for k in ks:
            shell_x = _shell(shape_x, k, config.smooth_x, incl)
            shell_y = _shell(shape_y, k, "sigmoid", incl)
            fmap, tau = system.solve(k, shell_x, shell_y, map_x_to_y, map_y_to_x, config.ridge)
            fmap, tau = fmap.to(shape_x.evecs.dtype), tau.to(shape_x.evecs.dtype)
            emb_x, emb_y, deformed = _full_embedding(shape_x, shape_y, k, fmap, tau, config.refine_fac_spec,
                                                     config.refine_fac_norm, config, shell_x, shell_y, buffers)
            map_x_to_y, map_y_to_x = bidirectional_nearest_neighbors(emb_x, emb_y, backend=config.nn_backend,
                                                                workers=torch.get_num_threads())
    return DeepShellsMatch(map_x_to_y=map_x_to_y, map_y_to_x=map_y_to_x, fmap=fmap, tau=tau, deformed_x=deformed)


def deep_shells_query(
    feat_x: torch.Tensor,
    feat_y: torch.Tensor,
    shape_x: SpectralShape,
    shape_y: SpectralShape,
    config: DeepShellsConfig = DeepShellsConfig(),
    refine: bool = True,
) -> DeepShellsMatch:
    """Test-time matching of a pair from full-resolution features (the original ``test_model``).

    1. If a shape has more than ``max_query_points`` vertices, both are farthest-point subsampled to
       ``min(n_x - 1, n_y - 1, max_query_points)`` points (deterministic start at vertex 0; the original
       starts at a random vertex) for steps 2-3.
    2. Feature Sinkhorn; one OT level at ``k = k_array[0]``: ``(C, tau)`` from the soft maps.
    3. Full-resolution product embedding of that level (``fac_spec``, ``fac_norm``) and bidirectional nearest
       neighbours.
    4. :func:`refine_deep_shells` (skipped if ``refine=False``).

    Parameters
    ----------
    feat_x : (n_x, c) float
        Features at every vertex of X.
    feat_y : (n_y, c) float
    shape_x, shape_y : SpectralShape
    config : DeepShellsConfig
    refine : bool

    Returns
    -------
    DeepShellsMatch
        Point-to-point maps in both directions.
    """
    n_x, n_y = shape_x.n_verts, shape_y.n_verts
    if feat_x.shape[0] != n_x or feat_y.shape[0] != n_y or feat_x.shape[1] != feat_y.shape[1]:
        raise ConfigError(
            f"deep_shells_query: need features at every vertex, got {tuple(feat_x.shape)} for {n_x} vertices "
            f"and {tuple(feat_y.shape)} for {n_y}"
        )
    k = config.k_array[0]
    _check_eigs(shape_x, (k,), config)
    _check_eigs(shape_y, (k,), config)
    with torch.no_grad():
        if max(n_x, n_y) > config.max_query_points:
            num = min(n_x - 1, n_y - 1, config.max_query_points)
            samples_x = torch.from_numpy(farthest_point_sampling(shape_x.verts.cpu(), num)).to(feat_x.device)
            samples_y = torch.from_numpy(farthest_point_sampling(shape_y.verts.cpu(), num)).to(feat_y.device)
        else:
            samples_x = torch.arange(n_x, device=feat_x.device)
            samples_y = torch.arange(n_y, device=feat_y.device)
        fx, fy = feat_x[samples_x], feat_y[samples_y]
        if not all_finite(fx, fy):
            raise NumericalError("deep_shells_query: the features contain NaN or Inf")
        incl = config.sigmoid_inclusive
        phi_x, phi_y = shape_x.evecs[samples_x, :k], shape_y.evecs[samples_y, :k]
        shell_x = _shell(shape_x, k, config.smooth_x, incl, rows=samples_x)
        shell_y = _shell(shape_y, k, "sigmoid", incl, rows=samples_y)
        py, qx, _, _ = _transport(config, fx, fy, torch.cat([phi_y, shell_y], 1), torch.cat([phi_x, shell_x], 1))
        fmap, tau = deformation_from_products(py, qx, phi_x, phi_y, shell_x, shell_y, config.ridge)
    coarse = product_embedding_maps(shape_x, shape_y, fmap, tau, config)
    if not refine:
        return coarse
    return refine_deep_shells(shape_x, shape_y, coarse.map_x_to_y, coarse.map_y_to_x, config)
