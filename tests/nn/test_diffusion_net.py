"""DiffusionNet: spectral diffusion limits, rotation invariance, discretization agnosticism, the backbone."""

import itertools
from types import SimpleNamespace

import numpy as np
import pytest
import scipy.sparse as sp
import torch
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from shapecorr.errors import ConfigError
from shapecorr.geometry.descriptors import hks
from shapecorr.geometry.diffusion_operators import diffusion_gradients
from shapecorr.geometry.laplace_beltrami import eigenbasis
from shapecorr.geometry.remeshing import remesh
from shapecorr.nn.backbone import Backbone
from shapecorr.nn.diffusion_net import (
    DiffusionNet,
    DiffusionNetBackbone,
    gradient_operators,
    spectral_diffusion,
)

K_EIG = 32
# Fixed times, so that both meshings get the same descriptor channels; long enough that exp(-lambda_k t) is
# small at the last of the K_EIG eigenvalues (the truncated HKS is then insensitive to the meshing).
HKS_TIMES = np.geomspace(0.05, 1.0, 16)


def _torch_sparse(m: sp.spmatrix) -> torch.Tensor:
    coo = m.tocoo()
    idx = torch.from_numpy(np.vstack([coo.row, coo.col]).astype(np.int64))
    return torch.sparse_coo_tensor(idx, torch.from_numpy(coo.data.astype(np.float32)), coo.shape,
                                   check_invariants=True).coalesce()


def _sample(verts, faces, k=K_EIG):
    """A stand-in for a registry sample: ``.verts``, ``.faces``, ``.operators``."""
    evals, evecs, mass = eigenbasis(verts, faces, k)
    grads = diffusion_gradients(verts, faces)
    ops = {
        "eigenbasis": {
            "evals": torch.tensor(evals, dtype=torch.float32),
            "evecs": torch.tensor(evecs, dtype=torch.float32),
            "mass": torch.tensor(mass, dtype=torch.float32),
        },
        "diffusion_gradients": {"grad_x": _torch_sparse(grads["grad_x"]), "grad_y": _torch_sparse(grads["grad_y"])},
        "hks": {"hks": torch.tensor(hks(evals, evecs, times=HKS_TIMES, normalize="sum"), dtype=torch.float32)},
    }
    return SimpleNamespace(verts=torch.tensor(verts, dtype=torch.float32), faces=torch.tensor(faces), operators=ops)


def _ellipsoid(subdivisions=2):
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    return np.asarray(m.vertices) * np.array([1.0, 0.8, 0.6]), np.asarray(m.faces)


def _untrained(seed=0, **kw):
    torch.manual_seed(seed)
    net = DiffusionNetBackbone(input_features="hks", in_channels=len(HKS_TIMES), k_eig=K_EIG, width=32,
                               out_channels=16, **kw)
    with torch.no_grad():  # spread the diffusion times so that diffusion does something
        for block in net.net.blocks:
            block.diffusion.times.copy_(torch.rand(block.diffusion.times.shape) * 0.05)
    return net.eval()


@pytest.fixture(scope="module")
def ellipsoid():
    return _sample(*_ellipsoid())


def test_spectral_diffusion_limits():
    evals, evecs, mass = (torch.from_numpy(a) for a in eigenbasis(*_ellipsoid(), K_EIG))  # float64
    torch.manual_seed(0)
    x = evecs @ torch.randn(K_EIG, 5, dtype=torch.float64)  # in the span of the basis
    same = spectral_diffusion(x, evals, evecs, mass, torch.zeros(5, dtype=torch.float64))
    assert torch.allclose(same, x, atol=1e-8)
    y = torch.randn(len(mass), 5, dtype=torch.float64)  # any function: tends to its mass-weighted mean
    mean = (mass[:, None] * y).sum(0) / mass.sum()
    far = spectral_diffusion(y, evals, evecs, mass, torch.full((5,), 1e3, dtype=torch.float64))
    assert torch.allclose(far, mean.expand_as(far), atol=1e-8)
    # in between, diffusion smooths monotonically: the mass-weighted L2 norm decreases with t
    energies = [float((spectral_diffusion(y, evals, evecs, mass, torch.full((5,), t, dtype=torch.float64)) ** 2
                       * mass[:, None]).sum()) for t in (0.0, 0.01, 0.1, 1.0)]
    assert all(a > b for a, b in itertools.pairwise(energies))


def test_features_are_invariant_to_rotation_for_intrinsic_input():
    v, f = _ellipsoid()
    rot = Rotation.random(random_state=7).as_matrix()
    net = _untrained()
    a = net(_sample(v, f))
    b = net(_sample(v @ rot.T, f))
    assert a.shape == (len(v), 16)
    assert (a - b).abs().max() < 1e-3 * a.abs().max()
    # with xyz input, the same rotation changes the features (the test above can fail)
    torch.manual_seed(0)
    xyz = DiffusionNetBackbone(k_eig=K_EIG, width=32, out_channels=16).eval()
    c, d = xyz(_sample(v, f)), xyz(_sample(v @ rot.T, f))
    assert (c - d).abs().max() > 0.05 * c.abs().max()


def test_features_agree_across_two_meshings_of_the_same_surface():
    v, f = _ellipsoid(subdivisions=3)  # 642 vertices
    u, g = remesh(v, f, 450)  # an isotropic remeshing of the same surface, different connectivity
    net = _untrained(seed=1)
    sa, sb = _sample(v, f), _sample(u, g)
    with torch.no_grad():
        fa, fb = net(sa).numpy(), net(sb).numpy()
    nearest = cKDTree(v).query(u)[1]  # vertex positions differ by up to about half an edge
    chance = np.random.default_rng(0).permutation(len(v))[: len(u)]

    def mismatch(a, b):  # feature distance at nearest points over distance at random points (centred)
        a, b = a - a.mean(0), b - b.mean(0)
        return np.linalg.norm(b - a[nearest], axis=1).mean() / np.linalg.norm(b - a[chance], axis=1).mean()

    out = mismatch(fa, fb)
    inp = mismatch(*(s.operators["hks"]["hks"].numpy() for s in (sa, sb)))
    assert out < 0.2, out  # measured 0.10-0.11 over three seeds
    assert out < 1.5 * inp, (out, inp)  # the network adds (almost) no dependence on the meshing to its input's


def test_backbone_interface_rows_operators_and_dropout(ellipsoid):
    torch.manual_seed(0)
    net = DiffusionNetBackbone(k_eig=K_EIG, width=16, out_channels=8)
    assert isinstance(net, Backbone) and net.trainable and net.out_channels == 8
    assert net.required_operators == {"eigenbasis": {"k": K_EIG}, "diffusion_gradients": {}}
    hks_net = DiffusionNetBackbone("hks", in_channels=16, descriptor_params={"count": 16}, k_eig=K_EIG)
    assert hks_net.required_operators["hks"] == {"count": 16}
    rows = torch.tensor([3, 0, 7])
    net.eval()
    full, part = net(ellipsoid), net(ellipsoid, rows)
    assert full.shape == (len(ellipsoid.verts), 8) and full.dtype == torch.float32
    assert torch.equal(part, full[rows])
    assert torch.equal(net(ellipsoid), full)  # eval: deterministic
    net.train()
    assert not torch.equal(net(ellipsoid), net(ellipsoid))  # dropout on while training


@pytest.mark.parametrize("n_blocks", [0, 1, 3])
def test_features_at_rows_equal_the_full_features_at_those_rows(ellipsoid, n_blocks):
    """Queries run the last block's per-vertex layers at the rows only: the values must not change (with dropout on
    too: the full computation's masks); with gradients everything runs at every vertex."""
    torch.manual_seed(0)
    net = DiffusionNetBackbone(k_eig=K_EIG, width=16, out_channels=8, n_blocks=n_blocks)
    with torch.no_grad():  # diffusion that does something
        for block in net.net.blocks:
            block.diffusion.times.copy_(torch.rand(block.diffusion.times.shape) * 0.05)
    rows = torch.tensor([5, 0, 7, 5, len(ellipsoid.verts) - 1])  # repeated rows, as in the training samples
    net.eval()
    with torch.no_grad():
        full = net(ellipsoid)
        assert torch.equal(net(ellipsoid, rows), full[rows])
    part = net(ellipsoid, rows)  # with gradients
    assert torch.equal(part, full[rows]) and part.requires_grad
    net.train()
    for grad in (False, True):
        with torch.set_grad_enabled(grad):
            torch.manual_seed(1)
            full = net(ellipsoid)
            torch.manual_seed(1)
            assert torch.equal(net(ellipsoid, rows), full[rows])


def test_training_at_rows_has_the_gradients_of_the_full_computation(ellipsoid):
    """With gradients every vertex is computed: features, gradients and random state those of the full computation."""
    torch.manual_seed(0)
    net = DiffusionNetBackbone(k_eig=K_EIG, width=16, out_channels=8, n_blocks=2).train()
    with torch.no_grad():
        for block in net.net.blocks:
            block.diffusion.times.copy_(torch.rand(block.diffusion.times.shape) * 0.05)
    rows = torch.tensor([5, 0, 7, 5, 40, len(ellipsoid.verts) - 1])
    up = torch.randn(len(rows), 8)

    def grads(at_rows):
        net.zero_grad(set_to_none=True)
        torch.manual_seed(1)
        out = net(ellipsoid, rows) if at_rows else net(ellipsoid)[rows]
        out.backward(up)
        return out.detach(), {k: p.grad.clone() for k, p in net.named_parameters()}, torch.get_rng_state()

    full, g_full, state_full = grads(False)
    part, g_part, state_part = grads(True)
    assert torch.equal(part, full) and torch.equal(state_part, state_full)
    for name, g in g_full.items():
        assert torch.equal(g_part[name], g), name
    with torch.no_grad():  # a query with dropout on (dropout_at_test): the rows path, the full computation's masks
        torch.manual_seed(2)
        full = net(ellipsoid)
        state = torch.get_rng_state()
        torch.manual_seed(2)
        assert torch.equal(net(ellipsoid, rows), full[rows]) and torch.equal(torch.get_rng_state(), state)


def test_gradient_operators_are_the_sparse_products_with_their_gradients(ellipsoid):
    ops = ellipsoid.operators["diffusion_gradients"]
    gx, gy = ops["grad_x"], ops["grad_y"]
    applied = gradient_operators(gx, gy)
    assert gradient_operators(gx, gy) is applied  # cached per operator tensor
    h = torch.randn(len(ellipsoid.verts), 5, requires_grad=True)
    up_x, up_y = torch.randn_like(h), torch.randn_like(h)
    ax, ay = applied.apply(h)
    (g,) = torch.autograd.grad([ax, ay], h, [up_x, up_y])
    rx, ry = gx @ h, gy @ h
    (g_ref,) = torch.autograd.grad([rx, ry], h, [up_x, up_y])
    assert torch.equal(ax, rx) and torch.equal(ay, ry) and torch.equal(g, g_ref)


def test_gradients_reach_every_parameter_and_times_stay_non_negative(ellipsoid):
    torch.manual_seed(0)
    net = DiffusionNetBackbone(k_eig=K_EIG, width=16, out_channels=8, dropout=0.0)
    other = _sample(*_ellipsoid(subdivisions=1))
    # two forward passes (the two shapes of a pair) before one backward
    loss = net(ellipsoid).square().mean() + net(other).square().mean()
    loss.backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0, name
    block = net.net.blocks[0].diffusion
    with torch.no_grad():
        block.times.fill_(-1.0)
    net(ellipsoid)
    assert (block.times == 0).all()


def test_no_gradient_features_variant_and_errors(ellipsoid):
    net = DiffusionNet(3, 4, width=8, n_blocks=2, with_gradient_features=False, last_activation="relu")
    eig, grads = ellipsoid.operators["eigenbasis"], ellipsoid.operators["diffusion_gradients"]
    out = net(ellipsoid.verts, eig["evals"], eig["evecs"], eig["mass"], grads["grad_x"], grads["grad_y"])
    assert out.shape == (len(ellipsoid.verts), 4) and (out >= 0).all()
    with pytest.raises(ConfigError, match="in_channels"):
        DiffusionNetBackbone("wks")
    with pytest.raises(ConfigError):
        DiffusionNet(3, 4, dropout=1.0)
    with pytest.raises(ConfigError, match="eigenpairs"):
        DiffusionNetBackbone(k_eig=K_EIG + 1)(ellipsoid)
    with pytest.raises(ConfigError, match="expects input"):
        net(ellipsoid.verts[:, :2], eig["evals"], eig["evecs"], eig["mass"], grads["grad_x"], grads["grad_y"])


def test_config_builds_the_published_network():
    from pathlib import Path

    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    cfg = OmegaConf.load(Path(__file__).parents[2] / "configs" / "model" / "backbone" / "diffusion_net.yaml")
    net = instantiate(cfg)
    assert isinstance(net, DiffusionNetBackbone)
    assert net.required_operators == {"eigenbasis": {"k": 128}, "diffusion_gradients": {}}
    assert net.out_channels == 128 and len(net.net.blocks) == 4 and net.net.width == 128
    # 3 -> 128 input layer, 4 blocks of (128 times, complex 128x128, MLP 384-128-128-128), 128 -> 128 output
    block = 128 + 2 * 128 * 128 + (384 * 128 + 128) + 2 * (128 * 128 + 128)
    assert sum(p.numel() for p in net.parameters()) == (3 * 128 + 128) + 4 * block + (128 * 128 + 128)
    assert sum(isinstance(m, torch.nn.Dropout) and m.p == 0.5 for m in net.modules()) == 8
