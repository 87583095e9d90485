"""``model=neuromorph_original``: the original code's choices, composed and instantiated (no data needed); the
published default keeps ours."""

from __future__ import annotations

from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

REPO = Path(__file__).resolve().parents[2]


def _model(name: str, tmp_path):
    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base="1.3"):
        cfg = compose("train", overrides=[f"model={name}", f"paths.cache_dir={tmp_path}",
                                          f"paths.output_dir={tmp_path}"])
    return cfg, instantiate(cfg.model, _convert_="object")


def test_original_preset_sets_the_original_choices(tmp_path):
    cfg, model = _model("neuromorph_original", tmp_path)
    assert model.feature_net.net.pool == model.interpolator.net.pool == "channel"
    assert model.arap_edge_weight_scale == 1.0 and model.geodesics == "original"
    arap = cfg.model.loss.terms.arap.fn
    assert arap.mode == "average" and arap.detach_rotations is False
    # only fc_1.weight zeroed: the residual branches start with their random bias
    assert all(torch.count_nonzero(b.block.fc1.bias) > 0 and torch.count_nonzero(b.block.fc1.weight) == 0
               for b in model.feature_net.net.blocks)
    # everything else is the published configuration
    assert model.loss.weights == {"registration": 1.0, "arap": 1.0, "geo": 50.0} and model.sigma == 100.0
    assert list(cfg.callbacks.neuromorph_T.milestones) == [[0, 0], [300, 1], [450, 3], [525, 7]]


def test_default_keeps_our_choices(tmp_path):
    cfg, model = _model("neuromorph", tmp_path)
    assert model.feature_net.net.pool == "global" and model.arap_edge_weight_scale == 0.5
    assert model.geodesics == "heat" and cfg.model.loss.terms.arap.fn.mode == "both-sides"
    assert all(torch.count_nonzero(b.block.fc1.bias) == 0 for b in model.feature_net.net.blocks)
