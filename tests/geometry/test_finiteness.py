"""The finiteness test by one reduction agrees with the elementwise test on every kind of input."""

import pytest
import torch

from shapecorr.geometry.finiteness import all_finite


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16])
def test_all_finite_agrees_with_isfinite(dtype):
    g = torch.Generator().manual_seed(0)
    base = torch.randn(40, 7, generator=g).to(dtype)
    big = torch.finfo(dtype).max
    cases = [base, base[:, 2:5], base.new_empty(0, 3)]
    for value in (float("nan"), float("inf"), -float("inf")):
        bad = base.clone()
        bad[13, 4] = value
        cases += [bad, bad.transpose(0, 1)]
    both_inf = base.clone()
    both_inf[0, 0], both_inf[1, 1] = float("inf"), -float("inf")  # the sum is NaN
    overflow = base.new_full((4,), big)  # finite elements whose sum overflows: still finite
    cases += [both_inf, overflow, -overflow]
    for t in cases:
        assert all_finite(t) == bool(torch.isfinite(t).all()), t
    assert all_finite(overflow) and all_finite(base, overflow) and not all_finite(base, cases[3])


def test_all_finite_other_inputs():
    assert all_finite()
    assert all_finite(torch.arange(5), torch.ones(3, dtype=torch.bool))
    x = torch.randn(5, requires_grad=True)
    assert all_finite(x * 2.0)
    y = x.detach().clone()
    y[2] = float("nan")
    assert not all_finite(y.requires_grad_())
    z = torch.tensor([1 + 2j, float("inf") + 0j])
    assert not all_finite(z) and all_finite(z[:1])
