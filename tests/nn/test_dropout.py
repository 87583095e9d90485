"""RowDropout: torch's dropout, and the full tensor's mask applied to some of its rows."""

import pytest
import torch

from shapecorr.errors import ConfigError
from shapecorr.nn import dropout as rd
from shapecorr.nn.dropout import RowDropout, rand_mask_matches_bernoulli


@pytest.mark.parametrize("p", [0.5, 0.3])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_equals_torch_dropout_values_gradients_and_random_state(p, dtype):
    x = torch.randn(300, 17, dtype=dtype, requires_grad=True)
    up = torch.randn(300, 17, dtype=dtype)
    torch.manual_seed(3)
    ref = torch.nn.functional.dropout(x, p, training=True)
    (g_ref,) = torch.autograd.grad(ref, x, up)
    state = torch.get_rng_state()
    torch.manual_seed(3)
    out = RowDropout(p).train()(x)
    (g,) = torch.autograd.grad(out, x, up)
    assert torch.equal(out, ref) and torch.equal(g, g_ref)
    assert torch.equal(torch.get_rng_state(), state)
    assert 0.2 < float((out == 0).double().mean()) / p < 1.8  # the entries are dropped at about rate p


def test_rows_get_the_full_tensors_mask_and_the_stream_advances_alike():
    full = torch.randn(50, 8)
    rows = torch.tensor([4, 0, 4, 49])
    layer = RowDropout(0.5).train()
    torch.manual_seed(7)
    ref = layer(full)
    state = torch.get_rng_state()
    torch.manual_seed(7)
    part = layer(full[rows], rows, full_rows=50)
    assert torch.equal(part, ref[rows]) and torch.equal(torch.get_rng_state(), state)
    assert torch.equal(layer.eval()(full), full)  # eval: identity, nothing drawn
    with pytest.raises(ConfigError, match="full_rows"):
        layer.train()(full[rows], rows)


def test_fallback_draw_gives_the_same_mask(monkeypatch):
    """Where the uniform draw did not match (other builds), the Bernoulli draw is used: the same values."""
    x = torch.randn(40, 6)
    layer = RowDropout(0.25).train()
    torch.manual_seed(1)
    fast = layer(x)
    assert rand_mask_matches_bernoulli(0.25)  # this build: the uniform draw is the dropout mask
    monkeypatch.setitem(rd._MATCHES, 0.25, False)
    torch.manual_seed(1)
    assert torch.equal(layer(x), fast)
    torch.manual_seed(1)
    assert torch.equal(torch.nn.functional.dropout(x, 0.25, training=True), fast)
