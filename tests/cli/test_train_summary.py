"""A tiny ``train.py`` run with mid-epoch validation, summarized by ``benchmarks/deep_shells_faust_r.py``.

One CLI run (debug=tiny, 4 training pairs, gradients accumulated over 2, validation every 2 pairs, a checkpoint
every optimizer step together with the default every-epoch setting) feeds the learning-curve summarizer; a second,
in-process run checks that a Lightning misconfiguration found only while fitting (a checkpoint monitoring a metric
nobody logs) ends as a ConfigError.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra.utils import instantiate

from shapecorr.cli.common import EXIT_INVALID_INPUT
from shapecorr.cli.train import train

REPO = Path(__file__).resolve().parents[2]
BENCH = REPO / "benchmarks" / "deep_shells_faust_r.py"
NM_BENCH = REPO / "benchmarks" / "neuromorph_faust_r.py"
ACCUMULATE, TRAIN_PAIRS, VAL_EVERY = 2, 4, 2
TINY = ["debug=tiny", f"trainer.limit_train_batches={TRAIN_PAIRS}", f"trainer.accumulate_grad_batches={ACCUMULATE}",
        f"trainer.val_check_interval={VAL_EVERY}", "trainer.limit_val_batches=1", "test=false",
        "trainer.num_sanity_val_steps=0"]


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory):
    # shared by the tests of this module: the tiny synthetic set is generated once
    return tmp_path_factory.mktemp("summary_cache")


def _load_script(path: Path):
    sys.path.insert(0, str(path.parent))  # the scripts import bench_common and training_runs from their folder
    try:
        spec = importlib.util.spec_from_file_location(path.stem, path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(path.parent))
    return module


@pytest.fixture(scope="module")
def bench():
    return _load_script(BENCH)


@pytest.fixture(scope="module")
def nm_bench():
    return _load_script(NM_BENCH)


@pytest.fixture(scope="module")
def runs(bench):
    return sys.modules["training_runs"]  # imported by the benchmark script


@pytest.fixture(scope="module")
def tiny_run(cache_dir, tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("runs") / "tiny"
    env = {**os.environ, "PYTHONWARNINGS": "ignore", "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, str(REPO / "train.py"), *TINY, f"paths.cache_dir={cache_dir}",
                           "checkpoint.every_n_train_steps=1", f"hydra.run.dir={run_dir}"],
                          cwd=REPO, capture_output=True, text=True, timeout=600, env=env, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return run_dir


@pytest.mark.slow
def test_run_writes_step_checkpoints_and_pairs_seen(tiny_run, runs):
    # every_n_train_steps=1 won over the default every_n_epochs=1: one checkpoint per optimizer step
    steps = sorted(p.name for p in (tiny_run / "checkpoints").glob("epoch*.ckpt"))
    assert steps == ["epoch000-step000001.ckpt", "epoch000-step000002.ckpt"]
    scalars = runs.read_scalars(tiny_run)
    assert [v for _, v, _ in scalars["val/pairs_seen"]] == [2.0, 4.0]
    assert len(scalars["val/geodesic_error"]) == TRAIN_PAIRS // VAL_EVERY


@pytest.mark.slow
def test_summarize_tiny_run(tiny_run, bench, tmp_path, capsys):
    eval_dir = tmp_path / "eval"
    eval_dir.mkdir()
    (eval_dir / "metrics.json").write_text(json.dumps({
        "n_pairs": 2, "mean_geodesic_error": 0.0312, "median_geodesic_error": 0.02, "pck_auc": 0.91,
        "seconds_per_pair": 1.5, "pck": {"thresholds": [0.0], "fractions": [0.1]}}))
    out = tmp_path / "summary.json"
    assert bench.main(["--summarize", str(tiny_run), "--eval-dir", str(eval_dir), "--out", str(out)]) == 0
    summary = json.loads(out.read_text())
    curve = summary["curve"]
    assert curve["pairs_per_optimizer_step"] == ACCUMULATE
    val = curve["validation"]
    assert [p["pairs_seen"] for p in val] == [2, 4] and all(p["pairs_seen_exact"] for p in val)
    # where val/pairs_seen is not logged, (step + 1) x accumulate gives the same numbers
    assert [(p["step"] + 1) * ACCUMULATE for p in val] == [2, 4]
    assert all(0.0 <= p["val_geodesic_error"] < 1.0 for p in val)
    assert summary["last_validation"] == val[-1]
    assert summary["best_validation"]["val_geodesic_error"] == min(p["val_geodesic_error"] for p in val)
    assert [p["pairs_seen"] for p in curve["train_loss"]] == [2, 4]
    assert summary["final"]["trained"]["mean_geodesic_error"] == 0.0312
    assert "ablation_no_learning" not in summary["final"]
    assert summary["command"].startswith("deep_shells_faust_r.py --summarize")
    assert summary["machine"]["cores"] == os.cpu_count()
    assert any("accumulate_grad_batches" in o for o in summary["overrides"])
    printed = capsys.readouterr().out
    assert "| 4 | 2 |" in printed  # pairs seen 4, optimizer steps 2
    assert "| trained | 2 | 3.12 | 2.00 | 0.910 |" in printed


def test_summarize_without_events_is_a_clear_error(bench, tmp_path):
    with pytest.raises(SystemExit, match="no TensorBoard event files"):
        bench.main(["--summarize", str(tmp_path), "--out", str(tmp_path / "s.json")])


def test_misconfiguration_while_fitting_is_a_config_error(cache_dir, tmp_path, capsys, compose_config):
    cfg = compose_config("train", [*TINY, f"paths.cache_dir={cache_dir}", f"paths.output_dir={tmp_path}",
                                   "~logger", "trainer.enable_progress_bar=false",
                                   ("+callbacks.best={_target_: pytorch_lightning.callbacks.ModelCheckpoint,"
                                    "monitor: val/not_logged}")])
    with pytest.raises(SystemExit) as exit_info:
        train(cfg)
    assert exit_info.value.code == EXIT_INVALID_INPUT
    err = capsys.readouterr().err
    assert "error: invalid trainer or callback options" in err and "val/not_logged" in err


def test_launch_commands_compose_without_plus_overrides(bench, tmp_path, compose_config):
    from shapecorr.cli.train import checkpoint_callback

    cmds = bench.launch_commands(tmp_path / "run", "/data/FAUST_r", with_published=True)
    assert set(cmds) == {"train", "eval", "ablation", "published"}
    train_args = [a for a in cmds["train"][2:] if not a.startswith("hydra.")]
    assert not any(a.startswith("+") for a in train_args)
    cfg = compose_config("train", [*train_args, f"paths.output_dir={tmp_path}"])
    assert cfg.trainer.max_time == "00:02:00:00" and cfg.trainer.val_check_interval == 1000
    assert cfg.trainer.accumulate_grad_batches == 4 and cfg.model.val_refine_levels is None
    assert cfg.data.root == "/data/FAUST_r" and cfg.model.num_samples == 2000
    assert checkpoint_callback(cfg, tmp_path)._every_n_train_steps == 100
    assert f"ckpt_path={tmp_path / 'run' / 'checkpoints' / 'last.ckpt'}" in cmds["eval"]
    assert "model=deep_shells_ablation" in cmds["ablation"] and "data=faust_r" in cmds["ablation"]


@pytest.mark.slow
def test_neuromorph_summary_and_launch_commands(tiny_run, nm_bench, tmp_path, capsys, compose_config):
    interp = tmp_path / "interp.json"
    mean = {"cd_mid_neuromorph": 0.25, "cd_mid_blend_soft": 1.5, "cd_mid_blend_hard": 3.0, "chamfer_end": 0.02,
            "chamfer_end_one_sided": 0.01, "full_cd_mid_neuromorph": 0.3, "full_cd_mid_blend_hard": 3.2,
            "full_chamfer_end": 0.025, "full_chamfer_end_one_sided": 0.012}
    interp.write_text(json.dumps({"n_pairs": 2, "time": 0.5, "mean": mean, "pairs": [{"pair": "a__b"}],
                                  "fraction_of_pairs_neuromorph_below": {
                                      "cd_mid_blend_soft": 1.0, "cd_mid_blend_hard": 0.5,
                                      "full_cd_mid_blend_hard": 1.0}}))
    out = tmp_path / "nm.json"
    assert nm_bench.main(["--summarize", str(tiny_run), "--interp-json", str(interp), "--out", str(out)]) == 0
    summary = json.loads(out.read_text())
    assert summary["interpolation"]["mean"] == mean and "pairs" not in summary["interpolation"]
    assert [p["pairs_seen"] for p in summary["curve"]["validation"]] == [2, 4]
    printed = capsys.readouterr().out
    assert "| linear blend x + t(y[p2p] - x) | 3.000 | 50 % of pairs |" in printed
    assert "Chamfer X(1) to y (% of sqrt(area)): working resolution 2.00" in printed
    # the CPU-budget overrides compose against the published experiment
    cmds = nm_bench.launch_commands(tmp_path / "run", "/data/FAUST_r")
    train_args = [a for a in cmds["train"][2:] if not a.startswith("hydra.")]
    cfg = compose_config("train", [*train_args, f"paths.output_dir={tmp_path}"])
    assert cfg.trainer.accumulate_grad_batches == 4 and cfg.trainer.limit_train_batches == 640
    assert cfg.model.augment.variants == 4 and cfg.model.query_resolution == 2000
    assert [list(m) for m in cfg.callbacks.neuromorph_T.milestones] == [[0, 0], [6, 1]]


def test_neuromorph_geodesic_map_variant_composes(nm_bench, tmp_path, compose_config):
    overrides, out = nm_bench.VARIANTS["geodesic-map"]
    assert out.name == "neuromorph_faust_r_geodesic_map.json"
    cmds = nm_bench.launch_commands(tmp_path / "run", "/data/FAUST_r", overrides)
    train_args = [a for a in cmds["train"][2:] if not a.startswith("hydra.")]
    cfg = compose_config("train", [*train_args, f"paths.output_dir={tmp_path}"])
    assert cfg.model.map_gradient == "geodesic" and cfg.model.optimizer.lr == pytest.approx(1e-3)
    assert cfg.trainer.max_time == "00:01:55:00" and cfg.trainer.accumulate_grad_batches == 4
    assert [list(m) for m in cfg.callbacks.neuromorph_lambda_geo.milestones] == [[0, 50.0], [8, 0.0]]
    model = instantiate(cfg.model, _convert_="object")
    assert model.map_gradient == "geodesic"
