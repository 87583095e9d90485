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

One layer (:func:`_match_layer`) of size k: sigmoid shells ``X_k``, ``Y_k``; ``X* = X_k + Phi_X[:, :k] tau``;
for each of ``num_sub`` rounds: correspondences by nearest neighbours between
``[X*, a_n n(X*), a_f (Phi_X C)[:, :k_prev] w_prev]`` and ``[Y_k, a_n n(Y_k), a_f Phi_Y[:, :k_prev] w_prev]``
(``C``, ``w_prev``: previous layer's map and sigmoid weights); ``tau[:k]`` minimizing
``sum_i |X*_i - Y_k[pi(i)]|^2 + sum_j |X*_{pi'(j)} - Y_k,j|^2 + l_arap E_arap(tau)`` (rotations of the
current ``X*`` frozen); ``C`` (size k + 9) by area-weighted least squares on the same pairs plus the
descriptor term, then projected onto the orthogonal matrices.

All of it is torch on any device (the precomputed SHOT / HKS come from :mod:`shapecorr.geometry`);
least-squares solves are float64 with the project's relative ridge. Decisions on the ambiguous points of the
original are listed in docs/smooth_shells.md §6.
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from scipy.spatial import cKDTree

from shapecorr.errors import ConfigError, InvalidMeshError, NumericalError
from shapecorr.geometry.descriptors import hks
from shapecorr.geometry.laplace_beltrami import ORIGINAL_EIGENVALUE_FACTOR
from shapecorr.geometry.mesh_graph import undirected_edges
from shapecorr.geometry.normals import vertex_normals
from shapecorr.geometry.sampling import farthest_point_sampling
from shapecorr.geometry.shells import sigmoid_shell_weights, spectral_coefficients
from shapecorr.geometry.spectral_shape import SpectralShape, make_spectral_shape
from shapecorr.losses.arap import arap_rotations
from shapecorr.matching.least_squares import DEFAULT_RIDGE
from shapecorr.matching.nearest_neighbors import bidirectional_nearest_neighbors
from shapecorr.matching.result import MatchResult

# ---------------------------------------------------------------------------------------------------------
# published constants (docs/smooth_shells.md §5; the released MATLAB code, standardparams / example scripts)

#: First shell size of the main run, last size of the surrogate runs, and the offset of the ARAP weight.
K_START = 20
#: Normals enter the embedding only for shells larger than this (matchlayer: ``normalDamping * (k > 10)``).
NORMAL_K_MIN = 10
#: Surrogate runs of the rigid stage: shell sizes 2..20.
RIGID_K_MIN = 2
#: Random search: shell sizes 6..20, perturbation of the 6 lowest spectral coordinates.
MCMC_K_MIN = 6
#: HKS of the basis features: 200 eigenpairs (without the constant), 100 times log-spaced in
#: [0.002, 0.05] in the original (doubled) eigenvalue scale.
HKS_NUM_EIGS = 200
HKS_NUM_TIMES = 100
HKS_T_MIN = 0.002
HKS_T_MAX = 0.05
#: Rows of X per block of the batched brute-force nearest-neighbour search (memory ~ block x batch x n_y).
NN_BLOCK_ENTRIES = 1 << 24


# ---------------------------------------------------------------------------------------------------------
# configuration


@dataclass(frozen=True)
class SmoothShellsConfig:
    """Hyperparameters of Smooth Shells; defaults are the published isometric settings.

    Attributes
    ----------
    k_max, k_array_length : int
        Main schedule :func:`k_schedule` (500, 50 -> 51 sizes from 20 to 500).
    fac_feat : float
        Weight of the spectral block of the main-run embedding (``facFeat``).
    normal_damping : float
        Weight of the normals in the embedding (``normalDamping``), used for k > 10.
    lambda_feat : float
        Weight of the descriptor term in the functional-map solve (``lambdaFeat``; interclass 0.1).
    lambda_arap_init : float
        ARAP weight ``lambda_arap_init * sqrt(max(k - 20, 0))`` (``lambdaArapInit``).
    lambda_lap : float
        Laplacian-commutativity weight of the main run (``lambdaLap``, 0).
    area_preservation : bool
        Project each ``C`` onto the orthogonal matrices (interclass: False).
    no_rigid : bool
        Skip the rigid alignment (interclass: True).
    num_mcmc : int
        Random-search proposals (interclass: 500); 0 skips the initialization.
    problem_size_init : int
        Farthest-point samples per shape for the rigid surrogate runs and the random search.
    mcmc_fac_feat, mcmc_lambda_laps : float, tuple
        Random-search surrogate runs: spectral weight 1.5, ``lambda_lap`` drawn from {0, 10}.
    score_fac_feat : float
        Spectral weight of the correspondences that score proposals and rigid candidates (0.11).
    rigid_fac_feat, rigid_normal_damping, rigid_lambda_lap, rigid_num_sub : float, float, float, int
        Rigid surrogate runs (0.11, 0.1, 1, 5 rounds per layer).
    rigid_rotations : tuple of int
        Candidate counts: 2 rotations about the 3rd principal axis, then 4 about the 1st.
    score_descriptors : float
        Weight of a descriptor-agreement term in the scores of the rigid candidates and of the random-search
        proposals (project option; 0 = the original): the per-vertex basis features (``Phi F``, SHOT + HKS,
        :func:`basis_features`) join ``[xyz, normals]`` in the residual, scaled to ``score_descriptors * ||Y||``.
        Intrinsic descriptors tell a human's front from its back where the extrinsic residual of the short
        surrogate runs barely does (docs/smooth_shells.md §6); needs ``lambda_feat > 0`` (the features).
    rigid_joint : bool
        Score all combinations of the two candidate sets together (2 x 4 = 8 surrogate runs) instead of the
        original's greedy sequence (2 + 4), which misses a half turn about the 2nd principal axis when the
        first set's choice is wrong (project option, docs/smooth_shells.md §6; default: the original).
    rigid_keep_input : bool
        Score X's input orientation (only re-centred) by a surrogate run as well, and keep it when it scores
        lower than the rigid stage's choice (project option; the divergence-free matcher's pre-alignment uses it,
        docs/divfree.md §1; default: the original).
    icp_iterations : int
        Axis-ICP iterations (5 x 10).
    mcmc_batch : int
        Proposals evaluated together (memory ~ batch x samples^2 floats); does not change results.
    seed : int
        Seed of the farthest-point starts and the proposals.
    ridge : float
        Relative ridge of the float64 solves (project choice, docs/deep_shells.md §9).
    nn_backend : {"auto", "kdtree", "brute"}
        Full-resolution nearest neighbours (:mod:`shapecorr.matching.nearest_neighbors`).
    """

    k_max: int = 500
    k_array_length: int = 50
    fac_feat: float = 0.25
    normal_damping: float = 0.04
    lambda_feat: float = 25.0
    lambda_arap_init: float = 0.02
    lambda_lap: float = 0.0
    area_preservation: bool = True
    no_rigid: bool = False
    num_mcmc: int = 100
    problem_size_init: int = 1000
    mcmc_fac_feat: float = 1.5
    mcmc_lambda_laps: tuple[float, ...] = (0.0, 10.0)
    score_fac_feat: float = 0.11
    rigid_fac_feat: float = 0.11
    rigid_normal_damping: float = 0.1
    rigid_lambda_lap: float = 1.0
    rigid_num_sub: int = 5
    rigid_rotations: tuple[int, ...] = (2, 4)
    score_descriptors: float = 0.0
    rigid_joint: bool = False
    rigid_keep_input: bool = False
    icp_iterations: int = 50
    mcmc_batch: int = 16
    seed: int = 0
    ridge: float = DEFAULT_RIDGE
    nn_backend: str = "auto"

    def __post_init__(self):
        object.__setattr__(self, "mcmc_lambda_laps", tuple(float(v) for v in self.mcmc_lambda_laps))
        object.__setattr__(self, "rigid_rotations", tuple(int(v) for v in self.rigid_rotations))
        if self.k_max < K_START or self.k_array_length < 1:
            raise ConfigError(f"smooth_shells: need k_max >= {K_START} and k_array_length >= 1, got "
                              f"{self.k_max}, {self.k_array_length}")
        for name in ("fac_feat", "normal_damping", "lambda_feat", "lambda_arap_init", "lambda_lap", "mcmc_fac_feat",
                     "score_fac_feat", "rigid_fac_feat", "rigid_normal_damping", "rigid_lambda_lap", "ridge",
                     "score_descriptors"):
            if not getattr(self, name) >= 0:
                raise ConfigError(f"smooth_shells.{name} must be >= 0, got {getattr(self, name)}")
        if self.num_mcmc < 0 or self.problem_size_init < 2 or self.rigid_num_sub < 1 or self.mcmc_batch < 1:
            raise ConfigError("smooth_shells: num_mcmc >= 0, problem_size_init >= 2, rigid_num_sub >= 1 and "
                              "mcmc_batch >= 1 are required")
        if len(self.rigid_rotations) != 2 or min(self.rigid_rotations) < 1:
            raise ConfigError(f"smooth_shells.rigid_rotations must be two counts >= 1, got {self.rigid_rotations}")
        if not self.mcmc_lambda_laps or min(self.mcmc_lambda_laps) < 0:
            raise ConfigError("smooth_shells.mcmc_lambda_laps must be non-negative values, "
                              f"got {self.mcmc_lambda_laps}")
        if self.nn_backend not in ("auto", "kdtree", "brute"):
            raise ConfigError(f"smooth_shells.nn_backend must be auto, kdtree or brute, got {self.nn_backend!r}")

    @property
    def k_array(self) -> tuple[int, ...]:
        """Shell sizes of the main run."""
        return k_schedule(self.k_max, self.k_array_length)

    @property
    def num_eigs(self) -> int:
        """Eigenpairs the pipeline needs: the sigmoid length of the largest shell (k_max + 9)."""
        return int(sigmoid_shell_weights(self.k_max).shape[0])


def k_schedule(k_max: int = 500, length: int = 50, k_start: int = K_START) -> tuple[int, ...]:
    """Quartic shell schedule ``[k_start, k_start + round(linspace(1, (k_max - k_start)^(1/4), length)^4)]``.

    With the published values: 51 sizes 20, 21, 21, 22, 22, 23, ..., 441, 470, 500 (rounding half away from
    zero, as MATLAB's ``round``).

    Returns
    -------
    tuple of int, non-decreasing
    """
    if k_max < k_start or length < 1:
        raise ConfigError(f"k schedule: need k_max >= k_start and length >= 1, got {k_max}, {k_start}, {length}")
    if k_max == k_start:
        return (k_start,) * (length + 1)
    steps = np.floor(np.linspace(1.0, (k_max - k_start) ** 0.25, length) ** 4 + 0.5).astype(int)
    return (int(k_start),) + tuple(int(k_start + s) for s in steps)


# ---------------------------------------------------------------------------------------------------------
# inputs and outputs


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


# ---------------------------------------------------------------------------------------------------------
# basis features


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


# ---------------------------------------------------------------------------------------------------------
# the pair: shared per-pair tensors


class _Pair:
    """Per-pair tensors shared by all stages (Y fixed; X's pose may change)."""

    def __init__(self, x: ShellsShape, y: ShellsShape, feats, need_arap: bool):
        self.x, self.y = x, y
        self.phi_x, self.phi_y = x.spectral.evecs, y.spectral.evecs
        # float64 copies for the normal equations, made once per pair instead of once per solve
        self.phi_x64, self.phi_y64 = self.phi_x.to(torch.float64), self.phi_y.to(torch.float64)
        self.mass_x, self.mass_y = x.spectral.mass, y.spectral.mass
        self.faces_x, self.faces_y = x.spectral.faces, y.spectral.faces
        self.n_x, self.n_y = x.spectral.n_verts, y.spectral.n_verts
        self.device, self.dtype = self.phi_x.device, self.phi_x.dtype
        self.feat_x, self.feat_y = feats if feats is not None else (None, None)
        self.evals_x, self.evals_y = x.evals, y.evals
        self.verts_y = y.spectral.verts
        self.coeffs_y = y.spectral.coeffs
        self.edges_x = undirected_edges(self.faces_x, self.n_x).to(self.device)
        self.arap_gram = None
        if need_arap:
            # sum over directed edges of (Phi_i - Phi_j)^T (Phi_i - Phi_j) = 2 Phi^T L Phi (uniform graph
            # Laplacian); built once for all k from a sparse L (the original loops over the neighbour list).
            a, b = self.edges_x[:, 0], self.edges_x[:, 1]
            diff = (self.phi_x[a] - self.phi_x[b]).to(torch.float64)
            self.arap_gram = 2.0 * diff.transpose(0, 1) @ diff
        self._shell_y = {}
        self._feature_systems = {}

    def feature_system(self, kk: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Descriptor term of the functional-map solve of size ``kk``, cached per size.

        Returns ``F_X F_X^T (kk, kk)``, ``F_X F_Y^T (kk, kk)`` (float64) and the spectral norm of the first.
        """
        if kk not in self._feature_systems:
            fx, fy = self.feat_x[:kk].to(torch.float64), self.feat_y[:kk].to(torch.float64)
            if fx.shape[0] < kk:
                raise ConfigError(f"the basis features have {fx.shape[0]} rows, a functional map of size {kk} "
                                  "needs more")
            mfeat = fx @ fx.transpose(0, 1)
            self._feature_systems[kk] = (mfeat, fx @ fy.transpose(0, 1), _spectral_norm_psd(mfeat))
        return self._feature_systems[kk]

    def shell_y(self, k: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``Y_k`` (n_y, 3) and its normals, cached."""
        if k not in self._shell_y:
            sy = _shell(self.phi_y, self.coeffs_y[None], k)[0]
            self._shell_y[k] = (sy, vertex_normals(sy, self.faces_y))
        return self._shell_y[k]


def _batched_normals(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Vertex normals ``(B, n, 3)`` of a batch of poses ``(B, n, 3)`` of one mesh, pose by pose.

    Faster on the CPU than one batched gather / index_add over the middle dimension (46 vs 89 ms for
    16 x 5000 vertices, measured).
    """
    return torch.stack([vertex_normals(v, faces) for v in verts])


def _shell(evecs: torch.Tensor, coeffs: torch.Tensor, k: int) -> torch.Tensor:
    """Sigmoid shells of a batch of poses: ``(B, n, 3)`` from ``coeffs (B, K, 3)``."""
    w = sigmoid_shell_weights(k, dtype=evecs.dtype, device=evecs.device)
    kk = w.shape[0]
    if kk > evecs.shape[1]:
        raise ConfigError(f"a shell of size {k} needs {kk} eigenfunctions, the shape has {evecs.shape[1]}")
    return torch.matmul(evecs[:, :kk], w[None, :, None] * coeffs[:, :kk])


# ---------------------------------------------------------------------------------------------------------
# batched building blocks


def _nearest(queries: torch.Tensor, points: torch.Tensor, backend: str = "auto") -> torch.Tensor:
    """Exact Euclidean nearest neighbours in batches.

    For ``queries (B or 1, q, d)``, ``points (B or 1, p, d)`` (a batch dimension of 1 is shared by every batch
    element): the index ``(B, q)`` of the nearest point.

    Written here because :mod:`shapecorr.matching.nearest_neighbors` has no batch dimension; the random search
    and the rigid surrogate runs solve many small independent problems at once. On the GPU: one distance
    block per chunk of queries for the whole batch (float32); on the CPU: scipy k-d trees (exact, float64),
    which are faster there for these low-dimensional embeddings (measured: brute force was ~20x slower for
    1000 x 5000 points in 26 dimensions, and batched float32 brute force ~1.7x slower for 1000 x 1000). A shared
    point set is one tree for the whole batch (the Y side of every search: Y's embedding does not depend on
    the proposal); the batch elements are spread over torch's intra-op thread count (scipy releases the GIL).
    """
    b = max(queries.shape[0], points.shape[0])
    q, p = queries.shape[1], points.shape[1]
    if backend == "auto":
        backend = "kdtree" if queries.device.type == "cpu" else "brute"
    if backend == "kdtree":
        pts = points.detach().to(torch.float64).cpu().numpy()
        qrs = queries.detach().to(torch.float64).cpu().numpy()
        shared = cKDTree(pts[0]) if pts.shape[0] == 1 else None
        out = np.empty((b, q), dtype=np.int64)

        def one(i: int) -> None:
            tree = shared if shared is not None else cKDTree(pts[i])
            out[i] = tree.query(qrs[0] if qrs.shape[0] == 1 else qrs[i], k=1)[1]

        _side_by_side(one, list(range(b)), torch.device("cpu"))
        return torch.from_numpy(out).to(queries.device)
    queries, points = queries.expand(b, -1, -1), points.expand(b, -1, -1)
    chunk = max(1, NN_BLOCK_ENTRIES // max(1, b * p))
    out = torch.empty(b, q, dtype=torch.int64, device=queries.device)
    pp = points.square().sum(-1)[:, None, :]
    for start in range(0, q, chunk):
        qb = queries[:, start:start + chunk]
        d = torch.baddbmm(pp, qb, points.transpose(1, 2), alpha=-2.0)
        out[:, start:start + chunk] = d.argmin(-1)
    return out


def _side_by_side(fn, items: list, device: torch.device) -> list:
    """``[fn(item) for item in items]``, on the CPU with the items spread over torch's thread count.

    The surrogate runs of the random search and of the rigid stage are independent batches of small tensors,
    for which torch's intra-op threads barely help: whole batches run side by side instead, each thread with
    one intra-op thread (torch and scipy release the GIL). Every item is computed exactly as in the serial loop.
    """
    previous = torch.get_num_threads()
    threads = min(previous, len(items))
    if device.type != "cpu" or threads < 2:
        return [fn(item) for item in items]

    def one(item):
        torch.set_num_threads(1)  # one intra-op thread per worker thread
        return fn(item)

    try:
        with ThreadPoolExecutor(max_workers=threads) as pool:
            return list(pool.map(one, items))
    finally:
        torch.set_num_threads(previous)


def _solve_spd(gram: torch.Tensor, rhs: torch.Tensor, ridge: float, what: str) -> torch.Tensor:
    """Batched ``(G + ridge mean(diag G) I) X = rhs`` in float64 by Cholesky.

    The batched form of :func:`shapecorr.matching.least_squares.solve_normal_equations` (same relative ridge),
    which has no batch dimension.

    Parameters
    ----------
    gram : (..., k, k) float
    rhs : (..., k, c) float

    Returns
    -------
    (..., k, c) float64
    """
    g = gram.to(torch.float64)
    z = rhs.to(torch.float64)
    if not (torch.isfinite(g).all() and torch.isfinite(z).all()):
        raise NumericalError(f"{what}: the normal equations contain NaN or Inf")
    k = g.shape[-1]
    scale = torch.diagonal(g, dim1=-2, dim2=-1).mean(-1)
    scale = torch.where(scale > 0, scale, torch.ones_like(scale))
    g = g + (ridge * scale)[..., None, None] * torch.eye(k, dtype=g.dtype, device=g.device)
    chol, info = torch.linalg.cholesky_ex(g)
    if bool((info != 0).any()):
        raise NumericalError(f"{what}: a {k}x{k} Gram matrix is not positive definite; the correspondences do "
                             f"not determine the {k} unknowns (ridge {ridge})")
    sol = torch.cholesky_solve(z, chol)
    if not torch.isfinite(sol).all():
        raise NumericalError(f"{what}: the solution contains NaN or Inf")
    return sol


def _spectral_norm_psd(m: torch.Tensor) -> torch.Tensor:
    """Spectral norm of symmetric positive semi-definite ``(..., k, k)`` matrices: ``(...,)``.

    The largest eigenvalue (cheaper than the SVD behind ``matrix_norm(ord=2)``).
    """
    return torch.linalg.eigvalsh(m)[..., -1].clamp_min(0)


def _orthogonalize(c: torch.Tensor) -> torch.Tensor:
    """Closest orthogonal matrices ``U V^T`` (area preservation), batched (..., k, k)."""
    u, _, vh = torch.linalg.svd(c.to(torch.float64))
    return u @ vh


def _inf_norm(m: torch.Tensor) -> torch.Tensor:
    """Maximum absolute row sum of ``(..., k, k)``."""
    return m.abs().sum(-1).amax(-1)


def _scatter_rows(n: int, index: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """``(B, n, c)`` zeros with ``values (B, r, c)`` added at rows ``index (B, r)``."""
    out = values.new_zeros(values.shape[0], n, values.shape[2])
    return out.scatter_add_(1, index[:, :, None].expand(-1, -1, values.shape[2]), values)


def _gather_rows(values: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``values (B or 1, n, c)`` at rows ``index (B, r)`` -> ``(B, r, c)``."""
    if values.shape[0] == 1 and index.shape[0] > 1:
        values = values.expand(index.shape[0], -1, -1)
    return torch.gather(values, 1, index[:, :, None].expand(-1, -1, values.shape[2]))


# ---------------------------------------------------------------------------------------------------------
# one layer


@dataclass
class _Run:
    """Settings of one layered run (main, surrogate or proposal)."""

    fac_feat: float
    normal_damping: float
    lambda_feat: float
    lambda_lap: torch.Tensor  # (B,)
    lambda_arap_init: float
    area_preservation: bool
    num_sub: int
    mode: int  # 1: samples -> all vertices; 2: samples -> samples
    samples_x: torch.Tensor  # (s,)
    samples_y: torch.Tensor  # (s',)
    ridge: float
    nn_backend: str
    cfix: torch.Tensor | None = None  # (B, f, f)
    record: bool = False


@dataclass
class _State:
    """What a layer carries to the next: pose of X, ``tau``, ``C`` and the previous sigmoid weights."""

    verts_x: torch.Tensor  # (B, n, 3)
    coeffs_x: torch.Tensor  # (B, K, 3)
    tau: torch.Tensor  # (B, K_tau, 3) float64
    fmap: torch.Tensor | None  # (B, k', k')
    k_prev: int = 0
    w_prev: torch.Tensor | None = None
    pairs: tuple[torch.Tensor, torch.Tensor] | None = None  # last (assignment, assignment_inv)
    objectives: list = field(default_factory=list)


def _embedding_scales(pair: _Pair, shell_y, normals_y, k_prev, fac_feat, damping):
    """Weights of the spectral block and of the normals, from Y (shared by both sides; docs/smooth_shells.md §6)."""
    y_norm = shell_y.norm()
    fac_n = damping * y_norm / normals_y.norm().clamp_min(1e-30)
    fac_s = None
    if k_prev:
        fac_s = fac_feat * y_norm / pair.phi_y[:, :k_prev].norm().clamp_min(1e-30)
    return fac_s, fac_n


def _embeddings(pair: _Pair, st: _State, deformed, normals_x, shell_y, normals_y, fac_feat, damping):
    """Full-resolution product embeddings ``(B, n_x, d)``, ``(1, n_y, d)``."""
    fac_s, fac_n = _embedding_scales(pair, shell_y, normals_y, st.k_prev if st.fmap is not None else 0,
                                     fac_feat, damping)
    ex = [deformed]
    ey = [shell_y[None]]
    if fac_n > 0:
        ex.append(fac_n * normals_x)
        ey.append(fac_n * normals_y[None])
    if fac_s is not None:
        kp, kc = st.k_prev, st.fmap.shape[-1]
        w = st.w_prev[:kp].to(deformed.dtype)
        spec_x = torch.matmul(pair.phi_x[:, :kc], st.fmap[:, :, :kp].to(deformed.dtype))
        ex.append(fac_s * w * spec_x)
        ey.append((fac_s * w * pair.phi_y[:, :kp])[None])
    return torch.cat(ex, -1), torch.cat(ey, -1)


def _correspondences(pair: _Pair, run: _Run, emb_x, emb_y):
    """Assignments X samples -> Y (B, s) and Y samples -> X (B, s'), as full vertex indices."""
    sx, sy = run.samples_x, run.samples_y
    b = emb_x.shape[0]
    full_x, full_y = sx.numel() == pair.n_x, sy.numel() == pair.n_y
    if run.mode == 2 and b == 1 and full_x and full_y:
        a, ai = bidirectional_nearest_neighbors(emb_x[0], emb_y[0], backend=run.nn_backend,
                                                workers=torch.get_num_threads())
        return a[None], ai[None]
    qx, qy = emb_x[:, sx], emb_y[:, sy]
    if run.mode == 2:
        a = sy[_nearest(qx, qy)]
        ai = sx[_nearest(qy, qx)]
    else:
        a = _nearest(qx, emb_y)
        ai = _nearest(qy, emb_x)
    return a, ai


def _row_normal_equations(phi: torch.Tensor, rows: torch.Tensor, values: torch.Tensor,
                          vertex_weights: torch.Tensor | None = None):
    """``sum_r w phi_r^T phi_r`` and ``sum_r w phi_r^T v_r`` over the rows ``r`` of each batch element.

    Parameters
    ----------
    phi : (n, k) float64
        Basis of X.
    rows : (B, r) int64
        Vertex of every pair (a vertex may repeat).
    values : (B, r, c) float64
        Target of every pair.
    vertex_weights : (n,) float64, optional
        Weight ``w`` of each vertex (1 if omitted).

    Returns
    -------
    gram : (B, k, k) float64
    rhs : (B, k, c) float64

    With fewer pairs than vertices (the surrogate runs on samples) the rows are gathered; otherwise they are
    first summed per vertex (a scatter): the products run over min(r, n) rows.
    """
    b, r = rows.shape
    n = phi.shape[0]
    if r < n:
        phi_r = phi[rows]  # (B, r, k)
        weighted = phi_r if vertex_weights is None else phi_r * vertex_weights[rows][..., None]
        return torch.matmul(weighted.transpose(1, 2), phi_r), torch.matmul(weighted.transpose(1, 2), values)
    counts = _scatter_rows(n, rows, torch.ones(b, r, 1, dtype=phi.dtype, device=phi.device))
    summed = _scatter_rows(n, rows, values)
    if vertex_weights is not None:
        counts = counts * vertex_weights[None, :, None]
        summed = vertex_weights[None, :, None] * summed
    return torch.matmul(phi.transpose(0, 1), counts * phi), torch.matmul(phi.transpose(0, 1), summed)


def _tau_system(pair: _Pair, run: _Run, shell_x, shell_y, assign, assign_inv, k):
    """Data part of the ``tau`` normal equations (not area weighted, as in the original): (B, k, k), (B, k, 3)."""
    b = shell_x.shape[0]
    sx, sy = run.samples_x[None].expand(b, -1), run.samples_y[None].expand(b, -1)
    sx64, sy64 = shell_x.to(torch.float64), shell_y.to(torch.float64)[None]
    rows = torch.cat([sx, assign_inv], 1)
    target = torch.cat([_gather_rows(sy64, assign) - _gather_rows(sx64, sx),
                        _gather_rows(sy64, sy) - _gather_rows(sx64, assign_inv)], 1)
    return _row_normal_equations(pair.phi_x64[:, :k], rows, target)


def _arap_system(pair: _Pair, shell_x, deformed, k):
    """ARAP part with the rotations of the current ``X*`` frozen: ``(B, k, k)``, ``(B, k, 3)``, rotations."""
    rot = arap_rotations(shell_x, deformed, pair.edges_x).to(torch.float64)  # (B, n, 3, 3): e_X* ~ R e_Xk
    a, b = pair.edges_x[:, 0], pair.edges_x[:, 1]
    eye = torch.eye(3, dtype=torch.float64, device=rot.device)
    d = (shell_x[:, a] - shell_x[:, b]).to(torch.float64)  # x_a - x_b
    g = torch.matmul(rot[:, a] + rot[:, b] - 2 * eye, d[..., None])[..., 0]
    s = torch.zeros_like(shell_x, dtype=torch.float64).index_add_(1, a, g).index_add_(1, b, -g)
    phi = pair.phi_x64[:, :k]
    return pair.arap_gram[:k, :k], torch.matmul(phi.transpose(0, 1), s), rot


def _tau_objective(pair, run, shell_x, shell_y, assign, assign_inv, tau, k, rot, arap_weight):
    """``sum |X* - Y_k[pi]|^2 + sum |X*[pi'] - Y_k|^2 + w sum_directed |(Phi_i - Phi_j) tau - (R_i - I) d_ij|^2``."""
    phi = pair.phi_x64[:, :k]
    disp = torch.matmul(phi, tau[:, :k])
    cur = shell_x.to(torch.float64) + disp
    sy64 = shell_y.to(torch.float64)[None]
    b = cur.shape[0]
    sx = run.samples_x[None].expand(b, -1)
    sy = run.samples_y[None].expand(b, -1)
    data = (_gather_rows(cur, sx) - _gather_rows(sy64, assign)).square().sum((1, 2))
    data = data + (_gather_rows(cur, assign_inv) - _gather_rows(sy64, sy)).square().sum((1, 2))
    if rot is None:
        return data
    a, bb = pair.edges_x[:, 0], pair.edges_x[:, 1]
    eye = torch.eye(3, dtype=torch.float64, device=rot.device)
    d = (shell_x[:, a] - shell_x[:, bb]).to(torch.float64)
    delta = disp[:, a] - disp[:, bb]
    arap = (delta - torch.matmul(rot[:, a] - eye, d[..., None])[..., 0]).square().sum((1, 2))
    arap = arap + (delta - torch.matmul(rot[:, bb] - eye, d[..., None])[..., 0]).square().sum((1, 2))
    return data + arap_weight * arap


def _functional_map(pair: _Pair, run: _Run, kk: int, assign=None, assign_inv=None, batch: int = 1):
    """Functional map of size ``kk`` (B, kk, kk): area-weighted pairs, descriptors, Laplacian, orthogonality."""
    f64 = torch.float64
    if assign is not None:
        b = assign.shape[0]
        sx, sy = run.samples_x[None].expand(b, -1), run.samples_y[None].expand(b, -1)
        rows = torch.cat([sx, assign_inv], 1)
        phi_y = pair.phi_y64[:, :kk][None]
        targets = torch.cat([_gather_rows(phi_y, assign), _gather_rows(phi_y, sy)], 1)
        gram, rhs = _row_normal_equations(pair.phi_x64[:, :kk], rows, targets, pair.mass_x.to(f64))
        lambda_feat = run.lambda_feat
    else:
        b = batch
        gram = torch.zeros(b, kk, kk, dtype=f64, device=pair.device)
        rhs = torch.zeros_like(gram)
        lambda_feat = 1.0  # descriptors only (the original's FM without correspondences)
    if pair.feat_x is not None and lambda_feat > 0:
        mfeat, zfeat, mfeat_norm = pair.feature_system(kk)
        c = _spectral_norm_psd(gram) / mfeat_norm
        c = torch.where(c > 0, c, torch.ones_like(c))
        gram = gram + (c * lambda_feat)[:, None, None] * mfeat
        rhs = rhs + (c * lambda_feat)[:, None, None] * zfeat
    lam = run.lambda_lap.to(device=pair.device, dtype=f64).expand(b)
    what = f"Smooth Shells functional map (size {kk})"
    if bool((lam > 0).any()):
        # Laplacian commutativity, diagonal in the entries of C: sum_ij L_ij C_ij^2 with
        # L = lambda mean|M| sqrt|ev_X,i - ev_Y,j| / (column mean) -> one system per column of C.
        lx, ly = pair.evals_x[:kk].to(f64), pair.evals_y[:kk].to(f64)
        lap = torch.sqrt((lx[:, None] - ly[None, :]).abs())
        lap = lap / lap.mean(0, keepdim=True).clamp_min(1e-30)
        pen = (lam * gram.abs().mean((1, 2)))[:, None, None] * lap  # (B, kk, kk): [b, i, j]
        systems = gram[:, None] + torch.diag_embed(pen.transpose(1, 2))  # (B, j, kk, kk)
        cols = _solve_spd(systems, rhs.transpose(1, 2)[..., None], run.ridge, what)[..., 0]  # (B, j, kk)
        fmap = cols.transpose(1, 2)
    else:
        fmap = _solve_spd(gram, rhs, run.ridge, what)
    if run.area_preservation:
        fmap = _orthogonalize(fmap)
    if run.cfix is not None:
        f = run.cfix.shape[-1]
        fixed = torch.zeros_like(fmap)
        fixed[:, :f, :f] = run.cfix.to(f64)
        if kk > f:
            rest = fmap[:, f:, f:]
            fixed[:, f:, f:] = _orthogonalize(rest) if run.area_preservation else rest
        fmap = fixed
    return fmap


def _match_layer(pair: _Pair, run: _Run, st: _State, k: int, first_pairs=None) -> _State:
    """One layer of size ``k`` (``run.num_sub`` rounds), updating ``st`` in place; see the module docstring."""
    w = sigmoid_shell_weights(k, dtype=pair.dtype, device=pair.device)
    kk = w.shape[0]
    shell_x = _shell(pair.phi_x, st.coeffs_x, k)  # (B, n, 3)
    shell_y, normals_y = pair.shell_y(k)
    damping = run.normal_damping if k > NORMAL_K_MIN else 0.0
    lambda_arap = run.lambda_arap_init * math.sqrt(max(k - K_START, 0))
    phi_k = pair.phi_x[:, :k]
    for sub in range(run.num_sub):
        deformed = shell_x + torch.matmul(phi_k, st.tau[:, :k].to(pair.dtype))
        if first_pairs is not None and sub == 0:
            assign, assign_inv = first_pairs
        else:
            normals_x = _batched_normals(deformed, pair.faces_x) if damping > 0 else None
            emb_x, emb_y = _embeddings(pair, st, deformed, normals_x, shell_y, normals_y, run.fac_feat, damping)
            assign, assign_inv = _correspondences(pair, run, emb_x, emb_y)
        gram, rhs = _tau_system(pair, run, shell_x, shell_y, assign, assign_inv, k)
        rot, weight = None, 0.0
        if lambda_arap > 0:
            if pair.arap_gram is None:
                raise ConfigError("internal: ARAP needed but not prepared")
            g_arap, z_arap, rot = _arap_system(pair, shell_x, deformed, k)
            weight = lambda_arap * _inf_norm(gram) / _inf_norm(g_arap).clamp_min(1e-300)  # (B,)
            gram = gram + weight[:, None, None] * g_arap
            rhs = rhs + weight[:, None, None] * z_arap
        if run.record:
            before = _tau_objective(pair, run, shell_x, shell_y, assign, assign_inv, st.tau, k, rot, weight)
        sol = _solve_spd(gram, rhs, run.ridge, f"Smooth Shells deformation solve at k={k}")
        tau = st.tau.clone()
        tau[:, :k] = sol
        st.tau = tau
        if run.record:
            after = _tau_objective(pair, run, shell_x, shell_y, assign, assign_inv, st.tau, k, rot, weight)
            st.objectives.append(torch.stack([before[0], after[0]]))
        st.fmap = _functional_map(pair, run, kk, assign, assign_inv)
        st.pairs = (assign, assign_inv)
        st.k_prev, st.w_prev = k, w  # the next round already embeds with this C (as the original)
    return st


def _layered(pair: _Pair, run: _Run, st: _State, ks, first_pairs=None, cfix_k_max: int = K_START) -> _State:
    cfix = run.cfix
    for i, k in enumerate(ks):
        run.cfix = cfix if (cfix is not None and k <= cfix_k_max) else None
        _match_layer(pair, run, st, k, first_pairs if i == 0 else None)
    run.cfix = cfix
    return st


# ---------------------------------------------------------------------------------------------------------
# detail re-attachment and scoring


def _reattach_detail(pair: _Pair, verts_x, coeffs_x, tau, k):
    """``R_i (X - X_k) + X_k + Phi tau``: the detail of X rotated by the per-vertex ARAP rotations of the shell.

    Returns
    -------
    (B, n, 3) float
    """
    shell_x = _shell(pair.phi_x, coeffs_x, k)
    shifted = shell_x + torch.matmul(pair.phi_x[:, :k], tau[:, :k].to(pair.dtype))
    rot = arap_rotations(shell_x, shifted, pair.edges_x)
    return torch.matmul(rot, (verts_x - shell_x)[..., None])[..., 0] + shifted


def _descriptor_block(pair: _Pair, feats, weight: float):
    """Per-vertex basis features ``Phi F`` of X (n_x, c) and Y (n_y, c), scaled to ``weight * ||Y||``.

    None when ``weight == 0``; ``feats``: :func:`basis_features` (required otherwise).
    """
    if not weight > 0:
        return None
    if feats is None:
        raise ConfigError("smooth_shells.score_descriptors needs the basis features (lambda_feat > 0)")
    k = feats[0].shape[0]
    desc_x = pair.phi_x[:, :k] @ feats[0].to(pair.dtype)
    desc_y = pair.phi_y[:, :k] @ feats[1].to(pair.dtype)
    scale = weight * pair.verts_y.norm() / desc_y.norm().clamp_min(1e-30)
    return scale * desc_x, scale * desc_y


def _score(pair: _Pair, run: _Run, st: _State, full_x, fac_feat, damping, normals_y_full, descriptors=None):
    """Area-weighted residual of the correspondences of the re-attached shapes (lower is better): (B,).

    ``descriptors`` (:func:`_descriptor_block`) add the descriptor disagreement of the pairs to the residual.
    """
    normals_x = _batched_normals(full_x, pair.faces_x)
    emb_x, emb_y = _embeddings(pair, st, full_x, normals_x, pair.verts_y, normals_y_full, fac_feat, damping)
    assign, assign_inv = _correspondences(pair, run, emb_x, emb_y)
    _, fac_n = _embedding_scales(pair, pair.verts_y, normals_y_full, 0, fac_feat, damping)
    px = torch.cat([full_x, fac_n * normals_x], -1)
    py = torch.cat([pair.verts_y, fac_n * normals_y_full], -1)[None]
    if descriptors is not None:
        desc_x, desc_y = descriptors
        px = torch.cat([px, desc_x[None].expand(px.shape[0], -1, -1)], -1)
        py = torch.cat([py, desc_y[None]], -1)
    b = full_x.shape[0]
    sx, sy = run.samples_x[None].expand(b, -1), run.samples_y[None].expand(b, -1)
    d = (_gather_rows(px, sx) - _gather_rows(py, assign)).norm(dim=-1)
    d_inv = (_gather_rows(px, assign_inv) - _gather_rows(py, sy)).norm(dim=-1)
    res = torch.cat([pair.mass_x[run.samples_x][None] * d, pair.mass_y[run.samples_y][None] * d_inv], 1)
    return res.to(torch.float64).mean(1)


def _fps(verts: torch.Tensor, num: int, gen: torch.Generator) -> torch.Tensor:
    """Sorted farthest-point samples from a random start drawn from ``gen`` (the original starts at random)."""
    n = verts.shape[0]
    num = min(num, n)
    start = int(torch.randint(0, n, (1,), generator=gen))
    idx = np.sort(farthest_point_sampling(verts.detach().cpu(), num, start=start))
    return torch.from_numpy(idx).to(verts.device)


# ---------------------------------------------------------------------------------------------------------
# rigid alignment


def _rotation_between(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """The minimal rotation (3, 3) taking direction ``a`` to direction ``b`` (Rodrigues)."""
    a = a / a.norm()
    b = b / b.norm()
    v = torch.linalg.cross(a, b)
    s, c = v.norm(), torch.dot(a, b)
    if float(s) < 1e-12:
        if float(c) > 0:
            return torch.eye(3, dtype=a.dtype, device=a.device)
        # antiparallel: half turn about any axis orthogonal to a
        helper = torch.eye(3, dtype=a.dtype, device=a.device)[int(torch.argmin(a.abs()))]
        axis = torch.linalg.cross(a, helper)
        return _axis_angle(axis / axis.norm(), math.pi)
    return _axis_angle(v / s, float(torch.atan2(s, c)))


def _axis_angle(axis: torch.Tensor, angle: float) -> torch.Tensor:
    """Rotation matrix (3, 3) about the unit ``axis`` by ``angle`` (Rodrigues' formula)."""
    kx = torch.zeros(3, 3, dtype=axis.dtype, device=axis.device)
    kx[0, 1], kx[0, 2], kx[1, 2] = -axis[2], axis[1], -axis[0]
    kx = kx - kx.transpose(0, 1)
    eye = torch.eye(3, dtype=axis.dtype, device=axis.device)
    return eye + math.sin(angle) * kx + (1.0 - math.cos(angle)) * (kx @ kx)


def _axis_icp(src: torch.Tensor, dst: torch.Tensor, axis: torch.Tensor, iterations: int) -> torch.Tensor:
    """Rotation (3, 3) about ``axis`` through the mean of ``src`` that best aligns ``src`` to ``dst``.

    ICP with bidirectional nearest neighbours; for fixed pairs the optimal angle about a fixed axis has the
    closed form ``atan2(sum q . (u x p), sum q . p_perp)`` (the original takes one Gauss-Newton step on the
    angle per iteration instead).
    """
    u = (axis / axis.norm()).to(torch.float64)
    centre = src.mean(0).to(torch.float64)
    p0 = src.to(torch.float64) - centre
    q = dst.to(torch.float64) - centre
    rot = torch.eye(3, dtype=torch.float64, device=src.device)
    for _ in range(iterations):
        p = p0 @ rot.transpose(0, 1)
        a, ai = bidirectional_nearest_neighbors(p, q, backend="kdtree" if p.device.type == "cpu" else "brute",
                                                workers=torch.get_num_threads())
        pp = torch.cat([p, p[ai]], 0)
        qq = torch.cat([q[a], q], 0)
        perp = pp - (pp @ u)[:, None] * u
        num = (qq * torch.linalg.cross(u.expand_as(pp), pp, dim=-1)).sum()
        den = (qq * perp).sum()
        angle = float(torch.atan2(num, den))
        if abs(angle) < 1e-12:
            break
        rot = _axis_angle(u, angle) @ rot
    return rot


def _area_centroid(verts: torch.Tensor, mass: torch.Tensor) -> torch.Tensor:
    return (mass[:, None] * verts).sum(0) / mass.sum()


def rigid_alignment(x: ShellsShape, y: ShellsShape, config: SmoothShellsConfig = SmoothShellsConfig(),
                    feats=None, generator: torch.Generator | None = None):
    """Rigid pre-alignment of X onto Y (module docstring, step 2).

    Parameters
    ----------
    x, y : ShellsShape
    config : SmoothShellsConfig
    feats : tuple of (K, c) tensors, optional
        :func:`basis_features` (for the descriptor-only initial functional map of the surrogate runs).
    generator : torch.Generator, optional
        Farthest-point starts (default: seeded with ``config.seed``).

    Returns
    -------
    rotation : (3, 3) float
    translation : (3,) float
        ``aligned = x.verts @ rotation.T + translation``.
    scores : list of (c,) float64
        Candidate scores of each surrogate set.
    """
    gen = generator if generator is not None else torch.Generator().manual_seed(config.seed)
    sx, sy = x.spectral, y.spectral
    dtype, dev = sx.verts.dtype, sx.verts.device
    # (a) first non-constant spectral coordinate of X onto +-that of Y
    dir_x, dir_y = sx.coeffs[1].to(torch.float64), sy.coeffs[1].to(torch.float64)
    if float(dir_x.norm()) == 0 or float(dir_y.norm()) == 0:
        raise NumericalError(f"rigid alignment of {sx.name}, {sy.name}: zero first spectral coordinate")
    if float(torch.dot(dir_x, dir_y)) < 0:
        dir_y = -dir_y
    rot = _rotation_between(dir_x, dir_y)
    verts0 = sx.verts.to(torch.float64)
    m_x, m_y = sx.mass.to(torch.float64), sy.mass.to(torch.float64)
    # The original centres both shapes on load; here X's area-weighted centroid is moved onto Y's so that the
    # axis ICP below works for any input placement.
    trans = _area_centroid(sy.verts.to(torch.float64), m_y) - rot @ _area_centroid(verts0, m_x)

    def apply(r, t):
        return verts0 @ r.transpose(0, 1) + t

    # (b) ICP about Y's axis on farthest-point samples of the (normalized) 6-eigenfunction hard shells
    def hard6(s: SpectralShape, verts):
        coeffs = spectral_coefficients(s.evecs[:, :6], s.mass, verts.to(s.evecs.dtype))
        v = s.evecs[:, :6] @ coeffs
        v = v - v.mean(0)
        return v / v.square().mean(0).clamp_min(1e-30)

    cur = apply(rot, trans)
    samples_x = _fps(hard6(sx, cur), config.problem_size_init, gen)
    samples_y = _fps(hard6(sy, sy.verts), config.problem_size_init, gen)
    r_icp = _axis_icp(cur[samples_x], sy.verts[samples_y].to(torch.float64), dir_y, config.icp_iterations)
    centre = cur[samples_x].mean(0)
    rot = r_icp @ rot
    trans = r_icp @ trans + centre - r_icp @ centre
    # (c) area-weighted centroids
    trans = trans + _area_centroid(sy.verts.to(torch.float64), m_y) - _area_centroid(apply(rot, trans), m_x)
    # (d) surrogate runs resolving flips
    pair = _Pair(x, y, feats, need_arap=False)
    samples_x = _fps(apply(rot, trans).to(dtype), config.problem_size_init, gen)
    samples_y = _fps(sy.verts, config.problem_size_init, gen)
    run = _Run(fac_feat=config.rigid_fac_feat, normal_damping=config.rigid_normal_damping,
               lambda_feat=config.lambda_feat, lambda_lap=torch.tensor([config.rigid_lambda_lap]),
               lambda_arap_init=0.0, area_preservation=config.area_preservation, num_sub=config.rigid_num_sub,
               mode=1, samples_x=samples_x, samples_y=samples_y, ridge=config.ridge, nn_backend=config.nn_backend)
    w_init = sigmoid_shell_weights(K_START, dtype=dtype, device=dev)
    c_init = _functional_map(pair, replace(run, lambda_lap=torch.tensor([0.0])), w_init.shape[0], batch=1)
    normals_y_full = vertex_normals(_shell(pair.phi_y, sy.coeffs[None], config.k_max)[0], sy.faces)
    y_centroid = _area_centroid(sy.verts.to(torch.float64), m_y)
    descriptors = _descriptor_block(pair, feats, config.score_descriptors)
    for k in range(RIGID_K_MIN, K_START + 1):
        pair.shell_y(k)  # fill the cache of Y's shells before the candidates share it

    def principal_axes(r, t):
        aligned = apply(r, t)
        return torch.linalg.svd(aligned - aligned.mean(0), full_matrices=False)[2]  # rows: decreasing variance

    def evaluate(turns, r, t):
        """Score the poses ``turn @ (r, t)`` (re-centred) by a surrogate run each; returns (scores, poses)."""
        poses = []
        for turn in turns:
            r_c, t_c = turn @ r, turn @ t
            t_c = t_c + y_centroid - _area_centroid(verts0 @ r_c.transpose(0, 1) + t_c, m_x)
            poses.append((r_c, t_c))
        def surrogate(chunk):  # a batch of candidate poses
            verts_b = torch.stack([apply(r_c, t_c) for r_c, t_c in chunk]).to(dtype)
            coeffs_b = torch.stack([spectral_coefficients(sx.evecs, sx.mass, v) for v in verts_b])
            b = verts_b.shape[0]
            st = _State(verts_x=verts_b, coeffs_x=coeffs_b,
                        tau=torch.zeros(b, K_START, 3, dtype=torch.float64, device=dev),
                        fmap=c_init.expand(b, -1, -1), k_prev=K_START, w_prev=w_init)
            run_b = replace(run, lambda_lap=torch.full((b,), config.rigid_lambda_lap))
            _layered(pair, run_b, st, range(RIGID_K_MIN, K_START + 1))
            full = _reattach_detail(pair, verts_b, coeffs_b, st.tau, K_START)
            return _score(pair, run_b, st, full, config.rigid_fac_feat, config.rigid_normal_damping, normals_y_full,
                          descriptors)

        threads = torch.get_num_threads() if dev.type == "cpu" else 1  # one batch per thread (side by side)
        per_thread = -(-len(poses) // max(1, threads))
        chunks = [poses[i:i + per_thread] for i in range(0, len(poses), per_thread)]
        return torch.cat(_side_by_side(surrogate, chunks, dev)), poses

    all_scores = []
    count3, count1 = config.rigid_rotations
    if config.rigid_joint:
        # every combination of the two sets at once (the 3rd and 1st principal axes of the current pose)
        axes = principal_axes(rot, trans)
        turns = [_axis_angle(axes[0], 2.0 * math.pi * j / count1) @ _axis_angle(axes[2], 2.0 * math.pi * i / count3)
                 for i in range(1, count3 + 1) for j in range(1, count1 + 1)]
        scores, poses = evaluate(turns, rot, trans)
        rot, trans = poses[int(torch.argmin(scores))]
        all_scores.append(scores.cpu())
    else:
        # the original: first the turns about the 3rd principal axis, then about the (new) 1st one
        for count, axis_index in ((count3, 2), (count1, 0)):
            axis = principal_axes(rot, trans)[axis_index]
            turns = [_axis_angle(axis, 2.0 * math.pi * i / count) for i in range(1, count + 1)]  # last: current
            scores, poses = evaluate(turns, rot, trans)
            rot, trans = poses[int(torch.argmin(scores))]
            all_scores.append(scores.cpu())
    if config.rigid_keep_input:
        eye = torch.eye(3, dtype=torch.float64, device=dev)
        scores, poses = evaluate([eye], eye, torch.zeros(3, dtype=torch.float64, device=dev))
        all_scores.append(scores.cpu())
        if float(scores[0]) < float(all_scores[-2].min()):
            rot, trans = poses[0]
    return rot.to(dtype), trans.to(dtype), all_scores


# ---------------------------------------------------------------------------------------------------------
# random-search initialization


def random_search_init(x: ShellsShape, y: ShellsShape, aligned_x: torch.Tensor,
                       config: SmoothShellsConfig = SmoothShellsConfig(), feats=None,
                       generator: torch.Generator | None = None):
    """The original's "MCMC" initialization: independent random proposals, best score wins (step 3).

    Every proposal perturbs the 6 lowest spectral coordinates of X (``a_i = |xi_i| N(0, I_3)``, none for the
    constant), draws ``lambda_lap`` from ``config.mcmc_lambda_laps``, runs the surrogate layers k = 6..20 on
    farthest-point samples (spectral weight 1.5, no descriptor term, no ARAP), re-attaches the detail and is
    scored by :func:`_score`. All random numbers are drawn up front, so the result does not depend on
    ``mcmc_batch``.

    Parameters
    ----------
    x, y : ShellsShape
    aligned_x : (n_x, 3) float
        X after the rigid stage.
    config : SmoothShellsConfig
    feats : tuple, optional
        :func:`basis_features`: unused by the proposals (``lambda_feat = 0``), only by the scores when
        ``config.score_descriptors > 0``.
    generator : torch.Generator, optional

    Returns
    -------
    tau_init : (20, 3) float64
    cfix : (29, 29) float64
        Final functional map of the best proposal (fixes that block of C while k <= 20).
    scores : (num_mcmc,) float64
    """
    gen = generator if generator is not None else torch.Generator().manual_seed(config.seed)
    sx, sy = x.spectral, y.spectral
    dev, dtype = sx.verts.device, sx.verts.dtype
    pair = _Pair(x, y, None, need_arap=False)
    coeffs = spectral_coefficients(sx.evecs, sx.mass, aligned_x)
    samples_x = _fps(aligned_x, config.problem_size_init, gen)
    samples_y = _fps(sy.verts, config.problem_size_init, gen)
    num = config.num_mcmc
    choice = torch.randint(0, len(config.mcmc_lambda_laps), (num,), generator=gen)
    noise = torch.randn(num, MCMC_K_MIN, 3, generator=gen, dtype=torch.float64)
    sigma = coeffs[:MCMC_K_MIN].to(torch.float64).norm(dim=1).cpu()
    sigma[0] = 0.0
    props = (sigma[None, :, None] * noise).to(dev)
    laps = torch.tensor(config.mcmc_lambda_laps, dtype=torch.float64)[choice]
    w20 = sigmoid_shell_weights(K_START, dtype=dtype, device=dev)
    normals_y_full = vertex_normals(_shell(pair.phi_y, sy.coeffs[None], config.k_max)[0], sy.faces)
    descriptors = _descriptor_block(pair, feats, config.score_descriptors)
    def proposals(start: int):
        stop = min(num, start + config.mcmc_batch)
        b = stop - start
        tau = torch.zeros(b, K_START, 3, dtype=torch.float64, device=dev)
        tau[:, :MCMC_K_MIN] = props[start:stop]
        st = _State(verts_x=aligned_x[None].expand(b, -1, -1), coeffs_x=coeffs[None].expand(b, -1, -1), tau=tau,
                    fmap=None, k_prev=0, w_prev=w20)
        run = _Run(fac_feat=config.mcmc_fac_feat, normal_damping=config.normal_damping, lambda_feat=0.0,
                   lambda_lap=laps[start:stop], lambda_arap_init=0.0, area_preservation=config.area_preservation,
                   num_sub=1, mode=2, samples_x=samples_x, samples_y=samples_y, ridge=config.ridge,
                   nn_backend=config.nn_backend)
        _layered(pair, run, st, range(MCMC_K_MIN, K_START + 1))
        full = _reattach_detail(pair, st.verts_x, st.coeffs_x, st.tau, K_START)
        score = _score(pair, run, st, full, config.score_fac_feat, config.normal_damping, normals_y_full,
                       descriptors)
        return score, st.tau, st.fmap

    for k in range(MCMC_K_MIN, K_START + 1):
        pair.shell_y(k)  # fill the cache of Y's shells before the batches share it
    scores, taus, fmaps = zip(*_side_by_side(proposals, list(range(0, num, config.mcmc_batch)), dev))
    scores_t = torch.cat(scores)
    if not torch.isfinite(scores_t).all():
        raise NumericalError(f"random-search initialization of {sx.name}, {sy.name}: a proposal score is NaN/Inf")
    best = int(torch.argmin(scores_t))
    return torch.cat(taus)[best], torch.cat(fmaps)[best], scores_t.cpu()


# ---------------------------------------------------------------------------------------------------------
# main entry points


def _check_inputs(x: ShellsShape, y: ShellsShape, config: SmoothShellsConfig):
    need = config.num_eigs
    for s in (x, y):
        if s.spectral.n_eigs < need:
            raise ConfigError(f"{s.name}: Smooth Shells up to k_max={config.k_max} needs {need} eigenpairs, the "
                              f"shape has {s.spectral.n_eigs}; compute more (data.operators.n_eig) or lower k_max")
    if x.spectral.verts.device != y.spectral.verts.device:
        raise ConfigError(f"{x.name} and {y.name} are on different devices")


def _main_run(x, y, config, feats, aligned, tau_init, cfix, ks, first_pairs=None):
    pair = _Pair(x, y, feats if config.lambda_feat > 0 else None, need_arap=config.lambda_arap_init > 0)
    dev = aligned.device
    coeffs = spectral_coefficients(x.spectral.evecs, x.spectral.mass, aligned)
    tau = torch.zeros(1, config.k_max, 3, dtype=torch.float64, device=dev)
    if tau_init is not None:
        tau[0, :tau_init.shape[0]] = tau_init.to(torch.float64)
    st = _State(verts_x=aligned[None], coeffs_x=coeffs[None], tau=tau, fmap=None)
    run = _Run(fac_feat=config.fac_feat, normal_damping=config.normal_damping, lambda_feat=config.lambda_feat,
               lambda_lap=torch.tensor([config.lambda_lap]), lambda_arap_init=config.lambda_arap_init,
               area_preservation=config.area_preservation, num_sub=1, mode=2,
               samples_x=torch.arange(x.spectral.n_verts, device=dev),
               samples_y=torch.arange(y.spectral.n_verts, device=dev), ridge=config.ridge,
               nn_backend=config.nn_backend, cfix=None if cfix is None else cfix[None], record=True)
    _layered(pair, run, st, ks, first_pairs)
    return st


def _result(x, st, aligned, rot, trans, ks, mcmc_scores=None, rigid_scores=()):
    k = st.tau.shape[1]
    tau = st.tau[0].to(aligned.dtype)
    deformed = aligned + x.spectral.evecs[:, :k] @ tau
    if not torch.isfinite(deformed).all():
        raise NumericalError(f"Smooth Shells: the deformed shape of {x.name} contains NaN or Inf")
    objectives = torch.stack(st.objectives).cpu() if st.objectives else torch.zeros(0, 2, dtype=torch.float64)
    return SmoothShellsResult(map_x_to_y=st.pairs[0][0], map_y_to_x=st.pairs[1][0], tau=tau,
                              fmap=st.fmap[0].to(aligned.dtype), deformed_x=deformed, aligned_x=aligned,
                              rotation=rot, translation=trans, k_array=tuple(ks), level_objectives=objectives,
                              mcmc_scores=mcmc_scores, rigid_scores=list(rigid_scores))


def smooth_shells(x: ShellsShape, y: ShellsShape, config: SmoothShellsConfig = SmoothShellsConfig()
                  ) -> SmoothShellsResult:
    """The full Smooth Shells pipeline for one ordered pair (module docstring).

    Parameters
    ----------
    x, y : ShellsShape
        Normalized shapes with at least ``config.num_eigs`` eigenpairs (509 for k_max = 500); SHOT on both
        unless ``lambda_feat == 0``.
    config : SmoothShellsConfig

    Returns
    -------
    SmoothShellsResult
        Deterministic for a given ``config.seed`` (same device and library versions).
    """
    _check_inputs(x, y, config)
    gen = torch.Generator().manual_seed(config.seed)
    with torch.no_grad():
        feats = basis_features(x, y) if config.lambda_feat > 0 else None
        dtype, dev = x.spectral.verts.dtype, x.spectral.verts.device
        rot = torch.eye(3, dtype=dtype, device=dev)
        trans = torch.zeros(3, dtype=dtype, device=dev)
        rigid_scores = []
        if not config.no_rigid:
            rot, trans, rigid_scores = rigid_alignment(x, y, config, feats, gen)
        aligned = x.spectral.verts @ rot.transpose(0, 1) + trans
        tau_init = cfix = mcmc_scores = None
        if config.num_mcmc > 0:
            tau_init, cfix, mcmc_scores = random_search_init(x, y, aligned, config, feats, gen)
        ks = config.k_array
        st = _main_run(x, y, config, feats, aligned, tau_init, cfix, ks)
        return _result(x, st, aligned, rot, trans, ks, mcmc_scores, rigid_scores)


def refine(x: ShellsShape, y: ShellsShape, initial_map: torch.Tensor, k_start: int = K_START,
           initial_map_inv: torch.Tensor | None = None, config: SmoothShellsConfig = SmoothShellsConfig()
           ) -> SmoothShellsResult:
    """Smooth Shells layered matching initialized from a given map (no rigid stage, no random search).

    The first layer (size ``k_start``) fits ``tau`` and ``C`` to the given pairs instead of searching
    neighbours; the layers of the published schedule above ``k_start`` follow. This is the post-processing
    of a learned matcher's map (NeuroMorph's paper refines its maps this way).

    Parameters
    ----------
    x, y : ShellsShape
    initial_map : (n_x,) int64
        Map X -> Y.
    k_start : int
        Shell size of the first layer (``<= config.k_max``).
    initial_map_inv : (n_y,) int64, optional
        Map Y -> X; without it the first layer uses the X -> Y pairs only.
    config : SmoothShellsConfig
        ``no_rigid`` and ``num_mcmc`` are ignored.

    Returns
    -------
    SmoothShellsResult
    """
    _check_inputs(x, y, config)
    n_x, n_y = x.spectral.n_verts, y.spectral.n_verts
    dev = x.spectral.verts.device
    initial_map = torch.as_tensor(initial_map).to(device=dev, dtype=torch.int64)
    if initial_map.shape != (n_x,) or int(initial_map.min()) < 0 or int(initial_map.max()) >= n_y:
        raise ConfigError(f"refine: initial_map must be ({n_x},) indices into the {n_y} vertices of {y.name}")
    if initial_map_inv is not None:
        initial_map_inv = torch.as_tensor(initial_map_inv).to(device=dev, dtype=torch.int64)
        if initial_map_inv.shape != (n_y,) or int(initial_map_inv.min()) < 0 or int(initial_map_inv.max()) >= n_x:
            raise ConfigError(f"refine: initial_map_inv must be ({n_y},) indices into the {n_x} vertices of {x.name}")
    if not 1 <= k_start <= config.k_max:
        raise ConfigError(f"refine: k_start must be in [1, {config.k_max}], got {k_start}")
    ks = (int(k_start),) + tuple(k for k in k_schedule(config.k_max, config.k_array_length) if k > k_start)
    with torch.no_grad():
        feats = basis_features(x, y) if config.lambda_feat > 0 else None
        dtype = x.spectral.verts.dtype
        rot, trans = torch.eye(3, dtype=dtype, device=dev), torch.zeros(3, dtype=dtype, device=dev)
        aligned = x.spectral.verts
        if initial_map_inv is None:
            first = (initial_map[None], torch.zeros(1, 0, dtype=torch.int64, device=dev))
            samples_y_first = torch.zeros(0, dtype=torch.int64, device=dev)
        else:
            first = (initial_map[None], initial_map_inv[None])
            samples_y_first = None
        pair = _Pair(x, y, feats if config.lambda_feat > 0 else None, need_arap=config.lambda_arap_init > 0)
        coeffs = spectral_coefficients(x.spectral.evecs, x.spectral.mass, aligned)
        st = _State(verts_x=aligned[None], coeffs_x=coeffs[None],
                    tau=torch.zeros(1, config.k_max, 3, dtype=torch.float64, device=dev), fmap=None)
        run = _Run(fac_feat=config.fac_feat, normal_damping=config.normal_damping, lambda_feat=config.lambda_feat,
                   lambda_lap=torch.tensor([config.lambda_lap]), lambda_arap_init=config.lambda_arap_init,
                   area_preservation=config.area_preservation, num_sub=1, mode=2,
                   samples_x=torch.arange(n_x, device=dev), samples_y=torch.arange(n_y, device=dev),
                   ridge=config.ridge, nn_backend=config.nn_backend, record=True)
        if samples_y_first is not None:  # one-sided first layer: no Y -> X pairs
            if len(ks) == 1:
                ks = ks + ks  # a second layer searches both directions
            _match_layer(pair, replace(run, samples_y=samples_y_first), st, ks[0], first)
            _layered(pair, run, st, ks[1:])
        else:
            _layered(pair, run, st, ks, first)
        return _result(x, st, aligned, rot, trans, ks)


# ---------------------------------------------------------------------------------------------------------
# the matcher for evaluate.py


def shape_from_sample(sample, need_shot: bool = True) -> ShellsShape:
    """:class:`ShellsShape` from a data-pipeline ``ShapeSample`` (verts, faces, evals, evecs, mass, SHOT)."""
    shot = sample.features.get("shot") if need_shot else None
    if need_shot and shot is None:
        raise ConfigError(f"shape {sample.name!r} has no 'shot' descriptor; add it to data.operators.request "
                          "(e.g. +data.operators.request={shot:{}})")
    return shells_shape(sample.verts, sample.faces, sample.evals, sample.evecs, sample.mass, shot=shot,
                        name=sample.name)


class SmoothShells:
    """Smooth Shells as a matcher (``evaluate.py model=smooth_shells``): no training.

    ``match`` returns both maps and, as an interpolating matcher, the frames ``X + t (X* - X)`` from X (in its
    input pose) to the deformed shape X* (in Y's frame); ``interpolate(x, y, times)`` gives any times.
    The keyword arguments are the fields of :class:`SmoothShellsConfig` (published values as defaults;
    configs/model/smooth_shells*.yaml).

    Parameters
    ----------
    interp_times : sequence of float
        Frames of :meth:`match` (the project's one name for frame times, as ``evaluate.py interp_times``).
    **settings
        :class:`SmoothShellsConfig` fields.
    """

    needs_ground_truth = False

    def __init__(self, interp_times=(0.0, 0.25, 0.5, 0.75, 1.0), **settings):
        try:
            self.config = SmoothShellsConfig(**settings)
        except TypeError as err:
            raise ConfigError(f"smooth_shells: {err}") from None
        values = [float(t) for t in interp_times]
        if not values or not all(np.isfinite(values)):
            raise ConfigError(f"smooth_shells.interp_times must be finite numbers, got {values}")
        self.interp_times = tuple(values)

    @property
    def required_operators(self) -> dict:
        """Operator request: the eigenbasis of ``config.num_eigs`` pairs, and SHOT when features are used."""
        out = {"eigenbasis": {"k": self.config.num_eigs}}
        if self.config.lambda_feat > 0:
            out["shot"] = {}
        return out

    def run(self, x, y) -> SmoothShellsResult:
        """The full pipeline on two ``ShapeSample`` objects."""
        need = self.config.lambda_feat > 0
        return smooth_shells(shape_from_sample(x, need), shape_from_sample(y, need), self.config)

    def interpolate(self, x, y, times) -> MatchResult:
        """Maps and frames ``X + t (X* - X)`` at ``times (T,)``."""
        times = torch.as_tensor(times, dtype=x.verts.dtype, device=x.verts.device).reshape(-1)
        if not torch.isfinite(times).all():
            raise NumericalError(f"interpolation times must be finite, got {times.tolist()}")
        res = self.run(x, y)
        step = res.deformed_x - x.verts
        frames = x.verts[None] + times[:, None, None] * step[None]
        return MatchResult(p2p=res.map_x_to_y, p2p_inv=res.map_y_to_x, deformation=frames, times=times,
                           extras={"k_array": res.k_array, "level_objectives": res.level_objectives})

    def match(self, x, y) -> MatchResult:
        """:meth:`interpolate` at the default ``times``."""
        return self.interpolate(x, y, torch.tensor(self.interp_times))
