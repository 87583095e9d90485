"""DeepShells LightningModule: training step, match, hyperparameters, configs.

The pair is built in memory: an icosphere (642 vertices) and a smoothly bent, vertex-permuted copy of it with
the eigenbasis of each; the "descriptor" is a smooth random signal (fixed per base vertex, so X and Y agree
at corresponding points) standing in for SHOT, which keeps the tests independent of the descriptor code.
"""

from __future__ import annotations

from functools import partial

import numpy as np
import pytest
import torch
import trimesh
from hydra.utils import instantiate

from shapecorr.data.datasets import PairSample, ShapeSample
from shapecorr.data.shape import make_shape
from shapecorr.errors import ConfigError, NumericalError
from shapecorr.geometry.laplace_beltrami import eigenbasis
from shapecorr.losses.shells import level_energy_loss
from shapecorr.losses.weighted import WeightedLoss
from shapecorr.models.deep_shells import DeepShells
from shapecorr.nn.identity import IdentityBackbone
from shapecorr.nn.spectral_conv import SpectralBackbone

N_EIG = 40
N_CHANNELS = 16
# small but complete settings: 3 training levels, short refinement within N_EIG eigenpairs
SMALL_BACKBONE = dict(in_channels=N_CHANNELS, out_channels=8, num_eigs=30)
SMALL_LAYER = dict(num_samples=150, refine=True,
                   layer=dict(k_array=[6, 8, 10], refine_k_min=6, refine_k_max=25, refine_levels=4))


def shells_loss(level_weights=None, **terms) -> WeightedLoss:
    """The Deep Shells loss (configs/model/loss/deep_shells.yaml) with the given level weights, plus ``terms``."""
    fn = partial(level_energy_loss, level_weights=level_weights)
    return WeightedLoss({"shells": {"fn": fn, "weight": 1.0}, **terms})


def small(**overrides) -> DeepShells:
    """A small model with a fresh spectral backbone (``backbone=`` another one) and the published loss."""
    return DeepShells(**{"backbone": SpectralBackbone(**SMALL_BACKBONE), "loss": shells_loss(), **SMALL_LAYER,
                         **overrides})


def identity() -> IdentityBackbone:
    return IdentityBackbone("shot", out_channels=N_CHANNELS)

pytestmark = pytest.mark.filterwarnings("ignore:You are trying to `self.log\\(\\)`")


def _sample(verts, faces, feats, name) -> ShapeSample:
    shape = make_shape(verts, faces, name)
    evals, evecs, mass = eigenbasis(shape.verts.numpy(), shape.faces.numpy(), N_EIG)
    return ShapeSample(
        shape=shape,
        operators={
            "eigenbasis": {
                "evals": torch.as_tensor(evals, dtype=torch.float32),
                "evecs": torch.as_tensor(evecs, dtype=torch.float32),
                "mass": torch.as_tensor(mass, dtype=torch.float32),
            },
            "shot": {"shot": torch.as_tensor(feats)},
        },
    )


@pytest.fixture(scope="module")
def pair():
    """(PairSample, perm): y's vertex perm[i] is x's vertex i."""
    rng = np.random.default_rng(0)
    mesh = trimesh.creation.icosphere(subdivisions=3)
    base, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    feats = (np.stack([np.sin((k + 1) * base @ rng.normal(size=3)) for k in range(N_CHANNELS)], 1)
             .astype(np.float32))
    x = _sample(base, faces, feats, "x")
    perm = rng.permutation(len(base))
    bent = base * [1.3, 1.0, 0.8]
    bent[:, 2] += 0.2 * np.sin(1.5 * bent[:, 1])
    verts_y, feats_y = np.empty_like(bent), np.empty_like(feats)
    verts_y[perm], feats_y[perm] = bent, feats
    y = _sample(verts_y, perm[faces], feats_y, "y")
    return PairSample(x, y), perm


def test_training_step_finite_loss_and_gradients(pair):
    batch, _ = pair
    torch.manual_seed(0)
    model = small()
    loss = model.training_step(batch, 0)
    assert loss.dim() == 0 and torch.isfinite(loss) and loss > 0
    loss.backward()
    for name, p in model.named_parameters():
        assert p.grad is not None, name
        assert torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, name


def test_level_weights_select_levels(pair):
    batch, _ = pair
    uniform = small()
    last = small(loss=shells_loss([0.0, 0.0, 2.0]))
    last.load_state_dict(uniform.state_dict())
    # same samples (same seed, epoch, batch index): the one-hot loss is the last level's energy
    from shapecorr.matching.deep_shells import deep_shells_layer, random_samples

    gen = uniform.sample_generator(3)
    sx = random_samples(batch.x.shape.n_verts, 150, generator=gen)
    sy = random_samples(batch.y.shape.n_verts, 150, generator=gen)
    out = deep_shells_layer(uniform.features(batch.x, sx), uniform.features(batch.y, sy),
                            uniform.spectral_shape(batch.x), uniform.spectral_shape(batch.y), sx, sy, uniform.config)
    with torch.no_grad():
        assert torch.allclose(uniform.training_step(batch, 3), out.level_energies.mean(), rtol=1e-5)
        assert torch.allclose(last.training_step(batch, 3), out.level_energies[-1], rtol=1e-5)
    with pytest.raises(ConfigError, match="level_weights"):
        small(loss=shells_loss([1.0, 1.0])).training_step(batch, 3)
    # the term's weight scales the loss (loss.terms.shells.weight=, and the loss schedules)
    half = small(loss=WeightedLoss({"shells": {"fn": level_energy_loss, "weight": 0.5}}))
    half.load_state_dict(uniform.state_dict())
    with torch.no_grad():
        assert torch.allclose(half.training_step(batch, 3), 0.5 * out.level_energies.mean(), rtol=1e-5)
    with pytest.raises(ConfigError, match="model.loss"):
        small(loss=None).training_step(batch, 3)


def test_sample_generator_depends_on_seed_epoch_batch():
    model = small()
    def draw(m, b):
        return torch.randint(0, 10**6, (5,), generator=m.sample_generator(b))
    assert torch.equal(draw(model, 4), draw(model, 4))
    assert not torch.equal(draw(model, 4), draw(model, 5))
    assert not torch.equal(draw(model, 4), draw(small(seed=1), 4))


def test_nan_features_raise_numerical_error(pair):
    batch, _ = pair
    model = small()
    with torch.no_grad():
        model.backbone.layers[0].bias[0, 0] = float("nan")
    with pytest.raises(NumericalError):
        model.training_step(batch, 0)
    with pytest.raises(NumericalError, match="NaN"):
        model.match(batch.x, batch.y)


def test_match_valid_maps_and_recovers_permutation(pair):
    batch, perm = pair
    model = small(backbone=identity())  # the descriptor is exact: an oracle
    result = model.match(batch.x, batch.y).validate(batch.x.shape.n_verts, batch.y.shape.n_verts)
    assert result.p2p.dtype == torch.int64 and result.p2p_inv.shape == (batch.y.shape.n_verts,)
    assert (result.p2p.numpy() == perm).mean() > 0.8
    # the learned backbone (random weights) still gives valid full-length maps
    learned = small().match(batch.x, batch.y)
    learned.validate(batch.x.shape.n_verts, batch.y.shape.n_verts)


def test_cheap_validation_mode():
    model = small(val_refine_levels=2)
    cfg, refine = model.match_config()
    assert refine and cfg.refine_levels == 4
    model._validating_during_fit = True
    cfg, refine = model.match_config()
    assert refine and cfg.refine_levels == 2
    model_off = small(val_refine_levels=0)
    model_off._validating_during_fit = True
    assert model_off.match_config()[1] is False


def test_required_operators():
    published = DeepShells()
    # refinement up to k = 499 with k+9 sigmoid weights
    assert published.required_operators == {"eigenbasis": {"k": 508}, "shot": {}}
    assert DeepShells(refine=False).required_operators["eigenbasis"]["k"] == 200  # the filter bank's eigenpairs
    ablation = DeepShells(backbone=IdentityBackbone(), refine=False)
    assert ablation.required_operators == {"shot": {}, "eigenbasis": {"k": 30}}  # k = 21 + 9
    assert list(DeepShells(backbone=IdentityBackbone()).parameters()) == []
    assert DeepShells(backbone=IdentityBackbone()).configure_optimizers() is None


def test_invalid_options_raise_config_error():
    with pytest.raises(ConfigError, match="backbone"):
        DeepShells(backbone="resnet")
    with pytest.raises(ConfigError, match="layer option"):
        DeepShells(layer={"not_an_option": 1})
    with pytest.raises(ConfigError, match="lr"):
        DeepShells(optimizer=partial(torch.optim.Adam, lr=0.0))
    with pytest.raises(ConfigError, match="model.loss"):
        DeepShells(loss=level_energy_loss)
    with pytest.raises(TypeError):
        DeepShells(num_eigs=30)  # backbone options belong to model.backbone


def test_configs_compose_and_instantiate(tmp_path, compose_config):
    cfg = compose_config("train", [f"paths.cache_dir={tmp_path}", "paths.output_dir=" + str(tmp_path),
                                   "model.optimizer.lr=0.001",
                                   "model.loss.terms.shells.fn.level_weights=[0,0,0,0,1,1,1,1]"])
    model = instantiate(cfg.model, _convert_="object")
    assert isinstance(model, DeepShells) and model.lr == 1e-3
    energies = torch.arange(8.0)
    assert float(model.loss(level_energies=energies)[0]) == pytest.approx(float(energies[4:].mean()))
    assert cfg.trainer.accelerator == "cpu" and cfg.logger._target_.endswith("TensorBoardLogger")
    trainer = instantiate(cfg.trainer, logger=False, enable_checkpointing=False)
    assert trainer.max_epochs == cfg.trainer.max_epochs

    exp = compose_config("train", ["experiment=deep_shells_faust_r", "data.root=/nonexistent", "logger=csv"])
    assert exp.trainer.accumulate_grad_batches == 53 and exp.model.num_samples == 2000
    assert exp.model.optimizer.lr == 1e-4 and exp.trainer.limit_train_batches == 1.0
    assert exp.data.splits.train.index_range == [0, 80]
    assert exp.logger._target_.endswith("CSVLogger")

    ablation = instantiate(compose_config("evaluate", ["model=deep_shells_ablation"]).model, _convert_="object")
    assert isinstance(ablation.backbone, IdentityBackbone) and ablation.refine
    for name in ("evaluate", "train"):
        ev_cfg = compose_config(name, ["model=deep_shells", "model/backbone=identity"])
        ev = instantiate(ev_cfg.model, _convert_="object")
        assert isinstance(ev.backbone, IdentityBackbone) and not ev.backbone.trainable
    tiny = instantiate(compose_config("train", ["debug=tiny"]).model, _convert_="object")
    assert isinstance(tiny.backbone, SpectralBackbone) and tiny.backbone.num_eigs == 200
