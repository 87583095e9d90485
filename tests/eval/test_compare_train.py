"""The end of a training run: ``metrics.json`` in evaluate.py's keys and hyperparameters for TensorBoard's HParams
tab (shapecorr.cli.run_metrics), and two such runs compared like evaluation runs."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from shapecorr.cli.compare import compare_sweep
from shapecorr.cli.run_metrics import finish_training_run, flat_hparams, summarize_test_metrics


class RecordingLogger:
    def __init__(self):
        self.calls = []

    def log_hyperparams(self, params, metrics=None):
        self.calls.append((params, metrics))


def _trainer(error: float, logger=None):
    logged = {"test/geodesic_error": torch.tensor(error), "test/seconds_per_pair": torch.tensor(0.5),
              "val/geodesic_error": torch.tensor(9.0)}
    return SimpleNamespace(is_global_zero=True, callback_metrics=logged, logger=logger,
                           strategy=SimpleNamespace(root_device=torch.device("cpu")))


def test_summary_keys_match_evaluate():
    errors = [np.array([0.0, 0.1, 0.2]), np.array([0.3, 0.3, 0.3])]
    summary = summarize_test_metrics({"test/geodesic_error": torch.tensor(0.2), "train/loss": 1.0}, errors, "cpu")
    assert summary["mean_geodesic_error"] == pytest.approx(0.2) and summary["n_pairs"] == 2
    assert summary["median_geodesic_error"] == pytest.approx(0.25)
    assert 0.0 < summary["pck_auc"] < 1.0 and summary["peak_memory_mb"] > 0
    assert "train/loss" not in summary and summary["run"]["device"] == "cpu"
    # without a logged mean: the mean over pairs of the per-pair means
    assert summarize_test_metrics({}, errors, "cpu")["mean_geodesic_error"] == pytest.approx((0.1 + 0.3) / 2)


def test_flat_hparams(compose_config):
    cfg = compose_config("train", ["model.optimizer.lr=0.003"])
    flat = flat_hparams(cfg)
    assert flat["model/optimizer/lr"] == 0.003
    assert all(isinstance(v, (bool, int, float, str)) for v in flat.values())
    assert any(k.startswith("trainer/") for k in flat) and any(k.startswith("data/") for k in flat)


def test_training_runs_write_metrics_log_hparams_and_compare(compose_config, tmp_path):
    sweep = tmp_path / "multirun"
    errors = {"0": [np.array([0.05, 0.1])], "1": [np.array([0.2, 0.4])]}
    for job, lr in (("0", "0.001"), ("1", "0.0001")):
        out = sweep / job
        out.mkdir(parents=True)
        logger = RecordingLogger()
        model = SimpleNamespace(_eval_errors={"test": errors[job]})
        cfg = compose_config("train", [f"model.optimizer.lr={lr}"])
        summary = finish_training_run(cfg, _trainer(float(np.mean(errors[job][0])), logger), model, out)
        assert json.loads((out / "metrics.json").read_text())["mean_geodesic_error"] == summary["mean_geodesic_error"]
        (params, metrics), = logger.calls
        assert params["model/optimizer/lr"] == float(lr)
        assert metrics["hparams/mean_geodesic_error"] == pytest.approx(np.mean(errors[job][0]))
        (out / ".hydra").mkdir()
        (out / ".hydra" / "overrides.yaml").write_text(f"- model.optimizer.lr={lr}\n- data=synthetic_small\n")
    md = compare_sweep(sweep).read_text()
    assert "| model.optimizer.lr=0.001 | 1 | **7.50** |" in md
    assert "| model.optimizer.lr=0.0001 | 1 | 30.00 |" in md


def test_no_test_errors_writes_nothing(tmp_path):
    model = SimpleNamespace(_eval_errors={"test": []})
    assert finish_training_run(None, _trainer(0.1), model, tmp_path) is None
    assert not (tmp_path / "metrics.json").exists()
