"""Tests of the spectral filter bank (shapecorr.nn.spectral_conv)."""

from __future__ import annotations

import math

import pytest
import torch

from shapecorr.errors import ConfigError
from shapecorr.nn.spectral_conv import (
    DEFAULT_MAX_FREQUENCY,
    ORIGINAL_FILTER_SCALE,
    SpectralConv,
    SpectralFilterBank,
    cosine_filter_basis,
    load_original_deep_shells_weights,
)


def _operators(n=60, k=24, dtype=torch.float64, seed=0):
    """Random operators: a mass vector and eigenvectors orthonormal w.r.t. it, ascending eigenvalues."""
    g = torch.Generator().manual_seed(seed)
    mass = torch.rand(n, generator=g, dtype=dtype) + 0.5
    q, _ = torch.linalg.qr(torch.randn(n, k, generator=g, dtype=dtype))
    evecs = q / mass.sqrt()[:, None]  # evecs^T diag(mass) evecs = I
    evals = torch.sort(torch.rand(k, generator=g, dtype=dtype) * 3e4).values
    evals[0] = 0.0
    return evecs, evals, mass


def _naive_forward(layer: SpectralConv, features, evecs, evals, mass):
    """g_j = sum_c Phi diag(h_cj(lambda)) Phi^T A f_c with every filter evaluated one by one."""
    k = layer.num_eigs
    phi, lam = evecs[:, :k], evals[:k]
    out = torch.zeros(features.shape[0], layer.out_channels, dtype=features.dtype)
    for j in range(layer.out_channels):
        for c in range(layer.in_channels):
            h = torch.stack([
                sum(layer.weight[m, c, j] * math.cos(m * math.pi * float(lam[i]) / layer.max_frequency)
                    for m in range(layer.num_basis)) + layer.bias[c, j]
                for i in range(k)
            ])
            out[:, j] += phi @ (h * (phi.T @ (mass * features[:, c])))
    return out


def test_forward_matches_naive_per_filter_oracle():
    torch.manual_seed(0)
    evecs, evals, mass = _operators()
    layer = SpectralConv(4, 3, num_basis=5, num_eigs=20, max_frequency=2.5e4).double()
    f = torch.randn(60, 4, dtype=torch.float64)
    with torch.no_grad():
        torch.testing.assert_close(layer(f, evecs, evals, mass), _naive_forward(layer, f, evecs, evals, mass))
        filt = layer.filters(evals[:20])
        assert filt.shape == (20, 4, 3)


def test_linear_in_features_and_rows_select_vertices():
    torch.manual_seed(1)
    evecs, evals, mass = _operators()
    bank = SpectralFilterBank(5, 7, num_basis=6, num_eigs=16).double()
    f1, f2 = torch.randn(60, 5, dtype=torch.float64), torch.randn(60, 5, dtype=torch.float64)
    with torch.no_grad():
        lhs = bank(2.0 * f1 - 0.5 * f2, evecs, evals, mass)
        rhs = 2.0 * bank(f1, evecs, evals, mass) - 0.5 * bank(f2, evecs, evals, mass)
        torch.testing.assert_close(lhs, rhs)
        rows = torch.tensor([3, 3, 0, 59, 17])
        torch.testing.assert_close(bank(f1, evecs, evals, mass, rows=rows), bank(f1, evecs, evals, mass)[rows])


def test_identity_filter_reproduces_band_limited_signals():
    evecs, evals, mass = _operators()
    layer = SpectralConv(3, 3, num_basis=4, num_eigs=24).double()
    with torch.no_grad():
        layer.weight.zero_()
        layer.bias.copy_(torch.eye(3, dtype=torch.float64))
        signal = evecs[:, :24] @ torch.randn(24, 3, dtype=torch.float64)  # in the span of the basis
        torch.testing.assert_close(layer(signal, evecs, evals, mass), signal)


def test_invariant_to_eigenvector_signs():
    torch.manual_seed(2)
    evecs, evals, mass = _operators()
    bank = SpectralFilterBank(4, 2, num_eigs=20).double()
    flip = torch.ones(24, dtype=torch.float64)
    flip[[1, 4, 7, 19]] = -1
    f = torch.randn(60, 4, dtype=torch.float64)
    with torch.no_grad():
        torch.testing.assert_close(bank(f, evecs * flip, evals, mass), bank(f, evecs, evals, mass))


def test_default_is_the_published_single_linear_layer():
    bank = SpectralFilterBank()
    assert len(bank.layers) == 1
    layer = bank.layers[0]
    assert (layer.in_channels, layer.out_channels, layer.num_basis, layer.num_eigs) == (352, 120, 16, 200)
    assert bank.max_frequency == DEFAULT_MAX_FREQUENCY == ORIGINAL_FILTER_SCALE / 2
    assert sum(p.numel() for p in bank.parameters()) == 352 * 120 * 16 + 352 * 120


def test_cosine_basis_values():
    lam = torch.tensor([0.0, 2.5e4, 1.25e4], dtype=torch.float64)
    basis = cosine_filter_basis(lam, 3, 2.5e4)
    expected = torch.tensor([[1.0, 1.0, 1.0], [1.0, -1.0, 1.0], [1.0, 0.0, -1.0]], dtype=torch.float64)
    torch.testing.assert_close(basis, expected, atol=1e-12, rtol=0)


def test_stacked_layers_are_nonlinear_and_train_all_parameters():
    torch.manual_seed(3)
    evecs, evals, mass = _operators()
    bank = SpectralFilterBank(4, 3, hidden_channels=(6, 5), num_eigs=20, activation="relu").double()
    f = torch.randn(60, 4, dtype=torch.float64)
    out = bank(f, evecs, evals, mass)
    assert out.shape == (60, 3)
    assert not torch.allclose(bank(-f, evecs, evals, mass), -out)
    out.square().sum().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in bank.parameters())


def _write_original_checkpoint(path, c_in, c_out, num_basis, seed=0, filter_scale=ORIGINAL_FILTER_SCALE):
    g = torch.Generator().manual_seed(seed)
    state = {
        "conv.a.0.weight": torch.randn(c_in * c_out, num_basis, generator=g),
        "conv.a.0.bias": torch.randn(c_in * c_out, generator=g),
    }
    torch.save({"i_epoch": 20, "feat_mod": state, "par": {"filter_scale": filter_scale, "fac_spec": 0.3}}, path)
    return state


def test_load_original_weights_reproduces_the_original_formula(tmp_path):
    """Original: L = Linear(16 -> c_in*c_out)(cos(m pi lambda2 / 5e4)), index c*c_out + j, lambda2 = 2 lambda."""
    c_in, c_out, nb, k = 5, 3, 16, 20
    path = tmp_path / "ckpt_ep20.pth"
    state = _write_original_checkpoint(path, c_in, c_out, nb)
    bank = SpectralFilterBank(c_in, c_out, num_basis=nb, num_eigs=k)
    par = load_original_deep_shells_weights(bank, path)
    assert par["fac_spec"] == 0.3

    evecs, evals, mass = _operators(k=24, dtype=torch.float32)
    f = torch.randn(60, c_in)
    evals_doubled = 2.0 * evals[:k]
    basis = torch.cos(torch.arange(nb)[None, :] * evals_doubled[:, None] * math.pi / ORIGINAL_FILTER_SCALE)
    filt = (basis @ state["conv.a.0.weight"].T + state["conv.a.0.bias"]).view(k, c_in, c_out)
    spec = (evecs[:, :k].T @ (f * mass[:, None]))[:, :, None]
    expected = evecs[:, :k] @ (spec * filt).sum(1)
    with torch.no_grad():
        got = bank(f, evecs, evals, mass)  # shapecorr eigenvalues (half the original ones)
    torch.testing.assert_close(got, expected, rtol=1e-4, atol=1e-5 * float(expected.abs().max()))


def test_load_original_weights_errors(tmp_path):
    bank = SpectralFilterBank(5, 3, num_basis=16, num_eigs=20)
    with pytest.raises(ConfigError, match="not found"):
        load_original_deep_shells_weights(bank, tmp_path / "missing.pth")
    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(b"not a checkpoint")
    with pytest.raises(ConfigError, match="garbage.pth"):
        load_original_deep_shells_weights(bank, garbage)
    wrong = tmp_path / "wrong.pth"
    _write_original_checkpoint(wrong, 4, 3, 16)
    with pytest.raises(ConfigError, match="do not fit"):
        load_original_deep_shells_weights(bank, wrong)
    scale = tmp_path / "scale.pth"
    _write_original_checkpoint(scale, 5, 3, 16, filter_scale=1e4)
    with pytest.raises(ConfigError, match="filter_scale"):
        load_original_deep_shells_weights(bank, scale)
    no_keys = tmp_path / "nokeys.pth"
    torch.save({"feat_mod": {"something": torch.zeros(1)}}, no_keys)
    with pytest.raises(ConfigError, match="missing"):
        load_original_deep_shells_weights(bank, no_keys)
    good = tmp_path / "good.pth"
    _write_original_checkpoint(good, 5, 3, 16)
    with pytest.raises(ConfigError, match="single layer"):
        load_original_deep_shells_weights(SpectralFilterBank(5, 3, hidden_channels=(4,), num_eigs=20), good)


def test_bad_inputs_raise_config_errors():
    evecs, evals, mass = _operators(dtype=torch.float32)
    bank = SpectralFilterBank(4, 2, num_eigs=20)
    with pytest.raises(ConfigError, match="features"):
        bank(torch.randn(60, 5), evecs, evals, mass)
    with pytest.raises(ConfigError, match="eigenpairs"):
        SpectralFilterBank(4, 2, num_eigs=30)(torch.randn(60, 4), evecs, evals, mass)
    with pytest.raises(ConfigError, match="operators"):
        bank(torch.randn(60, 4), evecs[:50], evals, mass[:50])
    with pytest.raises(ConfigError):
        SpectralFilterBank(4, 2, activation="swish")
    with pytest.raises(ConfigError):
        SpectralConv(4, 2, max_frequency=0.0)
