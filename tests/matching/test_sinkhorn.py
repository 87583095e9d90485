"""Tests of the Deep Shells Sinkhorn layer (shapecorr.matching.sinkhorn)."""

from __future__ import annotations

import pytest
import torch

import shapecorr.matching.sinkhorn as sk
from shapecorr.errors import ConfigError, NumericalError
from shapecorr.matching.sinkhorn import (
    pairwise_sq_dists,
    sinkhorn,
    sinkhorn_log_reference,
    sinkhorn_sq_euclidean,
)


def _points(n, m, d, dtype=torch.float64, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(n, d, generator=g, dtype=dtype), torch.randn(m, d, generator=g, dtype=dtype)


def test_pairwise_sq_dists_matches_naive_and_is_nonnegative():
    x, y = _points(17, 11, 5)
    d = pairwise_sq_dists(x, y)
    naive = ((x[:, None, :] - y[None, :, :]) ** 2).sum(-1)
    torch.testing.assert_close(d, naive, rtol=1e-12, atol=1e-12)
    # identical sets: the expansion can round below zero; the clamp keeps the diagonal at >= 0
    dd = pairwise_sq_dists(x * 1e3, x * 1e3)
    assert (dd >= 0).all()
    assert dd.diagonal().abs().max() < 1e-6 * dd.max()


def test_pairwise_sq_dists_gradcheck():
    x, y = _points(4, 5, 3)
    x.requires_grad_(True)
    y.requires_grad_(True)
    assert torch.autograd.gradcheck(pairwise_sq_dists, (x, y))


@pytest.mark.parametrize("num_iters", [0, 1, 3, 10])
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-5)])
def test_fast_paths_match_log_domain_reference(num_iters, dtype, tol):
    x, y = _points(40, 33, 6, dtype=dtype, seed=num_iters)
    cost = pairwise_sq_dists(x, y)
    ref = sinkhorn_log_reference(cost, 0.1, num_iters)
    for plans in (sinkhorn(cost, 0.1, num_iters), sinkhorn_sq_euclidean(x, y, 0.1, num_iters)):
        torch.testing.assert_close(plans.plan, ref.plan, rtol=0, atol=tol)
        torch.testing.assert_close(plans.plan_adj, ref.plan_adj, rtol=0, atol=tol)


def test_plans_are_row_stochastic_and_converge_to_doubly_stochastic():
    x, y = _points(30, 30, 4)
    plan, plan_adj = sinkhorn_sq_euclidean(x, y, sigma=0.3, num_iters=3)
    assert plan.shape == (30, 30) and plan_adj.shape == (30, 30)
    torch.testing.assert_close(plan.sum(1), torch.ones(30, dtype=torch.float64))
    torch.testing.assert_close(plan_adj.sum(1), torch.ones(30, dtype=torch.float64))
    assert (plan >= 0).all() and (plan_adj >= 0).all()
    # few iterations: not doubly stochastic; many: columns sum to 1 too and both plans agree
    assert (plan.sum(0) - 1).abs().max() > 1e-4
    plan, plan_adj = sinkhorn_sq_euclidean(x, y, sigma=0.3, num_iters=500)
    torch.testing.assert_close(plan.sum(0), torch.ones(30, dtype=torch.float64), atol=1e-8, rtol=0)
    torch.testing.assert_close(plan_adj.transpose(0, 1), plan, atol=1e-8, rtol=0)


def test_zero_iterations_is_a_row_softmax_oracle():
    x, y = _points(9, 7, 3)
    cost = pairwise_sq_dists(x, y)
    sigma = 0.2
    logits = -cost / cost.mean() / (2 * sigma**2)
    plan_oracle = torch.softmax(logits, dim=1)
    adj_oracle = (plan_oracle / plan_oracle.sum(0, keepdim=True)).transpose(0, 1)
    plan, plan_adj = sinkhorn(cost, sigma, 0)
    torch.testing.assert_close(plan, plan_oracle)
    torch.testing.assert_close(plan_adj, adj_oracle)


def test_plans_are_invariant_to_cost_scale():
    x, y = _points(12, 10, 3)
    cost = pairwise_sq_dists(x, y)
    a = sinkhorn(cost, 0.1, 3)
    b = sinkhorn(cost * 37.5, 0.1, 3)
    torch.testing.assert_close(a.plan, b.plan)
    torch.testing.assert_close(a.plan_adj, b.plan_adj)


@pytest.mark.parametrize("num_iters", [0, 2])
def test_gradcheck_cost_version(num_iters):
    g = torch.Generator().manual_seed(1)
    cost = torch.rand(5, 6, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda c: sinkhorn(c, 0.3, num_iters), (cost,))
    # gradients of one output only (the other gets no gradient)
    assert torch.autograd.gradcheck(lambda c: sinkhorn(c, 0.3, num_iters).plan, (cost,))
    assert torch.autograd.gradcheck(lambda c: sinkhorn(c, 0.3, num_iters).plan_adj, (cost,))


@pytest.mark.parametrize("num_iters", [0, 3])
def test_gradcheck_fused_version(num_iters):
    x, y = _points(5, 6, 3, seed=2)
    x.requires_grad_(True)
    y.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: sinkhorn_sq_euclidean(a, b, 0.3, num_iters), (x, y))


def test_gradients_match_reference_autograd():
    x, y = _points(60, 45, 8, seed=3)
    x.requires_grad_(True)
    y.requires_grad_(True)
    g = torch.Generator().manual_seed(4)
    w1 = torch.randn(60, 45, generator=g, dtype=torch.float64)
    w2 = torch.randn(45, 60, generator=g, dtype=torch.float64)

    def grads(fn):
        plan, plan_adj = fn()
        return torch.autograd.grad((plan * w1).sum() + (plan_adj * w2).sum(), (x, y))

    ref = grads(lambda: sinkhorn_log_reference(pairwise_sq_dists(x, y), 0.1, 3))
    for fn in (lambda: sinkhorn(pairwise_sq_dists(x, y), 0.1, 3), lambda: sinkhorn_sq_euclidean(x, y, 0.1, 3)):
        for got, want in zip(grads(fn), ref):
            torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-12)


def test_concentrated_high_dimensional_costs_need_no_fallback(monkeypatch):
    # Untrained 352-D features: all distances near the mean, log-kernel entries ~ -50 everywhere; the row
    # shift keeps float32 exact without the slow path.
    calls = []
    monkeypatch.setattr(sk, "sinkhorn_log_reference", lambda *a, **k: calls.append(1))
    x, y = _points(200, 150, 352, dtype=torch.float32, seed=5)
    plan, plan_adj = sinkhorn_sq_euclidean(x, y, 0.1, 3)
    assert not calls
    monkeypatch.undo()
    ref = sinkhorn_log_reference(pairwise_sq_dists(x.double(), y.double()), 0.1, 3)
    torch.testing.assert_close(plan.double(), ref.plan, atol=1e-5, rtol=0)
    torch.testing.assert_close(plan_adj.double(), ref.plan_adj, atol=1e-5, rtol=0)


def test_underflowing_column_falls_back_to_log_domain(monkeypatch):
    # One point of Y far from all of X: its column of the float32 kernel underflows to 0.
    x, y = _points(50, 40, 3, dtype=torch.float32, seed=6)
    y[0] += 40.0
    calls = []
    original = sk.sinkhorn_log_reference

    def counting(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(sk, "sinkhorn_log_reference", counting)
    x.requires_grad_(True)
    plan, plan_adj = sinkhorn_sq_euclidean(x, y, 0.1, 3)
    assert calls, "the fast path should have detected the underflow"
    assert torch.isfinite(plan).all() and torch.isfinite(plan_adj).all()
    torch.testing.assert_close(plan_adj.sum(1), torch.ones(40))
    ref = original(pairwise_sq_dists(x.detach().double(), y.double()), 0.1, 3)
    torch.testing.assert_close(plan.detach().double(), ref.plan, atol=1e-5, rtol=0)
    # gradients still flow through the fallback
    (plan_adj[0] * torch.arange(50.0)).sum().backward()
    assert torch.isfinite(x.grad).all()


def test_invalid_inputs_raise():
    x, y = _points(5, 4, 2)
    cost = pairwise_sq_dists(x, y)
    bad = cost.clone()
    bad[1, 2] = float("nan")
    with pytest.raises(NumericalError):
        sinkhorn(bad)
    with pytest.raises(NumericalError):
        sinkhorn_log_reference(bad)
    with pytest.raises(NumericalError):
        sinkhorn(torch.zeros(3, 4, dtype=torch.float64))
    with pytest.raises(NumericalError):
        sinkhorn_sq_euclidean(torch.ones(3, 2), torch.ones(4, 2))
    with pytest.raises(ConfigError):
        sinkhorn(cost, sigma=0.0)
    with pytest.raises(ConfigError):
        sinkhorn(cost, num_iters=-1)
    with pytest.raises(ConfigError):
        sinkhorn_sq_euclidean(x, y[:, :1])


def _saved_large_tensors(fn, n, m):
    """Number of tensors with >= n*m elements that autograd keeps for backward."""
    count = []

    def pack(t):
        if t.numel() >= n * m:
            count.append(t.numel())
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        fn()
    return len(count)


def test_backward_memory_is_a_few_plans():
    n, m = 64, 48
    x, y = _points(n, m, 5, dtype=torch.float32, seed=7)
    x.requires_grad_(True)
    fast = _saved_large_tensors(lambda: sinkhorn_sq_euclidean(x, y, 0.1, 3), n, m)
    reference = _saved_large_tensors(lambda: sinkhorn_log_reference(pairwise_sq_dists(x, y), 0.1, 3), n, m)
    assert fast <= 3  # kernel + the two outputs
    assert reference > 2 * fast
