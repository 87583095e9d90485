"""Plumbing shared by every learned correspondence model (LightningModule).

A concrete model implements ``training_step`` (features -> matching -> loss -> ``self.log``) and ``match``
(the matcher protocol of :mod:`shapecorr.matching.result`). This base class adds what every model needs:

- validation and test steps that run ``match`` on the pair, score the map with the evaluation protocol
  (:func:`shapecorr.eval.scoring.score_map`: geodesic error / sqrt(area) against the ground truth) and log
  ``val/geodesic_error`` (``test/geodesic_error``), the conformal distortion and the time per pair, and while
  fitting ``val/pairs_seen`` (training pairs seen so far: the x-axis of learning curves);
- at the end of a validation epoch a PCK-curve figure and the colored correspondence of the first validation
  pair (TensorBoard meshes + a headless render), when the logger is TensorBoard;
- ``required_operators``: the per-shape operators the model needs, an operator request
  ``{name: {param: value}}`` (:mod:`shapecorr.data.operators`), merged into the data module's operators by
  ``train.py`` / ``evaluate.py``;
- optimizer / LR-scheduler factories (``model.optimizer`` / ``model.scheduler`` ``_partial_: true`` nodes):
  :func:`build_optimizers`, :func:`adam`;
- the model's **recipe** (:attr:`CorrespondenceModule.recipe`): the resolved ``model`` config node it was built
  from, written into every checkpoint under :data:`RECIPE_KEY` (:mod:`shapecorr.models.recipe` builds models
  from it).

Geodesic matrices come from the data module's shape cache; a small in-memory LRU keeps the few shapes of the
validation set.
"""

from __future__ import annotations

import functools
import time
from collections import OrderedDict
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np
import pytorch_lightning as pl
import torch

from shapecorr.errors import ConfigError
from shapecorr.eval import metrics
from shapecorr.eval.scoring import score_map
from shapecorr.matching.result import MatchResult
from shapecorr.viz.tensorboard import log_correspondence_meshes, log_pck_figure

#: Geodesic matrices kept in memory by a model during validation/test (100 MB each at 5k vertices).
GEODESIC_LRU_SIZE = 8


#: Checkpoint entry holding the model's recipe (the resolved ``model`` config node, plain containers).
RECIPE_KEY = "model_recipe"

#: An optimizer factory: ``hydra.utils.instantiate`` of a ``_partial_: true`` node, called with the parameters.
OptimizerFactory = Callable[[Iterable[torch.nn.Parameter]], torch.optim.Optimizer]
#: An LR-scheduler factory (``_partial_: true`` node), called with the optimizer.
SchedulerFactory = Callable[[torch.optim.Optimizer], Any]


def adam(lr: float) -> OptimizerFactory:
    """Adam with learning rate ``lr``: the optimizer factory used when a model gets no ``optimizer`` node."""
    if not lr > 0:
        raise ConfigError(f"optimizer: lr must be positive, got {lr}")
    return functools.partial(torch.optim.Adam, lr=float(lr))


def build_optimizers(
    parameters: Iterable[torch.nn.Parameter],
    optimizer: OptimizerFactory,
    scheduler: SchedulerFactory | None = None,
    scheduler_interval: str = "epoch",
):
    """What ``configure_optimizers`` returns for a model with the given factories.

    Parameters
    ----------
    parameters
        The trainable parameters (those with ``requires_grad``; an empty list returns ``None``: nothing to learn).
    optimizer
        Optimizer factory, e.g. the ``model.optimizer`` node
        ``{_target_: torch.optim.Adam, _partial_: true, lr: 1e-4}``.
    scheduler
        Optional LR-scheduler factory (``model.scheduler`` node), stepped every ``scheduler_interval``
        (``"epoch"`` or ``"step"``).
    """
    params = [p for p in parameters if p.requires_grad]
    if not params:
        return None
    if not callable(optimizer):
        raise ConfigError(f"model.optimizer must be an optimizer factory (a _partial_: true node), got {optimizer!r}")
    opt = optimizer(params)
    if scheduler is None:
        return opt
    if scheduler_interval not in ("epoch", "step"):
        raise ConfigError(f"model.scheduler_interval must be 'epoch' or 'step', got {scheduler_interval!r}")
    return {"optimizer": opt, "lr_scheduler": {"scheduler": scheduler(opt), "interval": scheduler_interval}}


class CorrespondenceModule(pl.LightningModule):
    """Base class of the learned models; see the module docstring."""

    #: Operator request ``{name: {param: value}}`` the model needs from the data (overridden by subclasses).
    required_operators: dict = {}
    #: Options that only initialize the weights (e.g. a file of pretrained weights): the recipe stored in a
    #: checkpoint sets them to null, since the checkpoint holds the weights themselves.
    weight_options: tuple[str, ...] = ()

    def __init__(self):
        super().__init__()
        #: The resolved ``model`` config node this module was built from (set by
        #: :func:`shapecorr.models.recipe.build_model`); None for a module built in code.
        self.recipe: dict | None = None
        #: Where the weights came from (a checkpoint or a pretrained file); None for a fresh initialization.
        self.trained_from: str | None = None
        self._geodesics: OrderedDict[tuple[str, str], np.ndarray] = OrderedDict()
        self._eval_errors: dict[str, list[np.ndarray]] = {"val": [], "test": []}
        self._first_val_pair = None

    # -- to implement --------------------------------------------------------------------------------------
    def match(self, x, y) -> MatchResult:  # pragma: no cover - abstract
        """Point-to-point map x -> y (see :mod:`shapecorr.matching.result`)."""
        raise NotImplementedError

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        """Write the recipe into the checkpoint (:data:`RECIPE_KEY`), the weight-only options set to null."""
        if self.recipe is not None:
            checkpoint[RECIPE_KEY] = {**self.recipe, **{k: None for k in self.weight_options if k in self.recipe}}

    # -- evaluation ----------------------------------------------------------------------------------------
    def _geodesic_matrix(self, split: str, sample) -> np.ndarray:
        key = (split, sample.name)
        if key in self._geodesics:
            self._geodesics.move_to_end(key)
            return self._geodesics[key]
        shapes = self.trainer.datamodule.shapes(split)
        dist = shapes.ground_truth_geodesics(shapes.index(sample.name))
        self._geodesics[key] = dist
        while len(self._geodesics) > GEODESIC_LRU_SIZE:
            self._geodesics.popitem(last=False)
        return dist

    def _evaluate_pair(self, batch, split: str) -> dict:
        start = time.perf_counter()
        result = self.match(batch.x, batch.y)
        seconds = time.perf_counter() - start
        scores = score_map(result.p2p, batch.x, batch.y, self._geodesic_matrix(split, batch.y))
        self._eval_errors[split].append(scores["errors"])
        log = dict(batch_size=1, on_epoch=True, on_step=False, sync_dist=True)
        self.log(f"{split}/geodesic_error", float(np.mean(scores["errors"])), prog_bar=True, **log)
        self.log(f"{split}/conformal_distortion", float(scores["conformal_distortion"]), **log)
        self.log(f"{split}/seconds_per_pair", seconds, **log)
        if scores["errors_sym"] is not None:
            self.log(f"{split}/geodesic_error_sym", float(np.mean(scores["errors_sym"])), **log)
        return {"result": result, **scores}

    def validation_step(self, batch, batch_idx: int):
        """Score the validation pair's map (logged); keep the first pair for the figure."""
        out = self._evaluate_pair(batch, "val")
        if batch_idx == 0:
            self._first_val_pair = (batch, out["result"].p2p)

    def test_step(self, batch, batch_idx: int):
        """Score the test pair's map (logged)."""
        self._evaluate_pair(batch, "test")

    def on_validation_epoch_start(self) -> None:
        """Reset the validation errors of the epoch."""
        self._eval_errors["val"] = []

    def on_test_epoch_start(self) -> None:
        """Reset the test errors of the epoch."""
        self._eval_errors["test"] = []

    def on_validation_epoch_end(self) -> None:
        """Log the pairs seen (when fitting), the PCK AUC of the validation errors, and (rank 0) the figures."""
        trainer = self._trainer
        if trainer is not None and trainer.state.fn == "fit" and not trainer.sanity_checking:
            # x-axis of learning curves: training pairs (batches x ranks) seen so far, exact also mid-epoch and
            # with gradient accumulation (the logged step counts optimizer steps)
            seen = trainer.fit_loop.epoch_loop.batch_progress.total.completed * trainer.world_size
            self.log("val/pairs_seen", float(seen), batch_size=1)
        errors = self._eval_errors["val"]
        if not errors or self.trainer.sanity_checking:
            return
        all_errors = np.concatenate(errors)
        t, frac = metrics.pck_curve(all_errors)
        self.log("val/pck_auc", metrics.pck_auc(t, frac), sync_dist=True)
        if self.global_rank == 0 and self.logger is not None:
            log_pck_figure(self.logger, all_errors, step=self.global_step)
            if self._first_val_pair is not None:
                batch, p2p = self._first_val_pair
                x, y = batch.x.shape, batch.y.shape
                log_correspondence_meshes(self.logger, x.verts, x.faces, y.verts, y.faces, p2p, step=self.global_step)

    def test_errors(self) -> np.ndarray:
        """Per-reference-point errors of the last test run, concatenated over pairs."""
        errors = self._eval_errors["test"]
        return np.concatenate(errors) if errors else np.zeros(0)
