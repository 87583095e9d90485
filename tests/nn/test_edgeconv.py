"""EdgeConv / ResnetEC: fast path == reference == a per-vertex loop oracle (values and gradients, float64),
permutation equivariance, pooling, zero-initialized residual branch, max-aggregation ties, errors."""

import pytest
import torch
import trimesh

from shapecorr.errors import ConfigError
from shapecorr.geometry.mesh_graph import undirected_edges
from shapecorr.nn.edgeconv import EdgeConv, ResnetBlockFC, ResnetEC, max_aggregate

DTYPE = torch.float64


@pytest.fixture(scope="module")
def mesh():
    m = trimesh.creation.icosphere(subdivisions=1)  # 42 vertices, 120 edges
    return torch.from_numpy(m.vertices).to(DTYPE), undirected_edges(torch.from_numpy(m.faces))


def _randomize(module: torch.nn.Module, seed: int = 0, std: float = 0.3) -> torch.nn.Module:
    """Non-zero weights everywhere (the zero-initialized fc1 would hide the residual branch)."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(torch.randn(p.shape, generator=gen, dtype=p.dtype) * std)
    return module


def _loop_oracle(conv: EdgeConv, x, edges, shared=None):
    """EdgeConv written the obvious way: for every vertex, the block on each neighbour's message, then max."""
    n = x.shape[0]
    u = x if shared is None else torch.cat((x, shared.expand(n, -1)), dim=1)
    neighbours = [[] for _ in range(n)]
    for a, b in edges.tolist():
        neighbours[a].append(b)
        neighbours[b].append(a)
    rows = []
    for i in range(n):
        if not neighbours[i]:
            rows.append(torch.zeros(conv.out_channels, dtype=x.dtype))
            continue
        j = torch.tensor(neighbours[i])
        msg = torch.cat((u[i].expand(len(j), -1), u[j] - u[i]), dim=1)
        rows.append(conv.block(msg).max(dim=0).values)
    return torch.stack(rows)


def _grads(out, inputs, params, seed=1):
    gen = torch.Generator().manual_seed(seed)
    weight = torch.randn(out.shape, generator=gen, dtype=out.dtype)
    return torch.autograd.grad((out * weight).sum(), [*inputs, *params])


def _assert_all_close(a_list, b_list):
    for a, b in zip(a_list, b_list):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("shared_channels", [0, 4])
def test_edgeconv_fast_equals_reference_and_loop_oracle(mesh, shared_channels):
    verts, edges = mesh
    torch.manual_seed(0)
    conv = _randomize(EdgeConv(5, 7, shared_channels=shared_channels)).to(DTYPE)
    x = torch.randn(verts.shape[0], 5, dtype=DTYPE, requires_grad=True)
    shared = torch.randn(shared_channels, dtype=DTYPE, requires_grad=True) if shared_channels else None
    inputs = [x] + ([shared] if shared is not None else [])
    params = list(conv.parameters())
    outs = [conv(x, edges, shared=shared, fast=True), conv(x, edges, shared=shared, fast=False),
            _loop_oracle(conv, x, edges, shared)]
    grads = [_grads(o, inputs, params) for o in outs]
    for o, g in zip(outs[1:], grads[1:]):
        torch.testing.assert_close(outs[0], o, rtol=1e-10, atol=1e-10)
        _assert_all_close(grads[0], g)


@pytest.mark.parametrize("pool", ["global", "channel"])
def test_resnet_ec_fast_equals_reference_batched(mesh, pool):
    verts, edges = mesh
    torch.manual_seed(1)
    net = _randomize(ResnetEC(6, 5, hidden_channels=16, n_blocks=3, pool=pool), seed=2, std=0.2).to(DTYPE)
    p = torch.randn(3, verts.shape[0], 6, dtype=DTYPE, requires_grad=True)
    params = list(net.parameters())
    fast, ref = net(p, edges, fast=True), net(p, edges, fast=False)
    assert fast.shape == (3, verts.shape[0], 5)
    torch.testing.assert_close(fast, ref, rtol=1e-10, atol=1e-10)
    _assert_all_close(_grads(fast, [p], params), _grads(ref, [p], params))
    # Batch elements are independent: the batched result equals per-element runs.
    torch.testing.assert_close(fast[1], net(p[1], edges), rtol=1e-12, atol=1e-12)


def test_duplicate_and_flipped_edges_do_not_change_the_result(mesh):
    verts, edges = mesh
    conv = _randomize(EdgeConv(3, 4), seed=3).to(DTYPE)
    x = torch.randn(verts.shape[0], 3, dtype=DTYPE)
    noisy = torch.cat((edges, edges.flip(1), edges[:10])).flip(0)
    for fast in (True, False):
        torch.testing.assert_close(conv(x, noisy, fast=fast), conv(x, edges), rtol=1e-12, atol=1e-12)


def test_isolated_vertex_gets_zero(mesh):
    verts, edges = mesh
    conv = _randomize(EdgeConv(3, 4), seed=4).to(DTYPE)
    x = torch.randn(verts.shape[0] + 1, 3, dtype=DTYPE)  # the last vertex is in no edge
    for fast in (True, False):
        out = conv(x, edges, fast=fast)
        assert torch.count_nonzero(out[-1]) == 0
        assert torch.count_nonzero(out[:-1]) > 0


@pytest.mark.parametrize("pool", ["global", "channel"])
def test_permutation_equivariance(mesh, pool):
    verts, edges = mesh
    n = verts.shape[0]
    net = _randomize(ResnetEC(6, 4, hidden_channels=8, n_blocks=3, pool=pool), seed=5, std=0.3).to(DTYPE)
    p = torch.randn(n, 6, dtype=DTYPE)
    gen = torch.Generator().manual_seed(6)
    perm = torch.randperm(n, generator=gen)  # new vertex k is old vertex perm[k]
    inv = torch.empty_like(perm)
    inv[perm] = torch.arange(n)
    edges_perm = inv[edges][torch.randperm(edges.shape[0], generator=gen)]
    out = net(p, edges)
    out_perm = net(p[perm], edges_perm)
    torch.testing.assert_close(out_perm, out[perm], rtol=1e-10, atol=1e-10)
    # Anything pooled over the vertices is invariant.
    torch.testing.assert_close(out_perm.amax(dim=0), out.amax(dim=0), rtol=1e-10, atol=1e-10)


def test_global_pool_reaches_every_vertex_channel_pool_does_not(mesh):
    """Global pooling gives every vertex information about the whole shape after one pooled layer; the
    original's channel 'pool' is per vertex, so a change at one vertex stays local (receptive field of the
    two EdgeConv layers: 2 rings). The bump is large so that it wins the max over vertices."""
    verts, edges = mesh
    n = verts.shape[0]
    p = torch.randn(n, 6, dtype=DTYPE)
    bumped = p.clone()
    bumped[0] += 100.0
    changed = {}
    for pool in ("global", "channel"):
        net = _randomize(ResnetEC(6, 4, hidden_channels=8, n_blocks=2, pool=pool), seed=7, std=0.3).to(DTYPE)
        diff = (net(bumped, edges) - net(p, edges)).abs().amax(dim=1)
        changed[pool] = int((diff > 1e-12).sum())
    assert changed["global"] == n
    assert changed["channel"] < n


def test_zero_initialized_branch_makes_block_its_shortcut():
    torch.manual_seed(8)
    block = ResnetBlockFC(10, 6).to(DTYPE)
    assert torch.count_nonzero(block.fc1.weight) == 0 and torch.count_nonzero(block.fc1.bias) == 0
    m = torch.randn(20, 10, dtype=DTYPE)
    torch.testing.assert_close(block(m), m @ block.shortcut.weight.T, rtol=0, atol=0)
    identity_block = ResnetBlockFC(6, 6).to(DTYPE)
    assert identity_block.shortcut is None
    torch.testing.assert_close(identity_block(m[:, :6]), m[:, :6], rtol=0, atol=0)


def test_edgeconv_at_init_is_max_of_shortcut_messages(mesh):
    verts, edges = mesh
    torch.manual_seed(9)
    conv = EdgeConv(3, 4).to(DTYPE)
    x = torch.randn(verts.shape[0], 3, dtype=DTYPE)
    w = conv.block.shortcut.weight
    oracle = []
    for i in range(x.shape[0]):
        j = torch.cat((edges[edges[:, 0] == i, 1], edges[edges[:, 1] == i, 0]))
        msg = torch.cat((x[i].expand(len(j), -1), x[j] - x[i]), dim=1)
        oracle.append((msg @ w.T).max(dim=0).values)
    torch.testing.assert_close(conv(x, edges), torch.stack(oracle), rtol=1e-12, atol=1e-12)


def test_identity_shortcut_fast_path(mesh):
    """in == out for the block (2 * in_channels == out_channels): the shortcut is the identity."""
    verts, edges = mesh
    conv = EdgeConv(3, 6)
    assert conv.block.shortcut is None
    conv = _randomize(conv, seed=10).to(DTYPE)
    x = torch.randn(verts.shape[0], 3, dtype=DTYPE)
    torch.testing.assert_close(conv(x, edges), conv(x, edges, fast=False), rtol=1e-10, atol=1e-10)


def test_max_aggregate_ties_split_gradient_like_torch():
    values = torch.tensor([[1.0, 2.0], [1.0, 0.0], [3.0, 2.0], [0.5, -1.0]], dtype=DTYPE, requires_grad=True)
    receivers = torch.tensor([0, 0, 1, 0])
    out = max_aggregate(values, receivers, 3)
    torch.testing.assert_close(out, torch.tensor([[1.0, 2.0], [3.0, 2.0], [0.0, 0.0]], dtype=DTYPE))
    (grad,) = torch.autograd.grad(out.sum(), values)
    ref_values = values.detach().clone().requires_grad_()
    ref = torch.zeros(3, 2, dtype=DTYPE).scatter_reduce(
        0, receivers[:, None].expand(-1, 2), ref_values, "amax", include_self=False
    )
    (ref_grad,) = torch.autograd.grad(ref.sum(), ref_values)
    torch.testing.assert_close(grad, ref_grad)
    assert grad[0, 0] == grad[1, 0] == 0.5  # tie at vertex 0, channel 0


def test_errors(mesh):
    verts, edges = mesh
    conv = EdgeConv(3, 4, shared_channels=2)
    x = torch.randn(verts.shape[0], 3)
    with pytest.raises(ConfigError, match="input channels"):
        conv(torch.randn(verts.shape[0], 5), edges, shared=torch.randn(2))
    with pytest.raises(ConfigError, match="shared"):
        conv(x, edges)
    with pytest.raises(ConfigError, match="shared must have shape"):
        conv(x, edges, shared=torch.randn(3))
    with pytest.raises(ConfigError, match="outside"):
        conv(x, edges + verts.shape[0], shared=torch.randn(2))
    with pytest.raises(ConfigError, match=r"\(E, 2\)"):
        conv(x, edges.T, shared=torch.randn(2))
    with pytest.raises(ConfigError, match="pool"):
        ResnetEC(6, 3, pool="mean")
    with pytest.raises(ConfigError, match="n_blocks"):
        ResnetEC(6, 3, n_blocks=0)


@pytest.mark.parametrize("pool", ["global", "channel"])
@pytest.mark.parametrize("fast", [True, False])
def test_forward_separable_equals_forward_on_the_concatenated_input(mesh, pool, fast):
    """Inputs that differ between batch elements only in vertex-constant channels (the interpolator's t): the
    separable path (shared base and edge terms, t as a shared channel) == forward on [p_static, p_batch]."""
    verts, edges = mesh
    n = verts.shape[0]
    net = _randomize(ResnetEC(6, 5, hidden_channels=16, n_blocks=3, pool=pool), seed=11, std=0.2).to(DTYPE)
    gen = torch.Generator().manual_seed(12)
    p_static = torch.randn(n, 4, generator=gen, dtype=DTYPE, requires_grad=True)
    p_batch = torch.randn(3, 2, generator=gen, dtype=DTYPE, requires_grad=True)
    params = list(net.parameters())
    sep = net.forward_separable(p_static, p_batch, edges, fast=fast)
    full = net(torch.cat((p_static.expand(3, n, 4), p_batch[:, None].expand(3, n, 2)), dim=-1), edges, fast=False)
    assert sep.shape == (3, n, 5)
    torch.testing.assert_close(sep, full, rtol=1e-10, atol=1e-10)
    _assert_all_close(_grads(sep, [p_static, p_batch], params), _grads(full, [p_static, p_batch], params))
    with pytest.raises(ConfigError, match="c_s \\+ c_b"):
        net.forward_separable(p_static, p_batch[:, :1], edges)


@pytest.mark.parametrize("hidden", [4, 9])
def test_fast_path_with_block_hidden_width_different_from_output(mesh, hidden):
    """The backward reuses the max mask's buffer only when the hidden and output widths agree."""
    verts, edges = mesh
    conv = _randomize(EdgeConv(5, 7, hidden_channels=hidden), seed=13).to(DTYPE)
    x = torch.randn(2, verts.shape[0], 5, dtype=DTYPE, requires_grad=True)
    params = list(conv.parameters())
    fast, ref = conv(x, edges), conv(x, edges, fast=False)
    torch.testing.assert_close(fast, ref, rtol=1e-10, atol=1e-10)
    _assert_all_close(_grads(fast, [x], params), _grads(ref, [x], params))
