"""train.py options: default data, checkpoint intervals, trainer keys, and Lightning's configuration errors as
ConfigError (exit status 2, ``error: ...``, no traceback).

Everything here fails or is checked before any data is generated, so the tests run in-process on composed configs.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra.utils import instantiate
from pytorch_lightning.callbacks import ModelCheckpoint

from shapecorr.cli.common import EXIT_INVALID_INPUT
from shapecorr.cli.train import (
    _instantiate,
    build_callbacks,
    checkpoint_callback,
    train,
)
from shapecorr.errors import ConfigError


@pytest.fixture
def _cfg(compose_config):
    """``_cfg(tmp_path, *overrides)``: train.yaml with the cache and outputs under ``tmp_path``."""

    def compose_train(tmp_path, *overrides):
        return compose_config("train", [f"paths.cache_dir={tmp_path / 'cache'}",
                                        f"paths.output_dir={tmp_path / 'out'}", *overrides])
    return compose_train


def test_default_run_trains_on_the_small_synthetic_set(tmp_path, _cfg, compose_config):
    cfg = _cfg(tmp_path)
    syn = cfg.data.synthetic
    assert syn.n_human_subjects * syn.n_human_poses == 12 and syn.n_quad_subjects == 0
    assert Path(cfg.data.root).name == "small_seed0"
    # evaluate.py's default keeps the 100-shape set in its own folder; debug=tiny gets the tiny preset again
    ev = compose_config("evaluate", [f"paths.cache_dir={tmp_path}"])
    assert ev.data.synthetic.preset == "default" and "n_human_subjects" not in ev.data.synthetic
    assert Path(ev.data.root).name == "default_seed0"
    tiny = _cfg(tmp_path, "debug=tiny")
    assert dict(tiny.data.synthetic) == {"preset": "tiny", "seed": 0}
    assert Path(tiny.data.root).name == "tiny_seed0"
    # the model's quick settings (configs/quick/deep_shells/quick.yaml, debug=tiny: tiny.yaml)
    default = _cfg(tmp_path)
    assert default.model.num_samples == 400 and default.model.layer.refine_levels == 12
    assert tiny.model.num_samples == 100 and tiny.model.layer.refine_levels == 4
    published = _cfg(tmp_path, "model=deep_shells_published", "debug=tiny")
    assert published.model.num_samples == 100 and published.model.layer.smooth_x == "hard"
    # the published experiment is untouched by the quick defaults
    exp = _cfg(tmp_path, "experiment=deep_shells_faust_r", "data.root=/nonexistent")
    assert exp.model.optimizer.lr == 1e-4 and exp.model.num_samples == 2000 and exp.model.backbone.num_eigs == 200
    assert exp.model.layer.refine_k_max == 500 and exp.model.layer.refine_levels == 40
    assert exp.trainer.limit_train_batches == 1.0 and exp.trainer.limit_test_batches == 1.0


def test_every_n_train_steps_replaces_every_n_epochs(tmp_path, _cfg):
    both = checkpoint_callback(_cfg(tmp_path, "checkpoint.every_n_train_steps=100"), tmp_path)
    assert both._every_n_train_steps == 100 and both._every_n_epochs == 0
    epochs = checkpoint_callback(_cfg(tmp_path), tmp_path)
    assert epochs._every_n_train_steps == 0 and epochs._every_n_epochs == 1
    only_last = checkpoint_callback(_cfg(tmp_path, "checkpoint.every_n_epochs=null"), tmp_path)
    assert only_last._every_n_train_steps == 0 and only_last._every_n_epochs == 0 and only_last.save_last
    # and Lightning accepts the combination in a Trainer
    cfg = _cfg(tmp_path, "checkpoint.every_n_train_steps=100", "~logger")
    trainer = _instantiate(cfg.trainer, "trainer", callbacks=build_callbacks(cfg, tmp_path), logger=False)
    assert isinstance(trainer.checkpoint_callback, ModelCheckpoint)
    assert trainer.checkpoint_callback._every_n_train_steps == 100


def test_max_time_and_val_check_interval_are_trainer_keys(tmp_path, _cfg):
    cfg = _cfg(tmp_path, "trainer.max_time=00:02:00:00", "trainer.val_check_interval=1000")
    trainer = instantiate(cfg.trainer, logger=False, enable_checkpointing=False)
    assert trainer.val_check_interval == 1000
    assert trainer.max_epochs == cfg.trainer.max_epochs
    defaults = _cfg(tmp_path).trainer
    assert defaults.max_time is None and defaults.val_check_interval is None


@pytest.mark.parametrize("override, message", [
    ("checkpoint.every_n_train_steps=-1", "invalid checkpoint options"),
    ("checkpoint.every_n_epochs=-2", "invalid checkpoint options"),
    ("trainer.max_time=garbage", "invalid trainer options"),
    ("trainer.val_check_interval=-2", "invalid trainer options"),
    ("trainer.devices=0", "invalid trainer options"),
])
def test_lightning_misconfiguration_is_a_config_error(tmp_path, override, message, _cfg):
    cfg = _cfg(tmp_path, override)
    with pytest.raises(ConfigError, match=message):
        _instantiate(cfg.trainer, "trainer", callbacks=build_callbacks(cfg, tmp_path), logger=False)


def test_cli_prints_the_error_without_traceback(tmp_path, capsys, _cfg):
    cfg = _cfg(tmp_path, "trainer.max_time=2h", "~logger")
    with pytest.raises(SystemExit) as exit_info:
        train(cfg)
    assert exit_info.value.code == EXIT_INVALID_INPUT
    err = capsys.readouterr().err
    assert err.startswith("error: invalid trainer options") and "DD:HH:MM:SS" in err
    assert "Traceback" not in err
    assert not (tmp_path / "cache" / "synthetic").exists()  # failed before generating any data


def test_a_model_without_parameters_is_refused_before_any_data_work(tmp_path, capsys, _cfg):
    with pytest.raises(SystemExit) as exit_info:
        train(_cfg(tmp_path, "model/backbone=identity", "~logger"))
    assert exit_info.value.code == EXIT_INVALID_INPUT
    assert "no trainable parameters" in capsys.readouterr().err
    assert not (tmp_path / "cache" / "synthetic").exists()


@pytest.mark.parametrize("terminal", [True, False])
def test_plain_progress_only_without_a_terminal(tmp_path, _cfg, monkeypatch, terminal):
    from shapecorr.cli.plain_progress import PlainProgress

    monkeypatch.setattr("shapecorr.cli.train.stdout_is_terminal", lambda: terminal)
    callbacks = build_callbacks(_cfg(tmp_path, "logger=none"), tmp_path)
    assert any(isinstance(c, PlainProgress) for c in callbacks) is not terminal


def test_logger_none_disables_logging_but_keeps_checkpoints(tmp_path, _cfg, monkeypatch):
    # on a terminal: no plain-progress callback either (test_plain_progress_only_without_a_terminal)
    monkeypatch.setattr("shapecorr.cli.train.stdout_is_terminal", lambda: True)
    for option in ("logger=none", "~logger"):
        cfg = _cfg(tmp_path, option)
        assert not cfg.get("logger")
        callbacks = build_callbacks(cfg, tmp_path)
        assert len(callbacks) == 1 and isinstance(callbacks[0], ModelCheckpoint)
        assert callbacks[0].state_key.startswith("ModelCheckpoint{")  # resumable from plain ModelCheckpoint states
    assert any(type(c).__name__ == "LearningRateMonitor" for c in build_callbacks(_cfg(tmp_path), tmp_path))
