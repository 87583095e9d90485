"""``last.ckpt`` is the final step also with ``checkpoint.every_n_train_steps`` (issue 17)."""

from __future__ import annotations

import pytorch_lightning as pl
import torch
from omegaconf import OmegaConf
from pytorch_lightning.demos.boring_classes import BoringModel

from shapecorr.cli.train import checkpoint_callback


def test_last_ckpt_is_the_final_step_with_every_n_train_steps(tmp_path):
    cfg = OmegaConf.create({"checkpoint": {"save_last": True, "every_n_epochs": 1, "every_n_train_steps": 2}})
    callback = checkpoint_callback(cfg, tmp_path)
    trainer = pl.Trainer(max_steps=5, callbacks=[callback], logger=False, enable_progress_bar=False,
                         enable_model_summary=False, limit_val_batches=0, default_root_dir=tmp_path)
    trainer.fit(BoringModel())
    assert trainer.global_step == 5
    last = torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=False)
    assert last["global_step"] == 5  # not 4, the last multiple of every_n_train_steps
