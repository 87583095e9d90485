"""As-rigid-as-possible (ARAP) deformation energy, shared by NeuroMorph and the axiomatic interpolations.

For a rest pose ``V_0`` and a deformed pose ``V_t`` of the same mesh, with edge vectors ``e_0 = v_0[b] -
v_0[a]`` and ``e_t = v_t[b] - v_t[a]`` for every edge ``(a, b)`` of weight ``w_e``:

* **rotations** (Sorkine & Alexa 2007): per vertex, ``R_i = argmin_{R in SO(3)} sum_{e ∋ i} w_e ||e_t - R
  e_0||^2``, i.e. the rotation closest to the covariance ``S_i = sum_{e ∋ i} w_e e_t e_0^T``: with ``S_i =
  U diag(s) V^T``, ``R_i = U diag(1, 1, det(U V^T)) V^T`` (batched 3x3 SVD in float64, determinant fix);
* **energy**, two variants (``mode``):

  - ``"both-sides"`` (default): ``sum_e w_e (||e_t - R_a e_0||^2 + ||e_t - R_b e_0||^2)``. This is the
    classic ARAP energy ``sum_i sum_{e ∋ i} w_e ||e_t - R_i e_0||^2`` (each undirected edge seen from both of
    its vertices, the same as a source-vertex rotation summed over directed edges) and the energy written in
    the NeuroMorph paper (eq. 5). With optimal rotations it is symmetric in the two poses:
    ``E(V_0 -> V_t) = E(V_t -> V_0)``, since ``min_R ||e_t - R e_0|| = min_R ||e_0 - R^T e_t||``.
  - ``"average"``: ``sum_e w_e ||e_t - 0.5 (R_a + R_b) e_0||^2``, what the NeuroMorph code computes
    (docs/neuromorph.md §6). ``0.5 (R_a + R_b)`` is not a rotation, and the ``R_i`` are not the minimizers of
    this energy.

Gradients and the rotations (``detach_rotations``):

* ``True`` (default): the rotations are treated as constants. For ``"both-sides"`` this is the *exact*
  gradient of the energy: every ``R_i`` minimizes its own vertex's part of the energy, so by the envelope
  theorem the derivative through ``R`` vanishes (tested: same gradient as differentiating through the SVD).
  For ``"average"`` it is an approximation (the ``R_i`` do not minimize that energy).
* ``False``: gradients flow through the rotations with a safe closed-form backward of the polar factor
  (:func:`rotations_from_covariances`), whose denominators are sums of singular values ``s_i + s_j``
  (not the differences of a generic SVD backward, which give NaN for repeated singular values). The sums
  vanish only when the rotation itself is not unique (rank-deficient covariance: a collinear one-ring,
  coincident vertices); they are regularized there, so values and gradients stay finite. The NeuroMorph code
  differentiates through ``torch.svd``.

Edges and weights. ``edges`` are undirected vertex pairs (``shapecorr.geometry.mesh_graph.undirected_edges``)
with optional non-negative weights (default 1). The NeuroMorph code lists every triangle edge once per face, in
one direction (``(f0, f1), (f0, f2), (f1, f2)`` of every face; the edge list with both directions is its
EdgeConv graph, not its ARAP one), so its sums count an edge ``counts`` times (the number of faces containing
it: twice for an interior edge). ``edge_weights = counts`` with ``mode="average"`` reproduces the original
exactly, energy and rotations (``model=neuromorph_original``; parity-tested on the original's outputs).
``mode="both-sides"`` has two residuals per listed edge, so ``edge_weights = 0.5 * counts`` (NeuroMorph's
default ``arap_edge_weight_scale``) gives it the original's number of residuals; on a closed mesh this is
uniform weight 1, the classic energy. Measured on the two parity reference pairs (``benchmarks/neuromorph_parity.py``):
both-sides at ``0.5 * counts`` is 5.9 % above the original's value (0.009395 vs 0.008870 and 0.009908 vs
0.009358), the difference between the two energies; at ``counts`` it would be twice that (0.01874).
"""

from __future__ import annotations

import torch

from shapecorr.errors import ConfigError, NumericalError

ARAP_MODES = ("both-sides", "average")
#: NeuroMorph code: every ARAP evaluation adds 1e-6 * ||V_t - V_0||^2 (docs/neuromorph.md §6).
NEUROMORPH_DISPLACEMENT_WEIGHT = 1e-6
#: Regularization of the polar-factor backward: singular-value sums s_i + s_j below this fraction of the mean
#: largest singular value (over the batch) are damped as 1 / (s_i + s_j) -> d / (d^2 + eps^2). Project choice:
#: changes regular gradients by a relative (eps / d)^2 <= 1e-12 and bounds degenerate ones.
POLAR_GRAD_REL_EPS = 1e-6


def _check_pose_pair(verts_0: torch.Tensor, verts_t: torch.Tensor, edges: torch.Tensor) -> None:
    if verts_0.shape != verts_t.shape or verts_0.ndim < 2 or verts_0.shape[-1] != 3:
        raise ConfigError(
            f"verts_0 and verts_t must both be (..., n, 3) with equal shapes, got {tuple(verts_0.shape)} and "
            f"{tuple(verts_t.shape)}"
        )
    if edges.ndim != 2 or edges.shape[1] != 2 or edges.shape[0] == 0 or edges.dtype.is_floating_point:
        raise ConfigError(f"edges must be a non-empty (E, 2) integer tensor, got {tuple(edges.shape)} {edges.dtype}")
    if int(edges.min()) < 0 or int(edges.max()) >= verts_0.shape[-2]:
        raise ConfigError(f"edges index vertices outside [0, {verts_0.shape[-2]})")
    for name, v in (("verts_0", verts_0), ("verts_t", verts_t)):
        if not bool(torch.isfinite(v).all()):
            raise NumericalError(f"{name} contains NaN or Inf; cannot evaluate the ARAP energy")


def _check_weights(edge_weights: torch.Tensor | None, n_edges: int) -> None:
    if edge_weights is None:
        return
    if edge_weights.shape != (n_edges,):
        raise ConfigError(f"edge_weights must have shape ({n_edges},), got {tuple(edge_weights.shape)}")
    if bool((edge_weights < 0).any()) or not bool(torch.isfinite(edge_weights).all()):
        raise ConfigError("edge_weights must be finite and non-negative")


def edge_vectors(verts: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """``v[b] - v[a]`` for every edge: (..., E, 3)."""
    return verts.index_select(-2, edges[:, 1]) - verts.index_select(-2, edges[:, 0])


def arap_covariances(
    verts_0: torch.Tensor,
    verts_t: torch.Tensor,
    edges: torch.Tensor,
    edge_weights: torch.Tensor | None = None,
) -> torch.Tensor:
    """Per-vertex covariances ``S_i = sum_{e ∋ i} w_e e_t e_0^T``.

    Parameters
    ----------
    verts_0, verts_t : (..., n, 3) float
        Rest and deformed positions.
    edges : (E, 2) int64
        Undirected edges.
    edge_weights : (E,) float, optional
        Non-negative weights (default 1).

    Returns
    -------
    (..., n, 3, 3) float
    """
    _check_pose_pair(verts_0, verts_t, edges)
    _check_weights(edge_weights, edges.shape[0])
    edges = edges.to(device=verts_0.device, dtype=torch.int64)
    e0, et = edge_vectors(verts_0, edges), edge_vectors(verts_t, edges)
    outer = et.unsqueeze(-1) * e0.unsqueeze(-2)  # (..., E, 3, 3)
    if edge_weights is not None:
        outer = outer * edge_weights.to(outer).view(-1, 1, 1)
    outer = outer.flatten(-2)  # (..., E, 9)
    cov = outer.new_zeros(*outer.shape[:-2], verts_0.shape[-2], 9)
    cov = cov.index_add(-2, edges[:, 0], outer).index_add(-2, edges[:, 1], outer)
    return cov.unflatten(-1, (3, 3))


def _det3(m: torch.Tensor) -> torch.Tensor:
    """Determinants of ``(..., 3, 3)`` matrices by the triple product of their rows (cheaper than an LU per matrix).

    Used for the signs of the orthogonal SVD factors (determinant +-1), where any formula gives the same sign.
    """
    return (m[..., 0, :] * torch.linalg.cross(m[..., 1, :], m[..., 2, :], dim=-1)).sum(-1)


def _signed_svd(cov64: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """SVD with the determinant fix folded in: ``cov = U' diag(s') V^T`` with ``det(U' V^T) = +1``."""
    u, s, vh = torch.linalg.svd(cov64)
    sign = torch.sign(_det3(u) * _det3(vh))
    sign = torch.where(sign == 0, torch.ones_like(sign), sign)
    u = torch.cat((u[..., :2], u[..., 2:] * sign[..., None, None]), dim=-1)
    s = torch.cat((s[..., :2], s[..., 2:] * sign[..., None]), dim=-1)
    return u, s, vh


class _PolarRotation(torch.autograd.Function):
    """Closest rotation to a 3x3 matrix, with the polar-factor backward (module docstring).

    With ``S = U' diag(s') V^T`` (determinant fix folded into U' and s'), ``R = U' V^T`` and for an upstream
    gradient G: ``dL/dS = U' [(H - H^T) / (s'_i + s'_j)] V^T`` with ``H = U'^T G V``. (Differentiate
    ``S = R P``, ``P = V diag(s') V^T`` symmetric: the skew part of ``R^T dR`` in the V basis is
    ``(M - M^T)_ij / (s'_i + s'_j)`` with ``M = U'^T dS V``.)
    """

    @staticmethod
    def forward(ctx, cov: torch.Tensor):
        u, s, vh = _signed_svd(cov.detach().to(torch.float64))
        ctx.save_for_backward(u, s, vh)
        return (u @ vh).to(cov.dtype)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_r: torch.Tensor):
        u, s, vh = ctx.saved_tensors
        h = u.mT @ grad_r.to(torch.float64) @ vh.mT
        den = s.unsqueeze(-1) + s.unsqueeze(-2)
        scale = s[..., 0].abs().mean() if s.numel() else s.new_zeros(())
        eps2 = (POLAR_GRAD_REL_EPS * scale) ** 2
        denom = den.square() + eps2
        positive = denom > 0  # False only where the whole batch is zero: no rotation gradient there
        inv = torch.where(positive, den / torch.where(positive, denom, 1.0), 0.0)
        z = (h - h.mT) * inv
        return (u @ z @ vh).to(grad_r.dtype)


def rotations_from_covariances(cov: torch.Tensor, differentiable: bool = False) -> torch.Tensor:
    """Rotations closest to 3x3 matrices: ``argmax_{R in SO(3)} tr(R^T S)``.

    Parameters
    ----------
    cov : (..., 3, 3) float
        E.g. ARAP covariances from :func:`arap_covariances`.
    differentiable : bool
        Differentiate through the rotation with the safe polar backward; otherwise the result is detached.

    Returns
    -------
    (..., 3, 3) float
        Proper rotations (det = +1), in the dtype of ``cov`` (computed in float64). A zero or rank-deficient
        ``cov`` gives some valid rotation among the (then non-unique) optimal ones.
    """
    if cov.shape[-2:] != (3, 3):
        raise ConfigError(f"covariances must be (..., 3, 3), got {tuple(cov.shape)}")
    if not bool(torch.isfinite(cov).all()):
        raise NumericalError("ARAP covariances contain NaN or Inf; cannot fit rotations")
    if differentiable:
        return _PolarRotation.apply(cov)
    with torch.no_grad():
        u, _, vh = _signed_svd(cov.detach().to(torch.float64))
        return (u @ vh).to(cov.dtype)


#: Entries of the flattened 3x3 cofactor matrix: ``C_f = x[p1_f] x[p2_f] - x[q1_f] x[q2_f]`` (row-major f = 3 i + j).
_COFACTOR_TERMS = ((4, 5, 3, 2, 0, 1, 1, 2, 0), (8, 6, 7, 7, 8, 6, 5, 3, 4),
                   (5, 3, 4, 1, 2, 0, 2, 0, 1), (7, 8, 6, 8, 6, 7, 4, 5, 3))
#: Newton iterations of :func:`polar_rotations` at most (quadratic convergence: ~8 from a generic start).
POLAR_MAX_ITERATIONS = 30
#: :func:`polar_rotations` stops when no entry moves by more than this many float64 epsilons (entries are <= 1).
POLAR_TOLERANCE_EPS = 4.0
#: :func:`polar_rotations` sends matrices with ``det S <= this * |S|_F^3`` (reflections, nearly singular) to the SVD.
POLAR_MIN_RELATIVE_DET = 1e-6


def polar_rotations(cov: torch.Tensor) -> torch.Tensor:
    """:func:`rotations_from_covariances` (detached) by Newton's iteration for the polar factor, batched elementwise.

    For ``det S > 0`` the closest rotation is the orthogonal polar factor of S: the limit of the scaled Newton
    iteration ``X <- (zeta X + X^{-T} / zeta) / 2``, ``zeta = |det X|^{-1/3}``, from ``X = S`` (Higham 1986), run in
    float64 on all matrices at once with closed-form 3x3 cofactors (a batched SVD calls LAPACK once per matrix,
    about twice the time on one CPU thread). Matrices with ``det S <= POLAR_MIN_RELATIVE_DET |S|_F^3``
    (reflections, nearly singular) and any that have not converged take the SVD path. Both agree to float64
    round-off (~1e-14), so the float32 rotations are equal but for entries within that distance of a float32
    rounding boundary.

    Parameters
    ----------
    cov : (..., 3, 3) float

    Returns
    -------
    (..., 3, 3) float
        Proper rotations in the dtype of ``cov`` (detached).
    """
    if cov.shape[-2:] != (3, 3):
        raise ConfigError(f"covariances must be (..., 3, 3), got {tuple(cov.shape)}")
    if not bool(torch.isfinite(cov).all()):
        raise NumericalError("ARAP covariances contain NaN or Inf; cannot fit rotations")
    if cov.numel() == 0:
        return cov.detach().clone()
    with torch.no_grad():
        batch = cov.shape[:-2]
        s = cov.detach().to(torch.float64).reshape(-1, 9).T.contiguous()  # (9, N): entry-major
        p1, p2, q1, q2 = (torch.tensor(t, device=cov.device) for t in _COFACTOR_TERMS)

        def cofactors(x):
            return x.index_select(0, p1) * x.index_select(0, p2) - x.index_select(0, q1) * x.index_select(0, q2)

        cof = cofactors(s)
        det = (s[:3] * cof[:3]).sum(0)
        good = det > POLAR_MIN_RELATIVE_DET * s.square().sum(0).pow(1.5)
        if not bool(good.all()):  # the others start at the identity (converged at once) and take the SVD below
            x = torch.where(good, s, torch.eye(3, dtype=s.dtype, device=s.device).reshape(9, 1))
            cof = cofactors(x)
            det = (x[:3] * cof[:3]).sum(0)
        else:
            x = s
        tol = POLAR_TOLERANCE_EPS * torch.finfo(torch.float64).eps
        delta = torch.full_like(det, float("inf"))
        for i in range(POLAR_MAX_ITERATIONS):
            if i:
                cof = cofactors(x)
                det = (x[:3] * cof[:3]).sum(0)
            zeta = det.pow(-1.0 / 3.0)
            new = 0.5 * (zeta * x + cof / (zeta * det))
            delta = (new - x).abs().amax(0)
            x = new
            if float(delta.max()) <= tol:
                break
        out = x.T.reshape(*batch, 3, 3)
        redo = (~good | ~(delta <= tol)).reshape(batch)
        if bool(redo.any()):
            u, _, vh = _signed_svd(cov.detach()[redo].to(torch.float64))
            out[redo] = u @ vh
        return out.to(cov.dtype)


def arap_rotations(
    verts_0: torch.Tensor,
    verts_t: torch.Tensor,
    edges: torch.Tensor,
    edge_weights: torch.Tensor | None = None,
    differentiable: bool = False,
) -> torch.Tensor:
    """Per-vertex ARAP rotations mapping rest edges onto deformed edges, ``e_t ≈ R_i e_0``.

    Parameters
    ----------
    verts_0, verts_t : (..., n, 3) float
        Rest and deformed positions.
    edges : (E, 2) int64
        Undirected edges.
    edge_weights : (E,) float, optional
    differentiable : bool
        Keep the autograd graph through the rotations (safe backward); default detached.

    Returns
    -------
    (..., n, 3, 3) float
        Rotations; a vertex in no edge gets some rotation (its covariance is zero).
    """
    cov = arap_covariances(verts_0, verts_t, edges, edge_weights)
    return rotations_from_covariances(cov, differentiable=differentiable)


def arap_energy(
    verts_0: torch.Tensor,
    verts_t: torch.Tensor,
    edges: torch.Tensor,
    edge_weights: torch.Tensor | None = None,
    rotations: torch.Tensor | None = None,
    mode: str = "both-sides",
    detach_rotations: bool = True,
) -> torch.Tensor:
    """ARAP energy of the deformation ``verts_0 -> verts_t`` (module docstring).

    Parameters
    ----------
    verts_0, verts_t : (..., n, 3) float
        Rest and deformed positions.
    edges : (E, 2) int64
        Undirected edges.
    edge_weights : (E,) float, optional
        Non-negative weights (default 1); the face counts with ``mode="average"`` reproduce the NeuroMorph sums.
    rotations : (..., n, 3, 3) float, optional
        Precomputed rotations (used as given; ``detach_rotations`` is then ignored).
    mode : {"both-sides", "average"}
    detach_rotations : bool
        Treat the fitted rotations as constants (exact for "both-sides", see the module docstring).

    Returns
    -------
    (...,) float
        Energy per batch element; 0 for a rigid motion, > 0 otherwise.
    """
    if mode not in ARAP_MODES:
        raise ConfigError(f"ARAP mode must be one of {ARAP_MODES}, got {mode!r}")
    _check_pose_pair(verts_0, verts_t, edges)
    _check_weights(edge_weights, edges.shape[0])
    edges = edges.to(device=verts_0.device, dtype=torch.int64)
    if rotations is None:
        rotations = arap_rotations(verts_0, verts_t, edges, edge_weights, differentiable=not detach_rotations)
    elif rotations.shape != (*verts_0.shape, 3):
        raise ConfigError(f"rotations must have shape {(*verts_0.shape, 3)}, got {tuple(rotations.shape)}")
    e0, et = edge_vectors(verts_0, edges), edge_vectors(verts_t, edges)
    rot_a = rotations.index_select(-3, edges[:, 0])
    rot_b = rotations.index_select(-3, edges[:, 1])
    if mode == "average":
        residual = et - 0.5 * ((rot_a + rot_b) @ e0.unsqueeze(-1)).squeeze(-1)
        per_edge = residual.square().sum(-1)
    else:
        per_edge = (et - (rot_a @ e0.unsqueeze(-1)).squeeze(-1)).square().sum(-1)
        per_edge = per_edge + (et - (rot_b @ e0.unsqueeze(-1)).squeeze(-1)).square().sum(-1)
    if edge_weights is not None:
        per_edge = per_edge * edge_weights.to(per_edge)
    energy = per_edge.sum(-1)
    if not bool(torch.isfinite(energy).all()):
        raise NumericalError("ARAP energy is not finite")
    return energy


def arap_sequence_loss(
    frames: torch.Tensor,
    edges: torch.Tensor,
    edge_weights: torch.Tensor | None = None,
    mode: str = "both-sides",
    detach_rotations: bool = True,
    displacement_weight: float = NEUROMORPH_DISPLACEMENT_WEIGHT,
) -> torch.Tensor:
    """NeuroMorph's E_arap over an interpolation sequence, both directions between consecutive frames.

    ``sum_k [ARAP(F_k -> F_k+1) + ARAP(F_k+1 -> F_k)] + 2 * displacement_weight * sum_k ||F_k+1 - F_k||^2``
    (docs/neuromorph.md §6: the original adds ``1e-6 ||V_t - V_0||^2`` to each of its ARAP evaluations). The
    evaluations run as one batch. The "both-sides" energy is symmetric in its two poses, so it is evaluated
    in one direction and doubled (same value and gradient, half the SVDs); "average" is not symmetric and
    is evaluated both ways.

    Parameters
    ----------
    frames : (S, n, 3) float
        The sequence, S >= 2: e.g. ``[x, X(t_1), ..., X(t_T+1)]``.
    edges : (E, 2) int64
        Undirected edges of the (shared) mesh connectivity.
    edge_weights : (E,) float, optional
    mode, detach_rotations
        See :func:`arap_energy`.
    displacement_weight : float
        Weight of the displacement term (NeuroMorph code: 1e-6; 0 disables it).

    Returns
    -------
    () float
    """
    if frames.ndim != 3 or frames.shape[0] < 2:
        raise ConfigError(f"frames must be (S, n, 3) with S >= 2, got {tuple(frames.shape)}")
    if mode == "both-sides":
        # Symmetric in its two poses (min_R ||e_t - R e_0|| = min_R ||e_0 - R^T e_t||): one direction, doubled.
        loss = 2.0 * arap_energy(frames[:-1], frames[1:], edges, edge_weights, mode=mode,
                                 detach_rotations=detach_rotations).sum()
    else:
        rest = torch.cat((frames[:-1], frames[1:]), dim=0)
        deformed = torch.cat((frames[1:], frames[:-1]), dim=0)
        loss = arap_energy(rest, deformed, edges, edge_weights, mode=mode, detach_rotations=detach_rotations).sum()
    if displacement_weight:
        loss = loss + 2.0 * displacement_weight * (frames[1:] - frames[:-1]).square().sum()
    if not bool(torch.isfinite(loss.detach())):
        raise NumericalError("ARAP sequence loss is not finite")
    return loss
