"""Epoch-driven, piecewise-constant schedules of a LightningModule's settings, as Lightning callbacks.

A schedule is a list of ``[epoch, value]`` milestones: the value holds from its epoch until the next
milestone. NeuroMorph's published schedule (its released code, SettingsFaust), for example, is::

    callbacks:
      neuromorph_T:                       # intermediate time steps of the interpolation
        _target_: shapecorr.models.schedules.EpochSchedule
        target: n_intermediate
        milestones: [[0, 0], [300, 1], [450, 3], [525, 7]]
      neuromorph_lambda_geo:              # weight of the geodesic-distortion loss term
        _target_: shapecorr.models.schedules.LossWeightSchedule
        term: geo
        milestones: [[0, 50.0], [300, 0.0]]

:class:`EpochSchedule` sets an attribute of the module (a dotted path, e.g. ``n_intermediate`` or
``interpolator.some_flag``); :class:`LossWeightSchedule` sets the weight of a term of the module's
:class:`~shapecorr.losses.weighted.WeightedLoss` (``module.loss.set_weight(term, value)``).

The value is a function of the epoch only, so there is no state to save: it is (re)applied when training
starts (after a checkpoint has been restored, so a resumed run continues with the value of its epoch) and at
the start of every training epoch. Changes take effect at epoch boundaries only.
"""

from __future__ import annotations

import bisect
import itertools
import operator
from collections.abc import Sequence
from typing import Any

import pytorch_lightning as pl

from shapecorr.errors import ConfigError


class PiecewiseConstant:
    """``value(epoch)`` of a milestone list ``[[epoch_0, v_0], [epoch_1, v_1], ...]``.

    Parameters
    ----------
    milestones : sequence of (epoch, value)
        Strictly increasing epochs, the first one 0 (the value from the start of training).
    """

    def __init__(self, milestones: Sequence[Sequence[Any]]):
        bad = ConfigError(f"schedule milestones must be a list of [epoch, value] pairs, got {milestones!r}")
        if isinstance(milestones, (str, bytes)):
            raise bad
        try:
            pairs = [tuple(m) for m in milestones]
        except TypeError:
            raise bad from None
        if any(isinstance(m, (str, bytes)) for m in milestones) or any(len(p) != 2 for p in pairs):
            raise bad
        if not pairs:
            raise ConfigError("a schedule needs at least one [epoch, value] milestone")
        epochs = []
        for epoch, _ in pairs:
            if isinstance(epoch, bool) or not isinstance(epoch, (int, float)) or not float(epoch).is_integer() \
                    or epoch < 0:
                raise ConfigError(f"schedule epochs must be non-negative integers, got {epoch!r}")
            epochs.append(int(epoch))
        if epochs[0] != 0:
            raise ConfigError(f"the first schedule milestone must be at epoch 0 (the initial value), got {epochs[0]}")
        if any(b <= a for a, b in itertools.pairwise(epochs)):
            raise ConfigError(f"schedule epochs must be strictly increasing, got {epochs}")
        self.epochs = epochs
        self.values = [v for _, v in pairs]

    def __call__(self, epoch: int) -> Any:
        """Value at ``epoch`` (that of the last milestone at or before it)."""
        if epoch < 0:
            raise ConfigError(f"epoch must be >= 0, got {epoch}")
        return self.values[bisect.bisect_right(self.epochs, int(epoch)) - 1]

    def __repr__(self) -> str:
        return f"PiecewiseConstant({[[e, v] for e, v in zip(self.epochs, self.values)]})"


class EpochSchedule(pl.Callback):
    """Set ``module.<target>`` to a piecewise-constant function of the epoch (see the module docstring).

    Parameters
    ----------
    target : str
        Attribute of the LightningModule, a dotted path for nested objects.
    milestones : sequence of (epoch, value)
        See :class:`PiecewiseConstant`.
    log_name : str, optional
        Also log the value at every epoch start under this name (e.g. ``schedule/T``).
    """

    def __init__(self, target: str, milestones: Sequence[Sequence[Any]], log_name: str | None = None):
        if not isinstance(target, str) or not target or any(not part for part in target.split(".")):
            raise ConfigError(f"schedule target must be an attribute name or dotted path, got {target!r}")
        self.target = target
        self.schedule = PiecewiseConstant(milestones)
        self.log_name = log_name

    @property
    def state_key(self) -> str:
        """Callback state key, distinct per target."""
        # Several schedules of one class may coexist in a Trainer: make their keys distinct.
        return self._generate_state_key(target=self.target)

    def value_at(self, epoch: int) -> Any:
        """Scheduled value at ``epoch``."""
        return self.schedule(epoch)

    def set_value(self, pl_module: pl.LightningModule, value: Any) -> None:
        """Write ``value`` into the module (subclasses change where)."""
        *parents, name = self.target.split(".")
        try:
            owner = operator.attrgetter(".".join(parents))(pl_module) if parents else pl_module
            getattr(owner, name)
        except AttributeError:
            raise ConfigError(
                f"schedule target {self.target!r}: {type(pl_module).__name__} has no such attribute") from None
        setattr(owner, name, value)

    def apply(self, pl_module: pl.LightningModule, epoch: int) -> Any:
        """Set the value of ``epoch`` on the module; returns it."""
        value = self.value_at(epoch)
        self.set_value(pl_module, value)
        return value

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        """Set the value of the starting epoch (also on resume)."""
        self.apply(pl_module, trainer.current_epoch)

    def on_train_epoch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        """Set the value of the epoch and log it under ``log_name`` if given."""
        value = self.apply(pl_module, trainer.current_epoch)
        if self.log_name:
            pl_module.log(self.log_name, float(value), on_step=False, on_epoch=True, batch_size=1)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(target={self.target!r}, {self.schedule!r})"


class LossWeightSchedule(EpochSchedule):
    """Set the weight of one term of the module's :class:`~shapecorr.losses.weighted.WeightedLoss`.

    Parameters
    ----------
    term : str
        Loss term name (e.g. ``geo``).
    milestones : sequence of (epoch, weight)
    loss_attribute : str
        Attribute of the module holding the loss (default ``loss``).
    log_name : str, optional
    """

    def __init__(self, term: str, milestones: Sequence[Sequence[Any]], loss_attribute: str = "loss",
                 log_name: str | None = None):
        super().__init__(f"{loss_attribute}.{term}", milestones, log_name)
        self.term = term
        self.loss_attribute = loss_attribute

    def set_value(self, pl_module: pl.LightningModule, value: Any) -> None:
        """Set the weight of the loss term ``term`` (the module's loss must be a WeightedLoss)."""
        loss = getattr(pl_module, self.loss_attribute, None)
        if loss is None or not hasattr(loss, "set_weight"):
            raise ConfigError(f"{type(pl_module).__name__}.{self.loss_attribute} is not a WeightedLoss (no "
                              f"set_weight); cannot schedule the weight of {self.term!r}")
        loss.set_weight(self.term, value)
