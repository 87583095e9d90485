"""Epoch schedules: piecewise-constant values, switching at the right epochs, after a resume, errors.

The Lightning runs use a tiny module (one linear layer on random data, 3 batches per epoch) so that they
take a fraction of a second per epoch.
"""

from __future__ import annotations

import pytest
import pytorch_lightning as pl
import torch
from pytorch_lightning.callbacks import ModelCheckpoint
from torch.utils.data import DataLoader, TensorDataset

from shapecorr.errors import ConfigError
from shapecorr.losses.weighted import WeightedLoss
from shapecorr.models.schedules import (
    EpochSchedule,
    LossWeightSchedule,
    PiecewiseConstant,
)

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning", "ignore::DeprecationWarning")

BATCHES = 3
T_MILESTONES = [[0, 0], [1, 1], [3, 3], [4, 7]]
GEO_MILESTONES = [[0, 50.0], [2, 0.0]]


class Tiny(pl.LightningModule):
    """Records (epoch, steps, geo weight) at every training step."""

    def __init__(self):
        super().__init__()
        self.layer = torch.nn.Linear(2, 1)
        self.steps = 99  # a value no schedule uses: shows whether a schedule ran
        self.loss = WeightedLoss({"mse": {"fn": lambda pred, target: (pred - target).square().mean(), "weight": 1.0},
                                  "geo": {"fn": lambda pred: pred.abs().mean(), "weight": 5.0}})
        self.seen = []

    def training_step(self, batch, batch_idx):
        self.seen.append((self.current_epoch, self.steps, self.loss.weights["geo"]))
        pred = self.layer(batch[0])
        total, _ = self.loss(pred=pred, target=batch[1])
        return total

    def train_dataloader(self):
        g = torch.Generator().manual_seed(0)
        data = TensorDataset(torch.randn(BATCHES, 2, generator=g), torch.randn(BATCHES, 1, generator=g))
        return DataLoader(data, batch_size=1)

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.01)


def _callbacks():
    return [EpochSchedule("steps", T_MILESTONES, log_name="schedule/T"),
            LossWeightSchedule("geo", GEO_MILESTONES, log_name="schedule/lambda_geo")]


def _trainer(tmp_path, callbacks, **kwargs):
    checkpointing = any(isinstance(c, ModelCheckpoint) for c in callbacks)
    options = dict(accelerator="cpu", devices=1, max_epochs=5, logger=False, enable_progress_bar=False,
                   enable_model_summary=False, enable_checkpointing=checkpointing, callbacks=callbacks,
                   default_root_dir=str(tmp_path))
    return pl.Trainer(**{**options, **kwargs})


def _expected(epochs):
    t = PiecewiseConstant(T_MILESTONES)
    g = PiecewiseConstant(GEO_MILESTONES)
    return [(e, t(e), g(e)) for e in epochs for _ in range(BATCHES)]


def test_piecewise_constant_values_at_the_published_epochs():
    t = PiecewiseConstant([[0, 0], [300, 1], [450, 3], [525, 7]])
    assert [t(e) for e in (0, 1, 299, 300, 449, 450, 524, 525, 600, 10_000)] == [0, 0, 0, 1, 1, 3, 3, 7, 7, 7]
    geo = PiecewiseConstant([[0, 50.0], [300, 0.0]])
    assert (geo(0), geo(299), geo(300), geo(599)) == (50.0, 50.0, 0.0, 0.0)
    assert PiecewiseConstant([(0, "a")])(12) == "a"


@pytest.mark.parametrize("milestones", [[], [[1, 0]], [[0, 0], [0, 1]], [[0, 0], [5, 1], [3, 2]], [[-1, 0]],
                                        [[0.5, 1]], [[0, 1, 2]], [0, 1], "0,1", [["a", 1]], None])
def test_bad_milestones_raise_config_error(milestones):
    with pytest.raises(ConfigError):
        PiecewiseConstant(milestones)


def test_values_switch_at_the_right_epochs_and_are_logged(tmp_path):
    model = Tiny()
    trainer = _trainer(tmp_path, _callbacks())
    trainer.fit(model)
    assert model.seen == _expected(range(5))
    assert float(trainer.callback_metrics["schedule/T"]) == 7.0
    assert float(trainer.callback_metrics["schedule/lambda_geo"]) == 0.0


@pytest.mark.parametrize("stop_step", [2 * BATCHES, 2 * BATCHES - 1])  # end of epoch 1; mid-epoch 1
def test_resume_restores_the_scheduled_values(tmp_path, stop_step):
    ckpt = ModelCheckpoint(dirpath=str(tmp_path / "ckpt"), every_n_train_steps=stop_step, save_top_k=-1,
                           filename="step{step}", auto_insert_metric_name=False)
    first = Tiny()
    _trainer(tmp_path, [ckpt, *_callbacks()], max_steps=stop_step).fit(first)
    path = tmp_path / "ckpt" / f"step{stop_step}.ckpt"
    assert path.is_file()
    # a fresh module (steps = 99, geo weight 5) and fresh callbacks continue with the values of their epoch
    resumed = Tiny()
    _trainer(tmp_path, _callbacks()).fit(resumed, ckpt_path=str(path))
    full = _expected(range(5))
    assert resumed.seen == full[stop_step:]
    assert first.seen == full[:stop_step]


def test_two_schedules_of_one_class_have_distinct_state_keys():
    a, b = EpochSchedule("steps", [[0, 1]]), EpochSchedule("other", [[0, 1]])
    assert a.state_key != b.state_key
    assert "steps" in repr(a)


def test_unknown_targets_are_config_errors(tmp_path):
    model = Tiny()
    with pytest.raises(ConfigError, match="no such attribute"):
        EpochSchedule("layer.nope", [[0, 1]]).apply(model, 0)
    with pytest.raises(ConfigError, match="unknown loss term"):
        LossWeightSchedule("nope", [[0, 1.0]]).apply(model, 0)
    with pytest.raises(ConfigError, match="not a WeightedLoss"):
        LossWeightSchedule("geo", [[0, 1.0]], loss_attribute="layer").apply(model, 0)
    with pytest.raises(ConfigError):
        EpochSchedule("", [[0, 1]])
    EpochSchedule("layer.in_features", [[0, 3]]).apply(model, 0)  # dotted paths reach nested objects
    assert model.layer.in_features == 3
