"""The Hydra callback that ends every multirun (``evaluate.py -m`` / ``train.py -m``) with one comparison.

Configured in ``configs/hydra/default.yaml`` (``hydra.callbacks.compare``). At the end of the sweep it compares
the runs found in the sweep folder (:func:`shapecorr.cli.compare.compare_sweep`): ``comparison.csv``,
``comparison.md`` and, for evaluation runs, the figures and ``report.html`` (docs/compare.md). A comparison that
fails is reported on stderr without failing the sweep, whose runs are done and written.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig


class CompareSweep(Callback):
    """Write the comparison of a multirun's runs into its sweep folder (``hydra.sweep.dir``).

    Parameters
    ----------
    enabled : bool
        False: do nothing (``hydra.callbacks.compare.enabled=false``).
    """

    def __init__(self, enabled: bool = True) -> None:
        self.enabled = bool(enabled)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Compare the sweep's runs; imported lazily so that single runs and ``--help`` do not load it."""
        if not self.enabled:
            return
        from shapecorr.cli.compare import compare_sweep
        from shapecorr.errors import ShapeCorrError

        sweep_dir = Path(str(config.hydra.sweep.dir))
        try:
            written = compare_sweep(sweep_dir)
        except ShapeCorrError as err:
            print(f"error: comparison of the sweep not written: {err}", file=sys.stderr)
            return
        if written:
            print(f"comparison of the sweep: {written}", flush=True)
