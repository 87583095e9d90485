"""Original NeuroMorph weights: the loaded networks compute the original's ResnetECPos (a per-edge oracle written
from its description: channel layout ``[net, pooled, p]``, per-vertex channel max), the three file formats,
errors; the residual-block initializations."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from shapecorr.errors import ConfigError
from shapecorr.geometry.mesh_graph import undirected_edges
from shapecorr.nn.edgeconv import ResnetBlockFC, ResnetEC
from shapecorr.nn.neuromorph import NeuroMorphFeatureNet, NeuroMorphInterpolator
from shapecorr.nn.neuromorph_weights import (
    load_original_neuromorph_weights,
    load_original_resnet_ec,
)

DTYPE = torch.float64
H, BLOCKS = 8, 3


def _original_state(prefix: str, dim: int, out: int, seed: int) -> dict[str, torch.Tensor]:
    """Random parameters under the original's names (ResnetECPos with hidden width H)."""
    gen = torch.Generator().manual_seed(seed)
    state = {f"{prefix}.fc_pos.weight": torch.randn(2 * H, dim, generator=gen),
             f"{prefix}.fc_pos.bias": torch.randn(2 * H, generator=gen)}
    for k in range(BLOCKS):
        width = 2 * (2 * H) if k == 0 else 2 * (2 * H + dim)
        block = f"{prefix}.block_{k}.nn"
        state[f"{block}.fc_0.weight"] = torch.randn(H, width, generator=gen) / width**0.5
        state[f"{block}.fc_0.bias"] = torch.randn(H, generator=gen)
        state[f"{block}.fc_1.weight"] = torch.randn(H, H, generator=gen) / H**0.5
        state[f"{block}.fc_1.bias"] = torch.randn(H, generator=gen)
        state[f"{block}.shortcut.weight"] = torch.randn(H, width, generator=gen) / width**0.5
    state[f"{prefix}.fc_c.weight"] = torch.randn(out, H, generator=gen)
    state[f"{prefix}.fc_c.bias"] = torch.randn(out, generator=gen)
    return state


def _original_forward(state, prefix, p, directed):
    """The original ResnetECPos, edge by edge: messages nn([x_i, x_j - x_i]) maxed over j -> i."""
    s = {k[len(prefix) + 1:]: v.to(DTYPE) for k, v in state.items() if k.startswith(prefix)}
    def lin(name, x, bias=True):
        return x @ s[f"{name}.weight"].T + (s[f"{name}.bias"] if bias else 0.0)
    src, dst = directed

    def edgeconv(k, x):
        m = torch.cat((x[dst], x[src] - x[dst]), dim=1)
        b = f"block_{k}.nn"
        msg = lin(f"{b}.shortcut", m, bias=False) + lin(f"{b}.fc_1", torch.relu(lin(f"{b}.fc_0", torch.relu(m))))
        out = torch.full((x.shape[0], msg.shape[1]), -torch.inf, dtype=DTYPE)
        return out.scatter_reduce(0, dst[:, None].expand_as(msg), msg, "amax")

    net = edgeconv(0, lin("fc_pos", p))
    for k in range(1, BLOCKS):
        pooled = net.max(dim=1, keepdim=True).values.expand_as(net)
        net = edgeconv(k, torch.cat((net, pooled, p), dim=1))
    return lin("fc_c", torch.relu(net))


@pytest.fixture(scope="module")
def mesh():
    m = trimesh.creation.icosphere(2)
    faces = torch.from_numpy(m.faces)
    verts = torch.from_numpy(m.vertices).to(DTYPE)
    verts = verts * torch.tensor([1.0, 0.7, 1.3], dtype=DTYPE)
    edges = undirected_edges(faces)
    directed = (torch.cat((edges[:, 0], edges[:, 1])), torch.cat((edges[:, 1], edges[:, 0])))
    return verts, faces, edges, directed


@pytest.mark.parametrize("fast", [True, False])
def test_loaded_network_computes_the_original_function(mesh, fast):
    verts, _, edges, directed = mesh
    state = _original_state("rn_ec", 7, 3, seed=1)
    net = ResnetEC(7, 3, hidden_channels=H, n_blocks=BLOCKS, pool="channel")
    load_original_resnet_ec(net, state, "rn_ec")
    p = torch.cat((verts, torch.sin(3 * verts), verts[:, :1] ** 2), dim=1)
    expected = _original_forward(state, "rn_ec", p, directed)
    torch.testing.assert_close(net.to(DTYPE)(p, edges, fast=fast), expected, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("fmt", ["npz", "checkpoint", "state_dict"])
def test_file_formats_load_both_networks(mesh, tmp_path, fmt):
    verts, faces, edges, directed = mesh
    state = {**_original_state("feat_module", 6, 5, seed=2), **_original_state("rn_ec", 7, 3, seed=3)}
    path = tmp_path / ("w.npz" if fmt == "npz" else "w.pth")
    if fmt == "npz":
        np.savez(path, **{k: v.numpy() for k, v in state.items()})
    else:
        torch.save({"i_epoch": 3, "interp_module": state} if fmt == "checkpoint" else state, path)
    feat = NeuroMorphFeatureNet(5, hidden_channels=H, n_blocks=BLOCKS, pool="channel")
    interp = NeuroMorphInterpolator(hidden_channels=H, n_blocks=BLOCKS, pool="channel")
    load_original_neuromorph_weights(feat, interp, path)
    for net, prefix in ((feat.net, "feat_module"), (interp.net, "rn_ec")):
        torch.testing.assert_close(net.fc_pos.weight, state[f"{prefix}.fc_pos.weight"], rtol=0, atol=0)
        torch.testing.assert_close(net.blocks[1].block.fc1.bias, state[f"{prefix}.block_1.nn.fc_1.bias"],
                                   rtol=0, atol=0)
        # the pooled block's columns are permuted, not copied as they are
        assert not torch.equal(net.blocks[1].block.fc0.weight, state[f"{prefix}.block_1.nn.fc_0.weight"])
    # the feature net's input is [xyz, vertex normal]
    from shapecorr.geometry.normals import vertex_normals

    expected = _original_forward(state, "feat_module", torch.cat((verts, vertex_normals(verts, faces)), 1), directed)
    torch.testing.assert_close(feat.to(DTYPE)(verts, faces, edges), torch.nn.functional.normalize(expected, dim=1),
                               rtol=1e-10, atol=1e-10)


def test_errors(tmp_path):
    net = NeuroMorphInterpolator(hidden_channels=H, n_blocks=BLOCKS, pool="channel")
    with pytest.raises(ConfigError, match="not found"):
        load_original_neuromorph_weights(None, net, tmp_path / "missing.npz")
    bad = tmp_path / "bad.pth"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(ConfigError, match="not a readable torch checkpoint"):
        load_original_neuromorph_weights(None, net, bad)
    other = tmp_path / "other.npz"
    np.savez(other, something=np.zeros(3))
    with pytest.raises(ConfigError, match="no NeuroMorph parameters"):
        load_original_neuromorph_weights(None, net, other)
    state = _original_state("rn_ec", 7, 3, seed=4)
    del state["rn_ec.block_2.nn.fc_1.bias"]
    with pytest.raises(ConfigError, match="missing.*block_2.nn.fc_1.bias"):
        load_original_resnet_ec(net.net, state, "rn_ec")
    wide = ResnetEC(7, 3, hidden_channels=2 * H, n_blocks=BLOCKS, pool="channel")
    with pytest.raises(ConfigError, match="shape|columns"):
        load_original_resnet_ec(wide, _original_state("rn_ec", 7, 3, seed=4), "rn_ec")
    with pytest.raises(ConfigError, match="unexpected"):
        load_original_resnet_ec(ResnetEC(7, 3, hidden_channels=H, n_blocks=BLOCKS - 1, pool="channel"),
                                _original_state("rn_ec", 7, 3, seed=4), "rn_ec")


def test_residual_init_original_zeroes_only_the_last_weight():
    torch.manual_seed(5)
    ours = ResnetBlockFC(12, 6)
    torch.manual_seed(5)
    original = ResnetBlockFC(12, 6, residual_init="original")
    assert torch.count_nonzero(ours.fc1.bias) == 0 and torch.count_nonzero(original.fc1.weight) == 0
    assert torch.count_nonzero(original.fc1.bias) == 6 and float(original.fc1.bias.abs().max()) <= 1 / 6**0.5
    torch.testing.assert_close(ours.fc0.weight, original.fc0.weight, rtol=0, atol=0)
    torch.testing.assert_close(ours.shortcut.weight, original.shortcut.weight, rtol=0, atol=0)
    m = torch.randn(4, 12)
    # at initialization the original's branch is a constant per channel: its bias
    torch.testing.assert_close(original(m), m @ original.shortcut.weight.T + original.fc1.bias)
    with pytest.raises(ConfigError, match="residual_init"):
        ResnetBlockFC(4, 4, residual_init="ones")
    net = NeuroMorphFeatureNet(4, hidden_channels=H, n_blocks=2, residual_init="original")
    assert all(torch.count_nonzero(layer.block.fc1.bias) > 0 for layer in net.net.blocks)
