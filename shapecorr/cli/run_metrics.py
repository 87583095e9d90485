"""The end of a ``train.py`` run: its test metrics as ``metrics.json`` and its hyperparameters for TensorBoard.

``metrics.json`` uses the keys of ``evaluate.py``'s (``mean_geodesic_error``, ``median_geodesic_error``,
``pck_auc``, ``mean_conformal_distortion``, ``mean_geodesic_error_sym``, ``seconds_per_pair``,
``peak_memory_mb``, ``n_pairs``, ``run``), so a ``train.py -m`` sweep ends with the same comparison table as an
``evaluate.py -m`` one (:mod:`shapecorr.cli.sweep_callback`; docs/compare.md). The logger gets the flattened
options of the model, data and trainer with those metrics (``log_hyperparams(params, metrics)``): TensorBoard's
HParams tab then lines the runs of a sweep up.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from omegaconf import DictConfig, OmegaConf

from shapecorr.eval import metrics, reports

METRICS_FILE = "metrics.json"
#: Logged test metrics (``shapecorr.models.base``) -> key of metrics.json.
TEST_KEYS = {
    "test/geodesic_error": "mean_geodesic_error",
    "test/conformal_distortion": "mean_conformal_distortion",
    "test/geodesic_error_sym": "mean_geodesic_error_sym",
    "test/seconds_per_pair": "seconds_per_pair",
}
#: Config groups whose options are logged as hyperparameters.
HPARAM_GROUPS = ("model", "data", "trainer")


def flat_hparams(cfg: DictConfig) -> dict[str, Any]:
    """The scalar options of :data:`HPARAM_GROUPS` as ``{"model/lr": 1e-4, ...}`` (lists as text).

    Plus the command-line overrides of the run (``overrides``) when it runs under Hydra.
    """
    out: dict[str, Any] = {}

    def walk(prefix: str, node: Any) -> None:
        if isinstance(node, Mapping):
            for key, value in node.items():
                walk(f"{prefix}/{key}", value)
        elif isinstance(node, (bool, int, float, str)):
            out[prefix] = node
        elif isinstance(node, list):
            out[prefix] = json.dumps(node)

    for group in HPARAM_GROUPS:
        if cfg.get(group) is not None:
            walk(group, OmegaConf.to_container(cfg[group], resolve=False))
    overrides = _overrides()
    if overrides:
        out["overrides"] = " ".join(overrides)
    return out


def _overrides() -> list[str]:
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return []
    return list(HydraConfig.get().overrides.task)


def summarize_test_metrics(logged: Mapping[str, Any], errors: list[np.ndarray], device: str) -> dict[str, Any]:
    """``metrics.json`` of a training run from the logged test metrics and the per-pair test errors.

    Parameters
    ----------
    logged : dict
        ``trainer.callback_metrics`` after ``trainer.test`` (tensors or floats).
    errors : list of (R_k,) float
        Per-reference-point test errors of every test pair.
    device : str
    """
    out: dict[str, Any] = {TEST_KEYS[k]: float(v) for k, v in logged.items() if k in TEST_KEYS}
    if errors:
        pooled = np.concatenate([np.asarray(e, np.float64) for e in errors])
        t, frac = metrics.pck_curve(pooled)
        out.update(n_pairs=len(errors), median_geodesic_error=float(np.median(pooled)),
                   pck_auc=metrics.pck_auc(t, frac), pck={"thresholds": t.tolist(), "fractions": frac.tolist()})
        out.setdefault("mean_geodesic_error", float(np.mean([np.mean(e) for e in errors])))
    out.update(reports.peak_memory_mb())
    out["run"] = {"device": device, "overrides": _overrides()}
    return out


def finish_training_run(cfg: DictConfig, trainer, model, out_dir: Path) -> dict[str, Any] | None:
    """Write ``out_dir/metrics.json`` and log hyperparameters + test metrics (rank 0); None without test errors."""
    errors = getattr(model, "_eval_errors", {}).get("test", [])
    if not trainer.is_global_zero or not errors:
        return None
    summary = summarize_test_metrics(trainer.callback_metrics, errors, str(trainer.strategy.root_device))
    reports.write_metrics_json(out_dir / METRICS_FILE, summary)
    if trainer.logger is not None:
        scalars = {f"hparams/{k}": v for k, v in summary.items() if isinstance(v, float)}
        trainer.logger.log_hyperparams(flat_hparams(cfg), metrics=scalars)
    return summary
