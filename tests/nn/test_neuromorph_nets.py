"""NeuroMorph networks: time steps, unit-norm features, X(t) = x + t d, identity at init, gradients, errors."""

import pytest
import torch
import trimesh

from shapecorr.errors import ConfigError, NumericalError
from shapecorr.geometry.mesh_graph import undirected_edges
from shapecorr.nn.neuromorph import NeuroMorphFeatureNet, NeuroMorphInterpolator, interpolation_times


@pytest.fixture(scope="module")
def sphere():
    m = trimesh.creation.icosphere(subdivisions=2)  # 162 vertices
    faces = torch.from_numpy(m.faces)
    return torch.from_numpy(m.vertices).float(), faces, undirected_edges(faces)


def test_interpolation_times():
    torch.testing.assert_close(interpolation_times(0), torch.tensor([1.0]))
    torch.testing.assert_close(interpolation_times(3), torch.tensor([0.25, 0.5, 0.75, 1.0]))
    assert interpolation_times(7, dtype=torch.float64).dtype == torch.float64
    with pytest.raises(ConfigError):
        interpolation_times(-1)


def test_feature_net_outputs_unit_rows_fast_equals_reference(sphere):
    verts, faces, edges = sphere
    torch.manual_seed(0)
    net = NeuroMorphFeatureNet(out_channels=16, hidden_channels=16)
    feat = net(verts, faces, edges)
    assert feat.shape == (verts.shape[0], 16)
    torch.testing.assert_close(feat.norm(dim=1), torch.ones(verts.shape[0]))
    torch.testing.assert_close(feat, net(verts, faces, edges, fast=False), rtol=1e-4, atol=1e-5)


def test_interpolator_frames_follow_x_plus_t_d(sphere):
    verts, _, edges = sphere
    torch.manual_seed(1)
    net = NeuroMorphInterpolator(hidden_channels=16)
    target = verts * 1.3
    times = interpolation_times(3)
    disp = net(verts, target, edges, times)
    frames = net.interpolate(verts, target, edges, times)
    assert disp.shape == frames.shape == (4, verts.shape[0], 3)
    torch.testing.assert_close(frames, verts + times.view(-1, 1, 1) * disp)
    # Different times give different displacements (t is an input), each frame equals a single-time run.
    assert not torch.allclose(disp[0], disp[3])
    torch.testing.assert_close(disp[2], net(verts, target, edges, times[2:3])[0], rtol=1e-5, atol=1e-6)


def test_gradients_reach_every_parameter_and_the_target(sphere):
    verts, faces, edges = sphere
    torch.manual_seed(2)
    feat_net = NeuroMorphFeatureNet(out_channels=8, hidden_channels=8)
    interp = NeuroMorphInterpolator(hidden_channels=8)
    for module in (feat_net, interp):  # leave the zero init so the residual branches get gradients too
        for block in module.net.blocks:
            torch.nn.init.normal_(block.block.fc1.weight, std=0.1)
    target = (verts + 0.1).requires_grad_()
    loss = feat_net(verts, faces, edges)[:, 0].sum()
    loss = loss + interp.interpolate(verts, target, edges, interpolation_times(1)).square().sum()
    params = list(feat_net.parameters()) + list(interp.parameters())
    grads = torch.autograd.grad(loss, params + [target])
    assert all(bool(torch.isfinite(g).all()) for g in grads)
    assert all(g.abs().sum() > 0 for g in grads)


def test_errors(sphere):
    verts, faces, edges = sphere
    net = NeuroMorphInterpolator(hidden_channels=8)
    with pytest.raises(ConfigError, match="times"):
        net(verts, verts, edges, torch.tensor(1.0))
    with pytest.raises(ConfigError, match=r"\(n, 3\)"):
        net(verts, verts[:10], edges, interpolation_times(0))
    bad = verts.clone()
    bad[0, 0] = float("nan")
    with pytest.raises(NumericalError, match="target"):
        net(verts, bad, edges, interpolation_times(0))
    with pytest.raises(NumericalError, match="vertices"):
        NeuroMorphFeatureNet(out_channels=4, hidden_channels=8)(bad, faces, edges)
    with pytest.raises(ConfigError, match=r"\(n, 3\)"):
        NeuroMorphFeatureNet(out_channels=4, hidden_channels=8)(verts[None], faces, edges)


def test_interpolator_fast_equals_reference_in_float64(sphere):
    """The interpolator runs its time steps through ResnetEC.forward_separable: same values and gradients (target
    and weights) as the plain per-edge network on the concatenated [x, target - x, t] input."""
    verts, _, edges = sphere
    torch.manual_seed(5)
    net = NeuroMorphInterpolator(hidden_channels=8).double()
    with torch.no_grad():
        for p in net.parameters():
            p.normal_(0.0, 0.2)
    # Jittered: the icosphere repeats coordinate values between neighbours, and at such ties of max(x_i, x_j)
    # the two paths pick different (equally valid) subgradients.
    gen = torch.Generator().manual_seed(6)
    verts = verts.double() + 0.01 * torch.randn(verts.shape, generator=gen, dtype=torch.float64)
    target = (verts * 1.2 + 0.05 * torch.randn(verts.shape, generator=gen, dtype=torch.float64)).requires_grad_()
    times = interpolation_times(3, dtype=torch.float64)
    outs = [net.interpolate(verts, target, edges, times, fast=fast) for fast in (True, False)]
    torch.testing.assert_close(outs[0], outs[1], rtol=1e-10, atol=1e-10)
    weight = torch.randn(outs[0].shape, dtype=torch.float64)
    grads = [torch.autograd.grad((o * weight).sum(), [target, *net.parameters()]) for o in outs]
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)
