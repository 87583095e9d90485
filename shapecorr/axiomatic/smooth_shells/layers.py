"""Layered matching of Smooth Shells: one layer of size k and a sequence of layers, for a batch of poses of X.

One layer (:func:`match_layer`) of size k: sigmoid shells ``X_k``, ``Y_k``; ``X* = X_k + Phi_X[:, :k] tau``;
for each of ``num_sub`` rounds: correspondences by nearest neighbours between
``[X*, a_n n(X*), a_f (Phi_X C)[:, :k_prev] w_prev]`` and ``[Y_k, a_n n(Y_k), a_f Phi_Y[:, :k_prev] w_prev]``
(``C``, ``w_prev``: previous layer's map and sigmoid weights); ``tau[:k]`` minimizing
``sum_i |X*_i - Y_k[pi(i)]|^2 + sum_j |X*_{pi'(j)} - Y_k,j|^2 + l_arap E_arap(tau)`` (rotations of the
current ``X*`` frozen); ``C`` (size k + 9) by area-weighted least squares on the same pairs plus the
descriptor term, then projected onto the orthogonal matrices.

The main run works on one pose (batch 1) at full resolution; the surrogate runs of the rigid stage and of the
random search (:mod:`.surrogates`) on batches of poses and farthest-point samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from shapecorr.errors import ConfigError
from shapecorr.geometry.mesh_graph import undirected_edges
from shapecorr.geometry.normals import vertex_normals
from shapecorr.geometry.shells import sigmoid_shell_weights
from shapecorr.losses.arap import arap_rotations
from shapecorr.matching.least_squares import solve_normal_equations
from shapecorr.matching.nearest_neighbors import batched_nearest_neighbors, bidirectional_nearest_neighbors

from shapecorr.axiomatic.smooth_shells.config import K_START, NORMAL_K_MIN
from shapecorr.axiomatic.smooth_shells.shapes import ShellsShape


class PairTensors:
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
            sy = shells_of_poses(self.phi_y, self.coeffs_y[None], k)[0]
            self._shell_y[k] = (sy, vertex_normals(sy, self.faces_y))
        return self._shell_y[k]


def batched_normals(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Vertex normals ``(B, n, 3)`` of a batch of poses ``(B, n, 3)`` of one mesh, pose by pose.

    Faster on the CPU than one batched gather / index_add over the middle dimension (46 vs 89 ms for
    16 x 5000 vertices, measured).
    """
    return torch.stack([vertex_normals(v, faces) for v in verts])


def shells_of_poses(evecs: torch.Tensor, coeffs: torch.Tensor, k: int) -> torch.Tensor:
    """Sigmoid shells of a batch of poses: ``(B, n, 3)`` from ``coeffs (B, K, 3)``."""
    w = sigmoid_shell_weights(k, dtype=evecs.dtype, device=evecs.device)
    kk = w.shape[0]
    if kk > evecs.shape[1]:
        raise ConfigError(f"a shell of size {k} needs {kk} eigenfunctions, the shape has {evecs.shape[1]}")
    return torch.matmul(evecs[:, :kk], w[None, :, None] * coeffs[:, :kk])


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
    return _scatter_rows_onto(values.new_zeros(values.shape[0], n, values.shape[2]), index, values)


def _scatter_rows_onto(out: torch.Tensor, index: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """``out (B, n, c)`` with ``values (B, r, c)`` added at rows ``index (B, r)``, in place, in the order of r."""
    return out.scatter_add_(1, index[:, :, None].expand(-1, -1, values.shape[2]), values)


def gather_rows(values: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``values (B or 1, n, c)`` at rows ``index (B, r)`` -> ``(B, r, c)``."""
    if values.shape[0] == 1 and index.shape[0] > 1:
        values = values.expand(index.shape[0], -1, -1)
    return torch.gather(values, 1, index[:, :, None].expand(-1, -1, values.shape[2]))


@dataclass
class RunSettings:
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
class LayerState:
    """What a layer carries to the next: pose of X, ``tau``, ``C`` and the previous sigmoid weights."""

    verts_x: torch.Tensor  # (B, n, 3)
    coeffs_x: torch.Tensor  # (B, K, 3)
    tau: torch.Tensor  # (B, K_tau, 3) float64
    fmap: torch.Tensor | None  # (B, k', k')
    k_prev: int = 0
    w_prev: torch.Tensor | None = None
    pairs: tuple[torch.Tensor, torch.Tensor] | None = None  # last (assignment, assignment_inv)
    objectives: list = field(default_factory=list)


def embedding_scales(pair: PairTensors, shell_y, normals_y, k_prev, fac_feat, damping):
    """Weights of the spectral block and of the normals, from Y (shared by both sides; docs/smooth_shells.md §6)."""
    y_norm = shell_y.norm()
    fac_n = damping * y_norm / normals_y.norm().clamp_min(1e-30)
    fac_s = None
    if k_prev:
        fac_s = fac_feat * y_norm / pair.phi_y[:, :k_prev].norm().clamp_min(1e-30)
    return fac_s, fac_n


def product_embeddings(pair: PairTensors, st: LayerState, deformed, normals_x, shell_y, normals_y, fac_feat, damping):
    """Full-resolution product embeddings ``(B, n_x, d)``, ``(1, n_y, d)``."""
    fac_s, fac_n = embedding_scales(pair, shell_y, normals_y, st.k_prev if st.fmap is not None else 0,
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


def nearest_pairs(pair: PairTensors, run: RunSettings, emb_x, emb_y):
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
        a = sy[batched_nearest_neighbors(qx, qy)]
        ai = sx[batched_nearest_neighbors(qy, qx)]
    else:
        a = batched_nearest_neighbors(qx, emb_y)
        ai = batched_nearest_neighbors(qy, emb_x)
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


def _all_vertices(samples: torch.Tensor, n: int) -> bool:
    """Whether ``samples (s,)`` is ``0, 1, ..., n - 1`` (the main run's full resolution)."""
    return samples.numel() == n and bool(torch.equal(samples, torch.arange(n, device=samples.device)))


def _at_samples(values: torch.Tensor, samples: torch.Tensor, b: int) -> torch.Tensor:
    """``values (1, n, c)`` at the rows ``samples (s,)`` for a batch of ``b``: ``(b, s, c)`` (a view when all rows)."""
    if _all_vertices(samples, values.shape[1]):
        return values.expand(b, -1, -1)
    return gather_rows(values, samples[None].expand(b, -1))


def _full_normal_equations(phi: torch.Tensor, base: torch.Tensor, rows: torch.Tensor, values: torch.Tensor,
                           vertex_weights: torch.Tensor | None = None):
    """:func:`_row_normal_equations` for the pairs ``[(i, base_i) for every vertex i] + [(rows_r, values_r)]``.

    The main run pairs every vertex of X with one target (X -> Y) and adds the Y -> X pairs. The per-vertex sums
    start from ``base`` and add the extra rows in their order: the same additions as scattering all rows onto
    zeros, without forming the concatenated rows.

    Parameters
    ----------
    phi : (n, k) float64
    base : (B, n, c) float64
        Target of each vertex's own pair (overwritten: the sums are accumulated in place).
    rows : (B, r) int64
        Vertex of every further pair.
    values : (B, r, c) float64
    vertex_weights : (n,) float64, optional

    Returns
    -------
    gram : (B, k, k) float64
    rhs : (B, k, c) float64
    """
    b = rows.shape[0]
    counts = _scatter_rows_onto(torch.ones(b, phi.shape[0], 1, dtype=phi.dtype, device=phi.device), rows,
                                torch.ones(b, rows.shape[1], 1, dtype=phi.dtype, device=phi.device))
    summed = _scatter_rows_onto(base, rows, values)
    if vertex_weights is not None:
        counts = counts * vertex_weights[None, :, None]
        summed = vertex_weights[None, :, None] * summed
    return torch.matmul(phi.transpose(0, 1), counts * phi), torch.matmul(phi.transpose(0, 1), summed)


def _tau_system(pair: PairTensors, run: RunSettings, shell_x, shell_y, assign, assign_inv, k):
    """Data part of the ``tau`` normal equations (not area weighted, as in the original): (B, k, k), (B, k, 3)."""
    b = shell_x.shape[0]
    sx = run.samples_x[None].expand(b, -1)
    sx64, sy64 = shell_x.to(torch.float64), shell_y.to(torch.float64)[None]
    extra = _at_samples(sy64, run.samples_y, b) - gather_rows(sx64, assign_inv)
    if _all_vertices(run.samples_x, pair.n_x):
        return _full_normal_equations(pair.phi_x64[:, :k], gather_rows(sy64, assign) - sx64, assign_inv, extra)
    rows = torch.cat([sx, assign_inv], 1)
    target = torch.cat([gather_rows(sy64, assign) - gather_rows(sx64, sx), extra], 1)
    return _row_normal_equations(pair.phi_x64[:, :k], rows, target)


def _arap_system(pair: PairTensors, shell_x, deformed, k):
    """ARAP part with the rotations of the current ``X*`` frozen: ``(B, k, k)``, ``(B, k, 3)`` and the fit.

    The fit is ``(rot_a, rot_b, d)``: the rotations at both ends of every undirected edge ``(B, E, 3, 3)`` float64
    and the edge vectors ``d = x_a - x_b`` of the shell ``(B, E, 3)`` float64 (for :func:`_arap_targets`).
    """
    rot = arap_rotations(shell_x, deformed, pair.edges_x).to(torch.float64)  # (B, n, 3, 3): e_X* ~ R e_Xk
    a, b = pair.edges_x[:, 0], pair.edges_x[:, 1]
    eye = torch.eye(3, dtype=torch.float64, device=rot.device)
    d = (shell_x[:, a] - shell_x[:, b]).to(torch.float64)  # x_a - x_b
    rot_a, rot_b = rot[:, a], rot[:, b]
    g = torch.matmul(rot_a + rot_b - 2 * eye, d[..., None])[..., 0]
    s = torch.zeros_like(shell_x, dtype=torch.float64).index_add_(1, a, g).index_add_(1, b, -g)
    phi = pair.phi_x64[:, :k]
    return pair.arap_gram[:k, :k], torch.matmul(phi.transpose(0, 1), s), (rot_a, rot_b, d)


def _arap_targets(fit):
    """``(R_a - I) d`` and ``(R_b - I) d`` per undirected edge, ``(B, E, 3)`` each, from :func:`_arap_system`'s fit.

    The ARAP residual of a directed edge is ``(Phi_a - Phi_b) tau`` minus its target; both objective evaluations of a
    layer use the same targets.
    """
    rot_a, rot_b, d = fit
    eye = torch.eye(3, dtype=torch.float64, device=d.device)
    return (torch.matmul(rot_a - eye, d[..., None])[..., 0], torch.matmul(rot_b - eye, d[..., None])[..., 0])


def _tau_objective(pair, run, shell_x, shell_y, assign, assign_inv, tau, k, targets, arap_weight):
    """``sum |X* - Y_k[pi]|^2 + sum |X*[pi'] - Y_k|^2 + w sum_directed |(Phi_i - Phi_j) tau - (R_i - I) d_ij|^2``.

    ``targets``: :func:`_arap_targets` (None: no ARAP term).
    """
    phi = pair.phi_x64[:, :k]
    disp = torch.matmul(phi, tau[:, :k])
    cur = shell_x.to(torch.float64) + disp
    sy64 = shell_y.to(torch.float64)[None]
    b = cur.shape[0]
    sx = run.samples_x[None].expand(b, -1)
    sy = run.samples_y[None].expand(b, -1)
    data = (gather_rows(cur, sx) - gather_rows(sy64, assign)).square().sum((1, 2))
    data = data + (gather_rows(cur, assign_inv) - gather_rows(sy64, sy)).square().sum((1, 2))
    if targets is None:
        return data
    a, bb = pair.edges_x[:, 0], pair.edges_x[:, 1]
    delta = disp[:, a] - disp[:, bb]
    arap = (delta - targets[0]).square().sum((1, 2))
    arap = arap + (delta - targets[1]).square().sum((1, 2))
    return data + arap_weight * arap


def functional_map(pair: PairTensors, run: RunSettings, kk: int, assign=None, assign_inv=None, batch: int = 1):
    """Functional map of size ``kk`` (B, kk, kk): area-weighted pairs, descriptors, Laplacian, orthogonality."""
    f64 = torch.float64
    if assign is not None:
        b = assign.shape[0]
        sx, sy = run.samples_x[None].expand(b, -1), run.samples_y[None].expand(b, -1)
        phi_y = pair.phi_y64[:, :kk][None]
        if _all_vertices(run.samples_x, pair.n_x):
            gram, rhs = _full_normal_equations(pair.phi_x64[:, :kk], gather_rows(phi_y, assign), assign_inv,
                                               _at_samples(phi_y, run.samples_y, b), pair.mass_x.to(f64))
        else:
            rows = torch.cat([sx, assign_inv], 1)
            targets = torch.cat([gather_rows(phi_y, assign), gather_rows(phi_y, sy)], 1)
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
        cols = solve_normal_equations(systems, rhs.transpose(1, 2)[..., None], run.ridge, what)[..., 0]  # (B, j, kk)
        fmap = cols.transpose(1, 2)
    else:
        fmap = solve_normal_equations(gram, rhs, run.ridge, what)
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


def match_layer(pair: PairTensors, run: RunSettings, st: LayerState, k: int, first_pairs=None) -> LayerState:
    """One layer of size ``k`` (``run.num_sub`` rounds), updating ``st`` in place; see the module docstring."""
    w = sigmoid_shell_weights(k, dtype=pair.dtype, device=pair.device)
    kk = w.shape[0]
    shell_x = shells_of_poses(pair.phi_x, st.coeffs_x, k)  # (B, n, 3)
    shell_y, normals_y = pair.shell_y(k)
    damping = run.normal_damping if k > NORMAL_K_MIN else 0.0
    lambda_arap = run.lambda_arap_init * math.sqrt(max(k - K_START, 0))
    phi_k = pair.phi_x[:, :k]
    for sub in range(run.num_sub):
        deformed = shell_x + torch.matmul(phi_k, st.tau[:, :k].to(pair.dtype))
        if first_pairs is not None and sub == 0:
            assign, assign_inv = first_pairs
        else:
            normals_x = batched_normals(deformed, pair.faces_x) if damping > 0 else None
            emb_x, emb_y = product_embeddings(pair, st, deformed, normals_x, shell_y, normals_y, run.fac_feat, damping)
            assign, assign_inv = nearest_pairs(pair, run, emb_x, emb_y)
        gram, rhs = _tau_system(pair, run, shell_x, shell_y, assign, assign_inv, k)
        fit, weight = None, 0.0
        if lambda_arap > 0:
            if pair.arap_gram is None:
                raise ConfigError("internal: ARAP needed but not prepared")
            g_arap, z_arap, fit = _arap_system(pair, shell_x, deformed, k)
            weight = lambda_arap * _inf_norm(gram) / _inf_norm(g_arap).clamp_min(1e-300)  # (B,)
            gram = gram + weight[:, None, None] * g_arap
            rhs = rhs + weight[:, None, None] * z_arap
        if run.record:
            targets = None if fit is None else _arap_targets(fit)
            before = _tau_objective(pair, run, shell_x, shell_y, assign, assign_inv, st.tau, k, targets, weight)
        sol = solve_normal_equations(gram, rhs, run.ridge, f"Smooth Shells deformation solve at k={k}")
        tau = st.tau.clone()
        tau[:, :k] = sol
        st.tau = tau
        if run.record:
            after = _tau_objective(pair, run, shell_x, shell_y, assign, assign_inv, st.tau, k, targets, weight)
            st.objectives.append(torch.stack([before[0], after[0]]))
        st.fmap = functional_map(pair, run, kk, assign, assign_inv)
        st.pairs = (assign, assign_inv)
        st.k_prev, st.w_prev = k, w  # the next round already embeds with this C (as the original)
    return st


def match_layers(pair: PairTensors, run: RunSettings, st: LayerState, ks, first_pairs=None,
                 cfix_k_max: int = K_START) -> LayerState:
    """Layers of the sizes ``ks`` in turn (``first_pairs``: the first layer's pairs; ``run.cfix`` up to cfix_k_max)."""
    cfix = run.cfix
    for i, k in enumerate(ks):
        run.cfix = cfix if (cfix is not None and k <= cfix_k_max) else None
        match_layer(pair, run, st, k, first_pairs if i == 0 else None)
    run.cfix = cfix
    return st
