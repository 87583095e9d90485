"""Every model and experiment config composes with the entry points' configs and instantiates its model.

The files are discovered by globbing ``configs/model/*.yaml`` (top level: the sub-groups such as
``configs/model/optimizer/`` are parts of a model, not models) and ``configs/experiment/*.yaml``, so a new config
is covered without editing this test. Only the model node (and the callbacks a model config adds) is
instantiated: no data, no cache, no training.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra.utils import get_class, instantiate
from omegaconf import OmegaConf
from omegaconf.errors import MissingMandatoryValue

from shapecorr.matching.result import Matcher

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
MODELS = sorted(p.stem for p in (CONFIGS / "model").glob("*.yaml"))
EXPERIMENTS = sorted(p.stem for p in (CONFIGS / "experiment").glob("*.yaml"))


def test_the_globs_find_the_configs():
    # a wrong path would silently parametrize nothing
    assert {"deep_shells", "descriptor_nn", "identity_gt", "neuromorph"} <= set(MODELS)
    assert {"deep_shells_faust_r", "neuromorph_faust_r"} <= set(EXPERIMENTS)


def _instantiate_model(cfg, monkeypatch):
    """The model of a composed config. A mandatory value left open (``???``, e.g. the released Deep Shells weights
    that ``model=deep_shells_published`` reads from ``$SHAPECORR_DEEP_SHELLS_WEIGHTS``) must stop instantiation
    with an error naming the key; the test then sets it to null, as a user would with ``model.<key>=null``."""
    monkeypatch.delenv("SHAPECORR_DEEP_SHELLS_WEIGHTS", raising=False)
    for _ in range(len(cfg.model) + 1):
        try:
            model = instantiate(cfg.model, _convert_="object")
            break
        except MissingMandatoryValue as err:
            key = err.full_key
            assert key.startswith("model.") and key in str(err)
            OmegaConf.update(cfg, key, None, force_add=False)
    assert isinstance(model, get_class(cfg.model._target_))
    # evaluate.py scores any model through match(x, y)
    assert isinstance(model, Matcher)
    return model


@pytest.mark.parametrize("entry", ["train", "evaluate"])
@pytest.mark.parametrize("name", MODELS)
def test_model_config_composes_and_instantiates(name, entry, compose_config, monkeypatch, tmp_path):
    cfg = compose_config(entry, [f"model={name}", f"paths.cache_dir={tmp_path}", f"paths.output_dir={tmp_path}"])
    _instantiate_model(cfg, monkeypatch)
    for callback_name, node in (cfg.get("callbacks") or {}).items():
        if node is not None:
            assert hasattr(instantiate(node, _convert_="object"), "on_train_epoch_start"), callback_name


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_experiment_config_composes_and_instantiates(name, compose_config, monkeypatch, tmp_path):
    cfg = compose_config("train", [f"experiment={name}", f"data.root={tmp_path}", f"paths.cache_dir={tmp_path}",
                                   f"paths.output_dir={tmp_path}"])
    model = _instantiate_model(cfg, monkeypatch)
    # an experiment reproduces a published training schedule: it must train something
    assert sum(p.numel() for p in model.parameters() if p.requires_grad) > 0
    assert cfg.trainer.max_epochs >= 1
    trainer = instantiate(cfg.trainer, logger=False, enable_checkpointing=False, default_root_dir=str(tmp_path))
    assert trainer.max_epochs == cfg.trainer.max_epochs
    assert trainer.accumulate_grad_batches == cfg.trainer.accumulate_grad_batches


LOSSES = sorted(p.stem for p in (CONFIGS / "model" / "loss").glob("*.yaml"))
POSTPROCESS = sorted(p.stem for p in (CONFIGS / "postprocess").glob("*.yaml"))


@pytest.mark.parametrize("name", LOSSES)
def test_loss_config_composes_into_the_model_node(name, compose_config):
    from shapecorr.losses.weighted import WeightedLoss

    cfg = compose_config("train", ["model=deep_shells", f"model/loss={name}"])
    loss = instantiate(cfg.model.loss, _convert_="object")
    assert isinstance(loss, WeightedLoss) and loss.weights


@pytest.mark.parametrize("name", POSTPROCESS)
def test_postprocess_config_wraps_a_matcher(name, compose_config):
    cfg = compose_config("evaluate", ["model=descriptor_nn", f"postprocess={name}"])
    matcher = instantiate(cfg.model, _convert_="object")
    wrapped = instantiate(cfg.postprocess, _convert_="object")(matcher=matcher)
    assert isinstance(wrapped, Matcher) and wrapped.matcher is matcher


def test_losses_live_in_the_model_node():
    # every loss lives in its model's node (configs/model/loss/), not in a group of its own
    assert not (CONFIGS / "loss").exists()
    assert LOSSES and POSTPROCESS


@pytest.mark.parametrize("name", ["deep_shells", "deep_shells_published", "gmsm"])
def test_run_presets_reach_only_the_models_that_have_them(name, compose_config):
    """preset=quick / tiny: each model config applies its own settings (configs/quick/<family>/); variants inherit."""
    published = compose_config("evaluate", [f"model={name}"]).model
    quick = compose_config("train", [f"model={name}"]).model
    tiny = compose_config("train", [f"model={name}", "debug=tiny"]).model
    assert published.num_samples == 2000 and quick.num_samples == 400 and tiny.num_samples == 100
    assert compose_config("train", [f"model={name}", "preset=full"]).model == published
    if name == "gmsm":
        assert quick.graph.burn_in == 0 and published.graph.burn_in == 100
    neuromorph = compose_config("train", ["model=neuromorph", "debug=tiny"]).model
    assert neuromorph == compose_config("evaluate", ["model=neuromorph"]).model
