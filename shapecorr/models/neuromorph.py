"""NeuroMorph as a LightningModule: correspondence and interpolation in one network pass.

Eisenberger, Novotny, Kerchenbaum, Labatut, Neverova, Cremers, Vedaldi, CVPR 2021 (methods-digest §4). The
module is thin; the pieces live elsewhere:

* features: :class:`~shapecorr.nn.neuromorph.NeuroMorphFeatureNet` on ``[xyz, vertex normal]`` of each shape
  (unit-length 128-D rows);
* soft maps both ways: :func:`~shapecorr.matching.softmax.softmax_soft_maps` (row softmax of ``sigma``
  times the cosine similarities, published sigma = 100);
* interpolation: :class:`~shapecorr.nn.neuromorph.NeuroMorphInterpolator`, ``X(t) = x + t d(x, Pi y - x,
  t)`` at the training times ``t_i = i / (T + 1)``, ``i = 1 .. T + 1`` (T = :attr:`NeuroMorph.n_intermediate`);
* loss: a :class:`~shapecorr.losses.weighted.WeightedLoss` from the ``loss`` config group (published:
  registration 1, ARAP 1 over the sequence ``[x, X(t_1), ..., X(1)]``, geodesic distortion 50). Its terms
  receive ``verts_x_deformed`` (X(1)), ``verts_y``, ``pi_x_to_y``, ``pi_y_to_x``, ``frames``, ``edges``,
  ``edge_weights`` and, while the geodesic term is active, ``dist_x`` and ``dist_y``;
* schedules (published: T 0 -> 1 -> 3 -> 7 and lambda_geo 50 -> 0, digest §4.6) are Lightning callbacks
  (:mod:`shapecorr.models.schedules`) configured next to the model; the module only exposes the settable
  :attr:`NeuroMorph.n_intermediate` and the loss weights.

Training data (one pair per step, gradients accumulated by the Trainer, published 16 pairs): each shape is
remeshed to a resolution drawn from its fixed pool and both are rotated by one random angle about the up axis
(:class:`~shapecorr.data.augmentation.PairAugmenter`, ``augment`` options; remeshes and geodesic matrices are
cached with the shape cache, geodesics only looked up while the geodesic term has a non-zero weight). The
draws are seeded by ``(seed, epoch, batch index)``, so a resumed run sees the augmentations of the
uninterrupted one. Without remeshing, shapes larger than ``query_resolution`` are trained on their
working-resolution remesh (the original trained on 2000-vertex FAUST_r meshes).

Queries (:meth:`NeuroMorph.match`, :meth:`NeuroMorph.interpolate`) run on the shapes as given, or, with
``query_resolution`` set and a shape larger than that, on a cached remesh with that many vertices (published
working resolution: 2000); the map is carried back to the full-resolution shapes by nearest vertex and the
displacement field by barycentric interpolation on the remesh (:class:`~shapecorr.data.augmentation.Remeshed`),
so that frame ``t = 0`` is exactly x. Hard maps are the row argmax of the soft maps, computed in chunks.

Memory. Training holds the soft maps both ways, two ``n_x x n_y`` float32 matrices (16 MB each at 2000 x
2000), the geodesic matrices and the ``n^2`` products of the geodesic term, plus the activations of both
networks for ``T + 1`` time steps. Queries never hold a full soft map: ``match_chunk_size x n_y`` similarities
at a time (the interpolation target ``Pi y`` is accumulated per chunk), so full-resolution queries of 10k
vertices need ~160 MB for the similarities instead of 400 MB per soft map.

Decisions on the original's [BUG?] items (methods-digest §4.2, §4.5, §8): global max-pool over vertices
(``pool="global"``; original: per-vertex max over channels, ``"channel"``), detached ARAP rotations and the
"both-sides" ARAP energy (loss config; original: differentiated SVD, "average" of the two rotations), counted
with the original's edge multiplicity (``arap_edge_weight_scale=0.5``: on the parity reference pairs the energy
is 5.9 % above the original's, the difference of the two energies, not a factor 2), zero-initialized residual
biases (``residual_init``), no rotation at test time (the original rotated test pairs randomly as well).
``model=neuromorph_original`` sets the original's choices on all of these and reproduces its features, maps,
frames and loss terms on identical inputs (``tests/models/test_neuromorph_parity.py``).

Which terms train the features (``map_gradient``). Published: all of them. The registration term also moves the
soft maps towards the interpolator's current end point, which early in training is far from any isometric map;
measured on FAUST_r it holds the correspondence near 18 % error for the whole of a 2-hour CPU run while the
geodesic term alone fits it. ``map_gradient="geodesic"`` lets only the geodesic term train the maps (README,
"NeuroMorph: why map_gradient exists").
"""

from __future__ import annotations

import functools
import warnings
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from matplotlib.figure import Figure

from shapecorr.data.augmentation import (
    AugmentationConfig,
    PairAugmenter,
    Remeshed,
    cached_remesh,
    remeshed_sample,
)
from shapecorr.data.cache import ShapeCache, content_hash, default_cache_root
from shapecorr.errors import ConfigError, NumericalError
from shapecorr.eval.protocol import score_deformation
from shapecorr.geometry.mesh_graph import undirected_edges
from shapecorr.losses.arap import NEUROMORPH_DISPLACEMENT_WEIGHT, arap_sequence_loss
from shapecorr.losses.geodesic_distortion import geodesic_distortion_loss
from shapecorr.losses.registration import registration_loss
from shapecorr.losses.weighted import WeightedLoss
from shapecorr.matching.result import MatchResult
from shapecorr.matching.softmax import (
    DEFAULT_CHUNK_SIZE,
    DEFAULT_SIGMA,
    hard_maps,
    softmax_soft_maps,
)
from shapecorr.models.base import CorrespondenceModule
from shapecorr.nn.edgeconv import DEFAULT_HIDDEN, DEFAULT_N_BLOCKS
from shapecorr.nn.neuromorph import (
    DEFAULT_FEATURE_DIM,
    NeuroMorphFeatureNet,
    NeuroMorphInterpolator,
    interpolation_times,
)
from shapecorr.viz.render import (
    DEFAULT_VIEW,
    PANEL_SIZE,
    RENDER_DPI,
    coordinate_colors,
    draw_mesh,
    figure_to_rgb,
)
from shapecorr.viz.tensorboard import summary_writer

#: NeuroMorph optimizer: Adam, learning rate 1e-4, no scheduler (methods-digest §4.6).
DEFAULT_LR = 1e-4
#: Published loss weights (methods-digest §4.5): E_align 1, E_arap 1, E_geo 50 (the latter scheduled to 0).
DEFAULT_LOSS_WEIGHTS = {"registration": 1.0, "arap": 1.0, "geo": 50.0}
#: ARAP edge weight per face containing the edge. The original lists each face edge once (interior edges twice);
#: with the both-sides energy (two residuals per listed edge) 0.5 gives the original's number of residuals.
DEFAULT_ARAP_EDGE_WEIGHT_SCALE = 0.5
#: Name of the loss term needing geodesic matrices (their lookup is skipped while its weight is 0).
DEFAULT_GEO_TERM = "geo"
#: Frames returned by ``match`` (project choice: quarter steps from x to its image on y).
DEFAULT_EVAL_TIMES = (0.0, 0.25, 0.5, 0.75, 1.0)
#: Query remeshes kept in memory (a validation set's worth; a few hundred kB each).
QUERY_REMESH_LRU_SIZE = 64
#: Deep Shells settings that configs/train.yaml and configs/debug/tiny.yaml passed to every model before they
#: moved to configs/quick/<model>.yaml; NeuroMorph checkpoints written then carry them in their hyperparameters.
#: They are dropped with a warning; any other unknown option is an error.
LEGACY_CHECKPOINT_OPTIONS = frozenset({"num_samples", "val_refine_levels", "layer", "num_eigs"})
#: Which loss terms train the soft maps (and so the feature net), see :attr:`NeuroMorph.map_gradient`.
MAP_GRADIENT_MODES = ("all", "geodesic")
#: Time of the frame compared with the target in the interpolation metrics.
UNIT_TIME = 1.0
#: 8-bit color scale of TensorBoard's mesh plugin.
COLOR_MAX = 255
#: Gray level of the target panel of the interpolation strip.
TARGET_GRAY = 0.7


def default_loss() -> WeightedLoss:
    """The published NeuroMorph loss: registration 1, ARAP 1 (both-sides, detached rotations), geodesic 50."""
    return WeightedLoss({
        "registration": {"fn": registration_loss, "weight": DEFAULT_LOSS_WEIGHTS["registration"]},
        "arap": {"fn": functools.partial(arap_sequence_loss, displacement_weight=NEUROMORPH_DISPLACEMENT_WEIGHT),
                 "weight": DEFAULT_LOSS_WEIGHTS["arap"]},
        DEFAULT_GEO_TERM: {"fn": geodesic_distortion_loss, "weight": DEFAULT_LOSS_WEIGHTS["geo"]},
    })


def _check_times(times, device: torch.device) -> torch.Tensor:
    t = torch.as_tensor(times, dtype=torch.float32).to(device)
    if t.ndim != 1 or t.numel() == 0:
        raise ConfigError(f"interpolation times must be a non-empty 1-D sequence, got shape {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise ConfigError(f"interpolation times must be finite, got {t.tolist()}")
    return t


class NeuroMorph(CorrespondenceModule):
    """NeuroMorph: feature net + softmax correspondence + interpolator (see the module docstring).

    Parameters
    ----------
    loss : WeightedLoss, optional
        The training loss (Hydra: the ``loss`` group); default :func:`default_loss` (published). Not stored
        in the checkpoint's hyperparameters: a model loaded with ``load_from_checkpoint`` (evaluation) gets
        the default.
    feature_dim, hidden_channels, n_blocks, pool
        Network options (published: 128, 128, 5 EdgeConv layers; pool "global" is our decision, "channel"
        the original's).
    residual_init : {"zero", "original"}
        Initialization of the residual blocks' last layer: "zero" (weight and bias, ours) or "original" (weight
        only, the original code; :class:`~shapecorr.nn.edgeconv.ResnetBlockFC`).
    sigma : float
        Softmax inverse temperature (published 100).
    n_intermediate : int
        Intermediate time steps T used in training now (published schedule 0, 1, 3, 7; set by a callback).
    eval_times : sequence of float
        Frames returned by :meth:`match`.
    lr : float
        Adam learning rate (published 1e-4).
    map_gradient : {"all", "geodesic"}
        Which loss terms train the soft maps (and through them the feature net). "all" (published): every
        term, including registration and ARAP through the interpolator's input ``Pi y``. "geodesic": only the
        geodesic-distortion term; registration and ARAP see the maps and ``Pi y`` detached and train the
        interpolator only (with the geodesic weight at 0 the feature net then gets no gradient). Settable by
        an :class:`~shapecorr.models.schedules.EpochSchedule` (``target: map_gradient``). See README,
        "NeuroMorph: why map_gradient exists".
    arap_edge_weight_scale : float, optional
        ARAP edge weights = scale x (faces containing the edge); None = uniform weights. The original code
        lists every face edge once (an interior edge twice), so 1 with mode "average" reproduces its sums
        exactly; 0.5 (default) with the "both-sides" energy counts every residual of an interior edge once
        per end, the original's scale (2 residuals per interior edge; see :mod:`shapecorr.losses.arap`).
    geo_term : str
        Loss term that needs the geodesic matrices.
    augment : mapping, optional
        :class:`~shapecorr.data.augmentation.AugmentationConfig` options (remesh, rotate, resolution,
        variants, axis).
    query_resolution : int, optional
        Working resolution of queries (and of training without remeshing); None = the shapes as given.
    geodesics : {"heat", "exact", "original"}
        Training distance matrices: heat or exact geodesics of every remesh, or "original", the original's
        preprocessing (exact geodesics of the ``query_resolution`` mesh, clamped, sub-matrices for lower
        resolutions; :mod:`shapecorr.data.augmentation`).
    match_chunk_size : int
        Rows of x per similarity block in queries.
    cache_dir : str, optional
        Shape cache for remeshes and geodesics; default the data module's, else ``$SHAPECORR_CACHE`` /
        ``~/.cache/shapecorr``.
    seed : int
        Base seed of the augmentation draws and remesh pools.
    """

    def __init__(
        self,
        loss: WeightedLoss | None = None,
        feature_dim: int = DEFAULT_FEATURE_DIM,
        hidden_channels: int = DEFAULT_HIDDEN,
        n_blocks: int = DEFAULT_N_BLOCKS,
        pool: str = "global",
        residual_init: str = "zero",
        sigma: float = DEFAULT_SIGMA,
        n_intermediate: int = 0,
        eval_times: Sequence[float] = DEFAULT_EVAL_TIMES,
        lr: float = DEFAULT_LR,
        map_gradient: str = "all",
        arap_edge_weight_scale: float | None = DEFAULT_ARAP_EDGE_WEIGHT_SCALE,
        geo_term: str = DEFAULT_GEO_TERM,
        augment: Mapping[str, Any] | None = None,
        query_resolution: int | None = None,
        geodesics: str = "heat",
        match_chunk_size: int = DEFAULT_CHUNK_SIZE,
        cache_dir: str | None = None,
        seed: int = 0,
        **unknown_options: Any,
    ):
        super().__init__()
        unknown = sorted(set(unknown_options) - LEGACY_CHECKPOINT_OPTIONS)
        if unknown:
            # A clear message instead of instantiate's TypeError.
            raise ConfigError(f"neuromorph: unknown option(s) {unknown}")
        if unknown_options:
            warnings.warn(f"neuromorph: ignoring Deep Shells option(s) {sorted(unknown_options)}: they mean nothing "
                          "to NeuroMorph (checkpoints written before configs/quick/ existed carry them)",
                          stacklevel=2)
        self.save_hyperparameters(ignore=["loss", *unknown_options])
        if not lr > 0:
            raise ConfigError(f"neuromorph: lr must be positive, got {lr}")
        if not sigma > 0:
            raise ConfigError(f"neuromorph: sigma must be positive, got {sigma}")
        if arap_edge_weight_scale is not None and not arap_edge_weight_scale > 0:
            raise ConfigError(
                f"neuromorph: arap_edge_weight_scale must be positive or null, got {arap_edge_weight_scale}")
        if query_resolution is not None and int(query_resolution) < 4:
            raise ConfigError(f"neuromorph: query_resolution must be >= 4 or null, got {query_resolution}")
        if int(match_chunk_size) < 1:
            raise ConfigError(f"neuromorph: match_chunk_size must be >= 1, got {match_chunk_size}")
        if loss is not None and not isinstance(loss, WeightedLoss):
            raise ConfigError(f"neuromorph: loss must be a WeightedLoss, got {type(loss).__name__}")
        self.feature_net = NeuroMorphFeatureNet(feature_dim, hidden_channels, n_blocks, pool, residual_init)
        self.interpolator = NeuroMorphInterpolator(hidden_channels, n_blocks, pool, residual_init)
        self.loss = default_loss() if loss is None else loss
        self.sigma = float(sigma)
        self.n_intermediate = n_intermediate
        self.eval_times = tuple(float(t) for t in _check_times(list(eval_times), torch.device("cpu")).tolist())
        self.lr = float(lr)
        self.map_gradient = map_gradient
        self.arap_edge_weight_scale = None if arap_edge_weight_scale is None else float(arap_edge_weight_scale)
        self.geo_term = str(geo_term)
        self.augment = AugmentationConfig.from_options(augment)
        self.query_resolution = None if query_resolution is None else int(query_resolution)
        self.geodesics = str(geodesics)
        self.match_chunk_size = int(match_chunk_size)
        self.cache_dir = cache_dir
        self.seed = int(seed)
        self._cache: ShapeCache | None = None
        self._augmenter: PairAugmenter | None = None
        self._query_remeshes: OrderedDict[tuple[str, int], Remeshed] = OrderedDict()
        self._first_val_sequence = None

    # -- scheduled settings -------------------------------------------------------------------------------
    @property
    def n_intermediate(self) -> int:
        """Intermediate time steps T of the training interpolation (times ``i / (T + 1)``)."""
        return self._n_intermediate

    @n_intermediate.setter
    def n_intermediate(self, value: int) -> None:
        if isinstance(value, bool) or not float(value).is_integer() or int(value) < 0:
            raise ConfigError(f"neuromorph: n_intermediate must be an integer >= 0, got {value!r}")
        self._n_intermediate = int(value)

    @property
    def map_gradient(self) -> str:
        """Loss terms that train the soft maps: "all" (published) or "geodesic" (see the class docstring)."""
        return self._map_gradient

    @map_gradient.setter
    def map_gradient(self, value: str) -> None:
        if value not in MAP_GRADIENT_MODES:
            raise ConfigError(f"neuromorph: map_gradient must be one of {MAP_GRADIENT_MODES}, got {value!r}")
        self._map_gradient = str(value)

    @property
    def lambda_geo(self) -> float:
        """Current weight of the geodesic-distortion term (0 when the loss has no such term)."""
        return float(self.loss.weights.get(self.geo_term, 0.0))

    # -- caches -------------------------------------------------------------------------------------------
    def shape_cache(self) -> ShapeCache:
        """Cache of remeshes and geodesics: ``cache_dir``, else the data module's, else the default root."""
        if self._cache is None:
            root = self.cache_dir
            if root is None and self._trainer is not None:
                root = getattr(getattr(self._trainer, "datamodule", None), "cache_dir", None)
            self._cache = ShapeCache(default_cache_root() if root is None else root)
        return self._cache

    @property
    def augmenter(self) -> PairAugmenter:
        if self._augmenter is None:
            self._augmenter = PairAugmenter(self.augment, self.shape_cache(), max_vertices=self.query_resolution,
                                            seed=self.seed, geodesics=self.geodesics)
        return self._augmenter

    def step_rng(self, batch_idx: int) -> np.random.Generator:
        """Generator of one training step's augmentation, seeded by (seed, epoch, batch index)."""
        return np.random.default_rng([self.seed, int(self.current_epoch), int(batch_idx)])

    # -- building blocks ----------------------------------------------------------------------------------
    def forward_pair(self, x, y, times: torch.Tensor) -> dict[str, torch.Tensor]:
        """Features, soft maps and the interpolation of one pair (differentiable).

        Parameters
        ----------
        x, y : ShapeSample
        times : (T,) float

        Returns
        -------
        dict
            ``pi_x_to_y (n_x, n_y)``, ``pi_y_to_x (n_y, n_x)``, ``soft_target (n_x, 3)`` (``Pi y``, the
            interpolator's target), ``frames (T, n_x, 3)`` (x's vertices at ``times``), ``edges (E, 2)`` and
            ``edge_counts (E,)`` of x. With ``map_gradient == "geodesic"``, ``pi_y_to_x`` and ``soft_target``
            (hence the frames) are detached from the feature net; ``pi_x_to_y`` never is.
        """
        edges_x, counts_x = undirected_edges(x.faces, x.shape.n_verts, return_counts=True)
        edges_y = undirected_edges(y.faces, y.shape.n_verts)
        feat_x = self.feature_net(x.verts, x.faces, edges_x)
        feat_y = self.feature_net(y.verts, y.faces, edges_y)
        pi, pi_inv = softmax_soft_maps(feat_x, feat_y, self.sigma, normalize=False)
        target = pi @ y.verts
        if self.map_gradient == "geodesic":
            target, pi_inv = target.detach(), pi_inv.detach()
        frames = self.interpolator.interpolate(x.verts, target, edges_x, times)
        return {"pi_x_to_y": pi, "pi_y_to_x": pi_inv, "soft_target": target, "frames": frames, "edges": edges_x,
                "edge_counts": counts_x}

    # -- training -----------------------------------------------------------------------------------------
    def training_step(self, batch, batch_idx: int) -> torch.Tensor:
        use_geo = self.lambda_geo != 0.0
        aug = self.augmenter(batch, self.step_rng(batch_idx), geodesics=use_geo)
        pair = aug.pair.to(self.device)
        x, y = pair.x, pair.y
        times = interpolation_times(self.n_intermediate, device=self.device)
        out = self.forward_pair(x, y, times)
        frames = out["frames"]
        weights = None
        if self.arap_edge_weight_scale is not None:
            weights = self.arap_edge_weight_scale * out["edge_counts"].to(frames.dtype)
        inputs = dict(
            verts_x_deformed=frames[-1], verts_y=y.verts, pi_x_to_y=out["pi_x_to_y"], pi_y_to_x=out["pi_y_to_x"],
            soft_target=out["soft_target"], frames=torch.cat((x.verts.unsqueeze(0), frames)), edges=out["edges"],
            edge_weights=weights,
        )
        if use_geo:
            inputs.update(dist_x=aug.dist_x.to(self.device), dist_y=aug.dist_y.to(self.device))
        total, values = self.loss(**inputs)
        if not bool(torch.isfinite(total)):
            raise NumericalError(f"neuromorph: training loss is {float(total)} on pair {batch.name}")
        log = dict(batch_size=1, on_step=True, on_epoch=True)
        self.log("train/loss", total, prog_bar=True, **log)
        for name, value in values.items():
            self.log(f"train/{name}", value, **log)
        epoch_log = dict(batch_size=1, on_step=False, on_epoch=True)
        self.log("schedule/T", float(self.n_intermediate), **epoch_log)
        self.log("schedule/lambda_geo", self.lambda_geo, **epoch_log)
        self.log("schedule/map_gradient_all", float(self.map_gradient == "all"), **epoch_log)
        self.log("train/n_verts", float(x.shape.n_verts + y.shape.n_verts) / 2.0, **epoch_log)
        return total

    def configure_optimizers(self):
        return torch.optim.Adam(self.parameters(), lr=self.lr)

    # -- queries ------------------------------------------------------------------------------------------
    def _working(self, sample):
        """``(sample the networks see, its Remeshed or None)`` for a query (see ``query_resolution``)."""
        q = self.query_resolution
        if q is None or sample.shape.n_verts <= q:
            return sample, None
        verts, faces = sample.shape.verts.detach().cpu(), sample.shape.faces.detach().cpu()
        key = (content_hash(verts, faces), q)
        remeshed = self._query_remeshes.get(key)
        if remeshed is None:
            remeshed = cached_remesh(self.shape_cache(), verts, faces, q)
            self._query_remeshes[key] = remeshed
            while len(self._query_remeshes) > QUERY_REMESH_LRU_SIZE:
                self._query_remeshes.popitem(last=False)
        else:
            self._query_remeshes.move_to_end(key)
        return remeshed_sample(sample, remeshed).to(sample.verts.device), remeshed

    def _soft_target(self, feat_x: torch.Tensor, feat_y: torch.Tensor, verts_y: torch.Tensor) -> torch.Tensor:
        """``Pi_x_to_y @ verts_y`` (n_x, 3) without holding the soft map: ``match_chunk_size`` rows at a time."""
        parts = []
        for start in range(0, feat_x.shape[0], self.match_chunk_size):
            scores = self.sigma * (feat_x[start:start + self.match_chunk_size] @ feat_y.T)
            parts.append(torch.softmax(scores, dim=1) @ verts_y)
        return torch.cat(parts)

    @torch.no_grad()
    def interpolate(self, x, y, times) -> MatchResult:
        """Maps both ways and the interpolation of x towards y at arbitrary times (t > 1 extrapolates).

        Parameters
        ----------
        x, y : ShapeSample
            Any resolution (see ``query_resolution``).
        times : (T,) float
            Frame times; ``X(t) = x + t d(x, Pi y - x, t)``.

        Returns
        -------
        MatchResult
            ``p2p (n_x,)``, ``p2p_inv (n_y,)`` int64, ``deformation (T, n_x, 3)`` in x's normalized units
            (frame ``k`` at ``times[k]``; exactly x where t = 0) and ``times (T,)``.
        """
        device = x.verts.device
        t = _check_times(times, device)
        wx, rx = self._working(x)
        wy, ry = self._working(y)
        edges_x = undirected_edges(wx.faces, wx.shape.n_verts)
        edges_y = undirected_edges(wy.faces, wy.shape.n_verts)
        feat_x = self.feature_net(wx.verts, wx.faces, edges_x)
        feat_y = self.feature_net(wy.verts, wy.faces, edges_y)
        p2p, p2p_inv = hard_maps(feat_x, feat_y, normalize=False, chunk_size=self.match_chunk_size)
        frames = self.interpolator.interpolate(wx.verts, self._soft_target(feat_x, feat_y, wy.verts), edges_x, t)
        # Carry back to the full resolution: x's vertices through their nearest remesh vertex (maps) and the
        # barycentric interpolation of the displacement (frames); y's remesh vertices to their nearest vertex.
        if rx is not None:
            p2p = p2p[torch.as_tensor(rx.nearest_vertex, device=device)]
            p2p_inv = torch.as_tensor(rx.source_vertex, device=device)[p2p_inv]
            frames = x.verts + rx.lift(frames - wx.verts)
        if ry is not None:
            p2p = torch.as_tensor(ry.source_vertex, device=device)[p2p]
            p2p_inv = p2p_inv[torch.as_tensor(ry.nearest_vertex, device=device)]
        if not bool(torch.isfinite(frames).all()):
            raise NumericalError(f"neuromorph: the interpolation of {x.name} towards {y.name} contains NaN or Inf")
        return MatchResult(p2p=p2p, p2p_inv=p2p_inv, deformation=frames, times=t)

    def match(self, x, y) -> MatchResult:
        """Point-to-point maps x -> y and y -> x, with the interpolation frames at ``eval_times``.

        See :meth:`interpolate`.
        """
        return self.interpolate(x, y, torch.tensor(self.eval_times))

    # -- validation / test --------------------------------------------------------------------------------
    def _score_interpolation(self, batch, result: MatchResult, split: str) -> None:
        """Log Chamfer distance of X(1) to y and conformal distortion of the frames with 0 <= t <= 1."""
        times = result.times.detach().cpu()
        keep = torch.nonzero((times >= 0) & (times <= UNIT_TIME)).flatten()
        keep = keep[torch.argsort(times[keep])]
        frames, kept_times = result.deformation[keep.to(result.deformation.device)], times[keep]
        if not bool((kept_times == UNIT_TIME).any()):
            extra = self.interpolate(batch.x, batch.y, torch.tensor([UNIT_TIME]))
            frames = torch.cat((frames, extra.deformation))
        else:
            last = int(torch.nonzero(kept_times == UNIT_TIME)[0, 0])
            frames = frames[: last + 1]
        scores = score_deformation(frames, batch.x, batch.y)
        log = dict(batch_size=1, on_epoch=True, on_step=False, sync_dist=True)
        for key in ("chamfer", "chamfer_one_sided", "deformation_conformal_distortion", "volume_change"):
            if scores.get(key) is not None:
                self.log(f"{split}/{key}", float(scores[key]), **log)

    def validation_step(self, batch, batch_idx: int):
        out = self._evaluate_pair(batch, "val")
        result = out["result"]
        if batch_idx == 0:
            self._first_val_pair = (batch, result.p2p)
            self._first_val_sequence = (batch, result.cpu())
        self._score_interpolation(batch, result, "val")

    def test_step(self, batch, batch_idx: int):
        out = self._evaluate_pair(batch, "test")
        self._score_interpolation(batch, out["result"], "test")

    def on_validation_epoch_end(self) -> None:
        super().on_validation_epoch_end()
        if self.trainer.sanity_checking or self.global_rank != 0 or self._first_val_sequence is None:
            return
        batch, result = self._first_val_sequence
        log_interpolation(self.logger, result.deformation, batch.x.faces, result.times, batch.y.verts, batch.y.faces,
                          step=self.global_step)


# -- TensorBoard: interpolation sequences ---------------------------------------------------------------------
def interpolation_strip_figure(frames, faces, times, verts_y=None, faces_y=None, view=DEFAULT_VIEW) -> Figure:
    """One panel per frame (colored by the coordinates of the first frame), then the target if given.

    Parameters
    ----------
    frames : (T, n, 3) float
    faces : (f, 3) int
    times : (T,) float
    verts_y : (n_y, 3) float, optional
    faces_y : (f_y, 3) int, optional
    view : (elevation, azimuth, vertical axis)

    Returns
    -------
    matplotlib.figure.Figure
    """
    frames = torch.as_tensor(frames).detach().cpu().numpy()
    times = torch.as_tensor(times).detach().cpu().numpy().reshape(-1)
    if frames.ndim != 3 or frames.shape[0] != times.shape[0]:
        raise ConfigError(f"frames (T, n, 3) and times (T,) do not match: {frames.shape}, {times.shape}")
    colors = coordinate_colors(frames[0])
    panels = [(f, faces, colors, f"t = {t:.2f}") for f, t in zip(frames, times)]
    if verts_y is not None:
        vy = torch.as_tensor(verts_y).detach().cpu().numpy()
        panels.append((vy, faces_y, np.full((vy.shape[0], 3), TARGET_GRAY), "target"))
    fig = Figure(figsize=(PANEL_SIZE[0] * len(panels), PANEL_SIZE[1]), dpi=RENDER_DPI)
    for k, (v, f, c, title) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), k + 1, projection="3d")
        draw_mesh(ax, v, torch.as_tensor(f).detach().cpu().numpy(), c, view=view, title=title)
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.0, top=0.9, wspace=0.0)
    return fig


def log_interpolation(logger, frames, faces, times, verts_y=None, faces_y=None, step: int = 0,
                      tag: str = "val/interpolation") -> bool:
    """Log an interpolation sequence as TensorBoard meshes (``<tag>/t<k>``) and a rendered strip image.

    Returns
    -------
    bool
        Whether something was logged (False without a TensorBoard logger).
    """
    writer = summary_writer(logger)
    if writer is None:
        return False
    frames_t = torch.as_tensor(frames).detach().cpu().float()
    faces_t = torch.as_tensor(faces).detach().cpu().to(torch.int32)
    colors = torch.as_tensor(np.round(coordinate_colors(frames_t[0].numpy()) * COLOR_MAX).astype(np.uint8))
    for k in range(frames_t.shape[0]):
        writer.add_mesh(f"{tag}/t{k:02d}", vertices=frames_t[k][None], colors=colors[None], faces=faces_t[None],
                        global_step=step)
    fig = interpolation_strip_figure(frames_t, faces_t, times, verts_y, faces_y)
    writer.add_image(f"{tag}/strip", figure_to_rgb(fig), global_step=step, dataformats="HWC")
    return True
