"""Hyperparameters of Smooth Shells and its shell schedule.

Published constants and defaults: docs/smooth_shells.md §5 (the released MATLAB code, standardparams and the
example scripts).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shapecorr.errors import ConfigError
from shapecorr.geometry.shells import sigmoid_shell_weights
from shapecorr.matching.least_squares import DEFAULT_RIDGE


#: First shell size of the main run, last size of the surrogate runs, and the offset of the ARAP weight.
K_START = 20
#: Normals enter the embedding only for shells larger than this (matchlayer: ``normalDamping * (k > 10)``).
NORMAL_K_MIN = 10
#: Surrogate runs of the rigid stage: shell sizes 2..20.
RIGID_K_MIN = 2
#: Random search: shell sizes 6..20, perturbation of the 6 lowest spectral coordinates.
MCMC_K_MIN = 6


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
