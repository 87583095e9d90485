"""A model is built from its recipe (shapecorr.models.recipe): checkpoints, overrides, refused checkpoints.

Small Deep Shells / G-MSM models (tiny networks, no data): building, saving and reading checkpoints take
milliseconds. The command-line cases run ``evaluate(cfg)`` / ``train(cfg)`` in this process and stop before
any data is read.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from shapecorr.cli.model_request import model_request
from shapecorr.errors import ConfigError
from shapecorr.models.base import RECIPE_KEY
from shapecorr.models.deep_shells import DeepShells
from shapecorr.models.recipe import DELETE, build_model, load_model, merge_overrides, untrained_warning

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
BACKBONE = {"_target_": "shapecorr.nn.spectral_conv.SpectralBackbone", "in_channels": 6, "out_channels": 4,
            "num_basis": 5, "num_eigs": 12}
NODE = {"_target_": "shapecorr.models.deep_shells.DeepShells", "backbone": BACKBONE, "num_samples": 50,
        "refine": True, "layer": {"k_array": [6, 8], "refine_levels": 2, "refine_k_max": 10}}


def _save(model, path: Path) -> Path:
    checkpoint = {"state_dict": model.state_dict(), "epoch": 0}
    model.on_save_checkpoint(checkpoint)
    torch.save(checkpoint, path)
    return path


@pytest.fixture
def checkpoint(tmp_path) -> Path:
    torch.manual_seed(0)
    return _save(build_model(NODE), tmp_path / "model.ckpt")


def test_a_checkpoint_rebuilds_its_model_with_overrides_on_top(checkpoint):
    model = load_model(checkpoint)
    assert isinstance(model, DeepShells) and model.recipe == NODE and model.trained_from == str(checkpoint)
    saved = torch.load(checkpoint, weights_only=True)
    for name, value in saved["state_dict"].items():
        assert torch.equal(model.state_dict()[name], value), name
    # test-time options take effect and are part of the recipe the run records
    changed = load_model(checkpoint, overrides={"refine": False, "layer.refine_levels": 1})
    assert changed.refine is False and changed.config.refine_levels == 1
    assert changed.recipe["refine"] is False and changed.recipe["layer"]["k_array"] == [6, 8]
    assert torch.equal(changed.backbone.layers[0].weight, model.backbone.layers[0].weight)


def test_merge_overrides_sets_replaces_and_removes():
    merged = merge_overrides(NODE, {"layer.sigma": 0.2, "backbone": {**BACKBONE, "max_frequency": 9.0},
                                    "refine": DELETE, "new_key": 1})
    assert merged["layer"] == {**NODE["layer"], "sigma": 0.2} and merged["backbone"]["max_frequency"] == 9.0
    assert "refine" not in merged and merged["new_key"] == 1
    assert NODE["refine"] is True  # the recipe itself is not changed


def _truncated(path: Path, good: Path) -> None:
    path.write_bytes(good.read_bytes()[:200])


def _hostile(path: Path, good: Path) -> None:
    # an object outside the safe types of torch.load(weights_only=True): never unpickled
    torch.save({"state_dict": {}, "payload": Path("/etc/passwd")}, path)


def _foreign(path: Path, good: Path) -> None:
    torch.save([1, 2, 3], path)


def _no_recipe(path: Path, good: Path) -> None:
    state = torch.load(good, weights_only=True)
    del state[RECIPE_KEY]
    torch.save(state, path)


FILE_CASES = {
    "missing": (lambda path, good: None, "does not exist"),
    "directory": (lambda path, good: path.mkdir(), "is not a checkpoint file"),
    "empty": (lambda path, good: path.write_bytes(b""), "is empty"),
    "truncated": (_truncated, "not a readable checkpoint"),
    "garbage": (lambda path, good: path.write_text("not a checkpoint\n"), "not a readable checkpoint"),
    "hostile": (_hostile, "not a readable checkpoint"),
    "foreign": (_foreign, "not a shapecorr training checkpoint"),
    "no recipe": (_no_recipe, "holds no model recipe"),
}


@pytest.mark.parametrize("case", sorted(FILE_CASES))
def test_unreadable_checkpoints_are_one_line_errors_naming_the_file(case, checkpoint, tmp_path):
    make, message = FILE_CASES[case]
    path = tmp_path / "bad.ckpt"
    make(path, checkpoint)
    with pytest.raises(ConfigError, match=message) as err:
        load_model(path)
    text = str(err.value)
    assert text.startswith(str(path)) and "\n" not in text
    assert "train.py" in text or "retrain" in text  # the fix


def test_a_checkpoint_of_another_model_is_refused_naming_both(checkpoint):
    gmsm = {"_target_": "shapecorr.models.gmsm.GMSM"}
    with pytest.raises(ConfigError, match="holds a DeepShells model .* not the requested GMSM") as err:
        load_model(checkpoint, requested=gmsm)
    assert str(checkpoint) in str(err.value)
    assert isinstance(load_model(checkpoint, requested={"_target_": NODE["_target_"]}), DeepShells)


def test_an_override_changing_parameter_shapes_names_the_key(checkpoint):
    with pytest.raises(ConfigError, match=r"model\.backbone\.out_channels changes the parameter shapes") as err:
        load_model(checkpoint, overrides={"refine": False, "backbone.out_channels": 5})
    assert "\n" not in str(err.value) and "(6, 4)" in str(err.value)  # the checkpoint's shape


def test_model_request_reads_the_command_line():
    args = ["model=deep_shells", "model.refine=false", "++model.layer.sigma=0.2", "~model.seed",
            "model/backbone=identity", "data=synthetic"]
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose("evaluate", overrides=args, return_hydra_config=True)
    requested, overrides = model_request(cfg)
    assert requested._target_ == NODE["_target_"]
    assert overrides["refine"] is False and overrides["layer.sigma"] == 0.2 and overrides["seed"] is DELETE
    assert overrides["backbone"]["_target_"].endswith("IdentityBackbone")
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose("evaluate", overrides=["+model.refine=false"], return_hydra_config=True)
    assert model_request(cfg) == (None, {"refine": False})  # no model=: the checkpoint's own model


def _cli(entry: str, overrides, capsys, tmp_path):
    from shapecorr.cli.evaluate import evaluate
    from shapecorr.cli.train import train

    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose(entry, overrides=[*overrides, f"paths.output_dir={tmp_path / 'out'}",
                                        f"paths.cache_dir={tmp_path / 'cache'}"])
    with pytest.raises(SystemExit) as exit_info:
        (evaluate if entry == "evaluate" else train)(cfg)
    err = capsys.readouterr().err.strip().splitlines()
    return exit_info.value.code, err


@pytest.mark.parametrize("entry", ["evaluate", "train"])
@pytest.mark.parametrize("case", ["empty", "truncated", "garbage", "wrong model"])
def test_the_commands_refuse_bad_checkpoints_in_one_line(entry, case, checkpoint, tmp_path, capsys):
    path, model = tmp_path / "bad.ckpt", []
    if case == "wrong model":
        path, model = checkpoint, ["model=gmsm"]
    else:
        FILE_CASES[case][0](path, checkpoint)
    code, err = _cli(entry, [f"ckpt_path={path}", *model], capsys, tmp_path)
    assert code == 2 and len(err) == 1 and err[0].startswith(f"error: {path}: "), err
    if case == "wrong model":
        assert "DeepShells" in err[0] and "GMSM" in err[0]


def test_an_untrained_learned_model_is_evaluated_with_a_warning(checkpoint):
    assert "untrained" in untrained_warning(build_model(NODE))
    assert untrained_warning(load_model(checkpoint)) is None
    ablation = build_model({**NODE, "backbone": {"_target_": "shapecorr.nn.identity.IdentityBackbone"}})
    assert untrained_warning(ablation) is None  # nothing to train
    assert untrained_warning(build_model({"_target_": "shapecorr.matching.baselines.DescriptorNN"})) is None


def test_evaluate_warns_about_an_untrained_model(capsys):
    from shapecorr.cli.matcher_factory import build_matcher

    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose("evaluate", overrides=["model=gmsm"])
    build_matcher(cfg, torch.device("cpu"))
    assert "warning: GMSM has untrained" in capsys.readouterr().err
