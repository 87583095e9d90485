"""Every learned model x every backbone it accepts: train a step, evaluate the checkpoint, the same maps in-process.

For each pair (model, backbone) ``train.py model=<model> model/backbone=<backbone> debug=tiny`` runs one training
step in a subprocess (small network sizes, no validation or test). Then, in this process:

1. ``evaluate(cfg)`` with only ``ckpt_path=`` builds the model from the checkpoint's recipe and writes the map of
   one test pair;
2. the model composed from the same training options (``configs/train.yaml``), given the checkpoint's weights,
   matches the same pair: the maps are equal (the recipe is the model);
3. a test-time override (``+model.<key>=...``, the model's option that changes its maps) changes the map and is
   recorded in ``run.json``.

NeuroMorph takes only backbones that need no per-shape operators: it trains on augmented copies (rotated,
remeshed) and may query remeshes, which carry none (it refuses the others, tests/models/test_neuromorph.py). The
identity backbone has nothing to train (``train.py`` refuses it; ``evaluate.py model=deep_shells_ablation`` needs
no checkpoint).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

REPO = Path(__file__).resolve().parents[2]
CONFIGS = REPO / "configs"

#: Small networks: one training step and a query take seconds on ~300-vertex shapes.
BACKBONE_SIZES = {
    "spectral_conv": ["model.backbone.num_eigs=40", "model.backbone.out_channels=16"],
    "diffusion_net": ["model.backbone.width=16", "model.backbone.n_blocks=1", "model.backbone.k_eig=32",
                      "model.backbone.out_channels=16"],
    "edgeconv": ["model.backbone.hidden_channels=16", "model.backbone.n_blocks=2", "model.backbone.feature_dim=16"],
}
MODEL_OPTIONS = {
    "deep_shells": [],
    "gmsm": [],
    "neuromorph": ["model.augment.resolution=[200,300]", "model.augment.variants=1"],
}
#: (model, backbone, extra training options)
MATRIX = [
    ("deep_shells", "spectral_conv", []),
    ("deep_shells", "diffusion_net", []),
    ("deep_shells", "edgeconv", []),
    ("gmsm", "diffusion_net", []),
    ("gmsm", "spectral_conv", []),
    ("gmsm", "edgeconv", []),
    ("neuromorph", "edgeconv", []),
]
#: A test-time option per model that changes its maps.
TEST_TIME_OVERRIDE = {
    "deep_shells": ("refine", "false"),
    "gmsm": ("test_query", "deep_shells"),
    "neuromorph": ("query_resolution", "150"),
}
#: Evaluation data: the test split of the tiny synthetic preset, as debug=tiny trains on; pairwise maps (G-MSM
#: would otherwise compose its maps over a shape graph of the split).
EVAL_DATA = ["data=synthetic", "data.synthetic.preset=tiny", "data.operators.params.shot.radius_factor=0.25",
             "max_pairs=1", "n_examples=0", "progress=false", "write_interp=false", "++matching=pairwise"]

pytestmark = [pytest.mark.slow, pytest.mark.filterwarnings("ignore")]


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory) -> Path:
    """One shape cache for the whole matrix (the tiny synthetic shapes and their operators, computed once)."""
    return tmp_path_factory.mktemp("cache")


def _train_options(model: str, backbone: str, extra: list[str], cache: Path) -> list[str]:
    return [f"model={model}", f"model/backbone={backbone}", "debug=tiny", *BACKBONE_SIZES[backbone],
            *MODEL_OPTIONS[model], *extra, f"paths.cache_dir={cache}", "trainer.limit_train_batches=1",
            "trainer.limit_val_batches=0", "test=false", "logger=none"]


def _compose(name: str, overrides: list[str]):
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return compose(name, overrides=overrides, return_hydra_config=True)


def _evaluate(ckpt: Path, out: Path, cache: Path, *overrides: str) -> np.ndarray:
    from shapecorr.cli.evaluate import evaluate

    evaluate(_compose("evaluate", [f"ckpt_path={ckpt}", f"output_dir={out}", f"paths.cache_dir={cache}",
                                   *EVAL_DATA, *overrides]))
    (path,) = sorted((out / "maps").glob("*.npy"))
    return np.load(path)


@pytest.mark.parametrize("model, backbone, extra", MATRIX, ids=[f"{m}-{b}" for m, b, _ in MATRIX])
def test_train_then_evaluate_the_checkpoint(model, backbone, extra, cache_dir, tmp_path):
    """One cell of the matrix (module docstring)."""
    from shapecorr.data.operators import required_request

    run = tmp_path / "run"
    options = _train_options(model, backbone, extra, cache_dir)
    env = {**os.environ, "PYTHONWARNINGS": "ignore", "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, str(REPO / "train.py"), *options, f"hydra.run.dir={run}",
                           "trainer.enable_progress_bar=false", "checkpoint.every_n_epochs=0"],
                          cwd=REPO, capture_output=True, text=True, timeout=600, env=env, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    ckpt = run / "checkpoints" / "last.ckpt"
    assert ckpt.is_file() and (run / "model.yaml").is_file()

    # 1. evaluate.py ckpt_path=... (the checkpoint's recipe, no model= needed)
    maps = _evaluate(ckpt, tmp_path / "eval", cache_dir)

    # 2. the same maps from the model composed in this process with the checkpoint's weights
    reference = instantiate(_compose("train", options).model, _convert_="object")
    reference.load_state_dict(torch.load(ckpt, map_location="cpu", weights_only=True)["state_dict"])
    reference.eval()
    cfg = _compose("evaluate", [f"paths.cache_dir={cache_dir}", *EVAL_DATA])
    dm = instantiate(cfg.data, _convert_="object")
    dm.with_operators(required_request(reference))
    shapes = dm.shapes("test")
    (map_file,) = (tmp_path / "eval" / "maps").glob("*.npy")
    name_x, name_y = map_file.stem.split("__")
    x, y = shapes[shapes.names.index(name_x)], shapes[shapes.names.index(name_y)]
    with torch.no_grad():
        expected = reference.match(x, y).p2p.cpu().numpy()
    np.testing.assert_array_equal(maps, expected)

    # 3. a test-time override takes effect and is recorded
    key, value = TEST_TIME_OVERRIDE[model]
    changed = _evaluate(ckpt, tmp_path / "override", cache_dir, f"+model.{key}={value}")
    assert not np.array_equal(changed, maps)
    recorded = json.loads((tmp_path / "override" / "run.json").read_text())["model"]
    assert str(recorded[key]).lower() == value
