"""NeuroMorph as a LightningModule: correspondence and interpolation in one network pass.

Eisenberger, Novotny, Kerchenbaum, Labatut, Neverova, Cremers, Vedaldi, CVPR 2021 (docs/neuromorph.md). The
module is thin; the pieces live elsewhere:

* features: an injected :class:`~shapecorr.nn.backbone.Backbone` (``model/backbone`` config node; published:
  :class:`~shapecorr.nn.edgeconv_backbone.EdgeConvBackbone`, the EdgeConv feature net on ``[xyz, vertex
  normal]`` of each shape, unit-length 128-D rows);
* soft maps both ways: :func:`~shapecorr.matching.softmax.softmax_soft_maps` (row softmax of ``sigma``
  times the cosine similarities, published sigma = 100);
* interpolation: :class:`~shapecorr.nn.neuromorph.NeuroMorphInterpolator`, ``X(t) = x + t d(x, Pi y - x,
  t)`` at the training times ``t_i = i / (T + 1)``, ``i = 1 .. T + 1`` (T = :attr:`NeuroMorph.n_intermediate`);
* loss: a :class:`~shapecorr.losses.weighted.WeightedLoss`, ``model.loss`` (``configs/model/loss/``; published:
  registration 1, ARAP 1 over the sequence ``[x, X(t_1), ..., X(1)]``, geodesic distortion 50). Its terms
  receive ``verts_x_deformed`` (X(1)), ``verts_y``, ``pi_x_to_y``, ``pi_y_to_x``, ``frames``, ``edges``,
  ``edge_weights`` and, while the geodesic term is active, ``dist_x`` and ``dist_y``;
* TensorBoard drawing of the first validation pair's sequence: :func:`shapecorr.viz.interpolation.log_interpolation`;
* schedules (published: T 0 -> 1 -> 3 -> 7 and lambda_geo 50 -> 0, NeuroMorph code) are Lightning callbacks
  (:mod:`shapecorr.models.schedules`) configured next to the model; the module only exposes the settable
  :attr:`NeuroMorph.n_intermediate` and the loss weights.

Training data (one pair per step, gradients accumulated by the Trainer, published 16 pairs): each shape is
remeshed to a resolution drawn from its fixed pool and both are rotated by one random angle about the up axis
(:class:`~shapecorr.data.augmentation.PairAugmenter`, ``augment`` options; remeshes and geodesic matrices are
cached with the shape cache, geodesics only looked up in the epochs where the geodesic term has a non-zero
weight). The augmentation runs on the data side: in its ``setup`` hook the module hands the data module an
:class:`~shapecorr.data.augmentation.AugmentedPairDataset` wrapper (DataLoader workers remesh in parallel);
a plain :class:`~shapecorr.data.datasets.PairSample` batch (another loader, direct calls) is augmented in
``training_step`` with the same draws. The draws are seeded by ``(seed, epoch, batch index)``, so a resumed
run sees the augmentations of the uninterrupted one. Without remeshing, shapes larger than ``query_resolution``
are trained on their working-resolution remesh (the original trained on 2000-vertex FAUST_r meshes).

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

Deviations from the original code (docs/neuromorph.md §8): global max-pool over vertices
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
geodesic term alone fits it. ``map_gradient="geodesic"`` lets only the geodesic term train the maps (docs/benchmarks.md,
"NeuroMorph: why map_gradient exists").
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch

from shapecorr.data.augmentation import (
    AugmentationConfig,
    AugmentedPair,
    AugmentedPairDataset,
    PairAugmenter,
    Remeshed,
    cached_remesh,
    remeshed_sample,
    step_rng,
)
from shapecorr.data.cache import ShapeCache, content_hash, default_cache_root
from shapecorr.errors import ConfigError, NumericalError
from shapecorr.eval.matcher_run import UNIT_TIME, check_interp_times, unit_time_index
from shapecorr.eval.scoring import score_deformation
from shapecorr.geometry.mesh_graph import undirected_edges
from shapecorr.losses.weighted import WeightedLoss
from shapecorr.matching.result import MatchResult
from shapecorr.matching.softmax import (
    DEFAULT_CHUNK_SIZE,
    DEFAULT_SIGMA,
    hard_maps,
    softmax_soft_maps,
)
from shapecorr.models.base import CorrespondenceModule, adam, build_optimizers
from shapecorr.models.schedules import LossWeightSchedule
from shapecorr.nn.backbone import Backbone
from shapecorr.nn.edgeconv import DEFAULT_HIDDEN, DEFAULT_N_BLOCKS
from shapecorr.nn.edgeconv_backbone import DEFAULT_POOL, EdgeConvBackbone
from shapecorr.nn.neuromorph import NeuroMorphInterpolator, interpolation_times
from shapecorr.viz.interpolation import log_interpolation

#: NeuroMorph optimizer: Adam, learning rate 1e-4, no scheduler (NeuroMorph paper, CVPR 2021, and its released
#: training script); configs/model/optimizer/adam.yaml.
DEFAULT_LR = 1e-4
#: ARAP edge weight per face containing the edge. The original lists each face edge once (interior edges twice);
#: with the both-sides energy (two residuals per listed edge) 0.5 gives the original's number of residuals.
DEFAULT_ARAP_EDGE_WEIGHT_SCALE = 0.5
#: Name of the loss term needing geodesic matrices (their lookup is skipped while its weight is 0).
DEFAULT_GEO_TERM = "geo"
#: Frames returned by ``match`` (project choice: quarter steps from x to its image on y).
DEFAULT_INTERP_TIMES = (0.0, 0.25, 0.5, 0.75, 1.0)
#: Options of the interpolation network (NeuroMorph code: ResnetECPos, hidden 128, 5 EdgeConv layers; pool "global"
#: and residual_init "zero" are our decisions, the original's are "channel" and "original").
DEFAULT_INTERPOLATION_NET = {"hidden_channels": DEFAULT_HIDDEN, "n_blocks": DEFAULT_N_BLOCKS, "pool": DEFAULT_POOL,
                        "residual_init": "zero"}
#: Query remeshes kept in memory (a validation set's worth; a few hundred kB each).
QUERY_REMESH_LRU_SIZE = 64
#: Which loss terms train the soft maps (and so the feature net), see :attr:`NeuroMorph.map_gradient`.
MAP_GRADIENT_MODES = ("all", "geodesic")


class _NonZeroAt:
    """``epoch -> schedule(epoch) != 0`` of a loss-weight schedule (picklable, for data workers)."""

    def __init__(self, schedule):
        self.schedule = schedule

    def __call__(self, epoch: int) -> bool:
        return float(self.schedule(epoch)) != 0.0


def _check_times(times, device: torch.device) -> torch.Tensor:
    t = torch.as_tensor(times, dtype=torch.float32).to(device)
    if t.ndim != 1 or t.numel() == 0:
        raise ConfigError(f"interpolation times must be a non-empty 1-D sequence, got shape {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise ConfigError(f"interpolation times must be finite, got {t.tolist()}")
    return t


class NeuroMorph(CorrespondenceModule):
    """NeuroMorph: feature backbone + softmax correspondence + interpolator (see the module docstring).

    Parameters
    ----------
    backbone : Backbone, optional
        The feature extractor (Hydra: the ``model/backbone`` node, published ``edgeconv``); default
        :class:`EdgeConvBackbone` with the published options.
    loss : WeightedLoss, optional
        The training loss (``model.loss``, ``configs/model/loss/neuromorph.yaml``); needed for training only.
    interpolation_net : mapping, optional
        Options of the interpolation network :class:`~shapecorr.nn.neuromorph.NeuroMorphInterpolator`:
        ``hidden_channels``, ``n_blocks``, ``pool``, ``residual_init`` (published 128, 5; pool "global" and
        residual_init "zero" our decisions, "channel" / "original" the original code's, see
        :class:`~shapecorr.nn.edgeconv.ResnetBlockFC`).
    optimizer, scheduler
        Optimizer / LR-scheduler factories (``model/optimizer``, ``model/scheduler`` nodes, ``_partial_``);
        default Adam 1e-4 (published), no scheduler.
    sigma : float
        Softmax inverse temperature (published 100).
    n_intermediate : int
        Intermediate time steps T used in training now (published schedule 0, 1, 3, 7; set by a callback).
    interp_times : sequence of float
        Frames returned by :meth:`match` (strictly increasing; ``evaluate.py interp_times=`` overrides them).
    map_gradient : {"all", "geodesic"}
        Which loss terms train the soft maps (and through them the feature net). "all" (published): every
        term, including registration and ARAP through the interpolator's input ``Pi y``. "geodesic": only the
        geodesic-distortion term; registration and ARAP see the maps and ``Pi y`` detached and train the
        interpolator only (with the geodesic weight at 0 the feature net then gets no gradient). Settable by
        an :class:`~shapecorr.models.schedules.EpochSchedule` (``target: map_gradient``). See docs/benchmarks.md,
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
        backbone: Backbone | None = None,
        loss: WeightedLoss | None = None,
        interpolation_net: Mapping[str, Any] | None = None,
        optimizer=None,
        scheduler=None,
        sigma: float = DEFAULT_SIGMA,
        n_intermediate: int = 0,
        interp_times: Sequence[float] = DEFAULT_INTERP_TIMES,
        map_gradient: str = "all",
        arap_edge_weight_scale: float | None = DEFAULT_ARAP_EDGE_WEIGHT_SCALE,
        geo_term: str = DEFAULT_GEO_TERM,
        augment: Mapping[str, Any] | None = None,
        query_resolution: int | None = None,
        geodesics: str = "heat",
        match_chunk_size: int = DEFAULT_CHUNK_SIZE,
        cache_dir: str | None = None,
        seed: int = 0,
    ):
        super().__init__()
        if backbone is None:
            backbone = EdgeConvBackbone()
        if not isinstance(backbone, Backbone):
            raise ConfigError(f"neuromorph: model.backbone must be a Backbone module (a _target_ node of "
                              f"configs/model/backbone/), got {type(backbone).__name__}")
        net = {**DEFAULT_INTERPOLATION_NET, **dict(interpolation_net or {})}
        bad = sorted(set(net) - set(DEFAULT_INTERPOLATION_NET))
        if bad:
            raise ConfigError(f"neuromorph: unknown model.interpolation_net option(s) {bad}; allowed: "
                              f"{sorted(DEFAULT_INTERPOLATION_NET)}")
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
        self.feature_net = backbone
        self._backbone_takes_edges = "edges" in inspect.signature(backbone.forward).parameters
        # the interpolation network (model.interpolation_net options; parameters named interpolator.*)
        self.interpolator = NeuroMorphInterpolator(int(net["hidden_channels"]), int(net["n_blocks"]),
                                                   str(net["pool"]), str(net["residual_init"]))
        self.loss = loss
        self.optimizer = adam(DEFAULT_LR) if optimizer is None else optimizer
        self.scheduler = scheduler
        self.sigma = float(sigma)
        self.n_intermediate = n_intermediate
        self.interp_times = check_interp_times(list(interp_times))
        self.map_gradient = map_gradient
        self.arap_edge_weight_scale = None if arap_edge_weight_scale is None else float(arap_edge_weight_scale)
        self.geo_term = str(geo_term)
        self.augment = AugmentationConfig.from_options(augment)
        self.query_resolution = None if query_resolution is None else int(query_resolution)
        needs = dict(getattr(backbone, "required_operators", None) or {})
        if needs:  # training pairs are augmented copies (rotated, remeshed), queries may run on remeshes
            raise ConfigError(f"neuromorph: the {type(backbone).__name__} backbone reads per-shape operators "
                              f"{sorted(needs)}, which NeuroMorph's augmented and remeshed shapes do not carry; use "
                              "a backbone that needs none (model/backbone=edgeconv)")
        self.geodesics = str(geodesics)
        self.match_chunk_size = int(match_chunk_size)
        self.cache_dir = cache_dir
        self.seed = int(seed)
        self._cache: ShapeCache | None = None
        self._augmenter: PairAugmenter | None = None
        self._query_remeshes: OrderedDict[tuple[str, int], Remeshed] = OrderedDict()
        self._first_val_sequence = None

    @property
    def backbone(self) -> Backbone:
        """The feature extractor (stored as ``feature_net``: the parameter names in checkpoints)."""
        return self.feature_net

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
        """Current weight of the geodesic-distortion term (0 when the loss has no such term, or no loss)."""
        return 0.0 if self.loss is None else float(self.loss.weights.get(self.geo_term, 0.0))

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
        """The pair augmenter, built on first use from the augment options and the shape cache."""
        if self._augmenter is None:
            self._augmenter = PairAugmenter(self.augment, self.shape_cache(), max_vertices=self.query_resolution,
                                            seed=self.seed, geodesics=self.geodesics)
        return self._augmenter

    def step_rng(self, batch_idx: int) -> np.random.Generator:
        """Generator of one training step's augmentation, seeded by (seed, epoch, batch index)."""
        return step_rng(self.seed, int(self.current_epoch), int(batch_idx))

    def geodesic_epochs(self):
        """Whether a training epoch needs geodesic matrices: a picklable ``epoch -> bool`` for data workers.

        From the trainer's :class:`~shapecorr.models.schedules.LossWeightSchedule` of the geodesic term when
        there is one (published: epochs 0..299), else the term's current weight (a constant).
        """
        for callback in getattr(self._trainer, "callbacks", None) or []:
            if isinstance(callback, LossWeightSchedule) and callback.term == self.geo_term \
                    and callback.loss_attribute == "loss":
                return _NonZeroAt(callback.schedule)
        return self.lambda_geo != 0.0

    def setup(self, stage: str) -> None:
        """Before fitting: serve the training pairs augmented on the data side (in DataLoader workers)."""
        datamodule = getattr(self._trainer, "datamodule", None)
        if stage == "fit" and callable(getattr(datamodule, "augment_training", None)):
            datamodule.augment_training(functools.partial(AugmentedPairDataset, augmenter=self.augmenter,
                                                          geodesics=self.geodesic_epochs()))

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
        feat_x, feat_y = self.features(x, edges_x), self.features(y)
        pi, pi_inv = softmax_soft_maps(feat_x, feat_y, self.sigma, normalize=False)
        target = pi @ y.verts
        if self.map_gradient == "geodesic":
            target, pi_inv = target.detach(), pi_inv.detach()
        frames = self.interpolator.interpolate(x.verts, target, edges_x, times)
        return {"pi_x_to_y": pi, "pi_y_to_x": pi_inv, "soft_target": target, "frames": frames, "edges": edges_x,
                "edge_counts": counts_x}

    def features(self, sample, edges: torch.Tensor | None = None) -> torch.Tensor:
        """Backbone features ``(n, C)`` of a sample.

        Its undirected ``edges (E, 2)``, when the caller has them, go to a backbone that takes them
        (:class:`EdgeConvBackbone`: saves recomputing them).
        """
        if edges is not None and self._backbone_takes_edges:
            return self.feature_net(sample, edges=edges)
        return self.feature_net(sample)

    # -- training -----------------------------------------------------------------------------------------
    def training_step(self, batch, batch_idx: int) -> torch.Tensor:
        """Loss of one (augmented) training pair: interpolate x towards y and log the loss terms and schedules.

        Raises NumericalError when the loss is not finite, ConfigError without a loss.
        """
        if self.loss is None:
            raise ConfigError("neuromorph: no loss to train with (model.loss, configs/model/loss/)")
        use_geo = self.lambda_geo != 0.0
        if isinstance(batch, AugmentedPair):  # augmented on the data side (AugmentedPairDataset)
            aug = batch
        else:  # a plain pair (another loader, direct calls): the same draws here
            aug = self.augmenter(batch, self.step_rng(batch_idx), geodesics=use_geo)
        if use_geo and (aug.dist_x is None or aug.dist_y is None):
            # the data side did not expect the geodesic term in this epoch (weights changed by hand): look them up
            x_cpu, y_cpu = aug.pair.x.to("cpu"), aug.pair.y.to("cpu")
            aug = dataclasses.replace(aug, dist_x=self.augmenter.distances(x_cpu),
                                      dist_y=self.augmenter.distances(y_cpu))
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
        """Optimizer (and scheduler) from the ``optimizer`` / ``scheduler`` factories."""
        return build_optimizers(self.parameters(), self.optimizer, self.scheduler)

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
        feat_x, feat_y = self.features(wx, edges_x), self.features(wy)
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
        """Point-to-point maps x -> y and y -> x, with the interpolation frames at ``interp_times``.

        See :meth:`interpolate`.
        """
        return self.interpolate(x, y, torch.tensor(self.interp_times))

    # -- validation / test --------------------------------------------------------------------------------
    def _score_interpolation(self, batch, result: MatchResult, split: str) -> None:
        """Log Chamfer distance of X(1) to y and conformal distortion of the frames with 0 <= t <= 1.

        Times are matched with the evaluation protocol's tolerance (:func:`~shapecorr.eval.matcher_run.unit_time_index`,
        :func:`~shapecorr.eval.scoring.score_deformation`); without a frame at t = 1 it is computed here.
        """
        frames, times = result.deformation, result.times.detach().cpu()
        if unit_time_index(times) is None:
            extra = self.interpolate(batch.x, batch.y, torch.tensor([UNIT_TIME]))
            frames = torch.cat((frames, extra.deformation.to(frames)))
            times = torch.cat((times, extra.times.detach().cpu()))
        scores = score_deformation(frames, batch.x, batch.y, times=times)
        log = dict(batch_size=1, on_epoch=True, on_step=False, sync_dist=True)
        for key in ("chamfer", "chamfer_one_sided", "deformation_conformal_distortion", "volume_change"):
            if scores.get(key) is not None:
                self.log(f"{split}/{key}", float(scores[key]), **log)

    def validation_step(self, batch, batch_idx: int):
        """Score the validation pair's map and interpolation; keep the first pair's sequence for logging."""
        out = self._evaluate_pair(batch, "val")
        result = out["result"]
        if batch_idx == 0:
            self._first_val_pair = (batch, result.p2p)
            self._first_val_sequence = (batch, result.cpu())
        self._score_interpolation(batch, result, "val")

    def test_step(self, batch, batch_idx: int):
        """Score the test pair's map and interpolation."""
        out = self._evaluate_pair(batch, "test")
        self._score_interpolation(batch, out["result"], "test")

    def on_validation_epoch_end(self) -> None:
        """Log as the base model does, then (rank 0) the first validation pair's interpolation."""
        super().on_validation_epoch_end()
        if self.trainer.sanity_checking or self.global_rank != 0 or self._first_val_sequence is None:
            return
        batch, result = self._first_val_sequence
        log_interpolation(self.logger, result.deformation, batch.x.faces, result.times, batch.y.verts, batch.y.faces,
                          step=self.global_step)
