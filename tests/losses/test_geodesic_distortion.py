"""Geodesic distortion: zero for the identity / a permutation, value and gradients equal the plain autograd
formula (symmetric and non-symmetric D_y, gradients w.r.t. all inputs; the block-symmetric fast path with
several panels, a non-symmetric D_x split exactly), the blockwise symmetry check, errors."""

import pytest
import torch

from shapecorr.errors import ConfigError, NumericalError
from shapecorr.losses import geodesic_distortion as geo_module
from shapecorr.losses.geodesic_distortion import geodesic_distortion_loss, is_symmetric

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


# -- the symmetric fast path (block panels of Pi D_y Pi^T, symmetric residual) --------------------------------

def _compare_with_plain(pi, dist_x, dist_y, **kwargs):
    ours = [t.clone().requires_grad_() for t in (pi, dist_x, dist_y)]
    ref = [t.clone().requires_grad_() for t in (pi, dist_x, dist_y)]
    loss, ref_loss = geodesic_distortion_loss(*ours, **kwargs), _plain(*ref)
    assert float(loss.detach()) == pytest.approx(float(ref_loss.detach()), rel=1e-12)
    for g, r in zip(torch.autograd.grad(loss, ours), torch.autograd.grad(ref_loss, ref)):
        torch.testing.assert_close(g, r, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("block", [1, 4, 5, 17, 64])
def test_block_panels_equal_plain_autograd(monkeypatch, block):
    """Panels of 4 rows on 17 vertices: five panels, the last one short; 1 row and 64 rows are the extremes."""
    monkeypatch.setattr(geo_module, "SYMMETRIC_BLOCK", block)
    n_x, n_y = 17, 11
    _compare_with_plain(_soft_map(n_x, n_y, 20), _distance_matrix(n_x, 21), _distance_matrix(n_y, 22))


def test_fast_path_is_taken_for_symmetric_inputs(monkeypatch):
    calls = []
    original = geo_module._GeodesicDistortionSymmetric.apply
    monkeypatch.setattr(geo_module._GeodesicDistortionSymmetric, "apply",
                        lambda *args: calls.append(1) or original(*args))
    geodesic_distortion_loss(_soft_map(6, 5, 23), _distance_matrix(6, 24), _distance_matrix(5, 25))
    assert calls == [1]


def test_non_symmetric_dist_x_is_split_exactly(monkeypatch):
    """D_x = S + K: ||B - D_x||^2 = ||B - S||^2 + ||K||^2; the value and the gradient w.r.t. Pi are exact, and a
    D_x that needs a gradient takes the general path (its gradient is -2/N (B - D_x), not symmetric)."""
    monkeypatch.setattr(geo_module, "SYMMETRIC_BLOCK", 3)
    n_x, n_y = 9, 8
    pi, dist_y = _soft_map(n_x, n_y, 26), _distance_matrix(n_y, 27)
    dist_x = _distance_matrix(n_x, 28) + torch.rand(n_x, n_x, generator=torch.Generator().manual_seed(29),
                                                    dtype=DTYPE)
    assert not is_symmetric(dist_x)
    pi_ours, pi_ref = pi.clone().requires_grad_(), pi.clone().requires_grad_()
    loss, ref = geodesic_distortion_loss(pi_ours, dist_x, dist_y), _plain(pi_ref, dist_x, dist_y)
    assert float(loss.detach()) == pytest.approx(float(ref.detach()), rel=1e-12)
    torch.testing.assert_close(torch.autograd.grad(loss, pi_ours)[0], torch.autograd.grad(ref, pi_ref)[0],
                               rtol=1e-10, atol=1e-12)
    _compare_with_plain(pi, dist_x, dist_y)  # all three need gradients here


def test_is_symmetric_blockwise():
    d = _distance_matrix(23, 30)
    for block in (1, 4, 23, 256):
        assert is_symmetric(d, block=block)
    asym = d.clone()
    asym[21, 2] += 1e-9  # in an off-diagonal block, seen from one side only
    nan = d.clone()
    nan[5, 5] = float("nan")
    for block in (1, 4, 23, 256):
        assert not is_symmetric(asym, block=block)
        assert not is_symmetric(nan, block=block)


def test_symmetric_flags_skip_the_checks_and_a_wrong_flag_changes_the_result():
    dist_x, dist_y = _distance_matrix(7, 31), _distance_matrix(8, 32)
    pi = _soft_map(7, 8, 33)
    flagged = geodesic_distortion_loss(pi, dist_x, dist_y, symmetric_dist_y=True, symmetric_dist_x=True)
    assert float(flagged) == pytest.approx(float(_plain(pi, dist_x, dist_y)), rel=1e-12)
    asym_x = dist_x + torch.triu(torch.ones(7, 7, dtype=DTYPE), 1)
    pi = pi.requires_grad_()
    (wrong,) = torch.autograd.grad(geodesic_distortion_loss(pi, asym_x, dist_y, symmetric_dist_x=True), pi)
    (right,) = torch.autograd.grad(geodesic_distortion_loss(pi, asym_x, dist_y), pi)
    (ref,) = torch.autograd.grad(_plain(pi, asym_x, dist_y), pi)
    torch.testing.assert_close(right, ref)
    assert not torch.allclose(wrong, ref)
