"""Geodesic distortion: zero for the identity / a permutation, value and gradients equal the plain autograd
formula (symmetric and non-symmetric D_y, gradients w.r.t. all inputs), errors."""

import pytest
import torch

from shapecorr.errors import ConfigError, NumericalError
from shapecorr.losses.geodesic_distortion import geodesic_distortion_loss

DTYPE = torch.float64


def _distance_matrix(n, seed):
    """Euclidean distances of random points: symmetric, zero diagonal (a stand-in for geodesics)."""
    gen = torch.Generator().manual_seed(seed)
    pts = torch.randn(n, 3, generator=gen, dtype=DTYPE)
    return torch.cdist(pts, pts)


def _soft_map(n, m, seed):
    gen = torch.Generator().manual_seed(seed)
    return torch.softmax(torch.randn(n, m, generator=gen, dtype=DTYPE) * 2.0, dim=1)


def _plain(pi, dist_x, dist_y):
    return (pi @ dist_y @ pi.T - dist_x).square().mean()


def test_zero_for_identity_and_permutation():
    d = _distance_matrix(30, 0)
    assert float(geodesic_distortion_loss(torch.eye(30, dtype=DTYPE), d, d)) == 0.0
    perm = torch.randperm(30, generator=torch.Generator().manual_seed(1))
    pi = torch.eye(30, dtype=DTYPE)[perm]  # x vertex i -> y vertex perm[i]; D_x = D_y[perm][:, perm]
    assert float(geodesic_distortion_loss(pi, d[perm][:, perm], d)) == pytest.approx(0.0, abs=1e-24)


@pytest.mark.parametrize("symmetric", [True, False])
def test_value_and_gradients_match_plain_autograd(symmetric):
    n_x, n_y = 17, 23
    dist_x, dist_y = _distance_matrix(n_x, 2), _distance_matrix(n_y, 3)
    if not symmetric:
        dist_y = dist_y + 0.1 * torch.rand(n_y, n_y, generator=torch.Generator().manual_seed(4), dtype=DTYPE)
    inputs = [_soft_map(n_x, n_y, 5), dist_x, dist_y]
    ours = [t.clone().requires_grad_() for t in inputs]
    ref = [t.clone().requires_grad_() for t in inputs]
    loss = geodesic_distortion_loss(*ours)
    ref_loss = _plain(*ref)
    assert float(loss.detach()) == pytest.approx(float(ref_loss.detach()), rel=1e-12)
    grads = torch.autograd.grad(loss, ours)
    ref_grads = torch.autograd.grad(ref_loss, ref)
    for g, r in zip(grads, ref_grads):
        torch.testing.assert_close(g, r, rtol=1e-10, atol=1e-12)


def test_symmetry_flag_is_detected_and_forcing_it_wrong_changes_only_the_gradient():
    dist_x, dist_y = _distance_matrix(6, 6), _distance_matrix(7, 7)
    dist_y = dist_y + torch.triu(torch.ones(7, 7, dtype=DTYPE), 1)  # not symmetric
    pi = _soft_map(6, 7, 8).requires_grad_()
    (g_auto,) = torch.autograd.grad(geodesic_distortion_loss(pi, dist_x, dist_y), pi)
    (g_ref,) = torch.autograd.grad(_plain(pi, dist_x, dist_y), pi)
    torch.testing.assert_close(g_auto, g_ref)
    (g_forced,) = torch.autograd.grad(geodesic_distortion_loss(pi, dist_x, dist_y, symmetric_dist_y=True), pi)
    assert not torch.allclose(g_forced, g_ref)


def test_gradcheck():
    dist_x, dist_y = _distance_matrix(5, 9), _distance_matrix(6, 10)
    pi = _soft_map(5, 6, 11).requires_grad_()
    assert torch.autograd.gradcheck(lambda p: geodesic_distortion_loss(p, dist_x, dist_y), (pi,))


def test_float32_and_positive():
    dist_x, dist_y = _distance_matrix(12, 12).float(), _distance_matrix(12, 13).float()
    loss = geodesic_distortion_loss(_soft_map(12, 12, 14).float(), dist_x, dist_y)
    assert loss.dtype == torch.float32 and float(loss) > 0


def test_errors():
    d = _distance_matrix(4, 15)
    pi = torch.full((4, 4), 0.25, dtype=DTYPE)
    with pytest.raises(ConfigError, match="expected pi"):
        geodesic_distortion_loss(pi, d, d[:3, :3])
    bad = d.clone()
    bad[0, 1] = float("inf")
    with pytest.raises(NumericalError, match="dist_y"):
        geodesic_distortion_loss(pi, d, bad)
    pi_nan = pi.clone()
    pi_nan[1, 1] = float("nan")
    with pytest.raises(NumericalError, match="not finite"):
        geodesic_distortion_loss(pi_nan, d, d)
