"""CUDA smoke tests: every method runs on ``cuda`` and agrees with its CPU run within a tolerance.

Each test trains one step (learned methods: same seed, same samples, same weights on both devices) or matches one
pair (axiomatic methods) on the CPU and on CUDA and compares the numbers. Small synthetic shapes built here (a
~400-vertex ellipsoid and a bent, vertex-permuted copy), small networks; no configuration files, no data folder.
They are marked ``gpu`` and skip without a CUDA device:

    python -m pytest -m gpu tests/gpu -q
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
    pytest.mark.filterwarnings("ignore:You are trying to `self.log\\(\\)`"),
]

N_EIG = 40
N_CHANNELS = 16


def _ellipsoid(n_lat: int = 18, n_lon: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """Closed latitude-longitude ellipsoid: two poles and ``(n_lat - 1) n_lon`` ring vertices."""
    theta = np.linspace(0.0, np.pi, n_lat + 1)[1:-1]
    phi = np.linspace(0.0, 2.0 * np.pi, n_lon, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    ring = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3)
    verts = np.concatenate([[[0.0, 0.0, 1.0]], ring, [[0.0, 0.0, -1.0]]]) * [1.3, 0.9, 0.7]
    rings = n_lat - 1
    idx = 1 + np.arange(rings * n_lon).reshape(rings, n_lon)
    nxt = np.roll(idx, -1, axis=1)
    faces = [np.stack([np.zeros(n_lon, int), idx[0], nxt[0]], 1)]
    for r in range(rings - 1):
        faces += [np.stack([idx[r], idx[r + 1], nxt[r + 1]], 1), np.stack([idx[r], nxt[r + 1], nxt[r]], 1)]
    south = len(verts) - 1
    faces.append(np.stack([np.full(n_lon, south), nxt[-1], idx[-1]], 1))
    return verts, np.concatenate(faces).astype(np.int64)


@pytest.fixture(scope="module")
def pair():
    """PairSample (eigenbasis, smooth random descriptors as "shot", DiffusionNet gradients) and the permutation:
    y's vertex perm[i] is x's vertex i."""
    from shapecorr.data.datasets import PairSample, ShapeSample
    from shapecorr.data.shape import make_shape
    from shapecorr.geometry.diffusion_operators import diffusion_gradients
    from shapecorr.geometry.laplace_beltrami import eigenbasis

    rng = np.random.default_rng(0)
    base, faces = _ellipsoid()
    feats = np.stack([np.sin((k + 1) * base @ rng.normal(size=3)) for k in range(N_CHANNELS)], 1).astype(np.float32)
    perm = rng.permutation(len(base))
    bent = base.copy()
    bent[:, 2] += 0.2 * np.sin(1.5 * bent[:, 0])
    verts_y, feats_y = np.empty_like(bent), np.empty_like(feats)
    verts_y[perm], feats_y[perm] = bent, feats

    def sample(verts, f, feat, name, corres):
        shape = make_shape(verts, f, name)
        v, fa = shape.verts.numpy().astype(np.float64), shape.faces.numpy()
        evals, evecs, mass = eigenbasis(v, fa, N_EIG)
        return ShapeSample(shape=shape, operators={
            "eigenbasis": {"evals": torch.as_tensor(evals, dtype=torch.float32),
                           "evecs": torch.as_tensor(evecs, dtype=torch.float32),
                           "mass": torch.as_tensor(mass, dtype=torch.float32)},
            "shot": {"shot": torch.as_tensor(feat)},
            "diffusion_gradients": diffusion_gradients(v, fa),
        }, corres=torch.as_tensor(corres, dtype=torch.int64))

    x = sample(base, faces, feats, "x", np.arange(len(base)))
    return PairSample(x, sample(verts_y, perm[faces], feats_y, "y", perm)), perm


def _train_step_both(model, batch):
    """Loss and gradients of one training step on the CPU and on CUDA (same initial weights)."""
    out = {}
    for device in ("cpu", "cuda"):
        m = copy.deepcopy(model).to(device).train()
        loss = m.training_step(batch.to(device), 0)
        loss.backward()
        grads = torch.cat([p.grad.detach().reshape(-1).cpu() for p in m.parameters() if p.grad is not None])
        out[device] = (float(loss.detach()), grads)
    return out


def _assert_step_agrees(out, rtol=1e-3):
    (loss_cpu, grad_cpu), (loss_gpu, grad_gpu) = out["cpu"], out["cuda"]
    assert np.isfinite(loss_gpu) and loss_gpu == pytest.approx(loss_cpu, rel=rtol)
    assert float((grad_gpu - grad_cpu).norm() / grad_cpu.norm()) < 10 * rtol


@pytest.fixture(scope="module")
def published_loss(compose_config):
    """``published_loss(model)``: the loss of ``configs/model/<model>.yaml`` (its ``model.loss`` node), built."""
    from hydra.utils import instantiate

    return lambda model: instantiate(compose_config("train", [f"model={model}"]).model.loss, _convert_="object")


def _map_agreement(model, x, y) -> float:
    """Fraction of vertices of x mapped to the same vertex of y on both devices."""
    maps = {d: copy.deepcopy(model).to(d).eval().match(x.to(d), y.to(d)).p2p.cpu() for d in ("cpu", "cuda")}
    return float((maps["cpu"] == maps["cuda"]).float().mean())


def test_deep_shells_cuda(pair, published_loss):
    from shapecorr.models.deep_shells import DeepShells
    from shapecorr.nn.spectral_conv import SpectralBackbone

    batch, _ = pair
    torch.manual_seed(0)
    model = DeepShells(backbone=SpectralBackbone(in_channels=N_CHANNELS, out_channels=8, num_eigs=30),
                       loss=published_loss("deep_shells"), num_samples=150,
                       layer=dict(k_array=[6, 8, 10], refine_k_min=6, refine_k_max=25, refine_levels=4))
    _assert_step_agrees(_train_step_both(model, batch))
    assert _map_agreement(model, batch.x, batch.y) > 0.95


def test_gmsm_cuda(pair, published_loss):
    from shapecorr.models.gmsm import GMSM
    from shapecorr.nn.diffusion_net import DiffusionNetBackbone

    batch, _ = pair
    torch.manual_seed(0)
    # dropout off: its random masks differ between the devices
    model = GMSM(backbone=DiffusionNetBackbone(k_eig=32, out_channels=8, width=8, n_blocks=1, dropout=0.0),
                 loss=published_loss("gmsm"), num_samples=150,
                 layer={"k_array": [6, 10, 14], "refine_k_max": 20, "refine_levels": 2})
    _assert_step_agrees(_train_step_both(model, batch))
    assert _map_agreement(model, batch.x, batch.y) > 0.95


def test_neuromorph_cuda(pair, tmp_path, published_loss):
    from shapecorr.models.neuromorph import NeuroMorph
    from shapecorr.nn.edgeconv_backbone import EdgeConvBackbone

    batch, _ = pair
    torch.manual_seed(0)
    small = dict(hidden_channels=16, n_blocks=2)
    model = NeuroMorph(backbone=EdgeConvBackbone(feature_dim=16, **small), interpolation_net=small,
                       loss=published_loss("neuromorph"), cache_dir=str(tmp_path))
    out = _train_step_both(model, batch)
    _assert_step_agrees(out, rtol=2e-3)


def test_hamiltonian_cuda():
    from shapecorr.axiomatic.hamiltonian import hamiltonian_interpolation

    verts, faces = _ellipsoid()
    v = torch.as_tensor(verts, dtype=torch.float32)
    target = v.clone()
    target[:, 2] += 0.2 * torch.sin(2.0 * v[:, 0])
    cfg = {"n_modes": 3, "iterations": 10, "lr": 0.05, "samples": 200}
    fits = {d: hamiltonian_interpolation(v.to(d), torch.as_tensor(faces).to(d), target.to(d), cfg,
                                         times=[0.5, 1.0]) for d in ("cpu", "cuda")}
    assert fits["cuda"].frames.device.type == "cuda"
    torch.testing.assert_close(fits["cuda"].frames.cpu(), fits["cpu"].frames, rtol=0, atol=1e-3)
    assert fits["cuda"].energies["loss"] == pytest.approx(fits["cpu"].energies["loss"], rel=1e-2)


def test_divfree_cuda(pair):
    from shapecorr.axiomatic.divfree import DivFreeMatcher

    batch, _ = pair
    matcher = DivFreeMatcher(modes=[2, 3], samples=[100, 200], iterations=[10, 10], lr=[0.01, 0.005],
                             descriptor_weight=[0.0, 0.0])
    results = {d: matcher.match(batch.x.to(d), batch.y.to(d)) for d in ("cpu", "cuda")}
    agree = float((results["cpu"].p2p == results["cuda"].p2p.cpu()).float().mean())
    assert agree > 0.9
    assert results["cuda"].deformation.device.type == "cuda"


def test_smooth_shells_cuda(pair):
    from shapecorr.axiomatic.smooth_shells import SmoothShells

    batch, _ = pair
    matcher = SmoothShells(k_max=20, k_array_length=5, num_mcmc=4, problem_size_init=100, icp_iterations=5)
    results = {d: matcher.match(batch.x.to(d), batch.y.to(d)) for d in ("cpu", "cuda")}
    agree = float((results["cpu"].p2p == results["cuda"].p2p.cpu()).float().mean())
    assert agree > 0.9
