"""DeepShells ``pretrained``: the original's released ``.pth`` format, our ``.ckpt`` files, the published config.

The ``.pth`` files are written by the tests in the original's format (``feat_mod`` with ``conv.a.0.weight
(c_in * c_out, M)`` / ``conv.a.0.bias (c_in * c_out,)``, output index ``c * c_out + j``, and ``par`` with the
filter scale in the doubled eigenvalue convention); the filters they define are checked against a direct
evaluation of the original formula. The real released weights are tested opt-in (``reference``).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf.errors import MissingMandatoryValue

from shapecorr.data.datasets import ShapeSample
from shapecorr.data.shape import make_shape
from shapecorr.errors import ConfigError
from shapecorr.models.deep_shells import PRETRAINED_CHECKPOINT_KEY, DeepShells
from shapecorr.nn.identity import IdentityBackbone
from shapecorr.nn.spectral_conv import ORIGINAL_EIGENVALUE_FACTOR, SpectralBackbone

C_IN, C_OUT, N_BASIS, N_EIGS = 6, 4, 5, 12
SMALL_BACKBONE = {"in_channels": C_IN, "out_channels": C_OUT, "num_basis": N_BASIS, "num_eigs": N_EIGS,
                  "max_frequency": 50.0}
SMALL_LAYER = {"num_samples": 50,
               "layer": {"k_array": [6, 8], "refine_k_min": 6, "refine_k_max": 10, "refine_levels": 2}}


def small(pretrained=None, backbone=None, **backbone_overrides) -> DeepShells:
    """A small model with a fresh spectral backbone (or ``backbone``)."""
    if backbone is None:
        backbone = SpectralBackbone(**{**SMALL_BACKBONE, **backbone_overrides})
    return DeepShells(backbone=backbone, pretrained=pretrained, **SMALL_LAYER)
PUBLISHED_WEIGHTS = "published_weights_faust_scape_ep20.pth"


def _original_file(path: Path, seed: int = 0, filter_scale: float | None = None, num_evecs: int = N_EIGS,
                   weight_shape=(C_IN * C_OUT, N_BASIS)) -> dict:
    gen = torch.Generator().manual_seed(seed)
    weight = torch.randn(*weight_shape, generator=gen)
    bias = torch.randn(weight_shape[0], generator=gen)
    scale = ORIGINAL_EIGENVALUE_FACTOR * SMALL_BACKBONE["max_frequency"] if filter_scale is None else filter_scale
    torch.save({"feat_mod": {"conv.a.0.weight": weight, "conv.a.0.bias": bias},
                "par": {"filter_scale": scale, "num_evecs": num_evecs}}, path)
    return {"weight": weight, "bias": bias, "filter_scale": scale}


def test_original_format_defines_the_original_filters(tmp_path):
    path = tmp_path / "ckpt_ep20.pth"
    orig = _original_file(path)
    model = small(pretrained=path)
    assert model.pretrained == str(path)
    evals = torch.linspace(0.0, 80.0, N_EIGS)  # shapecorr convention
    ours = model.backbone.layers[0].filters(evals)  # (K, c_in, c_out)
    # the original: h(lambda_orig) = W @ [cos(m pi lambda_orig / filter_scale)]_m + b, lambda_orig = 2 lambda
    lam = ORIGINAL_EIGENVALUE_FACTOR * evals.double()
    basis = torch.cos(lam[:, None] * torch.arange(N_BASIS, dtype=torch.float64) * math.pi / orig["filter_scale"])
    expected = (basis @ orig["weight"].double().T + orig["bias"].double()).reshape(N_EIGS, C_IN, C_OUT)
    assert torch.allclose(ours.double(), expected, atol=1e-5)
    # a second model from the same file is identical; a fresh one is not
    again = small(pretrained=str(path))
    fresh = small()
    for name, value in model.state_dict().items():
        assert torch.equal(value, again.state_dict()[name]), name
    assert not torch.equal(model.backbone.layers[0].weight, fresh.backbone.layers[0].weight)


def test_lightning_checkpoint_weights_roundtrip(tmp_path):
    import pytorch_lightning as pl

    source = small()
    with torch.no_grad():
        source.backbone.layers[0].weight.add_(1.0)
    ckpt = tmp_path / "epoch001.ckpt"
    torch.save({"state_dict": source.state_dict(), "pytorch-lightning_version": pl.__version__}, ckpt)
    model = small(pretrained=ckpt)
    for name, value in source.backbone.state_dict().items():
        assert torch.equal(value, model.backbone.state_dict()[name]), name
    # other sizes do not fit; an identity-backbone checkpoint has nothing to load
    with pytest.raises(ConfigError, match="does not fit") as err:
        small(pretrained=ckpt, out_channels=C_OUT + 1)
    assert str(ckpt) in str(err.value)
    empty = tmp_path / "identity.ckpt"
    torch.save({"state_dict": small(backbone=IdentityBackbone()).state_dict()}, empty)
    with pytest.raises(ConfigError, match="no filter-bank weights"):
        small(pretrained=empty)


def test_checkpoint_of_a_pretrained_model_loads_without_the_file(tmp_path):
    from shapecorr.models.recipe import build_model, load_model

    weights = tmp_path / "ckpt.pth"
    _original_file(weights, seed=3)
    node = {"_target_": "shapecorr.models.deep_shells.DeepShells", "pretrained": str(weights),
            "backbone": {"_target_": "shapecorr.nn.spectral_conv.SpectralBackbone", **SMALL_BACKBONE}}
    model = build_model(node)
    assert model.trained_from == str(weights)
    checkpoint = {"state_dict": model.state_dict()}
    model.on_save_checkpoint(checkpoint)
    assert checkpoint[PRETRAINED_CHECKPOINT_KEY] == str(weights)
    assert checkpoint["model_recipe"]["pretrained"] is None  # the checkpoint holds the weights
    path = tmp_path / "trained.ckpt"
    torch.save(checkpoint, path)
    weights.unlink()
    loaded = load_model(path)
    assert loaded.pretrained is None and loaded.trained_from == str(path)
    assert torch.equal(loaded.backbone.layers[0].weight, model.backbone.layers[0].weight)


@pytest.mark.parametrize("case", ["missing", "garbage", "not_deep_shells", "filter_scale", "num_evecs", "shape",
                                  "identity"])
def test_bad_weights_raise_config_error_naming_the_file(tmp_path, case):
    path = tmp_path / "weights.pth"
    options = {}
    if case == "garbage":
        path.write_bytes(b"this is not a torch file")
    elif case == "not_deep_shells":
        torch.save({"feat_mod": {"fc.weight": torch.zeros(2, 2)}}, path)
    elif case == "filter_scale":
        _original_file(path, filter_scale=5e4)
    elif case == "num_evecs":
        _original_file(path, num_evecs=N_EIGS + 1)
    elif case == "shape":
        _original_file(path, weight_shape=(C_IN * C_OUT + 1, N_BASIS))
    elif case == "identity":
        _original_file(path)
        options["backbone"] = IdentityBackbone()
    with pytest.raises(ConfigError) as err:
        small(pretrained=path, **options)
    assert str(path) in str(err.value)


def test_published_config_reads_the_environment(tmp_path, monkeypatch, compose_config):
    monkeypatch.delenv("SHAPECORR_DEEP_SHELLS_WEIGHTS", raising=False)
    cfg = compose_config("evaluate", ["model=deep_shells_published", "model.backbone.in_channels=6",
                                      "model.backbone.out_channels=4", "model.backbone.num_basis=5",
                                      "model.backbone.num_eigs=12", "model.backbone.max_frequency=50.0"])
    with pytest.raises(MissingMandatoryValue, match="model.pretrained"):
        instantiate(cfg.model, _convert_="object")
    path = tmp_path / "ckpt.pth"
    orig = _original_file(path, seed=5)
    monkeypatch.setenv("SHAPECORR_DEEP_SHELLS_WEIGHTS", str(path))
    model = instantiate(cfg.model, _convert_="object")
    assert isinstance(model, DeepShells) and model.pretrained == str(path)
    expected = orig["weight"].t().reshape(N_BASIS, C_IN, C_OUT)
    assert torch.equal(model.backbone.layers[0].weight.detach(), expected)
    # the published model follows the original code's matching flags, on top of the published defaults
    assert (model.config.smooth_x, model.config.sigmoid_inclusive, model.config.normal_norm) == ("hard", False,
                                                                                                 "samples")
    assert model.config.refine_levels == 40 and model.config.k_array == (6, 7, 8, 10, 12, 14, 17, 21)
    monkeypatch.setenv("SHAPECORR_DEEP_SHELLS_WEIGHTS", str(tmp_path / "nope.pth"))
    with pytest.raises(InstantiationException, match="not found"):
        instantiate(cfg.model, _convert_="object")


@pytest.mark.reference
def test_released_weights_reproduce_the_original_features(compose_config):
    golden = os.environ.get("SHAPECORR_DEEP_SHELLS_GOLDEN")
    if not golden:
        pytest.skip("SHAPECORR_DEEP_SHELLS_GOLDEN is not set: point it to the Deep Shells golden files (published "
                    "weights and the original's features) to run this test")
    golden = Path(golden)
    cfg = compose_config("evaluate", ["model=deep_shells_published", f"model.pretrained={golden / PUBLISHED_WEIGHTS}"])
    model = instantiate(cfg.model, _convert_="object")
    pair = "tr_reg_080__tr_reg_081"
    inputs = np.load(golden / f"inputs_{pair}.npz")
    expected = torch.from_numpy(np.load(golden / f"original_output_{pair}.npz")["features_x"])
    sample = ShapeSample(
        shape=make_shape(inputs["x_verts"], inputs["x_faces"], "tr_reg_080"),
        operators={
            "eigenbasis": {
                # the golden eigenvalues are in the original doubled (full cot) convention
                "evals": torch.from_numpy(inputs["x_evals"]) / ORIGINAL_EIGENVALUE_FACTOR,
                "evecs": torch.from_numpy(inputs["x_evecs"]),
                "mass": torch.from_numpy(inputs["x_mass"]),
            },
            "shot": {"shot": torch.from_numpy(inputs["x_shot"])},
        },
    )
    with torch.no_grad():
        ours = model.features(sample)
    assert ours.shape == expected.shape == (sample.shape.n_verts, 120)
    torch.testing.assert_close(ours, expected, rtol=1e-4, atol=1e-5 * float(expected.abs().max()))
