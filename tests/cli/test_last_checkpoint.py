"""``last.ckpt`` is the final step also with ``checkpoint.every_n_train_steps``."""

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


def test_every_n_epochs_saves_also_in_epochs_without_validation(tmp_path):
    # Lightning saves epoch checkpoints after validation when there is a validation loop; with
    # check_val_every_n_epoch=2 the epochs in between would get no checkpoint although every_n_epochs=1.
    cfg = OmegaConf.create({"checkpoint": {"save_last": True, "every_n_epochs": 1, "every_n_train_steps": None}})
    callback = checkpoint_callback(cfg, tmp_path)
    trainer = pl.Trainer(max_epochs=3, limit_train_batches=2, limit_val_batches=1, check_val_every_n_epoch=2,
                         callbacks=[callback], logger=False, enable_progress_bar=False, enable_model_summary=False,
                         num_sanity_val_steps=0, default_root_dir=tmp_path)
    trainer.fit(BoringModel())
    names = sorted(p.name for p in (tmp_path / "checkpoints").glob("epoch*.ckpt"))
    assert names == ["epoch000-step000002.ckpt", "epoch001-step000004.ckpt", "epoch002-step000006.ckpt"]
