"""Divergence-free shape correspondence by deformation (Eisenberger, Lähner, Cremers, SGP 2019; docs/divfree.md).

x is flowed onto y along a stationary, divergence-free velocity field on the unit box
(:mod:`shapecorr.geometry.divergence_free`); the correspondence is read off the deformed x. The field
coefficients are optimized coarse to fine (more modes and more samples per level), alternating

1. **correspondences**: nearest neighbours in the product space ``[coordinates, w_n normals, w_d descriptor]``
   between the deformed samples of x and y, in both directions (samples of x -> all vertices of y, samples of
   y -> the deformed samples of x, so that only the samples are flowed with gradients), every ``corr_every``
   iterations;
2. **field updates**: Adam steps (torch autograd through the flow) on

   ``E = E_align + lambda_reg E_reg``, with
   ``E_align = 1/2 sum_dir (1 / (3 m)) sum_i w_i |X_T(x_i) - y_i|^2`` over the m pairs of each direction and
   the Huber weights ``w_i = min(1, delta / |r_i|)`` of the current residuals (iteratively reweighted least
   squares: its gradient is that of the Huber loss; with every residual below ``delta`` it is the original
   code's mean squared error), and
   ``E_reg = sum_t ARAP(x_0 -> x_t) / (m_s N 25 / k)`` over the N flow steps of the m_s samples on their
   k-nearest-neighbour graph (the original code's normalization, the project's ARAP energy with exact
   rotations, :func:`shapecorr.losses.arap.arap_energy`, ``mode="average"``).

The outputs are at full resolution: the flow is replayed on every vertex of x (in chunks), the maps are the
product-space nearest neighbours between the deformed x and y (x -> y and y -> x), and the deformation frames
are the flow at the requested times, mapped back to x's normalized units (docs/divfree.md §5).

The matcher follows the protocol of :mod:`shapecorr.matching.result` (``match`` and ``interpolate``), so
``evaluate.py model=divfree`` writes maps, metrics and ``interp/`` frames. It needs no training.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from shapecorr.errors import ConfigError, NumericalError
from shapecorr.geometry import divergence_free as df
from shapecorr.geometry.normals import vertex_normals
from shapecorr.geometry.sampling import farthest_point_sampling
from shapecorr.losses.arap import arap_covariances, arap_energy, polar_rotations, rotations_from_covariances
from shapecorr.matching.least_squares import normal_equations, solve_normal_equations
from shapecorr.matching.nearest_neighbors import bidirectional_nearest_neighbors
from shapecorr.matching.result import MatchResult

#: Default frames of :meth:`DivFreeMatcher.match` (as LinearBlend / NeuroMorph: 0, 1/4, ..., 1).
DIVFREE_TIMES = (0.0, 0.25, 0.5, 0.75, 1.0)
#: Neighbours of the ARAP graph on the samples (original code ``DivFreeParam.num_knn = 5``).
PUBLISHED_KNN = 5
#: Weight of the regularizer (original code ``DivFreeParam.lambda_reg = 20``).
PUBLISHED_LAMBDA_REG = 20.0
#: The original code divides the ARAP sum by ``n * n_steps * 25 / k`` (docs/divfree.md §4).
ARAP_NORMALIZATION = 25.0
#: Descriptor the product space uses by default (computed by the data pipeline; docs/divfree.md §4, §8).
DEFAULT_DESCRIPTOR = "wks"
#: Descriptor the Smooth Shells pre-alignment needs (its basis features, docs/smooth_shells.md).
DESCRIPTOR = "shot"
#: Descriptors the product space can use (operators of the data pipeline; docs/divfree.md §4).
DESCRIPTORS = ("shot", "wks", "hks")


@dataclass(frozen=True)
class Level:
    """One level of the coarse-to-fine schedule: modes per axis, samples per shape, Adam iterations."""

    n_modes: int
    n_samples: int
    iterations: int
    lr: float
    normal_weight: float
    descriptor_weight: float


def _as_list(value, n: int, name: str) -> list:
    values = list(value) if isinstance(value, (list, tuple)) else [value] * n
    if len(values) != n:
        raise ConfigError(f"divfree: {name} must have one entry per level ({n}), got {values}")
    return values


def knn_graph_edges(points: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Undirected edges of the k-nearest-neighbour graph and their multiplicity in the directed kNN list.

    Parameters
    ----------
    points : (n, 3) float
    k : int
        Neighbours per point (itself excluded), ``1 <= k < n``.

    Returns
    -------
    edges : (E, 2) int64
        Unique pairs ``(a, b)`` with ``a < b``, on the device of ``points``.
    counts : (E,) float
        1 or 2: how often the pair is listed among the directed ``i -> neighbour`` edges (the original code sums
        over that list, so these weights reproduce its sums).
    """
    n = points.shape[0]
    if not 1 <= k < n:
        raise ConfigError(f"the kNN graph needs 1 <= k < n = {n}, got k = {k}")
    p = points.detach().cpu().double().numpy()
    _, nn = cKDTree(p).query(p, k=k + 1)  # scipy: exact kd-tree search; column 0 is the point itself
    rows = np.repeat(np.arange(n), k)
    cols = np.asarray(nn[:, 1:]).reshape(-1)
    pairs = np.sort(np.stack([rows, cols], axis=1), axis=1)
    uniq, counts = np.unique(pairs, axis=0, return_counts=True)
    return (torch.from_numpy(uniq.astype(np.int64)).to(points.device),
            torch.from_numpy(counts.astype(np.float32)).to(points.device))


#: Pre-alignment modes (docs/divfree.md §1): none; the published PCA pre-alignment (4 orientations of x's principal
#: frame onto y's); the same with the 4 quarter turns about the first principal axis for each of the two senses of
#: that axis (8 orientations: also covers shapes whose second and third principal axes are swapped); the rigid stage
#: of Smooth Shells (spectral axis, axis ICP, candidate turns scored by short non-rigid runs; docs/smooth_shells.md).
PREALIGN_MODES = ("none", "pca", "pca_turns", "smooth_shells")


def principal_frame(points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Vertex mean and principal axes of a point set.

    Parameters
    ----------
    points : (n, 3) float

    Returns
    -------
    mean : (3,) float64
    axes : (3, 3) float64
        Columns: the principal axes by decreasing variance, a right-handed frame (determinant +1).
    """
    p = points.detach().to(torch.float64)
    mean = p.mean(0)
    centred = p - mean
    _, vecs = torch.linalg.eigh(centred.T @ centred / max(p.shape[0], 1))  # ascending eigenvalues
    axes = vecs.flip(1)
    if float(torch.linalg.det(axes)) < 0:
        axes[:, 2] = -axes[:, 2]
    return mean, axes


def orientation_candidates(points_x: torch.Tensor, points_y: torch.Tensor, mode: str = "pca") -> torch.Tensor:
    """Rotations that turn x's principal frame onto y's, one per candidate orientation.

    ``pca``: the 4 proper rotations ``A_y S A_x^T`` with ``S = diag(+-1, +-1, +-1)``, ``det S = 1`` (the sign of
    each principal axis is arbitrary). ``pca_turns``: ``A_y T A_x^T`` for the 8 proper ``T`` that keep the first
    axis up to its sign: the 4 quarter turns about it, for either sense (contains the 4 of ``pca``).

    Parameters
    ----------
    points_x : (n, 3) float
    points_y : (m, 3) float
    mode : {"pca", "pca_turns"}

    Returns
    -------
    (C, 3, 3) float64
        Rotations ``R`` (``det R = 1``) to apply to x's points centred on their mean.
    """
    if mode not in PREALIGN_MODES[1:]:
        raise ConfigError(f"divfree: orientation candidates need mode in {PREALIGN_MODES[1:]}, got {mode!r}")
    _, ax = principal_frame(points_x)
    _, ay = principal_frame(points_y)
    if mode == "pca":
        signs = [(1.0, 1.0, 1.0), (1.0, -1.0, -1.0), (-1.0, 1.0, -1.0), (-1.0, -1.0, 1.0)]
        mids = [torch.diag(torch.tensor(s, dtype=torch.float64)) for s in signs]
    else:
        mids = []
        for first in (1.0, -1.0):
            flip = torch.diag(torch.tensor([first, first, 1.0], dtype=torch.float64))  # det +1
            for c, s in ((1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0)):  # quarter turns about the first axis
                turn = torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], dtype=torch.float64)
                mids.append(flip @ turn)
    return torch.stack([ay @ m @ ax.T for m in mids])


def fractional_rotation(rotation: torch.Tensor, fraction: float) -> torch.Tensor:
    """``R^s``: the rotation about the same axis by ``s`` times the angle of ``rotation (3, 3)`` (float64)."""
    vec = Rotation.from_matrix(rotation.detach().cpu().double().numpy()).as_rotvec()
    return torch.from_numpy(Rotation.from_rotvec(fraction * vec).as_matrix()).to(rotation)


def rigid_icp(points_x: torch.Tensor, normals_x: torch.Tensor, points_y: torch.Tensor, normals_y: torch.Tensor,
              iterations: int = 30, normal_weight: float = 0.0, features_x: torch.Tensor | None = None,
              features_y: torch.Tensor | None = None, backend: str = "auto",
              workers: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """Rigid ICP of x onto y with pairs in both directions, in the product space ``[xyz, w_n normals, features]``.

    Each iteration pairs every point of x with its nearest point of y and every point of y with its nearest point
    of x (:func:`shapecorr.matching.nearest_neighbors.bidirectional_nearest_neighbors`), then fits the rotation and
    translation of all pairs by least squares (Procrustes, :func:`shapecorr.losses.arap.rotations_from_covariances`).

    Parameters
    ----------
    points_x, normals_x : (n, 3) float
    points_y, normals_y : (m, 3) float
    iterations : int
    normal_weight : float
        Weight of the normals against the coordinates (in the units of the points).
    features_x, features_y : (n, c), (m, c) float, optional
        Rotation-invariant descriptors, already weighted (e.g. SHOT): they pair points by what they look like,
        so that ICP is drawn to the intrinsically right pose.
    backend, workers
        Nearest-neighbour search options.

    Returns
    -------
    rotation : (3, 3) float64
    translation : (3,) float64
        ``rotation @ p + translation`` moves x onto y.
    """
    px, nx = points_x.detach().to(torch.float64), normals_x.detach().to(torch.float64)
    py, ny = points_y.detach().to(torch.float64), normals_y.detach().to(torch.float64)
    rot = torch.eye(3, dtype=torch.float64, device=px.device)
    trans = py.mean(0) - px.mean(0)
    extra_x = [] if features_x is None else [features_x.detach().to(torch.float64)]
    extra_y = [] if features_y is None else [features_y.detach().to(torch.float64)]
    emb_y = torch.cat([py, normal_weight * ny, *extra_y], dim=1).to(torch.float32)
    for _ in range(iterations):
        moved, turned = px @ rot.T + trans, nx @ rot.T
        emb_x = torch.cat([moved, normal_weight * turned, *extra_x], dim=1).to(torch.float32)
        nn_y, nn_x = bidirectional_nearest_neighbors(emb_x, emb_y, backend=backend, workers=workers)
        src = torch.cat([px, px[nn_x]])
        dst = torch.cat([py[nn_y], py])
        cs, cd = src.mean(0), dst.mean(0)
        new_rot = rotations_from_covariances((dst - cd).T @ (src - cs))
        new_trans = cd - new_rot @ cs
        done = bool(torch.allclose(new_rot, rot, atol=1e-10) and torch.allclose(new_trans, trans, atol=1e-10))
        rot, trans = new_rot, new_trans
        if done:
            break
    return rot, trans


#: Final-map extraction modes (docs/divfree.md §5): the product-space nearest neighbours of the deformed x
#: (``flow``), or the same product space with the aligned spectral embedding of a functional map fitted to the
#: flow's cycle-consistent pairs (``spectral``).
EXTRACTION_MODES = ("flow", "spectral")
#: Fits of the spectral extraction's functional map: ``orthogonal`` (Procrustes) or ``least_squares``.
EXTRACTION_FITS = ("orthogonal", "least_squares")


def cycle_consistent(points_x: torch.Tensor, points_y: torch.Tensor, p2p: torch.Tensor, p2p_inv: torch.Tensor,
                     tolerance: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Vertices whose round trip through the two maps returns within ``tolerance`` of where it started.

    Parameters
    ----------
    points_x : (n, 3) float
        x at rest (the round trip is measured on the undeformed shape).
    points_y : (m, 3) float
    p2p : (n,) int64
        Map x -> y.
    p2p_inv : (m,) int64
        Map y -> x.
    tolerance : float
        Largest Euclidean distance (units of the points) between a vertex and its round-trip image.

    Returns
    -------
    consistent_x : (n,) bool
        ``|x_i - x_{p2p_inv[p2p[i]]}| < tolerance``.
    consistent_y : (m,) bool
        ``|y_j - y_{p2p[p2p_inv[j]]}| < tolerance``.
    """
    back_x = (points_x - points_x[p2p_inv[p2p]]).norm(dim=1)
    back_y = (points_y - points_y[p2p[p2p_inv]]).norm(dim=1)
    return back_x < tolerance, back_y < tolerance


def functional_map_from_maps(evecs_x: torch.Tensor, evecs_y: torch.Tensor, mass_x: torch.Tensor,
                             mass_y: torch.Tensor, p2p: torch.Tensor, p2p_inv: torch.Tensor,
                             keep_x: torch.Tensor | None = None, keep_y: torch.Tensor | None = None,
                             orthogonal: bool = False) -> torch.Tensor:
    """Functional map ``C`` (y's coefficients -> x's) fitted to both point maps.

    Fits ``sum_i a_i |phi_x(i) C - phi_y(p2p[i])|^2 + sum_j b_j |phi_x(p2p_inv[j]) C - phi_y(j)|^2`` with the
    vertex areas ``a = mass_x``, ``b = mass_y`` restricted to the kept vertices: ``phi_x C`` is then y's spectral
    embedding pulled onto x, aligned with ``phi_y``. ``orthogonal=False``: the weighted least-squares ``C``.
    ``orthogonal=True``: ``C = U V^T`` from the SVD ``U S V^T`` of the weighted cross-covariance
    ``sum a_i phi_x(i)^T phi_y(p2p[i]) + sum b_j phi_x(p2p_inv[j])^T phi_y(j)``, the orthogonal map that best
    aligns the pairs (orthogonal Procrustes). Between near-isometric shapes with mass-orthonormal bases the
    functional map is close to orthogonal; the constraint keeps ``C`` determined on a body part whose pairs are
    left out (the unconstrained fit extrapolates freely there).

    Parameters
    ----------
    evecs_x : (n, k) float
    evecs_y : (m, k) float
        Mass-orthonormal eigenfunctions (the same ``k`` on both shapes).
    mass_x : (n,) float
    mass_y : (m,) float
    p2p : (n,) int64
        Map x -> y.
    p2p_inv : (m,) int64
        Map y -> x.
    keep_x : (n,) bool, optional
    keep_y : (m,) bool, optional
        Vertices whose pairs enter the fit (default all).
    orthogonal : bool
        Fit an orthogonal ``C`` (Procrustes) instead of the least-squares one.

    Returns
    -------
    (k, k) float64
    """
    wx = mass_x.to(torch.float64) * (1.0 if keep_x is None else keep_x.to(torch.float64))
    wy = mass_y.to(torch.float64) * (1.0 if keep_y is None else keep_y.to(torch.float64))
    design = torch.cat([evecs_x, evecs_x[p2p_inv]])
    target = torch.cat([evecs_y[p2p], evecs_y])
    gram, rhs = normal_equations(design, target, torch.cat([wx, wy]))
    if orthogonal:
        if not bool(torch.isfinite(rhs).all()):
            raise NumericalError("divfree spectral extraction (orthogonal functional map): non-finite inputs")
        u, _, vh = torch.linalg.svd(rhs)
        return u @ vh
    return solve_normal_equations(gram, rhs, what="divfree spectral extraction (functional map)")


def functional_map_residuals(evecs_x: torch.Tensor, evecs_y: torch.Tensor, fmap: torch.Tensor, p2p: torch.Tensor,
                             p2p_inv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """How far each pair of the two point maps lies from the functional map, in the aligned spectral embedding.

    Parameters
    ----------
    evecs_x : (n, k) float
    evecs_y : (m, k) float
    fmap : (k, k) float
        ``C`` of :func:`functional_map_from_maps`.
    p2p : (n,) int64
    p2p_inv : (m,) int64

    Returns
    -------
    residual_x : (n,) float64
        ``|phi_x(i) C - phi_y(p2p[i])|``.
    residual_y : (m,) float64
        ``|phi_x(p2p_inv[j]) C - phi_y(j)|``.
    """
    phi_x, phi_y, fmap = evecs_x.to(torch.float64), evecs_y.to(torch.float64), fmap.to(torch.float64)
    aligned = phi_x @ fmap
    return (aligned - phi_y[p2p]).norm(dim=1), (aligned[p2p_inv] - phi_y).norm(dim=1)


def trimmed_functional_map(evecs_x: torch.Tensor, evecs_y: torch.Tensor, mass_x: torch.Tensor,
                           mass_y: torch.Tensor, p2p: torch.Tensor, p2p_inv: torch.Tensor, keep_x: torch.Tensor,
                           keep_y: torch.Tensor, trim: float, steps: int, orthogonal: bool = True
                           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`functional_map_from_maps` with the pairs far from the fitted map left out, refitted (trimmed fit).

    A low-frequency functional map cannot follow one limb laid onto the other side while the rest of the body is
    right, so that limb's pairs keep large residuals (:func:`functional_map_residuals`) and drop out. Each of
    at most ``steps`` times: the residuals of all of ``keep_x``, ``keep_y`` under the current ``C``, their median
    ``s`` (over the vertices of both sides, unweighted), and the refit on those whose residual is below
    ``trim * s`` (``trim = 1``: the better half, a least-trimmed-squares fit). It stops early when the selection
    repeats; a step that would leave fewer than ``k`` vertices on a side keeps the previous fit.

    Parameters
    ----------
    evecs_x, evecs_y, mass_x, mass_y, p2p, p2p_inv
        As :func:`functional_map_from_maps`.
    keep_x : (n,) bool
    keep_y : (m,) bool
        Vertices that may enter the fit (e.g. :func:`cycle_consistent`).
    trim : float
        Residual threshold in multiples of the median residual (> 0).
    steps : int
        Refits (0: the plain fit on ``keep_x``, ``keep_y``).
    orthogonal : bool
        See :func:`functional_map_from_maps`.

    Returns
    -------
    fmap : (k, k) float64
    inliers_x : (n,) bool
    inliers_y : (m,) bool
        The vertices of the last fit.
    """
    k = evecs_x.shape[1]
    fmap = functional_map_from_maps(evecs_x, evecs_y, mass_x, mass_y, p2p, p2p_inv, keep_x, keep_y, orthogonal)
    in_x, in_y = keep_x, keep_y
    for _ in range(int(steps)):
        res_x, res_y = functional_map_residuals(evecs_x, evecs_y, fmap, p2p, p2p_inv)
        scale = torch.cat([res_x[keep_x], res_y[keep_y]]).median()
        new_x, new_y = keep_x & (res_x < trim * scale), keep_y & (res_y < trim * scale)
        if int(new_x.sum()) < k or int(new_y.sum()) < k or (torch.equal(new_x, in_x) and torch.equal(new_y, in_y)):
            break
        in_x, in_y = new_x, new_y
        fmap = functional_map_from_maps(evecs_x, evecs_y, mass_x, mass_y, p2p, p2p_inv, in_x, in_y, orthogonal)
    return fmap, in_x, in_y


class DivFreeMatcher:
    """Divergence-free deformation matcher (module docstring; parameters in configs/model/divfree.yaml).

    Parameters
    ----------
    modes : sequence of int
        Modes per axis K of each level (coarse to fine; the published K = 8 last).
    samples : sequence of int
        Farthest-point samples of each shape per level (clipped to the vertex count).
    iterations : sequence of int
        Adam iterations per level.
    normal_weight, descriptor_weight : float or sequence of float
        Weights of the normals and of the (unit-row) descriptor block in the product space, per level.
    n_steps : int
        Time steps of the flow.
    rule : {"midpoint", "original"}
        Step rule (:mod:`shapecorr.geometry.divergence_free`).
    lr : float or sequence of float
        Adam step size on the field coefficients, per level.
    lambda_reg : float
        Weight of the ARAP regularizer.
    knn : int
        Neighbours of the ARAP graph.
    huber_delta : float
        Residual (box units) above which correspondences are down-weighted.
    corr_every : int
        Iterations between correspondence updates.
    margin : float
        Box margin of the pair normalization.
    convention : {"published", "original_code"}
        Basis convention.
    interp_times : sequence of float
        Frames of :meth:`match` (the project's one name for frame times, as ``evaluate.py interp_times``).
    chunk_size : int
        Vertices per chunk when the flow is replayed at full resolution.
    seed : int
        Seed of the farthest-point starts (the method is otherwise deterministic).
    nn_backend : {"auto", "kdtree", "brute"}
        Nearest-neighbour search (:func:`shapecorr.matching.nearest_neighbors.bidirectional_nearest_neighbors`).
    nn_workers : int
        Threads of the kd-tree search (1: single-threaded).
    prealign : {"none", "pca", "pca_turns", "smooth_shells"}
        Rigid pre-alignment of x about its vertex mean (docs/divfree.md §1): ``pca`` / ``pca_turns``: the
        candidates of :func:`orientation_candidates`, refined by :func:`rigid_icp` and scored by :meth:`_score`;
        ``smooth_shells``: the rigid stage of Smooth Shells (needs the eigenbasis); ``none``: x as given.
    prealign_icp_iterations : int
        ICP iterations per candidate of the ``pca`` modes.
    prealign_keep_input : bool
        ``smooth_shells`` mode: x's input orientation is one more candidate of the rigid stage's scores.
    prealign_score_descriptors : float
        ``smooth_shells`` mode: weight of the intrinsic basis features in the candidates' scores (Smooth Shells'
        ``score_descriptors``; 0: its original geometric score).
    descriptor : str or sequence of str
        Descriptor(s) of the product space, of :data:`DESCRIPTORS`: ``"wks"`` (the default, the intrinsic wave
        kernel signature), ``"shot"`` (the earlier default), ``"hks"``; several are concatenated, each with unit
        rows (docs/divfree.md §4).
    """

    needs_ground_truth = False

    def __init__(
        self,
        modes=(2, 4, 8),
        samples=(500, 1000, 2000),
        iterations=(50, 50, 100),
        normal_weight=0.1,
        descriptor_weight=(2.0, 1.0, 0.5),
        n_steps: int = df.PUBLISHED_N_STEPS,
        rule: str = "midpoint",
        lr=(0.01, 0.005, 0.002),
        lambda_reg: float = PUBLISHED_LAMBDA_REG,
        knn: int = PUBLISHED_KNN,
        huber_delta: float = 0.05,
        corr_every: int = 10,
        margin: float = df.BOX_MARGIN,
        convention: str = "published",
        interp_times=DIVFREE_TIMES,
        chunk_size: int = df.DEFAULT_CHUNK_SIZE,
        seed: int = 0,
        nn_backend: str = "auto",
        nn_workers: int = 1,
        prealign: str = "smooth_shells",
        prealign_icp_iterations: int = 30,
        prealign_keep_input: bool = True,
        prealign_score_descriptors: float = 0.3,
        descriptor=DEFAULT_DESCRIPTOR,
        extraction: str = "spectral",
        extraction_k: int = 10,
        extraction_weight: float = 0.1,
        extraction_consistency: float = 0.03,
        extraction_iterations: int = 2,
        extraction_fit: str = "orthogonal",
        extraction_trim: float = 1.0,
        extraction_trim_steps: int = 10,
    ):
        modes = [int(m) for m in (modes if isinstance(modes, (list, tuple)) else [modes])]
        n = len(modes)
        samples = [int(s) for s in _as_list(samples, n, "samples")]
        iterations = [int(i) for i in _as_list(iterations, n, "iterations")]
        lrs = [float(v) for v in _as_list(lr, n, "lr")]
        normal_w = [float(w) for w in _as_list(normal_weight, n, "normal_weight")]
        desc_w = [float(w) for w in _as_list(descriptor_weight, n, "descriptor_weight")]
        if not modes or min(modes) < 1:
            raise ConfigError(f"divfree: modes must be a non-empty list of positive integers, got {modes}")
        if min(samples) < 2 or min(iterations) < 0:
            raise ConfigError(f"divfree: samples must be >= 2 and iterations >= 0, got {samples}, {iterations}")
        if min(normal_w + desc_w) < 0:
            raise ConfigError("divfree: product-space weights must be non-negative")
        if rule not in df.FLOW_RULES:
            raise ConfigError(f"divfree: rule must be one of {df.FLOW_RULES}, got {rule!r}")
        if prealign not in PREALIGN_MODES:
            raise ConfigError(f"divfree: prealign must be one of {PREALIGN_MODES}, got {prealign!r}")
        if convention not in df.CONVENTIONS:
            raise ConfigError(f"divfree: convention must be one of {df.CONVENTIONS}, got {convention!r}")
        for name, value in (("n_steps", n_steps), ("knn", knn), ("corr_every", corr_every), ("chunk_size", chunk_size)):
            if int(value) < 1:
                raise ConfigError(f"divfree: {name} must be >= 1, got {value}")
        if not (min(lrs) > 0 and huber_delta > 0 and lambda_reg >= 0):
            raise ConfigError("divfree: lr and huber_delta must be positive and lambda_reg non-negative")
        self.levels = tuple(Level(*row) for row in zip(modes, samples, iterations, lrs, normal_w, desc_w))
        self.n_steps = int(n_steps)
        self.rule = rule
        self.lambda_reg = float(lambda_reg)
        self.knn = int(knn)
        self.huber_delta = float(huber_delta)
        self.corr_every = int(corr_every)
        self.margin = float(margin)
        self.convention = convention
        self.interp_times = tuple(float(t) for t in interp_times)
        self.chunk_size = int(chunk_size)
        self.seed = int(seed)
        self.nn_backend = nn_backend
        self.nn_workers = int(nn_workers)
        self.prealign = prealign
        self.prealign_icp_iterations = int(prealign_icp_iterations)
        self.prealign_keep_input = bool(prealign_keep_input)
        self.prealign_score_descriptors = float(prealign_score_descriptors)
        names = [descriptor] if isinstance(descriptor, str) else [str(d) for d in descriptor]
        if not names or any(d not in DESCRIPTORS for d in names) or len(set(names)) != len(names):
            raise ConfigError(f"divfree: descriptor must be one or more distinct names of {DESCRIPTORS}, "
                              f"got {descriptor}")
        self.descriptors = tuple(names)
        if extraction not in EXTRACTION_MODES:
            raise ConfigError(f"divfree: extraction must be one of {EXTRACTION_MODES}, got {extraction!r}")
        if int(extraction_k) < 1 or int(extraction_iterations) < 1 or extraction_weight < 0 \
                or extraction_consistency <= 0:
            raise ConfigError("divfree: extraction_k and extraction_iterations must be >= 1, extraction_weight >= 0 "
                              "and extraction_consistency > 0")
        self.extraction = extraction
        self.extraction_k = int(extraction_k)
        self.extraction_weight = float(extraction_weight)
        self.extraction_consistency = float(extraction_consistency)
        self.extraction_iterations = int(extraction_iterations)
        if extraction_fit not in EXTRACTION_FITS:
            raise ConfigError(f"divfree: extraction_fit must be one of {EXTRACTION_FITS}, got {extraction_fit!r}")
        if not extraction_trim >= 0 or int(extraction_trim_steps) < 0:
            raise ConfigError("divfree: extraction_trim must be >= 0 (0: no trimming) and extraction_trim_steps >= 0")
        self.extraction_fit = extraction_fit
        self.extraction_trim = float(extraction_trim)
        self.extraction_trim_steps = int(extraction_trim_steps) if extraction_trim > 0 else 0
        uses_descriptor = any(level.descriptor_weight > 0 for level in self.levels)
        self.required_operators = {d: {} for d in self.descriptors} if uses_descriptor else {}
        if prealign == "smooth_shells":  # the rigid stage's basis features need SHOT
            self.required_operators[DESCRIPTOR] = {}
        if prealign == "smooth_shells":  # the eigenbasis of Smooth Shells' published preset (shared cache entries)
            from shapecorr.axiomatic.smooth_shells import SmoothShellsConfig

            self.required_operators["eigenbasis"] = {"k": SmoothShellsConfig().num_eigs}
        if extraction == "spectral":
            have = self.required_operators.get("eigenbasis", {}).get("k", 0)
            self.required_operators["eigenbasis"] = {"k": max(have, self.extraction_k)}

    # ------------------------------------------------------------------------------------------------------
    # pieces
    # ------------------------------------------------------------------------------------------------------
    def _descriptor(self, sample) -> torch.Tensor | None:
        """The product space's descriptor block of ``sample`` (n, c), or None when no level weights it.

        Each descriptor of ``self.descriptors`` with unit rows, divided by the square root of their count (so the
        block has unit rows).
        """
        if not any(level.descriptor_weight > 0 for level in self.levels):
            return None
        blocks = []
        for name in self.descriptors:
            feats = sample.features.get(name)
            if feats is None:
                raise ConfigError(
                    f"shape {sample.name!r} has no {name!r} descriptor: add it to data.operators.request "
                    f"(e.g. +data.operators.request={{{name}:{{}}}}), or set model.descriptor_weight=0"
                )
            if feats.ndim != 2 or feats.shape[0] != sample.shape.n_verts:
                raise ConfigError(f"{name} of {sample.name!r} has shape {tuple(feats.shape)}, expected (n, c)")
            if not bool(torch.isfinite(feats).all()):
                raise NumericalError(f"the {name} descriptor of {sample.name!r} contains NaN or infinite values")
            feats = feats.to(torch.float32)
            # Unit rows: the weight then sets the descriptor's share of the product-space distance.
            blocks.append(feats / feats.norm(dim=1, keepdim=True).clamp_min(torch.finfo(feats.dtype).tiny))
        return torch.cat(blocks, dim=1) / float(np.sqrt(len(blocks)))

    def _flow(self, points: torch.Tensor, coeffs: torch.Tensor, return_path: bool = False) -> torch.Tensor:
        return df.integrate_flow(points, coeffs, self.n_steps, self.rule, return_path=return_path,
                                 convention=self.convention, chunk_size=self.chunk_size)

    def _embed(self, points, normals, desc, level: Level) -> torch.Tensor:
        parts = [points, level.normal_weight * normals]
        if desc is not None and level.descriptor_weight > 0:
            parts.append(level.descriptor_weight * desc)
        return torch.cat(parts, dim=1)

    def _nn(self, a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return bidirectional_nearest_neighbors(a, b, backend=self.nn_backend, workers=self.nn_workers)

    def _huber_mse(self, residual: torch.Tensor) -> torch.Tensor:
        norm = residual.detach().norm(dim=1)
        weight = torch.where(norm > self.huber_delta, self.huber_delta / norm.clamp_min(1e-30), torch.ones_like(norm))
        return (weight * residual.square().sum(1)).sum() / (3 * residual.shape[0])

    # ------------------------------------------------------------------------------------------------------
    # optimization
    # ------------------------------------------------------------------------------------------------------
    def _pair_state(self, vx: torch.Tensor, vy: torch.Tensor, fy: torch.Tensor) -> dict:
        """Box transforms, box coordinates, y's normals and the FPS orders of one placement of x."""
        box_x, box_y = df.box_normalization(vx, vy, self.margin)
        bx, by = box_x.to_box(vx), box_y.to_box(vy)
        n_max = max(level.n_samples for level in self.levels)
        rng = np.random.default_rng(self.seed)
        # FPS orderings: every prefix is itself a farthest-point sample, so each level takes a prefix.
        order_x = torch.from_numpy(farthest_point_sampling(bx.cpu(), min(n_max, bx.shape[0]),
                                                           start=int(rng.integers(bx.shape[0])))).to(vx.device)
        order_y = torch.from_numpy(farthest_point_sampling(by.cpu(), min(n_max, by.shape[0]),
                                                           start=int(rng.integers(by.shape[0])))).to(vx.device)
        return {"box_x": box_x, "box_y": box_y, "bx": bx, "by": by, "ny": vertex_normals(by, fy),
                "order_x": order_x, "order_y": order_y}

    def _correspondences(self, st: dict, level: Level, coeffs: torch.Tensor, fx, dx, dy) -> tuple:
        """Product-space pairs of the current field: samples of x -> vertices of y, samples of y -> samples of x."""
        sx, sy = st["order_x"][:level.n_samples], st["order_y"][:level.n_samples]
        with torch.no_grad():
            emb_y_all = self._embed(st["by"], st["ny"], dy, level)
            moved = self._flow(st["bx"], coeffs.detach())
            emb_x_all = self._embed(moved, vertex_normals(moved, fx), dx, level)
            match_xy, _ = self._nn(emb_x_all[sx], emb_y_all)
            match_yx, _ = self._nn(emb_y_all[sy], emb_x_all[sx])
        return match_xy, match_yx

    def _energy(self, st: dict, level: Level, coeffs: torch.Tensor, pairs: tuple, graph: tuple):
        """``(E_align, E_reg)`` of ``coeffs`` for fixed pairs (differentiable in ``coeffs``)."""
        match_xy, match_yx = pairs
        xs = st["bx"][st["order_x"][:level.n_samples]]
        by, sy = st["by"], st["order_y"][:level.n_samples]
        path = self._flow(xs, coeffs, return_path=True)  # (N + 1, m, 3)
        end = path[-1]
        e_align = 0.5 * (self._huber_mse(end - by[match_xy]) + self._huber_mse(end[match_yx] - by[sy]))
        rest = path[:1].expand_as(path[1:])
        # the rotations of arap_energy (fitted, detached), by the batched Newton polar iteration
        rotations = polar_rotations(arap_covariances(rest, path[1:], *graph))
        e_reg = arap_energy(rest, path[1:], *graph, rotations=rotations, mode="average").sum()
        return e_align, e_reg / (xs.shape[0] * self.n_steps * ARAP_NORMALIZATION / self.knn)

    def _run_level(self, st: dict, i_level: int, coeffs: torch.Tensor, fx, dx, dy, names: str) -> tuple:
        """Adam on one level from ``coeffs`` (resized to the level's modes).

        Returns the coefficients, the last energies and the energy history ``(level, iteration, align, reg)`` at
        every correspondence update.
        """
        level = self.levels[i_level]
        coeffs = df.resize_coefficients(coeffs.detach(), level.n_modes).requires_grad_(True)
        xs = st["bx"][st["order_x"][:level.n_samples]]
        graph = knn_graph_edges(xs, min(self.knn, xs.shape[0] - 1))
        optimizer = torch.optim.Adam([coeffs], lr=level.lr)
        energies, history, pairs = {}, [], None
        for it in range(level.iterations):
            if it % self.corr_every == 0:
                pairs = self._correspondences(st, level, coeffs, fx, dx, dy)
            optimizer.zero_grad(set_to_none=True)
            e_align, e_reg = self._energy(st, level, coeffs, pairs, graph)
            loss = e_align + self.lambda_reg * e_reg
            if not bool(torch.isfinite(loss.detach())):
                raise NumericalError(f"divfree: the energy became non-finite on pair ({names}); lower model.lr")
            loss.backward()
            optimizer.step()
            energies = {"align": float(e_align.detach()), "reg": float(e_reg.detach())}
            if it % self.corr_every == 0:
                history.append((i_level, it, energies["align"], energies["reg"]))
        return coeffs.detach(), energies, history

    def _score(self, st: dict, fx, dx, dy) -> float:
        """Misalignment of a placement at rest (lower is better).

        Every sample of either shape is paired with its nearest sample of the other in ``[xyz, w_n normals]``;
        the score is the mean product-space distance ``|[xyz, w_n normals, w_d descriptor]|`` of these pairs (the
        first level's weights). The descriptor term makes it intrinsic where the coordinates are not: a body turned
        front to back overlaps itself in space, but its spatial pairs then disagree in the descriptor.
        """
        level = self.levels[0]
        sx, sy = st["order_x"][:level.n_samples], st["order_y"][:level.n_samples]
        geo_level = Level(level.n_modes, level.n_samples, level.iterations, level.lr, level.normal_weight, 0.0)
        geo_x = self._embed(st["bx"], vertex_normals(st["bx"], fx), None, geo_level)[sx]
        geo_y = self._embed(st["by"], st["ny"], None, geo_level)[sy]
        nn_y, nn_x = bidirectional_nearest_neighbors(geo_x, geo_y, backend="brute")
        full_x = geo_x if dx is None else torch.cat([geo_x, level.descriptor_weight * dx[sx]], dim=1)
        full_y = geo_y if dy is None else torch.cat([geo_y, level.descriptor_weight * dy[sy]], dim=1)
        return 0.5 * float((full_x - full_y[nn_y]).norm(dim=1).mean() + (full_y - full_x[nn_x]).norm(dim=1).mean())

    def _prealign(self, x, y, vx, vy, fx, fy, dx, dy) -> tuple[torch.Tensor, list[float]]:
        """The pre-alignment rotation of x (about its vertex mean) and the scores of all candidates."""
        eye = torch.eye(3, dtype=torch.float64, device=vx.device)
        if self.prealign == "none":
            return eye, []
        if self.prealign == "smooth_shells":
            from shapecorr.axiomatic import smooth_shells as ss

            shell_x, shell_y = ss.shape_from_sample(x), ss.shape_from_sample(y)
            config = ss.SmoothShellsConfig(seed=self.seed, rigid_keep_input=self.prealign_keep_input,
                                           score_descriptors=self.prealign_score_descriptors)
            rot, _, scores = ss.rigid_alignment(shell_x, shell_y, config, ss.basis_features(shell_x, shell_y))
            return rot.to(device=vx.device, dtype=torch.float64), [float(v) for c in scores for v in c]
        level = self.levels[0]
        mean_x = vx.to(torch.float64).mean(0)
        box_x, _ = df.box_normalization(vx, vy, self.margin)
        rng = np.random.default_rng(self.seed)
        sx = torch.from_numpy(farthest_point_sampling(vx.cpu(), min(level.n_samples, vx.shape[0]),
                                                      start=int(rng.integers(vx.shape[0])))).to(vx.device)
        sy = torch.from_numpy(farthest_point_sampling(vy.cpu(), min(level.n_samples, vy.shape[0]),
                                                      start=int(rng.integers(vy.shape[0])))).to(vx.device)
        nx, ny = vertex_normals(vx, fx), vertex_normals(vy, fy)
        # the first level's product space in input units: descriptors scaled from box units
        feat_x = None if dx is None else dx[sx] * (level.descriptor_weight / box_x.scale)
        feat_y = None if dy is None else dy[sy] * (level.descriptor_weight / box_x.scale)
        rotations, scores = [], []
        for cand in orientation_candidates(vx, vy, self.prealign).to(vx.device):
            # the candidate's orientation, refined by rigid ICP in the first level's product space
            placed = (vx.to(torch.float64) - mean_x) @ cand.T + mean_x
            icp, _ = rigid_icp(placed[sx], nx[sx].to(torch.float64) @ cand.T, vy[sy], ny[sy],
                               self.prealign_icp_iterations, level.normal_weight / box_x.scale,
                               feat_x, feat_y, backend="brute")  # a few hundred points: brute force
            rot = icp @ cand
            st = self._pair_state(((vx.to(torch.float64) - mean_x) @ rot.T + mean_x).to(torch.float32), vy, fy)
            rotations.append(rot)
            scores.append(self._score(st, fx, dx, dy))
        return rotations[int(np.argmin(scores))], scores

    def fit(self, x, y) -> dict:
        """Optimize the field flowing x onto y (after the pre-alignment, docs/divfree.md §1).

        With ``prealign`` on, x is first turned about its vertex mean (:meth:`_prealign`): each candidate rotation
        of :func:`orientation_candidates` is refined by :func:`rigid_icp`, and the one of the lowest alignment
        energy at rest (:meth:`_score`) is kept.

        Parameters
        ----------
        x, y : ShapeSample

        Returns
        -------
        dict with ``coeffs (3 K^3,)`` (finest level), the box transforms ``box_x``, ``box_y`` (x's of its turned
        placement), ``rotation (3, 3)`` float64 and ``mean_x (3,)`` (x was turned by ``rotation`` about
        ``mean_x``), the candidates' ``prealign_scores``, the energies of the last iteration, and ``seconds``.
        """
        start = time.perf_counter()
        vx = x.verts.detach().to(torch.float32)
        vy = y.verts.detach().to(device=vx.device, dtype=torch.float32)
        fx, fy = x.faces.to(vx.device), y.faces.to(vx.device)
        dx, dy = self._descriptor(x), self._descriptor(y)
        dx = None if dx is None else dx.to(vx.device)
        dy = None if dy is None else dy.to(vx.device)
        names = f"{x.name}, {y.name}"
        mean_x = vx.to(torch.float64).mean(0)
        rotation, scores = self._prealign(x, y, vx, vy, fx, fy, dx, dy)
        kept = bool(torch.equal(rotation, torch.eye(3, dtype=rotation.dtype, device=rotation.device)))
        placed = vx if kept else ((vx.to(torch.float64) - mean_x) @ rotation.T + mean_x).to(torch.float32)
        st = self._pair_state(placed, vy, fy)
        coeffs = torch.zeros(df.n_fields(self.levels[0].n_modes), device=vx.device)
        energies, history = {}, []
        for i_level in range(len(self.levels)):
            coeffs, level_energies, level_history = self._run_level(st, i_level, coeffs, fx, dx, dy, names)
            energies = level_energies or energies
            history += level_history
        return {"coeffs": coeffs, "box_x": st["box_x"], "box_y": st["box_y"], "energies": energies,
                "history": history, "seconds": time.perf_counter() - start, "box_verts": (st["bx"], st["by"]),
                "normals_y": st["ny"], "descriptors": (dx, dy), "rotation": rotation,
                "mean_x": mean_x.to(vx.device), "prealign_scores": scores}

    def _maps(self, fit: dict, x, y) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Full-resolution deformed x (box units) and the product-space maps x -> y, y -> x."""
        bx, by = fit["box_verts"]
        dx, dy = fit["descriptors"]
        level = self.levels[-1]
        moved = self._flow(bx, fit["coeffs"])
        emb_x = self._embed(moved, vertex_normals(moved, x.faces.to(moved.device)), dx, level)
        emb_y = self._embed(by, fit["normals_y"], dy, level)
        p2p, p2p_inv = self._nn(emb_x, emb_y)
        if self.extraction == "spectral":
            p2p, p2p_inv = self._spectral_maps(bx, by, emb_x, emb_y, p2p, p2p_inv, x, y)
        return moved, p2p, p2p_inv

    def _spectral_maps(self, bx, by, emb_x, emb_y, p2p, p2p_inv, x, y) -> tuple[torch.Tensor, torch.Tensor]:
        """The ``spectral`` extraction: the flow's product space plus the aligned spectral embedding of its maps.

        The flow's maps fit a functional map at ``extraction_k`` eigenfunctions on the vertices whose round trip
        x -> y -> x (y -> x -> y) returns within ``extraction_consistency`` box units at rest; a limb that the flow
        laid onto the other side's limb maps many-to-one and fails the round trip, so it does not enter the fit.
        ``phi_x C`` is intrinsic and, being fitted to the consistent part of the map, not left/right symmetric: in
        the product space it pulls such a limb to its own side while the coordinates keep the flow's accuracy
        elsewhere. With fewer consistent vertices than eigenfunctions on a side, all vertices enter the fit. A
        limb laid onto the other side's limb that passes the round trip anyway is left out by the trimmed fit
        (:func:`trimmed_functional_map`, ``extraction_trim`` times the median residual, ``extraction_trim_steps``
        refits), and the orthogonal fit (``extraction_fit``) keeps ``C`` right on the limbs left out. Each of
        the ``extraction_iterations`` rounds refits the functional map to the previous round's maps.
        """
        k = self.extraction_k
        for sample in (x, y):
            if sample.evecs.shape[1] < k:
                raise ConfigError(f"divfree: the spectral extraction needs {k} eigenfunctions, {sample.name!r} has "
                                  f"{sample.evecs.shape[1]} (raise data.operators.n_eig)")
        dev = emb_x.device
        phi_x = x.evecs[:, :k].to(device=dev, dtype=torch.float64)
        phi_y = y.evecs[:, :k].to(device=dev, dtype=torch.float64)
        w = self.extraction_weight
        for _ in range(self.extraction_iterations):
            keep_x, keep_y = cycle_consistent(bx, by, p2p, p2p_inv, self.extraction_consistency)
            if int(keep_x.sum()) < k or int(keep_y.sum()) < k:
                keep_x = keep_y = None
            if keep_x is None:
                keep_x = torch.ones(len(p2p), dtype=torch.bool, device=dev)
                keep_y = torch.ones(len(p2p_inv), dtype=torch.bool, device=dev)
            fmap, _, _ = trimmed_functional_map(phi_x, phi_y, x.mass.to(dev), y.mass.to(dev), p2p, p2p_inv, keep_x,
                                                keep_y, self.extraction_trim, self.extraction_trim_steps,
                                                self.extraction_fit == "orthogonal")
            spec_x = torch.cat([emb_x, w * (phi_x @ fmap).to(emb_x.dtype)], dim=1)
            spec_y = torch.cat([emb_y, w * phi_y.to(emb_y.dtype)], dim=1)
            p2p, p2p_inv = self._nn(spec_x, spec_y)
        return p2p, p2p_inv

    def _frames(self, fit: dict, x, times: torch.Tensor) -> torch.Tensor:
        """Flow of every vertex of x at ``times``, in x's normalized units.

        The box normalization centres x and y separately; the frames are mapped back with x's transform and
        moved by ``t (c_y - c_x)``, so the frame at t = 1 lies where y lies (a rigid translation, linear in t).
        """
        bx, _ = fit["box_verts"]
        frames = df.flow_frames(bx, fit["coeffs"], times, self.n_steps, self.rule, self.convention, self.chunk_size)
        box_x, box_y = fit["box_x"], fit["box_y"]
        shift = (box_y.center - box_x.center).to(frames)
        t = times.to(frames).reshape(-1, 1, 1)
        frames = box_x.from_box(frames) + t * shift
        rotation = fit["rotation"]
        if self.prealign == "none" or bool(torch.equal(rotation, torch.eye(3, dtype=rotation.dtype,
                                                                             device=rotation.device))):
            return frames
        # Undo the remaining part of the pre-alignment: frame t is turned by R^(t - 1) about its vertex mean, so
        # t = 0 is x as given and t = 1 is the flowed x in y's frame (a rotation: volume and angles unchanged).
        out = []
        for frame, tk in zip(frames, times.tolist()):
            turn = fractional_rotation(rotation, tk - 1.0).to(frame)
            centre = frame.mean(0)
            out.append((frame - centre) @ turn.T + centre)
        return torch.stack(out)

    def interpolate(self, x, y, times) -> MatchResult:
        """Maps x -> y, y -> x and the deformation of x at ``times (T,)`` (any finite values)."""
        times = torch.as_tensor(times, dtype=torch.float32).reshape(-1)
        if not bool(torch.isfinite(times).all()):
            raise NumericalError(f"interpolation times must be finite, got {times.tolist()}")
        with torch.enable_grad():  # evaluate.py calls matchers under no_grad; the fit needs autograd
            fit = self.fit(x, y)
        with torch.no_grad():
            moved, p2p, p2p_inv = self._maps(fit, x, y)
            frames = self._frames(fit, x, times.to(moved.device))
        extras = {"coeffs": fit["coeffs"].cpu(), "energies": fit["energies"], "history": fit["history"],
                  "fit_seconds": fit["seconds"], "prealign_rotation": fit["rotation"].cpu(),
                  "prealign_scores": fit["prealign_scores"]}
        return MatchResult(p2p=p2p, p2p_inv=p2p_inv, deformation=frames.to(x.verts.dtype),
                           times=times.to(frames.device), extras=extras)

    def match(self, x, y) -> MatchResult:
        """:meth:`interpolate` at the default frames ``interp_times``."""
        return self.interpolate(x, y, torch.tensor(self.interp_times))
