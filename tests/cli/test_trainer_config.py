"""configs/trainer/*.yaml: Lightning Trainer arguments are overridable without "+" and listing them changes nothing."""

from __future__ import annotations

import inspect
from pathlib import Path

import pytest
import pytorch_lightning as pl
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

TRAINER_CONFIGS = sorted((Path(__file__).resolve().parents[2] / "configs" / "trainer").glob("*.yaml"))
TRAINER_ARGUMENTS = set(inspect.signature(pl.Trainer.__init__).parameters) - {"self"}


@pytest.mark.parametrize("path", TRAINER_CONFIGS, ids=lambda p: p.stem)
def test_every_key_is_a_trainer_argument(path):
    keys = set(OmegaConf.load(path)) - {"_target_", "defaults"}
    assert keys and keys <= TRAINER_ARGUMENTS, sorted(keys - TRAINER_ARGUMENTS)
    # logger and callbacks are train.py's (logger=, callbacks.*), never the trainer node's
    assert not keys & {"logger", "callbacks", "plugins"}


@pytest.mark.parametrize("trainer", [p.stem for p in TRAINER_CONFIGS])
def test_common_trainer_arguments_need_no_plus(trainer, compose_config, tmp_path):
    cfg = compose_config("train", [f"trainer={trainer}", f"paths.output_dir={tmp_path}", "trainer.max_steps=7",
                                   "trainer.gradient_clip_val=0.5", "trainer.num_sanity_val_steps=0",
                                   "trainer.precision=bf16-mixed", "trainer.limit_predict_batches=3"])
    assert cfg.trainer.max_steps == 7 and cfg.trainer.gradient_clip_val == 0.5
    assert cfg.trainer.num_sanity_val_steps == 0 and cfg.trainer.precision == "bf16-mixed"


def test_listed_lightning_defaults_change_nothing(compose_config, tmp_path):
    cfg = compose_config("train", [f"paths.output_dir={tmp_path}"])
    from_config = instantiate(cfg.trainer, logger=False, enable_checkpointing=False)
    # the same Trainer built from the project's settings only
    plain = pl.Trainer(accelerator="cpu", devices=1, max_epochs=cfg.trainer.max_epochs, logger=False,
                       enable_checkpointing=False, default_root_dir=str(tmp_path),
                       limit_train_batches=cfg.trainer.limit_train_batches,
                       limit_val_batches=cfg.trainer.limit_val_batches,
                       limit_test_batches=cfg.trainer.limit_test_batches,
                       log_every_n_steps=cfg.trainer.log_every_n_steps, deterministic=False)
    for attr in ("max_steps", "min_steps", "min_epochs", "num_sanity_val_steps", "precision", "fast_dev_run",
                 "overfit_batches", "limit_predict_batches", "gradient_clip_val", "gradient_clip_algorithm",
                 "num_nodes", "reload_dataloaders_every_n_epochs", "accumulate_grad_batches", "val_check_interval",
                 "check_val_every_n_epoch"):
        assert getattr(from_config, attr) == getattr(plain, attr), attr
    assert type(from_config.strategy) is type(plain.strategy)
    assert from_config.max_steps == -1 and from_config.num_sanity_val_steps == 2  # Lightning's own defaults


class _Tiny(pl.LightningModule):
    """One linear layer on random data: enough to count optimizer steps."""

    def __init__(self):
        super().__init__()
        self.layer = torch.nn.Linear(2, 1)

    def training_step(self, batch, batch_idx):
        return self.layer(batch[0]).pow(2).mean()

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)

    def train_dataloader(self):
        data = torch.utils.data.TensorDataset(torch.randn(20, 2, generator=torch.Generator().manual_seed(0)))
        return torch.utils.data.DataLoader(data, batch_size=2)


def test_trainer_max_steps_stops_fitting(compose_config, tmp_path):
    """A step limit set without "+" reaches the Trainer: fitting stops after 3 of the 10 steps of an epoch."""
    cfg = compose_config("train", [f"paths.output_dir={tmp_path}", "trainer.max_steps=3", "trainer.max_epochs=5",
                                   "trainer.enable_progress_bar=false", "trainer.enable_model_summary=false",
                                   "trainer.limit_train_batches=null"])
    trainer = instantiate(cfg.trainer, logger=False, enable_checkpointing=False)
    trainer.fit(_Tiny())
    assert trainer.global_step == 3  # not 5 epochs x 10 batches
