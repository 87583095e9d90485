"""Tests of the plan-free Sinkhorn (``sinkhorn_sq_euclidean_products``) against the op-by-op log-domain oracle."""

from __future__ import annotations

import math

import pytest
import torch

import shapecorr.matching.sinkhorn as sk
from shapecorr.errors import ConfigError, NumericalError
from shapecorr.matching.sinkhorn import pairwise_sq_dists, sinkhorn_log_reference, sinkhorn_sq_euclidean_products


# Tiny tensors: one torch thread (OpenMP threading only adds overhead); fixture in tests/conftest.py.
pytestmark = pytest.mark.usefixtures("single_thread")


def _inputs(n, m, d, p, q, dtype=torch.float64, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(n, d, generator=g, dtype=dtype)
    y = torch.randn(m, d, generator=g, dtype=dtype)
    values_y = torch.randn(m, p, generator=g, dtype=dtype)
    values_x = torch.randn(n, q, generator=g, dtype=dtype)
    return x, y, values_y, values_x


def _reference(x, y, values_y, values_x, sigma, num_iters):
    plans = sinkhorn_log_reference(pairwise_sq_dists(x, y), sigma, num_iters)
    return plans.plan @ values_y, plans.plan_adj @ values_x, plans


@pytest.mark.parametrize("num_iters", [0, 1, 3, 10])
def test_products_equal_the_plans_applied_to_the_values(num_iters):
    x, y, vy, vx = _inputs(40, 33, 6, 5, 4, seed=num_iters)
    ref_py, ref_qx, ref = _reference(x, y, vy, vx, 0.1, num_iters)
    out = sinkhorn_sq_euclidean_products(x, y, vy, vx, 0.1, num_iters, return_plans=True)
    torch.testing.assert_close(out.py, ref_py, rtol=0, atol=1e-12)
    torch.testing.assert_close(out.qx, ref_qx, rtol=0, atol=1e-12)
    torch.testing.assert_close(out.plan, ref.plan, rtol=0, atol=1e-12)
    torch.testing.assert_close(out.plan_adj, ref.plan_adj, rtol=0, atol=1e-12)
    assert not out.plan.requires_grad
    plain = sinkhorn_sq_euclidean_products(x, y, vy, vx, 0.1, num_iters)
    assert plain.plan is None and plain.plan_adj is None


def test_constant_values_are_transported_to_constants():
    # rows of both plans sum to one: a constant is mapped to itself (float32, several kernel row blocks)
    x, y, _, _ = _inputs(70, 50, 3, 1, 1, dtype=torch.float32, seed=1)
    out = sinkhorn_sq_euclidean_products(x, y, torch.full((50, 2), 3.0), torch.full((70, 1), -2.0), 0.2, 3)
    torch.testing.assert_close(out.py, torch.full((70, 2), 3.0))
    torch.testing.assert_close(out.qx, torch.full((50, 1), -2.0))


@pytest.mark.parametrize("outputs", ["both", "py", "qx"])
def test_gradients_match_reference_autograd(outputs):
    x, y, vy, vx = _inputs(60, 45, 8, 7, 5, seed=3)
    leaves = [t.requires_grad_(True) for t in (x, y, vy, vx)]
    g = torch.Generator().manual_seed(4)
    w_py = torch.randn(60, 7, generator=g, dtype=torch.float64)
    w_qx = torch.randn(45, 5, generator=g, dtype=torch.float64)

    def loss(py, qx):
        terms = {"py": (py * w_py).sum(), "qx": (qx * w_qx).sum()}
        return terms["py"] + terms["qx"] if outputs == "both" else terms[outputs]

    ref_py, ref_qx, _ = _reference(x, y, vy, vx, 0.1, 3)
    ref = torch.autograd.grad(loss(ref_py, ref_qx), leaves, allow_unused=True)
    out = sinkhorn_sq_euclidean_products(x, y, vy, vx, 0.1, 3)
    got = torch.autograd.grad(loss(out.py, out.qx), leaves, allow_unused=True)
    for a, b in zip(got, ref):
        if b is None:  # values that do not reach the loss
            assert a is None or float(a.abs().max()) == 0.0
        else:
            torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("num_iters", [0, 2])
def test_gradcheck(num_iters):
    x, y, vy, vx = _inputs(5, 6, 3, 2, 3, seed=2)
    leaves = tuple(t.requires_grad_(True) for t in (x, y, vy, vx))
    assert torch.autograd.gradcheck(
        lambda *a: tuple(sinkhorn_sq_euclidean_products(*a, 0.3, num_iters)[:2]), leaves
    )


def test_nothing_of_size_n_times_m_is_kept_for_backward():
    n, m = 64, 48
    x, y, vy, vx = _inputs(n, m, 5, 4, 4, dtype=torch.float32, seed=7)
    x.requires_grad_(True)
    sizes = []

    def pack(t):
        sizes.append(t.numel())
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        sinkhorn_sq_euclidean_products(x, y, vy, vx, 0.1, 3)
    assert sizes and max(sizes) < n * m  # the kernel is rebuilt in backward


def test_second_backward_through_a_retained_graph_is_identical():
    # backward rebuilds the kernel and overwrites it with the gradient: a retained graph must not see that
    x, y, vy, vx = _inputs(30, 20, 4, 3, 2, seed=8)
    x.requires_grad_(True)
    out = sinkhorn_sq_euclidean_products(x, y, vy, vx, 0.1, 3)
    loss = out.py.square().sum() + out.qx.sum()
    first = torch.autograd.grad(loss, x, retain_graph=True)[0]
    second = torch.autograd.grad(loss, x)[0]
    assert torch.equal(first, second)


def test_kernel_blocks_give_the_unblocked_kernel(monkeypatch):
    x, y, _, _ = _inputs(50, 40, 4, 1, 1, dtype=torch.float32, seed=9)
    left, right, _, _ = sk._sq_euclidean_factors(x, y, 0.1)
    whole = sk._gibbs_kernel(left @ right.transpose(0, 1))
    monkeypatch.setattr(sk, "_BLOCK_BYTES", 7 * 40 * 4)  # 7 rows per block, the last one partial
    assert sk._row_block(50, 40, left) == 7
    blocked = sk._blocked_gibbs_kernel(left, right)
    # blocks change the float32 rounding of L (|L| <= 61 at the floor): |dK / K| = |dL| <= a few ulp(61)
    bound = 4 * torch.finfo(torch.float32).eps * 61
    torch.testing.assert_close(blocked, whole, rtol=bound, atol=0)
    assert torch.equal(blocked, sk._blocked_gibbs_kernel(left, right))  # rebuilt bitwise in backward
    # every row keeps its maximum at 1 and nothing below the floor
    torch.testing.assert_close(blocked.amax(1), torch.ones(50))
    assert float(blocked.min()) >= math.exp(sk._LOG_FLOOR_FRACTION * math.log(torch.finfo(torch.float32).tiny)) * 0.99


def test_concentrated_high_dimensional_features_need_no_fallback(monkeypatch):
    calls = []
    monkeypatch.setattr(sk, "sinkhorn_log_reference", lambda *a, **k: calls.append(1))
    x, y, vy, vx = _inputs(200, 150, 352, 3, 3, dtype=torch.float32, seed=5)
    out = sinkhorn_sq_euclidean_products(x, y, vy, vx, 0.1, 3)
    assert not calls
    monkeypatch.undo()
    ref_py, ref_qx, _ = _reference(x.double(), y.double(), vy.double(), vx.double(), 0.1, 3)
    torch.testing.assert_close(out.py.double(), ref_py, atol=1e-4, rtol=0)
    torch.testing.assert_close(out.qx.double(), ref_qx, atol=1e-4, rtol=0)


def test_underflowing_column_falls_back_to_log_domain(monkeypatch):
    x, y, vy, vx = _inputs(50, 40, 3, 2, 2, dtype=torch.float32, seed=6)
    y[0] += 40.0  # far from all of X: its kernel column underflows in float32
    calls = []
    original = sk.sinkhorn_log_reference

    def counting(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(sk, "sinkhorn_log_reference", counting)
    x.requires_grad_(True)
    out = sinkhorn_sq_euclidean_products(x, y, vy, vx, 0.1, 3, return_plans=True)
    assert calls, "the fast path should have detected the underflow"
    _, ref_qx, _ = _reference(x.detach().double(), y.double(), vy.double(), vx.double(), 0.1, 3)
    torch.testing.assert_close(out.qx.detach().double(), ref_qx, atol=1e-4, rtol=0)
    assert out.plan is not None and not out.plan.requires_grad
    (out.qx[0] * torch.arange(2.0)).sum().backward()
    assert torch.isfinite(x.grad).all()


def test_invalid_inputs_raise():
    x, y, vy, vx = _inputs(5, 4, 2, 3, 3)
    with pytest.raises(ConfigError):
        sinkhorn_sq_euclidean_products(x, y[:, :1], vy, vx)
    with pytest.raises(ConfigError, match="values_y"):
        sinkhorn_sq_euclidean_products(x, y, vy[:3], vx)
    with pytest.raises(ConfigError, match="values_y"):
        sinkhorn_sq_euclidean_products(x, y, vy, vx[:, 0])
    with pytest.raises(ConfigError, match="dtype"):
        sinkhorn_sq_euclidean_products(x, y, vy.float(), vx)
    with pytest.raises(ConfigError):
        sinkhorn_sq_euclidean_products(x, y, vy, vx, sigma=0.0)
    with pytest.raises(NumericalError):
        sinkhorn_sq_euclidean_products(torch.ones(3, 2), torch.ones(4, 2), torch.ones(4, 1), torch.ones(3, 1))
    bad = x.clone()
    bad[0, 0] = float("nan")
    with pytest.raises(NumericalError):
        sinkhorn_sq_euclidean_products(bad, y, vy, vx)
