"""Divergence-free shape correspondence by deformation (Eisenberger, Lähner, Cremers, SGP 2019; docs/divfree.md).

x is flowed onto y along a stationary, divergence-free velocity field on the unit box
(:mod:`shapecorr.geometry.divergence_free`); the correspondence is read off the deformed x. The field
coefficients are optimized coarse to fine (more modes and more samples per level), alternating

1. **correspondences**: nearest neighbours in the product space ``[coordinates, w_n normals, w_s SHOT]``
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

from shapecorr.errors import ConfigError, NumericalError
from shapecorr.geometry import divergence_free as df
from shapecorr.geometry.normals import vertex_normals
from shapecorr.geometry.sampling import farthest_point_sampling
from shapecorr.losses.arap import arap_energy
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
#: Descriptor the product space uses (computed by the data pipeline).
DESCRIPTOR = "shot"


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
        Weights of the normals and of the (unit-row) SHOT descriptor in the product space, per level.
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
    """

    needs_ground_truth = False

    def __init__(
        self,
        modes=(2, 4, 8),
        samples=(500, 1000, 2000),
        iterations=(50, 50, 100),
        normal_weight=0.1,
        descriptor_weight=(0.2, 0.1, 0.05),
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
        uses_descriptor = any(level.descriptor_weight > 0 for level in self.levels)
        self.required_operators = {DESCRIPTOR: {}} if uses_descriptor else {}

    # ------------------------------------------------------------------------------------------------------
    # pieces
    # ------------------------------------------------------------------------------------------------------
    def _descriptor(self, sample) -> torch.Tensor | None:
        if not any(level.descriptor_weight > 0 for level in self.levels):
            return None
        feats = sample.features.get(DESCRIPTOR)
        if feats is None:
            raise ConfigError(
                f"shape {sample.name!r} has no {DESCRIPTOR!r} descriptor: add it to data.operators.descriptors, "
                "or set model.descriptor_weight=0"
            )
        if feats.ndim != 2 or feats.shape[0] != sample.shape.n_verts:
            raise ConfigError(f"{DESCRIPTOR} of {sample.name!r} has shape {tuple(feats.shape)}, expected (n, c)")
        if not bool(torch.isfinite(feats).all()):
            raise NumericalError(f"the {DESCRIPTOR} descriptor of {sample.name!r} contains NaN or infinite values")
        feats = feats.to(torch.float32)
        # Unit rows: the weight then sets the descriptor's share of the product-space distance.
        return feats / feats.norm(dim=1, keepdim=True).clamp_min(torch.finfo(feats.dtype).tiny)

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
    def fit(self, x, y) -> dict:
        """Optimize the field flowing x onto y.

        Parameters
        ----------
        x, y : ShapeSample

        Returns
        -------
        dict with ``coeffs (3 K^3,)`` (finest level), the box transforms ``box_x``, ``box_y``, the energies of
        the last iteration, and ``seconds``.
        """
        start = time.perf_counter()
        vx = x.verts.detach().to(torch.float32)
        vy = y.verts.detach().to(device=vx.device, dtype=torch.float32)
        box_x, box_y = df.box_normalization(vx, vy, self.margin)
        bx, by = box_x.to_box(vx), box_y.to_box(vy)
        fx, fy = x.faces.to(vx.device), y.faces.to(vx.device)
        ny = vertex_normals(by, fy)
        dx, dy = self._descriptor(x), self._descriptor(y)
        dx = None if dx is None else dx.to(vx.device)
        dy = None if dy is None else dy.to(vx.device)
        n_max = max(level.n_samples for level in self.levels)
        rng = np.random.default_rng(self.seed)
        # FPS orderings: every prefix is itself a farthest-point sample, so each level takes a prefix.
        order_x = torch.from_numpy(farthest_point_sampling(bx.cpu(), min(n_max, bx.shape[0]),
                                                           start=int(rng.integers(bx.shape[0])))).to(vx.device)
        order_y = torch.from_numpy(farthest_point_sampling(by.cpu(), min(n_max, by.shape[0]),
                                                           start=int(rng.integers(by.shape[0])))).to(vx.device)
        coeffs = torch.zeros(df.n_fields(self.levels[0].n_modes), device=vx.device)
        energies, history = {}, []
        for i_level, level in enumerate(self.levels):
            coeffs = df.resize_coefficients(coeffs.detach(), level.n_modes).requires_grad_(True)
            sx, sy = order_x[:level.n_samples], order_y[:level.n_samples]
            xs = bx[sx]
            edges, counts = knn_graph_edges(xs, min(self.knn, xs.shape[0] - 1))
            optimizer = torch.optim.Adam([coeffs], lr=level.lr)
            emb_y_all = self._embed(by, ny, dy, level)
            emb_y_s = emb_y_all[sy]
            for it in range(level.iterations):
                if it % self.corr_every == 0:
                    with torch.no_grad():
                        moved = self._flow(bx, coeffs.detach())
                        emb_x_all = self._embed(moved, vertex_normals(moved, fx), dx, level)
                        match_xy, _ = self._nn(emb_x_all[sx], emb_y_all)  # samples of x -> vertices of y
                        match_yx, _ = self._nn(emb_y_s, emb_x_all[sx])  # samples of y -> samples of x
                    target_xy, target_yx = by[match_xy], by[sy]
                optimizer.zero_grad(set_to_none=True)
                path = self._flow(xs, coeffs, return_path=True)  # (N + 1, m, 3)
                end = path[-1]
                e_align = 0.5 * (self._huber_mse(end - target_xy) + self._huber_mse(end[match_yx] - target_yx))
                e_reg = arap_energy(path[:1].expand_as(path[1:]), path[1:], edges, counts, mode="average").sum()
                e_reg = e_reg / (xs.shape[0] * self.n_steps * ARAP_NORMALIZATION / self.knn)
                loss = e_align + self.lambda_reg * e_reg
                if not bool(torch.isfinite(loss.detach())):
                    raise NumericalError(
                        f"divfree: the energy became non-finite on pair ({x.name}, {y.name}); lower model.lr"
                    )
                loss.backward()
                optimizer.step()
                energies = {"align": float(e_align.detach()), "reg": float(e_reg.detach())}
                if it % self.corr_every == 0:
                    history.append((i_level, it, energies["align"], energies["reg"]))
        return {"coeffs": coeffs.detach(), "box_x": box_x, "box_y": box_y, "energies": energies, "history": history,
                "seconds": time.perf_counter() - start, "box_verts": (bx, by), "normals_y": ny,
                "descriptors": (dx, dy)}

    def _maps(self, fit: dict, x, y) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Full-resolution deformed x (box units) and the product-space maps x -> y, y -> x."""
        bx, by = fit["box_verts"]
        dx, dy = fit["descriptors"]
        level = self.levels[-1]
        moved = self._flow(bx, fit["coeffs"])
        emb_x = self._embed(moved, vertex_normals(moved, x.faces.to(moved.device)), dx, level)
        emb_y = self._embed(by, fit["normals_y"], dy, level)
        p2p, p2p_inv = self._nn(emb_x, emb_y)
        return moved, p2p, p2p_inv

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
        return box_x.from_box(frames) + t * shift

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
                  "fit_seconds": fit["seconds"]}
        return MatchResult(p2p=p2p, p2p_inv=p2p_inv, deformation=frames.to(x.verts.dtype),
                           times=times.to(frames.device), extras=extras)

    def match(self, x, y) -> MatchResult:
        """:meth:`interpolate` at the default frames ``interp_times``."""
        return self.interpolate(x, y, torch.tensor(self.interp_times))
