"""Softmax soft maps: stochasticity, oracle formula, identity recovery, chunked hard maps, errors."""

import pytest
import torch
import torch.nn.functional as F

from shapecorr.errors import ConfigError, NumericalError
from shapecorr.matching.softmax import (
    DEFAULT_SIGMA,
    cosine_similarity,
    hard_maps,
    soft_map_to_p2p,
    softmax_soft_maps,
)


def _features(n, d=16, seed=0, dtype=torch.float32):
    gen = torch.Generator().manual_seed(seed)
    return torch.randn(n, d, generator=gen, dtype=dtype)


def test_soft_maps_are_row_stochastic_and_match_formula():
    fx, fy = _features(30, seed=1, dtype=torch.float64), _features(45, seed=2, dtype=torch.float64)
    pi, pi_inv = softmax_soft_maps(fx, fy, sigma=7.0)
    assert pi.shape == (30, 45) and pi_inv.shape == (45, 30)
    torch.testing.assert_close(pi.sum(1), torch.ones(30, dtype=torch.float64))
    torch.testing.assert_close(pi_inv.sum(1), torch.ones(45, dtype=torch.float64))
    assert bool((pi >= 0).all()) and bool((pi_inv >= 0).all())
    s = F.normalize(fx, dim=1) @ F.normalize(fy, dim=1).T
    e = torch.exp(7.0 * s)
    torch.testing.assert_close(pi, e / e.sum(1, keepdim=True))
    torch.testing.assert_close(pi_inv, (e / e.sum(0, keepdim=True)).T)


def test_default_sigma_is_published_value_and_rows_stay_finite():
    assert DEFAULT_SIGMA == 100.0
    fx = _features(50, seed=3)
    pi, pi_inv = softmax_soft_maps(fx, fx * 3.0)  # scaling does not matter after normalization
    assert bool(torch.isfinite(pi).all()) and bool(torch.isfinite(pi_inv).all())
    torch.testing.assert_close(pi.sum(1), torch.ones(50))


def test_identical_features_recover_identity():
    fx = _features(200, d=32, seed=4)
    pi, pi_inv = softmax_soft_maps(fx, fx.clone())
    identity = torch.arange(200)
    assert torch.equal(soft_map_to_p2p(pi), identity)
    assert torch.equal(soft_map_to_p2p(pi_inv), identity)
    p2p, p2p_inv = hard_maps(fx, fx.clone())
    assert torch.equal(p2p, identity) and torch.equal(p2p_inv, identity)


def test_permuted_features_recover_permutation():
    fx = _features(60, seed=5)
    perm = torch.randperm(60, generator=torch.Generator().manual_seed(6))
    p2p, p2p_inv = hard_maps(fx, fx[perm], chunk_size=7)
    # x vertex i has the features of y vertex inv[i]
    inv = torch.empty_like(perm)
    inv[perm] = torch.arange(60)
    assert torch.equal(p2p, inv) and torch.equal(p2p_inv, perm)


def test_chunked_hard_maps_equal_full_argmax_including_ties():
    fx, fy = _features(37, seed=7), _features(23, seed=8)
    fy[5] = fy[11]  # duplicate target features: ties in the x -> y argmax
    fx[3] = fx[30]  # duplicate source features: ties in the y -> x argmax
    s = cosine_similarity(fx, fy)
    for chunk in (1, 5, 37, 100):
        p2p, p2p_inv = hard_maps(fx, fy, chunk_size=chunk)
        assert torch.equal(p2p, s.argmax(dim=1))
        assert torch.equal(p2p_inv, s.argmax(dim=0))
    assert not bool((p2p == 11).any())  # the first of two equal maxima wins


def test_gradients_flow_and_are_finite():
    fx = _features(20, seed=9).requires_grad_()
    fy = _features(25, seed=10).requires_grad_()
    pi, pi_inv = softmax_soft_maps(fx, fy)
    target = torch.randn(25, 3)
    loss = (pi @ target).square().sum() + (pi_inv @ torch.randn(20, 3)).square().sum()
    gx, gy = torch.autograd.grad(loss, [fx, fy])
    assert bool(torch.isfinite(gx).all()) and bool(torch.isfinite(gy).all())
    assert gx.abs().sum() > 0 and gy.abs().sum() > 0


def test_errors():
    fx, fy = _features(5), _features(6)
    with pytest.raises(ConfigError, match="same d"):
        softmax_soft_maps(fx, _features(6, d=8))
    with pytest.raises(ConfigError, match="positive"):
        softmax_soft_maps(fx, fy, sigma=0.0)
    bad = fy.clone()
    bad[2, 1] = float("nan")
    with pytest.raises(NumericalError, match="feat_y"):
        softmax_soft_maps(fx, bad)
    with pytest.raises(NumericalError):
        hard_maps(bad, fx)
    with pytest.raises(ConfigError, match="empty"):
        hard_maps(fx[:0], fy)
    with pytest.raises(ConfigError, match="chunk_size"):
        hard_maps(fx, fy, chunk_size=0)
    with pytest.raises(ConfigError, match=r"\(n, m\)"):
        soft_map_to_p2p(torch.ones(4))
