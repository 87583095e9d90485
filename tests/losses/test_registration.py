"""Registration loss: zero at perfect alignment, the three normalizations against explicit sums, errors."""

import pytest
import torch

from shapecorr.errors import ConfigError, NumericalError
from shapecorr.losses.registration import ORIGINAL_ALIGN_NUMERATOR, registration_loss

DTYPE = torch.float64


def _random_soft_map(n, m, seed):
    gen = torch.Generator().manual_seed(seed)
    return torch.softmax(torch.randn(n, m, generator=gen, dtype=DTYPE) * 3.0, dim=1)


def test_zero_at_perfect_alignment_through_a_permutation():
    gen = torch.Generator().manual_seed(0)
    verts_y = torch.randn(40, 3, generator=gen, dtype=DTYPE)
    perm = torch.randperm(40, generator=gen)
    pi = torch.eye(40, dtype=DTYPE)[perm]  # x vertex i -> y vertex perm[i]
    deformed_x = verts_y[perm]
    for reduction in ("original", "mean", "sum"):
        loss = registration_loss(deformed_x, verts_y, pi, pi.T, reduction=reduction)
        assert float(loss) == pytest.approx(0.0, abs=1e-24)


@pytest.mark.parametrize("reduction", ["original", "mean", "sum"])
def test_matches_explicit_sums(reduction):
    n_x, n_y = 30, 50
    gen = torch.Generator().manual_seed(1)
    deformed_x = torch.randn(n_x, 3, generator=gen, dtype=DTYPE)
    verts_y = torch.randn(n_y, 3, generator=gen, dtype=DTYPE)
    pi, pi_inv = _random_soft_map(n_x, n_y, 2), _random_soft_map(n_y, n_x, 3)
    term_x = sum(float(((pi[i, :, None] * verts_y).sum(0) - deformed_x[i]).square().sum()) for i in range(n_x))
    term_y = sum(float((verts_y[j] - (pi_inv[j, :, None] * deformed_x).sum(0)).square().sum()) for j in range(n_y))
    expected = {
        "original": ORIGINAL_ALIGN_NUMERATOR / n_x * (term_x + term_y),
        "mean": term_x / n_x + term_y / n_y,
        "sum": term_x + term_y,
    }[reduction]
    loss = registration_loss(deformed_x, verts_y, pi, pi_inv, reduction=reduction)
    assert float(loss) == pytest.approx(expected, rel=1e-12)
    assert float(loss) > 0


def test_published_normalization_constant():
    assert ORIGINAL_ALIGN_NUMERATOR == 201.0


def test_gradient_points_towards_alignment():
    gen = torch.Generator().manual_seed(4)
    verts_y = torch.randn(20, 3, generator=gen, dtype=DTYPE)
    pi = torch.eye(20, dtype=DTYPE)
    deformed_x = (verts_y + 0.1 * torch.randn(20, 3, generator=gen, dtype=DTYPE)).requires_grad_()
    loss = registration_loss(deformed_x, verts_y, pi, pi.T)
    (grad,) = torch.autograd.grad(loss, deformed_x)
    stepped = registration_loss(deformed_x.detach() - 1e-4 * grad, verts_y, pi, pi.T)
    assert float(stepped) < float(loss.detach())


def test_errors():
    x, y = torch.zeros(4, 3), torch.zeros(5, 3)
    pi, pi_inv = torch.full((4, 5), 0.2), torch.full((5, 4), 0.25)
    with pytest.raises(ConfigError, match="reduction"):
        registration_loss(x, y, pi, pi_inv, reduction="avg")
    with pytest.raises(ConfigError, match="soft maps"):
        registration_loss(x, y, pi.T, pi_inv)
    bad = x.clone()
    bad[0, 0] = float("nan")
    with pytest.raises(NumericalError, match="not finite"):
        registration_loss(bad, y, pi, pi_inv)


def test_precomputed_soft_target_gives_the_same_value_and_gradients():
    n_x, n_y = 12, 15
    gen = torch.Generator().manual_seed(7)
    deformed_x = torch.randn(n_x, 3, generator=gen, dtype=DTYPE)
    verts_y = torch.randn(n_y, 3, generator=gen, dtype=DTYPE)
    maps = [_random_soft_map(n_x, n_y, 8), _random_soft_map(n_y, n_x, 9)]
    results = []
    for shared in (False, True):
        pi, pi_inv, x1 = (t.clone().requires_grad_() for t in (*maps, deformed_x))
        target = pi @ verts_y
        loss = registration_loss(x1, verts_y, pi, pi_inv, soft_target=target if shared else None)
        loss = loss + target.square().sum()  # a second use of the target, as the interpolator's input
        results.append((loss.detach(), *torch.autograd.grad(loss, [pi, pi_inv, x1])))
    for a, b in zip(*results):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    with pytest.raises(ConfigError, match="soft_target"):
        registration_loss(deformed_x, verts_y, *maps, soft_target=verts_y)
