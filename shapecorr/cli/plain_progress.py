"""Training progress as plain text lines, for output that is not a terminal (a file, a batch system's log).

Lightning's progress bar redraws one line with carriage returns, which a redirected output shows late or as one
long line. ``train.py`` replaces it with :class:`PlainProgress` when its standard output is not a terminal.
"""

from __future__ import annotations

import time

import pytorch_lightning as pl

#: Seconds between two progress lines during an epoch (the first and last batch of an epoch always print).
DEFAULT_INTERVAL_S = 30.0


class PlainProgress(pl.Callback):
    """Prints ``epoch E/N batch B/M step S loss L (T s)`` every ``interval_s`` seconds and after validation."""

    def __init__(self, interval_s: float = DEFAULT_INTERVAL_S):
        self.interval_s = float(interval_s)
        self._start = self._last = 0.0

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        """Start the clock."""
        self._start = self._last = time.perf_counter()

    def on_train_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs, batch,
                           batch_idx: int) -> None:
        """A line at the first and last batch of an epoch and every ``interval_s`` seconds in between."""
        now = time.perf_counter()
        total = trainer.num_training_batches
        last = isinstance(total, int) and batch_idx + 1 >= total
        if batch_idx > 0 and not last and now - self._last < self.interval_s:
            return
        self._last = now
        epochs = trainer.max_epochs if trainer.max_epochs and trainer.max_epochs > 0 else "?"
        metrics = _scalars(trainer.progress_bar_metrics)
        print(f"epoch {trainer.current_epoch + 1}/{epochs} batch {batch_idx + 1}/{total} "
              f"step {trainer.global_step}{metrics} ({now - self._start:.0f} s)", flush=True)

    def on_validation_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        """The validation metrics (after the sanity check too)."""
        if trainer.sanity_checking:
            return
        metrics = _scalars({k: v for k, v in trainer.callback_metrics.items() if k.startswith("val")})
        print(f"validation at step {trainer.global_step}{metrics} "
              f"({time.perf_counter() - self._start:.0f} s)", flush=True)


def _scalars(metrics) -> str:
    parts = []
    for key, value in sorted(metrics.items()):
        try:
            parts.append(f" {key} {float(value):.4g}")
        except (TypeError, ValueError):
            continue
    return "".join(parts)
