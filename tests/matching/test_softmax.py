"""Softmax soft maps: stochasticity, oracle formula, identity recovery, chunked hard maps, the one-exponential
pair (gradients against plain autograd, the transposed view, the fallback when a row underflows), errors."""

import pytest
import torch
import torch.nn.functional as F

from shapecorr.errors import ConfigError, NumericalError
from shapecorr.matching import softmax as softmax_module
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


# -- one exponential for both maps, hand-written backward ------------------------------------------------------

def _plain_maps(fx, fy, sigma):
    s = sigma * (F.normalize(fx, dim=1) @ F.normalize(fy, dim=1).T)
    return torch.softmax(s, dim=1), torch.softmax(s.T, dim=1)


@pytest.mark.parametrize("use", ["both", "pi", "pi_inv"])
def test_gradients_equal_plain_autograd(use):
    """Value and gradients of both maps against two plain softmaxes (float64), with either map unused."""
    fx, fy = _features(13, d=5, seed=11, dtype=torch.float64), _features(17, d=5, seed=12, dtype=torch.float64)
    w1 = torch.randn(13, 17, generator=torch.Generator().manual_seed(13), dtype=torch.float64)
    w2 = torch.randn(17, 13, generator=torch.Generator().manual_seed(14), dtype=torch.float64)
    results = []
    for fn in (softmax_soft_maps, _plain_maps):
        a, b = fx.clone().requires_grad_(), fy.clone().requires_grad_()
        pi, pi_inv = fn(a, b, 9.0)
        loss = (0.0 if use == "pi_inv" else (pi * w1).sum()) + (0.0 if use == "pi" else (pi_inv * w2).sum())
        loss = loss + (0.0 if use == "pi" else (pi_inv @ torch.ones(13, 3, dtype=torch.float64)).square().sum())
        results.append((pi.detach(), pi_inv.detach(), *torch.autograd.grad(loss, [a, b])))
    for ours, ref in zip(*results):
        torch.testing.assert_close(ours, ref, rtol=1e-10, atol=1e-12)


def test_inverse_map_is_a_transposed_view_and_equals_the_formula():
    fx, fy = _features(8, seed=15), _features(6, seed=16)
    pi, pi_inv = softmax_soft_maps(fx, fy, sigma=5.0)
    assert pi.is_contiguous() and pi_inv.stride() == (1, 6)
    ref_pi, ref_inv = _plain_maps(fx, fy, 5.0)
    torch.testing.assert_close(pi, ref_pi)
    torch.testing.assert_close(pi_inv, ref_inv)
    torch.testing.assert_close(pi_inv.contiguous().view(-1), ref_inv.reshape(-1))


def test_underflowing_rows_fall_back_to_separate_shifts():
    """sigma = 1000 and one x feature opposite to all of y's: its row of exp(sigma S - max) underflows to 0
    (it would divide 0 by 0); the shared-shift path declines and two separately shifted softmaxes run."""
    fy = F.normalize(torch.ones(5, 4, dtype=torch.float64) + 0.1 * _features(5, d=4, seed=17, dtype=torch.float64),
                     dim=1)
    fx = torch.cat((fy[:3], -fy[:1]))
    assert softmax_module._SoftmaxBothWays.apply(fx, fy, 1000.0) is None
    fx = fx.clone().requires_grad_()
    pi, pi_inv = softmax_soft_maps(fx, fy, sigma=1000.0)
    assert bool(torch.isfinite(pi).all()) and bool(torch.isfinite(pi_inv).all())
    torch.testing.assert_close(pi.sum(1), torch.ones(4, dtype=torch.float64))
    torch.testing.assert_close(pi_inv.sum(1), torch.ones(5, dtype=torch.float64))
    ref_pi, ref_inv = _plain_maps(fx.detach(), fy, 1000.0)
    torch.testing.assert_close(pi, ref_pi)
    torch.testing.assert_close(pi_inv, ref_inv)
    (grad,) = torch.autograd.grad((pi @ torch.randn(5, 3, dtype=torch.float64)).square().sum(), fx)
    assert bool(torch.isfinite(grad).all())
