"""The refinement's normal equations carried from level to level equal the per-level solve."""

from __future__ import annotations

import pytest
import torch

import shapecorr.matching.deep_shells as ds
from shapecorr.errors import ConfigError
from shapecorr.matching.deep_shells import deformation_from_pairs


# Tiny tensors: one torch thread (OpenMP threading only adds overhead); fixture in tests/conftest.py.
pytestmark = pytest.mark.usefixtures("single_thread")


def _problem(n_x=180, n_y=150, kmax=40, seed=0):
    g = torch.Generator().manual_seed(seed)
    phi_x = torch.linalg.qr(torch.randn(n_x, kmax, generator=g, dtype=torch.float64))[0] * n_x**0.5
    phi_y = torch.linalg.qr(torch.randn(n_y, kmax, generator=g, dtype=torch.float64))[0] * n_y**0.5
    map_x_to_y = torch.randint(0, n_y, (n_x,), generator=g)
    map_y_to_x = torch.randint(0, n_x, (n_y,), generator=g)
    return phi_x, phi_y, map_x_to_y, map_y_to_x, g


def _perturb(m, n_target, fraction, g):
    m = m.clone()
    idx = torch.randperm(m.numel(), generator=g)[: int(fraction * m.numel())]
    m[idx] = torch.randint(0, n_target, (idx.numel(),), generator=g)
    return m


@pytest.mark.parametrize("row_block, dtype", [(None, torch.float64), (None, torch.float32), (37, torch.float64),
                                              (37, torch.float32)])
def test_carried_normal_equations_equal_the_per_level_solve(monkeypatch, row_block, dtype):
    """Also with products summed over row blocks (large meshes) and float32 bases (converted once when a basis fits
    in one block, else per block)."""
    if row_block is not None:
        monkeypatch.setattr(ds, "REFINE_ROW_BLOCK", row_block)
    phi_x, phi_y, mxy, myx, g = _problem()
    phi_x, phi_y = phi_x.to(dtype), phi_y.to(dtype)
    n_x, n_y = phi_x.shape[0], phi_y.shape[0]
    calls = {"_rebuild": 0, "_update": 0, "_extend": 0}
    for name in calls:
        original = getattr(ds._PairNormalEquations, name)

        def counted(self, *args, _original=original, _name=name):
            calls[_name] += 1
            return _original(self, *args)

        monkeypatch.setattr(ds._PairNormalEquations, name, counted)
    system = ds._PairNormalEquations(phi_x, phi_y)
    # one row block: the bases converted to float64 once; more: kept in their dtype, converted per block
    assert system.phi_x.dtype == (torch.float64 if row_block is None else dtype)
    assert system.phi_y.dtype == system.phi_x.dtype
    # growing k with few changed pairs (update + extension), a repeated k, most pairs changed, unchanged
    # pairs, and a smaller k (rebuild)
    schedule = [(6, 0.0), (6, 0.05), (9, 0.02), (14, 0.01), (20, 0.0), (20, 0.9), (27, 0.0), (33, 0.03),
                (40, 0.02), (12, 0.0)]
    for k, fraction in schedule:
        mxy, myx = _perturb(mxy, n_y, fraction, g), _perturb(myx, n_x, fraction, g)
        shell_x = torch.randn(n_x, 3, generator=g)
        shell_y = torch.randn(n_y, 3, generator=g)
        fmap, tau = system.solve(k, shell_x, shell_y, mxy, myx, 1e-8)
        ref_fmap, ref_tau = deformation_from_pairs(phi_x[:, :k].double(), phi_y[:, :k].double(), shell_x, shell_y,
                                                   mxy, myx, 1e-8)
        assert fmap.dtype == torch.float64 and fmap.shape == (k, k) and tau.shape == (k, 3)
        torch.testing.assert_close(fmap, ref_fmap, rtol=0, atol=1e-10 * float(ref_fmap.abs().max()))
        torch.testing.assert_close(tau, ref_tau, rtol=0, atol=1e-10 * float(ref_tau.abs().max()))
    # every path was taken (rebuilds: the first level and the smaller k)
    assert calls["_update"] >= 3 and calls["_extend"] >= 4 and calls["_rebuild"] >= 2


def test_carried_normal_equations_reject_a_k_beyond_the_basis():
    phi_x, phi_y, mxy, myx, _ = _problem(kmax=10)
    system = ds._PairNormalEquations(phi_x, phi_y)
    with pytest.raises(ConfigError, match="k=11"):
        system.solve(11, torch.zeros(180, 3), torch.zeros(150, 3), mxy, myx, 1e-8)


def test_embedding_buffers_hold_the_product_embedding():
    """The refinement's float64 embedding buffers hold exactly the values of the float32 product embedding."""
    g = torch.Generator().manual_seed(3)
    n_x, n_y, kmax = 70, 83, 25
    evecs_x, evecs_y = torch.randn(n_x, kmax + 4, generator=g), torch.randn(n_y, kmax + 4, generator=g)
    buffers = ds._EmbeddingBuffers(n_x, n_y, kmax, evecs_x)
    for k in (3, 11, 25, 7):  # growing, the largest, then smaller again: views of the same storage
        fmap = torch.randn(k, k, generator=g)
        deformed, normals_x = torch.randn(n_x, 3, generator=g), torch.randn(n_x, 3, generator=g)
        shell_y, normals_y = torch.randn(n_y, 3, generator=g), torch.randn(n_y, 3, generator=g)
        fac_s, fac_n = torch.tensor(0.37), torch.tensor(0.041)
        phi_x, phi_y = evecs_x[:, :k], evecs_y[:, :k]
        ref_x, ref_y = ds._product_embedding(deformed, phi_x @ fmap, normals_x, shell_y, phi_y, normals_y, fac_s,
                                             fac_n)
        emb_x, emb_y = buffers.fill(deformed, phi_x, fmap, normals_x, shell_y, phi_y, normals_y, fac_s, fac_n)
        assert emb_x.dtype == emb_y.dtype == torch.float64 and emb_x.is_contiguous() and emb_y.is_contiguous()
        assert torch.equal(emb_x, ref_x.double()) and torch.equal(emb_y, ref_y.double())
