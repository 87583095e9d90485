"""``train.py``: train a learned correspondence model, then score it on the test split.

    python train.py                                   # Deep Shells on the embedded synthetic data (minutes, CPU)
    python train.py experiment=deep_shells_faust_r data.root=/path/to/FAUST_r trainer=gpu
    python train.py ckpt_path=outputs/train/<run>/checkpoints/last.ckpt   # resume (same data order and samples)

Options: ``configs/train.yaml``. Steps: seed everything; build the data module and the model from its recipe, the
resolved ``model`` node (:mod:`shapecorr.models.recipe`; written to ``<run>/model.yaml`` and into every
checkpoint; to resume, the checkpoint's recipe with the command line's ``model.*`` overrides on top);
add the model's ``required_operators`` (an operator request, see
:mod:`shapecorr.data.operators`) to the data; fit with checkpoints
(``<run>/checkpoints``: ``last.ckpt`` plus one every ``checkpoint.every_n_epochs`` epochs, or every
``checkpoint.every_n_train_steps`` optimizer steps when that is set) and the logger of the ``logger`` group under
the Hydra run directory; with ``test=true`` run the test split on the final weights and print
``test geodesic error: <mean> (fraction of sqrt(area)) over <N> pairs`` as the last line. Options Lightning rejects
(its MisconfigurationException, while building the trainer and callbacks or once fitting starts) end as a
ConfigError: ``error: <message>`` and exit status 2, without a traceback.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import pytorch_lightning as pl
from omegaconf import DictConfig
from omegaconf.errors import OmegaConfBaseException
from pytorch_lightning.callbacks import LearningRateMonitor, ModelCheckpoint
from pytorch_lightning.utilities.exceptions import MisconfigurationException

from shapecorr.cli.common import check_output_dir, exit_on_user_error, user_config_error
from shapecorr.cli.plain_progress import PlainProgress
from shapecorr.cli.run_log import stdout_is_terminal
from shapecorr.cli.run_metrics import finish_training_run
from shapecorr.cli.threads import configure_threads
from shapecorr.data.operators import required_request
from shapecorr.errors import ConfigError
from shapecorr.models.recipe import build_model, load_model, save_recipe
from shapecorr.cli.model_request import model_request

CHECKPOINT_DIR = "checkpoints"
#: The resolved model node of the run (the recipe every checkpoint holds as well).
RECIPE_FILE = "model.yaml"


def _instantiate(node: DictConfig, what: str, **kwargs) -> Any:
    try:
        return hydra.utils.instantiate(node, _convert_="object", **kwargs)
    except hydra.errors.InstantiationException as err:
        cause = err.__cause__
        from shapecorr.errors import ShapeCorrError

        if isinstance(cause, ShapeCorrError):
            raise cause from None
        if isinstance(cause, MisconfigurationException):
            raise ConfigError(f"invalid {what} options: {cause}") from None
        raise ConfigError(f"cannot build the {what}: {err}") from None


class FinalLastCheckpoint(ModelCheckpoint):
    """ModelCheckpoint whose ``last.ckpt`` is always the final step.

    Lightning (2.6) writes ``last.ckpt`` with each periodic checkpoint and, at the end of fitting, only if no
    ``last.ckpt`` was written before: with ``every_n_train_steps`` and a final step that is not a multiple of
    it, ``last.ckpt`` would stay at the last periodic step.
    """

    @property
    def state_key(self) -> str:
        """The key of a plain ModelCheckpoint with the same options.

        So checkpoints written before this subclass existed (and by it) restore the checkpoint state on resume.
        """
        return ModelCheckpoint.__qualname__ + super().state_key[len(type(self).__qualname__):]

    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        """Save ``last.ckpt`` at the final step if it is not there yet, else finish as ModelCheckpoint does."""
        if self.save_last and self._last_global_step_saved != trainer.global_step:
            self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))
            return
        super().on_train_end(trainer, pl_module)


def checkpoint_callback(cfg: DictConfig, out_dir: Path) -> ModelCheckpoint:
    """The ModelCheckpoint of ``cfg.checkpoint``: ``last.ckpt`` plus periodic ones.

    ``every_n_train_steps`` (mid-epoch checkpoints every N optimizer steps) replaces ``every_n_epochs`` when both
    are set (Lightning accepts only one of them); ``0`` or ``null`` for both keeps only ``last.ckpt`` (written at
    the end of fitting; Lightning's own default for two nulls would be every epoch).

    Raises
    ------
    ConfigError
        Options Lightning rejects (e.g. a negative interval), with its message.
    """
    ck = cfg.checkpoint
    every_n_steps = ck.get("every_n_train_steps")
    every_n_epochs = None if every_n_steps else (ck.get("every_n_epochs") or 0)
    try:
        return FinalLastCheckpoint(
            dirpath=str(out_dir / CHECKPOINT_DIR),
            filename="epoch{epoch:03d}-step{step:06d}",
            auto_insert_metric_name=False,
            save_last=bool(ck.save_last),
            save_top_k=-1,  # keep every periodic checkpoint
            every_n_epochs=every_n_epochs,
            every_n_train_steps=every_n_steps,
            # epoch checkpoints at the end of every training epoch: Lightning's default with a validation loop is
            # to save after validation, so epochs without one (check_val_every_n_epoch > 1) would get none
            save_on_train_epoch_end=True if every_n_epochs else None,
        )
    except (MisconfigurationException, ValueError, TypeError) as err:
        raise ConfigError(f"invalid checkpoint options (checkpoint.every_n_train_steps={every_n_steps}, "
                          f"checkpoint.every_n_epochs={ck.get('every_n_epochs')}): {err}") from None


def build_callbacks(cfg: DictConfig, out_dir: Path) -> list[pl.Callback]:
    """ModelCheckpoint (last + periodic), with a logger the learning-rate monitor, then ``cfg.callbacks``."""
    callbacks: list[pl.Callback] = [checkpoint_callback(cfg, out_dir)]
    if not stdout_is_terminal():  # plain progress lines instead of the redrawn bar
        callbacks.append(PlainProgress())
    if cfg.get("logger"):
        callbacks.append(LearningRateMonitor(logging_interval="step"))
    # Callbacks of the model / experiment configs (e.g. NeuroMorph's epoch schedules), by name; null disables one.
    for name, node in (cfg.get("callbacks") or {}).items():
        if node is None:
            continue
        callback = _instantiate(node, f"callback {name!r}")
        if not isinstance(callback, pl.Callback):
            raise ConfigError(f"callbacks.{name} is not a Lightning callback (got {type(callback).__name__})")
        callbacks.append(callback)
    return callbacks


@exit_on_user_error
def train(cfg: DictConfig) -> dict[str, Any]:
    """Run the training described by ``cfg`` (configs/train.yaml).

    Returns
    -------
    dict
        ``checkpoint`` (path of the last checkpoint, or None), ``test_error`` (mean over reference points and
        pairs, or None without ``test``), ``test_pairs``, ``output_dir``.
    """
    try:
        configure_threads(cfg)
        out_dir = check_output_dir(Path(str(cfg.paths.output_dir)), "paths.output_dir=DIR or hydra.run.dir=DIR")
        print(f"output folder: {out_dir}", flush=True)
        pl.seed_everything(int(cfg.seed), workers=True)
        ckpt_path = cfg.get("ckpt_path")
        dm = _instantiate(cfg.data, "data module")
        if ckpt_path:  # resume: the checkpoint's recipe with the command line's model.* overrides on top
            requested, overrides = model_request(cfg)
            model = load_model(str(ckpt_path), requested, overrides)
        else:
            model = build_model(cfg.model)
        logger = _instantiate(cfg.logger, "logger") if cfg.get("logger") else False
        progress = {} if stdout_is_terminal() else {"enable_progress_bar": False}
        trainer = _instantiate(cfg.trainer, "trainer", callbacks=build_callbacks(cfg, out_dir), logger=logger,
                               **progress)
    except OmegaConfBaseException as err:
        raise user_config_error(err) from err
    if not any(p.requires_grad for p in model.parameters()):
        raise ConfigError(f"{type(model).__name__} has no trainable parameters with these options (e.g. "
                          "model/backbone=identity): nothing to train; evaluate it with evaluate.py instead")
    dm.with_operators(required_request(model))
    if trainer.is_global_zero:
        save_recipe(model, out_dir / RECIPE_FILE)
    try:
        trainer.fit(model, datamodule=dm, ckpt_path=str(ckpt_path) if ckpt_path else None)
    except MisconfigurationException as err:  # options Lightning only checks once fitting starts
        raise ConfigError(f"invalid trainer or callback options: {err}") from None
    except OSError as err:  # a storage fault in a logger or checkpoint writer that names no file: name the folder
        if err.filename is None and err.errno is not None:
            raise OSError(err.errno, err.strerror, str(out_dir)) from err
        raise
    checkpoint = trainer.checkpoint_callback.last_model_path if trainer.checkpoint_callback else None
    result: dict[str, Any] = {"checkpoint": checkpoint or None, "test_error": None, "test_pairs": 0,
                              "output_dir": str(out_dir)}
    if cfg.test:
        try:
            trainer.test(model, datamodule=dm, verbose=False)
        except MisconfigurationException as err:
            raise ConfigError(f"invalid trainer or callback options: {err}") from None
        errors = getattr(model, "_eval_errors", {}).get("test", [])
        if trainer.is_global_zero and errors:
            mean = float(np.mean(np.concatenate(errors)))
            result.update(test_error=mean, test_pairs=len(errors))
            finish_training_run(cfg, trainer, model, out_dir)  # metrics.json, hyperparameters + test metrics
            print(f"test geodesic error: {mean:.4f} (fraction of sqrt(area)) over {len(errors)} pairs", flush=True)
    # on stderr: the test error stays the last line of stdout
    print(f"output folder: {out_dir} (checkpoints/, train.log)", file=sys.stderr, flush=True)
    return result

