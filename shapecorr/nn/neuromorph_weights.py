"""Weights of the original NeuroMorph code in shapecorr's NeuroMorph networks.

The original (Eisenberger et al., CVPR 2021, facebookresearch release) holds both networks in one module,
``InterpolationModGeoEC``, whose state dict names the feature net ``feat_module.*`` and the interpolator
``rn_ec.*``; both are a ``ResnetECPos``::

    <net>.fc_pos.{weight,bias}                      -> ResnetEC.fc_pos
    <net>.block_k.nn.fc_0.{weight,bias}             -> ResnetEC.blocks[k].block.fc0
    <net>.block_k.nn.fc_1.{weight,bias}             -> ResnetEC.blocks[k].block.fc1
    <net>.block_k.nn.shortcut.weight                -> ResnetEC.blocks[k].block.shortcut
    <net>.fc_c.{weight,bias}                        -> ResnetEC.fc_out

The only change besides the names is a column permutation of ``fc_0`` and ``shortcut`` in the blocks after
the first: the original concatenates the per-vertex channels as ``[net (h), pooled (h), p (dim)]``, ours as
``[net, p, pooled]`` (:mod:`shapecorr.nn.edgeconv`, "Channel layout"), in each half of the message
``[u_i, u_j - u_i]``. The weights fit a network of either pooling mode (same shapes); they compute the
original's function only with ``pool="channel"``, the original's pooling.

Files: the original's checkpoints (``ckpt_ep*.pth``, a dict whose ``interp_module`` entry is the state dict),
a bare state dict (``.pth``), or a ``.npz`` mapping the state-dict names to arrays (the form of the parity
reference data, loadable without pickle).
"""

from __future__ import annotations

from collections.abc import Mapping
from os import PathLike
from pathlib import Path

import numpy as np
import torch
from torch import nn

from shapecorr.errors import ConfigError
from shapecorr.nn.edgeconv import ResnetEC

#: State-dict prefixes of the two networks in the original's InterpolationModGeoEC.
ORIGINAL_FEATURE_PREFIX = "feat_module"
ORIGINAL_INTERPOLATOR_PREFIX = "rn_ec"
#: Key of the state dict in the original's checkpoints (utils/base_tools.py, save_chkpt).
ORIGINAL_CHECKPOINT_KEY = "interp_module"


def read_original_neuromorph_state(path: str | PathLike) -> dict[str, torch.Tensor]:
    """Read the original's parameters from a checkpoint, a state dict or an ``.npz`` (module docstring).

    Parameters
    ----------
    path : path-like

    Returns
    -------
    dict
        State-dict name -> float32 CPU tensor.

    Raises
    ------
    ConfigError
        If the file is missing or unreadable, or holds no NeuroMorph parameters.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError("NeuroMorph weights not found", path=path)
    if path.suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as data:
                state = {k: torch.from_numpy(np.asarray(data[k], dtype=np.float32)) for k in data.files}
        except Exception as exc:  # numpy raises several unrelated types for damaged archives
            raise ConfigError(f"not a readable .npz file ({type(exc).__name__}: {exc})", path=path) from exc
    else:
        try:
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # torch raises several unrelated types for unreadable/unsafe pickles
            raise ConfigError(
                f"not a readable torch checkpoint ({type(exc).__name__}: {exc}); a checkpoint whose 'par' entry "
                "holds non-tensor objects can be converted to a bare state dict: "
                "torch.save(torch.load(path)['interp_module'], new_path)", path=path) from exc
        if not isinstance(ckpt, Mapping):
            raise ConfigError("not a NeuroMorph checkpoint (expected a dict)", path=path)
        state = ckpt.get(ORIGINAL_CHECKPOINT_KEY, ckpt)
        if not isinstance(state, Mapping):
            raise ConfigError(f"not a NeuroMorph checkpoint: {ORIGINAL_CHECKPOINT_KEY!r} is not a state dict",
                              path=path)
        state = {k: v.detach().to("cpu", torch.float32) for k, v in state.items() if isinstance(v, torch.Tensor)}
    if not any(k.startswith(f"{p}.") for k in state for p in (ORIGINAL_FEATURE_PREFIX, ORIGINAL_INTERPOLATOR_PREFIX)):
        raise ConfigError(
            f"no NeuroMorph parameters: expected names starting with {ORIGINAL_FEATURE_PREFIX!r} or "
            f"{ORIGINAL_INTERPOLATOR_PREFIX!r}", path=path)
    return state


def _original_to_ours_columns(hidden: int, dim: int) -> torch.Tensor:
    """Column order of a pooled block's input ``2 (2h + dim)`` in ours, as indices into the original's."""
    half = 2 * hidden + dim
    # ours per half: [net (h), p (dim), pooled (h)]; original per half: [net (h), pooled (h), p (dim)]
    one = torch.cat((torch.arange(hidden), torch.arange(2 * hidden, half), torch.arange(hidden, 2 * hidden)))
    return torch.cat((one, one + half))


def _copy(target: torch.Tensor, value: torch.Tensor, name: str, path) -> None:
    if tuple(value.shape) != tuple(target.shape):
        raise ConfigError(f"{name} has shape {tuple(value.shape)}, the network expects {tuple(target.shape)} "
                          "(different hidden width, number of blocks or input channels?)", path=path)
    with torch.no_grad():
        target.copy_(value.to(target))


def load_original_resnet_ec(net: ResnetEC, state: Mapping[str, torch.Tensor], prefix: str,
                            path: str | PathLike | None = None) -> None:
    """Copy one original ``ResnetECPos`` (names ``<prefix>.*``) into a :class:`ResnetEC`, in place.

    Parameters
    ----------
    net : ResnetEC
    state : mapping
        The original's state dict (:func:`read_original_neuromorph_state`).
    prefix : str
        ``"feat_module"`` or ``"rn_ec"``.
    path : path-like, optional
        Only for error messages.

    Raises
    ------
    ConfigError
        If a parameter is missing, unexpected or of another shape.
    """
    own = {k[len(prefix) + 1:]: v for k, v in state.items() if k.startswith(f"{prefix}.")}
    expected = {"fc_pos.weight": net.fc_pos.weight, "fc_pos.bias": net.fc_pos.bias,
                "fc_c.weight": net.fc_out.weight, "fc_c.bias": net.fc_out.bias}
    hidden, dim = net.blocks[0].out_channels, net.in_channels
    for k, layer in enumerate(net.blocks):
        blk = layer.block
        if blk.shortcut is None:
            raise ConfigError(f"block {k} has an identity shortcut; the original's blocks all have a linear one",
                              path=path)
        cols = None if k == 0 else _original_to_ours_columns(hidden, dim)
        for ours, theirs in ((blk.fc0.weight, "fc_0.weight"), (blk.shortcut.weight, "shortcut.weight")):
            name = f"block_{k}.nn.{theirs}"
            if name in own and cols is not None:
                if own[name].shape[-1] != cols.numel():
                    raise ConfigError(f"{prefix}.{name} has {own[name].shape[-1]} input columns, the network "
                                      f"expects {cols.numel()}", path=path)
                own = {**own, name: own[name][:, cols]}
            expected[name] = ours
        expected[f"block_{k}.nn.fc_0.bias"] = blk.fc0.bias
        expected[f"block_{k}.nn.fc_1.weight"] = blk.fc1.weight
        expected[f"block_{k}.nn.fc_1.bias"] = blk.fc1.bias
    missing = sorted(set(expected) - set(own))
    unexpected = sorted(set(own) - set(expected))
    if missing or unexpected:
        raise ConfigError(f"{prefix}: missing {[f'{prefix}.{m}' for m in missing]}, unexpected "
                          f"{[f'{prefix}.{u}' for u in unexpected]} (a different number of blocks?)", path=path)
    for name, target in expected.items():
        _copy(target, own[name], f"{prefix}.{name}", path)


def _resnet_ec(module: nn.Module, what: str) -> ResnetEC:
    net = module if isinstance(module, ResnetEC) else getattr(module, "net", None)
    if not isinstance(net, ResnetEC):
        raise ConfigError(f"the {what} must be a ResnetEC or hold one as `.net`, got {type(module).__name__}")
    return net


def load_original_neuromorph_weights(
    feature_net: nn.Module | None, interpolator: nn.Module | None, path: str | PathLike
) -> None:
    """Load the original's ``feat_module`` / ``rn_ec`` parameters into shapecorr's networks, in place.

    Parameters
    ----------
    feature_net : NeuroMorphFeatureNet or ResnetEC or None
        Receives ``feat_module.*`` (skipped when None).
    interpolator : NeuroMorphInterpolator or ResnetEC or None
        Receives ``rn_ec.*`` (skipped when None).
    path : path-like
        Checkpoint, state dict or ``.npz`` (module docstring).

    Raises
    ------
    ConfigError
        If the file is unreadable, lacks a network asked for, or does not fit the networks (shapes, number of
        blocks).
    """
    state = read_original_neuromorph_state(path)
    for module, prefix, what in ((feature_net, ORIGINAL_FEATURE_PREFIX, "feature net"),
                                 (interpolator, ORIGINAL_INTERPOLATOR_PREFIX, "interpolator")):
        if module is not None:
            load_original_resnet_ec(_resnet_ec(module, what), state, prefix, path=path)
