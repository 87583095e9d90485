"""One recipe builds a model: the resolved ``model`` config node, kept with the model and in its checkpoints.

``train.py`` builds a learned model with :func:`build_model` from its ``model`` node; the module keeps the node
(resolved, plain containers) as :attr:`~shapecorr.models.base.CorrespondenceModule.recipe` and writes it into
every checkpoint under :data:`~shapecorr.models.base.RECIPE_KEY`. Whoever reads a checkpoint (``evaluate.py
ckpt_path=``, ``train.py ckpt_path=`` to resume, pose transfer) calls :func:`load_model`, which

1. reads the file (:func:`read_checkpoint`: an empty, truncated or foreign file is a
   :class:`~shapecorr.errors.ConfigError` naming it and the fix);
2. checks that the checkpoint holds the requested model, when one was requested (``model=<name>``);
3. merges the command line's ``model.*`` overrides onto the checkpoint's recipe (:func:`merge_overrides`), so
   test-time options (``model.refine=false``) take effect;
4. instantiates the merged recipe and loads the state dict; an override that changes parameter shapes is a
   ConfigError naming the override.

The merged recipe is what the run records (``run.json`` of ``evaluate.py``).
"""

from __future__ import annotations

import copy
import os
import pickle
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from shapecorr.errors import ConfigError, ShapeCorrError
from shapecorr.models.base import RECIPE_KEY

#: Key of the weights in a Lightning checkpoint.
STATE_KEY = "state_dict"
#: How a user gets a readable checkpoint (ends the messages of :func:`read_checkpoint`).
CHECKPOINT_HINT = "give a .ckpt written by train.py (e.g. <run>/checkpoints/last.ckpt)"


def plain_node(node: Any) -> dict:
    """A config node (DictConfig or mapping) as plain, resolved containers."""
    from omegaconf import DictConfig, OmegaConf

    if isinstance(node, DictConfig):
        return OmegaConf.to_container(node, resolve=True)
    return copy.deepcopy(dict(node))


def model_name(node: Mapping[str, Any]) -> str:
    """The class name of a model node's ``_target_`` (what messages call the model)."""
    return str(node.get("_target_", "?")).rsplit(".", 1)[-1]


def build_model(node: Any):
    """Instantiate a ``model`` config node and keep it as the module's recipe.

    Parameters
    ----------
    node : DictConfig or mapping
        With ``_target_``; sub-nodes (backbone, loss, optimizer) are built by Hydra.

    Raises
    ------
    ConfigError
        No ``_target_``, or the node does not build (the cause's message when it is a ShapeCorrError).
    """
    import hydra

    recipe = plain_node(node)
    if "_target_" not in recipe:
        raise ConfigError("the model config has no _target_")
    try:
        model = hydra.utils.instantiate(recipe, _convert_="object")
    except hydra.errors.InstantiationException as err:
        cause = err.__cause__
        if isinstance(cause, ShapeCorrError):
            raise cause from None
        raise ConfigError(f"cannot build the model {model_name(recipe)}: {err}") from None
    if hasattr(model, "recipe"):
        model.recipe = recipe
    return model


def read_checkpoint(path: str | os.PathLike) -> dict:
    """The content of a checkpoint file written by ``train.py``, on the CPU.

    Raises
    ------
    ConfigError
        Missing, empty, truncated or unreadable file; not a training checkpoint; no recipe (the message names
        the file and what to do).
    """
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"checkpoint file does not exist; {CHECKPOINT_HINT}", path)
    if not path.is_file():
        raise ConfigError(f"is not a checkpoint file; {CHECKPOINT_HINT}", path)
    if path.stat().st_size == 0:
        raise ConfigError(f"checkpoint file is empty (an interrupted save?); {CHECKPOINT_HINT}", path)
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except (RuntimeError, pickle.UnpicklingError, EOFError, zipfile.BadZipFile, ValueError, OSError,
            AttributeError, TypeError) as err:
        detail = str(err).strip().splitlines()[0].split(". ")[0] if str(err).strip() else ""
        raise ConfigError(f"not a readable checkpoint, truncated or not written by torch.save "
                          f"({type(err).__name__}{': ' + detail if detail else ''}); {CHECKPOINT_HINT}",
                          path) from None
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get(STATE_KEY), Mapping):
        raise ConfigError(f"not a shapecorr training checkpoint (no {STATE_KEY!r}); {CHECKPOINT_HINT} "
                          "(published Deep Shells weights go to model.pretrained=FILE)", path)
    recipe = ckpt.get(RECIPE_KEY)
    if not isinstance(recipe, Mapping) or "_target_" not in recipe:
        raise ConfigError(f"the checkpoint holds no model recipe ({RECIPE_KEY!r}; written by a shapecorr version "
                          "without recipes): retrain, or build the model from its config and load the weights "
                          "(docs/architecture.md §4, old checkpoints)", path)
    return ckpt


def check_same_model(recipe: Mapping[str, Any], requested: Mapping[str, Any] | None, path) -> None:
    """Refuse a checkpoint of another model than the requested one (ConfigError naming both)."""
    if requested is None or "_target_" not in requested:
        return
    if str(requested["_target_"]) != str(recipe["_target_"]):
        theirs, ours = model_name(recipe), model_name(requested)
        raise ConfigError(f"the checkpoint holds a {theirs} model ({recipe['_target_']}), not the requested {ours} "
                          f"({requested['_target_']}); drop model= to use the checkpoint's own model, or give a "
                          f"{ours} checkpoint", path)


#: Value of an override that removes the key (``~model.key``).
DELETE = object()


def merge_overrides(recipe: Mapping[str, Any], overrides: Mapping[str, Any]) -> dict:
    """The recipe with the override values put on top.

    Parameters
    ----------
    recipe : mapping
        The checkpoint's model node.
    overrides : mapping of str -> value
        Dotted keys relative to the model node (``layer.refine_levels``; ``backbone`` for ``model/backbone=``) and
        their values (plain containers; :data:`DELETE` removes the key). A node value replaces the recipe's.
    """
    from omegaconf import OmegaConf

    merged = OmegaConf.create(plain_node(recipe))
    for key, value in overrides.items():
        if value is DELETE:
            parent, _, leaf = key.rpartition(".")
            node = OmegaConf.select(merged, parent) if parent else merged
            if node is not None and leaf in node:
                del node[leaf]
            continue
        OmegaConf.update(merged, key, value, merge=False, force_add=True)
    return OmegaConf.to_container(merged, resolve=True)


def _shape_mismatches(model: torch.nn.Module, state: Mapping[str, torch.Tensor]) -> list[str]:
    """Parameter names whose presence or shape differs between the module and a state dict."""
    own = model.state_dict()
    bad = sorted(set(own) ^ set(state))
    bad += sorted(k for k in set(own) & set(state) if tuple(own[k].shape) != tuple(state[k].shape))
    return bad


def _describe(name: str, model: torch.nn.Module, state: Mapping[str, torch.Tensor]) -> str:
    own = model.state_dict()
    if name not in own:
        return f"{name} only in the checkpoint"
    if name not in state:
        return f"{name} missing from the checkpoint"
    return f"{name}: {tuple(state[name].shape)} in the checkpoint, {tuple(own[name].shape)} here"


def load_model(path: str | os.PathLike, requested: Mapping[str, Any] | None = None,
               overrides: Mapping[str, Any] | None = None, map_location: str | torch.device = "cpu"):
    """The model of a checkpoint: its recipe with the overrides merged on top, with the checkpoint's weights.

    Parameters
    ----------
    path : path-like
        A checkpoint written by ``train.py``.
    requested : mapping, optional
        The ``model`` node the command asked for (``model=<name>``): its ``_target_`` must match the checkpoint's.
        None: whatever model the checkpoint holds.
    overrides : mapping of str -> value, optional
        The command line's ``model.*`` overrides (see :func:`merge_overrides`).
    map_location : device

    Raises
    ------
    ConfigError
        Unreadable file, another model, or an override that changes parameter shapes (naming the key).
    """
    ckpt = read_checkpoint(path)
    recipe, state = ckpt[RECIPE_KEY], ckpt[STATE_KEY]
    check_same_model(recipe, requested, path)
    overrides = dict(overrides or {})
    model = build_model(merge_overrides(recipe, overrides))
    bad = _shape_mismatches(model, state)
    if bad:
        culprits = [k for k, v in overrides.items()
                    if _shape_mismatches(build_model(merge_overrides(recipe, {k: v})), state)]
        what = _describe(bad[0], model, state)
        if culprits:
            raise ConfigError(f"model.{culprits[0]} changes the parameter shapes of the checkpoint's model ({what}); "
                              f"drop that override to use this checkpoint", path)
        raise ConfigError(f"the checkpoint's weights do not fit its own recipe ({what}); {CHECKPOINT_HINT}", path)
    model.load_state_dict(state, strict=True)
    model.trained_from = str(path)
    return model.to(map_location)


def save_recipe(model, path: str | os.PathLike) -> Path | None:
    """Write the model's recipe as YAML to ``path`` (atomically); None for a model without one."""
    from omegaconf import OmegaConf

    from shapecorr.data.cache import atomic_open

    recipe = getattr(model, "recipe", None)
    if recipe is None:
        return None
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(path) as fh:
        fh.write(OmegaConf.to_yaml(recipe).encode())
    return path


def untrained_warning(model) -> str | None:
    """A one-line warning when ``model`` is a learned model with freshly initialized weights, else None."""
    from shapecorr.models.base import CorrespondenceModule

    if not isinstance(model, CorrespondenceModule) or model.trained_from is not None:
        return None
    if not any(p.requires_grad for p in model.parameters()):
        return None
    return (f"warning: {type(model).__name__} has untrained (randomly initialized) weights; its maps mean little. "
            "Give ckpt_path=CKPT (a checkpoint of train.py) to evaluate a trained model")
