"""The backbones of configs/model/backbone: SpectralBackbone (the filter bank on a sample) and IdentityBackbone."""

from __future__ import annotations

from pathlib import Path

import hydra
import pytest
import torch
from hydra import compose, initialize_config_dir

from shapecorr.data.datasets import ShapeSample
from shapecorr.data.shape import make_shape
from shapecorr.errors import ConfigError
from shapecorr.nn.backbone import Backbone
from shapecorr.nn.identity import IdentityBackbone
from shapecorr.nn.spectral_conv import SpectralBackbone, SpectralFilterBank

REPO = Path(__file__).resolve().parents[2]


def _sample(n=60, k=24, channels=5) -> ShapeSample:
    """Random mass-orthonormal eigenbasis and a random 'shot' descriptor on n vertices."""
    g = torch.Generator().manual_seed(0)
    mass = torch.rand(n, generator=g) + 0.5
    evecs = torch.linalg.qr(torch.randn(n, k, generator=g))[0] / mass.sqrt()[:, None]
    evals = torch.sort(torch.rand(k, generator=g) * 30.0).values
    verts = torch.randn(n, 3, generator=torch.Generator().manual_seed(1))
    faces = torch.tensor([[0, 1, 2]])
    feats = torch.randn(n, channels, generator=torch.Generator().manual_seed(2))
    return ShapeSample(
        shape=make_shape(verts.numpy(), faces.numpy(), "s"),
        operators={"eigenbasis": {"evals": evals, "evecs": evecs, "mass": mass}, "shot": {"shot": feats}},
    )


def test_spectral_backbone_is_the_filter_bank_on_the_sample():
    sample = _sample()
    torch.manual_seed(0)
    backbone = SpectralBackbone(in_channels=5, out_channels=3, hidden_channels=[4], num_basis=6, num_eigs=20,
                                max_frequency=30.0)
    bank = SpectralFilterBank(5, 3, (4,), 6, 20, 30.0)
    bank.load_state_dict(backbone.state_dict())  # the same parameter names
    rows = torch.tensor([3, 0, 7])
    expected = bank(sample.features["shot"], sample.evecs, sample.evals, sample.mass, rows=rows)
    assert torch.allclose(backbone(sample, rows), expected)
    assert isinstance(backbone, Backbone) and backbone.trainable and backbone.out_channels == 3
    assert backbone.required_operators == {"eigenbasis": {"k": 20}, "shot": {}}
    with pytest.raises(ConfigError, match="'wks' descriptor"):
        SpectralBackbone(descriptor="wks", in_channels=5)(sample)


def test_identity_backbone_passes_the_descriptor_through():
    sample = _sample()
    backbone = IdentityBackbone("shot", out_channels=5)
    rows = torch.tensor([4, 4, 1])
    assert torch.equal(backbone(sample), sample.features["shot"])
    assert torch.equal(backbone(sample, rows), sample.features["shot"][rows])
    assert not backbone.trainable and list(backbone.parameters()) == []
    assert backbone.required_operators == {"shot": {}}
    with pytest.raises(ConfigError, match="out_channels"):
        IdentityBackbone("shot", out_channels=352)(sample)


@pytest.mark.parametrize("name, cls", [("spectral_conv", SpectralBackbone), ("identity", IdentityBackbone)])
def test_backbone_configs_instantiate_with_published_defaults(name, cls):
    with initialize_config_dir(config_dir=str(REPO / "configs" / "model" / "backbone"), version_base="1.3"):
        cfg = compose(name)
    backbone = hydra.utils.instantiate(cfg)
    assert isinstance(backbone, cls)
    default = cls()
    # the config's values are the class defaults (published): the same sizes, operators and parameter shapes
    assert backbone.out_channels == default.out_channels
    assert backbone.required_operators == default.required_operators
    def shapes(module):
        return {k: v.shape for k, v in module.state_dict().items()}

    assert shapes(backbone) == shapes(default)
