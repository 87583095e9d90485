"""Deep Shells as a LightningModule.

A backbone (spectral filter bank on SHOT) -> hierarchical OT layer -> loss of the level energies.

Eisenberger, Toker, Leal-Taixé, Cremers, NeurIPS 2020 (docs/deep_shells.md). The module is thin: the features come
from the injected backbone (:mod:`shapecorr.nn.backbone`; ``configs/model/backbone/``: ``spectral_conv`` =
:class:`~shapecorr.nn.spectral_conv.SpectralBackbone`, the published network; ``identity`` =
:class:`~shapecorr.nn.identity.IdentityBackbone`, the "no learning" ablation), the matching and the level energies from
:func:`~shapecorr.matching.deep_shells.deep_shells_layer`, test-time maps from
:func:`~shapecorr.matching.deep_shells.deep_shells_query`; the optimizer (and optional LR scheduler) are
``_partial_`` nodes (``configs/model/optimizer/adam.yaml``: Adam 1e-4, published).

Training step, for one pair: ``num_samples`` vertices per shape drawn uniformly with replacement (published:
2000), features evaluated at those rows only, the OT layer over the shell schedule ``layer.k_array``, then the loss of
the level energies. The sample generator is seeded from ``(seed, epoch, batch index)``, so a
run resumed from a checkpoint draws exactly the samples the uninterrupted run would have drawn (the global
step is not used: with gradient accumulation many batches share one).

Published weights: ``pretrained=PATH`` initializes the spectral backbone from the original's released checkpoint
(``ckpt_*.pth``, :func:`~shapecorr.nn.spectral_conv.load_original_deep_shells_weights`) or from one of our
Lightning checkpoints (``.ckpt``: its ``backbone.*`` weights); ``configs/model/deep_shells_published.yaml`` takes the
path from ``$SHAPECORR_DEEP_SHELLS_WEIGHTS`` so that ``evaluate.py model=deep_shells_published`` needs no checkpoint.
The recipe a checkpoint stores has ``pretrained: null`` (the checkpoint holds the weights themselves, and must
load after the file has moved); the path is recorded under :data:`PRETRAINED_CHECKPOINT_KEY` (provenance).

Loss: a :class:`~shapecorr.losses.weighted.WeightedLoss` (``model.loss``, ``configs/model/loss/deep_shells.yaml``)
whose terms receive ``level_energies (L,)``; published: the term ``shells``, the plain mean of the level energies
(:func:`~shapecorr.losses.shells.level_energy_loss`). Subclasses add inputs for further terms
(:meth:`DeepShells.loss_inputs`; G-MSM's graph term).

``match``: features at full resolution, the coarse OT level and the axiomatic refinement (``layer.refine_*``,
published 40 levels from 6 to 499). During training, validation uses a cheaper refinement with
``val_refine_levels`` log-spaced levels over the same range (``None``: the full schedule; ``0``: no refinement),
so that a validation pass costs seconds rather than minutes; ``evaluate.py`` and ``trainer.test`` always use the
full schedule (``refine=False`` disables it everywhere).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from shapecorr.data.operators import merge_requests
from shapecorr.errors import ConfigError, NumericalError
from shapecorr.geometry.finiteness import all_finite
from shapecorr.geometry.spectral_shape import make_spectral_shape
from shapecorr.matching.deep_shells import (
    DeepShellsConfig,
    deep_shells_layer,
    deep_shells_query,
    random_samples,
    shell_size,
)
from shapecorr.matching.result import MatchResult
from shapecorr.losses.weighted import WeightedLoss
from shapecorr.models.base import CorrespondenceModule, adam, build_optimizers
from shapecorr.nn.spectral_conv import (
    SpectralBackbone,
    SpectralFilterBank,
    load_original_deep_shells_weights,
)

#: Deep Shells optimizer: Adam with learning rate 1e-4 (Eisenberger et al. 2020, §5; the authors' train.py).
DEFAULT_LR = 1e-4
#: Key of our Lightning checkpoints whose ``backbone.*`` entries ``pretrained`` loads.
LIGHTNING_STATE_KEY = "state_dict"
#: Prefix of the filter-bank parameters in a DeepShells state dict.
BACKBONE_PREFIX = "backbone."
#: Extra checkpoint entry recording the file the weights were initialized from (provenance only).
PRETRAINED_CHECKPOINT_KEY = "deep_shells_pretrained"

def _as_config(layer: Mapping[str, Any] | DeepShellsConfig | None, num_samples: int) -> DeepShellsConfig:
    if isinstance(layer, DeepShellsConfig):
        return replace(layer, num_samples=int(num_samples))
    values = dict(layer or {})
    if "k_array" in values:
        values["k_array"] = tuple(int(k) for k in values["k_array"])
    try:
        return DeepShellsConfig(**{**values, "num_samples": int(num_samples)})
    except TypeError as err:
        raise ConfigError(f"deep_shells: invalid layer option: {err}") from None


class DeepShells(CorrespondenceModule):
    """Deep Shells: backbone features + differentiable smooth-shells OT (see the module docstring).

    Parameters
    ----------
    backbone : nn.Module, optional
        The feature extractor (a :class:`~shapecorr.nn.backbone.Backbone`: ``forward(sample, rows)``,
        ``required_operators``; Hydra builds it from ``model/backbone``). Default: the published
        :class:`~shapecorr.nn.spectral_conv.SpectralBackbone`.
    loss : WeightedLoss, optional
        The training loss (``model.loss``); its terms receive ``level_energies`` and :meth:`loss_inputs`. Needed
        for training only.
    num_samples : int
        Vertices drawn per shape and training step (published 2000, with replacement).
    optimizer : callable, optional
        Optimizer factory (``model.optimizer``, a ``_partial_: true`` node); default Adam 1e-4 (published).
    scheduler : callable, optional
        LR-scheduler factory (``model.scheduler``); default none (published: constant rate).
    scheduler_interval : {"epoch", "step"}
        When the scheduler steps.
    layer : mapping
        :class:`~shapecorr.matching.deep_shells.DeepShellsConfig` fields (shell schedule, Sinkhorn, refinement).
    refine : bool
        Run the axiomatic refinement in ``match`` (published: yes).
    val_refine_levels : int, optional
        Refinement levels during validation while fitting (cheap mode); ``None`` = the full schedule.
    seed : int
        Base seed of the per-step vertex sampling.
    pretrained : path-like, optional
        Initial backbone weights: the original's released ``.pth`` or one of our ``.ckpt`` files (see the module
        docstring); needs the spectral backbone with matching sizes. Not part of the recipe a checkpoint stores
        (it holds the weights).
    """

    weight_options = ("pretrained",)

    def __init__(
        self,
        backbone: nn.Module | None = None,
        loss: WeightedLoss | None = None,
        num_samples: int = DeepShellsConfig.num_samples,
        optimizer: Any = None,
        scheduler: Any = None,
        scheduler_interval: str = "epoch",
        layer: Mapping[str, Any] | None = None,
        refine: bool = True,
        val_refine_levels: int | None = None,
        seed: int = 0,
        pretrained: str | PathLike | None = None,
    ):
        super().__init__()
        backbone = SpectralBackbone() if backbone is None else backbone
        if not isinstance(backbone, nn.Module):
            raise ConfigError(f"deep_shells: model.backbone must be a torch module (a _target_ node of "
                              f"configs/model/backbone/), got {type(backbone).__name__}")
        if loss is not None and not isinstance(loss, WeightedLoss):
            raise ConfigError(f"deep_shells: model.loss must be a WeightedLoss, got {type(loss).__name__}")
        if optimizer is not None and not callable(optimizer):
            raise ConfigError(f"deep_shells: model.optimizer must be a _partial_: true node, got {optimizer!r}")
        self.optimizer = adam(DEFAULT_LR) if optimizer is None else optimizer
        self.scheduler = scheduler
        if self.lr is not None and not self.lr > 0:
            raise ConfigError(f"deep_shells: model.optimizer.lr must be positive, got {self.lr}")
        if scheduler_interval not in ("epoch", "step"):
            raise ConfigError(f"deep_shells: scheduler_interval must be 'epoch' or 'step', got {scheduler_interval!r}")
        self.scheduler_interval = scheduler_interval
        if val_refine_levels is not None and int(val_refine_levels) < 0:
            raise ConfigError(f"deep_shells: val_refine_levels must be >= 0 or null, got {val_refine_levels}")
        self.refine = bool(refine)
        self.val_refine_levels = None if val_refine_levels is None else int(val_refine_levels)
        self.seed = int(seed)
        self.config = _as_config(layer, num_samples)
        self.backbone = backbone
        self.loss = loss
        self._validating_during_fit = False
        self.pretrained = None
        if pretrained is not None:
            self.load_pretrained(pretrained)

    @property
    def lr(self) -> float | None:
        """Learning rate of the optimizer factory (None if it has none)."""
        keywords = getattr(self.optimizer, "keywords", {}) or {}
        return None if "lr" not in keywords else float(keywords["lr"])

    # -- published or trained weights -------------------------------------------------------------------------
    def load_pretrained(self, path: str | PathLike) -> None:
        """Load the filter-bank weights from the original's ``.pth`` or one of our Lightning ``.ckpt`` files.

        The format is recognized by content: a dict with ``state_dict`` is ours (its ``backbone.*`` entries, which
        must fit this module's sizes exactly), anything else goes to
        :func:`~shapecorr.nn.spectral_conv.load_original_deep_shells_weights` (which checks the sizes, the filter
        scale and the eigenpair count against this module).

        Raises
        ------
        ConfigError
            No spectral backbone, missing or unreadable file, not a Deep Shells checkpoint, or weights that do not
            fit (the message names the file).
        """
        path = Path(path).expanduser()
        if not isinstance(self.backbone, SpectralFilterBank):
            raise ConfigError(f"deep_shells: pretrained weights need the spectral_conv backbone (model/backbone="
                              f"spectral_conv), got {type(self.backbone).__name__}", path=path)
        if not path.is_file():
            raise ConfigError("deep_shells: pretrained weights file not found (model.pretrained; for "
                              "model=deep_shells_published set SHAPECORR_DEEP_SHELLS_WEIGHTS)", path=path)
        try:
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # noqa: BLE001 - torch raises several unrelated types for unreadable/unsafe files
            raise ConfigError(f"deep_shells: not a readable torch checkpoint ({type(exc).__name__}: {exc})",
                              path=path) from None
        if isinstance(ckpt, dict) and LIGHTNING_STATE_KEY in ckpt:
            self._load_backbone_state(ckpt[LIGHTNING_STATE_KEY], path)
        else:
            load_original_deep_shells_weights(self.backbone, path)
        self.pretrained = self.trained_from = str(path)

    def _load_backbone_state(self, state: Any, path: Path) -> None:
        if not isinstance(state, dict):
            raise ConfigError("deep_shells: the checkpoint's state_dict is not a dict", path=path)
        backbone = {k[len(BACKBONE_PREFIX):]: v for k, v in state.items() if k.startswith(BACKBONE_PREFIX)}
        if not backbone:
            raise ConfigError("deep_shells: the checkpoint holds no filter-bank weights (no 'backbone.*' entries; "
                              "trained with model/backbone=identity?)", path=path)
        try:
            self.backbone.load_state_dict(backbone, strict=True)
        except RuntimeError as exc:  # missing/unexpected keys or shape mismatches, listed by torch
            raise ConfigError(f"deep_shells: the checkpoint's filter bank does not fit this model (check "
                              f"in/out_channels, hidden_channels, num_basis): {exc}", path=path) from None

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        """Write the recipe, and the path of the pretrained weights loaded (if any, provenance only)."""
        super().on_save_checkpoint(checkpoint)
        if self.pretrained is not None:
            checkpoint[PRETRAINED_CHECKPOINT_KEY] = self.pretrained

    # -- data requirements ------------------------------------------------------------------------------------
    @property
    def required_operators(self) -> dict:  # type: ignore[override]
        """The backbone's operators merged with the eigenpairs the shells need (training and refinement levels)."""
        cfg = self.config
        ks = list(cfg.k_array) + (list(cfg.refine_k_array) if self.refine else [])
        need = max(max(shell_size(k, cfg.smooth_x, cfg.sigmoid_inclusive),
                       shell_size(k, "sigmoid", cfg.sigmoid_inclusive)) for k in ks)
        return merge_requests(getattr(self.backbone, "required_operators", {}), {"eigenbasis": {"k": int(need)}})

    # -- building blocks --------------------------------------------------------------------------------------
    def features(self, sample, rows: torch.Tensor | None = None) -> torch.Tensor:
        """Per-vertex features of a :class:`~shapecorr.data.datasets.ShapeSample` (the backbone's).

        Returns
        -------
        (n, c) or (len(rows), c) float
        """
        return self.backbone(sample, rows)

    @staticmethod
    def spectral_shape(sample):
        """:class:`~shapecorr.geometry.spectral_shape.SpectralShape` of a ShapeSample (coordinates' coefficients)."""
        return make_spectral_shape(sample.verts, sample.faces, sample.evecs, sample.mass, name=sample.name)

    def sample_generator(self, batch_idx: int) -> torch.Generator:
        """CPU generator for the vertex samples of one training step, seeded by (seed, epoch, batch index)."""
        state = np.random.SeedSequence([self.seed, int(self.current_epoch), int(batch_idx)]).generate_state(1)
        return torch.Generator().manual_seed(int(state[0]))

    # -- training ---------------------------------------------------------------------------------------------
    def training_step(self, batch, batch_idx: int) -> torch.Tensor:
        """The loss (``model.loss``) of the Deep Shells layer's level energies on random vertex samples of the pair.

        Logs the loss, every loss term and the energy of each level; raises NumericalError when an energy is not
        finite, ConfigError without a loss.
        """
        if self.loss is None:
            raise ConfigError(f"{type(self).__name__}: no loss to train with (model.loss, "
                              "configs/model/loss/)")
        x, y = batch.x, batch.y
        gen = self.sample_generator(batch_idx)
        num = self.config.num_samples
        samples_x = random_samples(x.shape.n_verts, num, generator=gen).to(x.verts.device)
        samples_y = random_samples(y.shape.n_verts, num, generator=gen).to(y.verts.device)
        out = deep_shells_layer(self.features(x, samples_x), self.features(y, samples_y), self.spectral_shape(x),
                                self.spectral_shape(y), samples_x, samples_y, self.config,
                                return_plans=False)  # the loss needs the energies only: never form n x m plans
        energies = out.level_energies
        if not torch.isfinite(energies).all():
            raise NumericalError(f"{type(self).__name__}: level energies {energies.detach().cpu().tolist()} on "
                                 f"pair {batch.name}")
        total, values = self.loss(level_energies=energies, **self.loss_inputs(batch, out))
        log = dict(batch_size=1, on_step=True, on_epoch=True)
        self.log("train/loss", total, prog_bar=True, **log)
        for k, e in zip(self.config.k_array, energies):
            self.log(f"train/energy_k{k}", e, **log)
        for name, value in values.items():
            self.log(f"train/{name}", value, **log)
        return total

    def loss_inputs(self, batch, out) -> dict[str, torch.Tensor]:
        """Inputs of further loss terms for a training step, by name; none here.

        Subclasses (G-MSM's graph term) read the layer output ``out``
        (:class:`~shapecorr.matching.deep_shells.DeepShellsOutput`: the last level's ``fmap``, ``tau``).
        """
        return {}

    def configure_optimizers(self):
        """Optimizer (and scheduler) from the ``optimizer`` / ``scheduler`` factories."""
        # None for a backbone without parameters (the identity ablation has nothing to learn)
        return build_optimizers(self.parameters(), self.optimizer, self.scheduler, self.scheduler_interval)

    def on_fit_start(self) -> None:
        """Refuse to fit a backbone without trainable parameters (ConfigError)."""
        if not any(p.requires_grad for p in self.parameters()):
            raise ConfigError(f"deep_shells: the {type(self.backbone).__name__} backbone has no parameters to train; "
                              "evaluate it without training (evaluate.py model=deep_shells_ablation)")

    def validation_step(self, batch, batch_idx: int):
        """Score the validation pair, with the cheaper refinement (``val_refine_levels``) while fitting."""
        self._validating_during_fit = self._trainer is not None and self._trainer.state.fn == "fit"
        try:
            return super().validation_step(batch, batch_idx)
        finally:
            self._validating_during_fit = False

    # -- matching ---------------------------------------------------------------------------------------------
    def match_config(self) -> tuple[DeepShellsConfig, bool]:
        """The layer config and refine flag ``match`` uses now (cheap refinement in validation while fitting)."""
        if not self.refine:
            return self.config, False
        if self._validating_during_fit and self.val_refine_levels is not None:
            if self.val_refine_levels == 0:
                return self.config, False
            return replace(self.config, refine_levels=self.val_refine_levels), True
        return self.config, True

    def match(self, x, y) -> MatchResult:
        """Point-to-point map x -> y (and y -> x) by the Deep Shells test-time pipeline.

        Parameters
        ----------
        x, y : ShapeSample
            With ``evals``, ``evecs``, ``mass`` and the descriptor (see :attr:`required_operators`).

        Returns
        -------
        MatchResult
            ``p2p (n_x,)`` int64, ``p2p_inv (n_y,)`` int64.
        """
        config, refine = self.match_config()
        with torch.no_grad():
            fx, fy = self.features(x), self.features(y)
            if not all_finite(fx, fy):
                raise NumericalError(f"deep_shells: the features of {x.name} or {y.name} contain NaN or Inf")
            result = deep_shells_query(fx, fy, self.spectral_shape(x), self.spectral_shape(y), config, refine=refine)
        return MatchResult(p2p=result.map_x_to_y, p2p_inv=result.map_y_to_x)
