"""What a command line asks of a checkpoint's model: the model it names and its ``model.*`` overrides.

``evaluate.py ckpt_path=CKPT`` (and ``train.py ckpt_path=`` to resume) builds the checkpoint's recipe
(:mod:`shapecorr.models.recipe`) with the command line's ``model.*`` options on top; this module reads them.
"""

from __future__ import annotations

from typing import Any


def command_line_overrides(cfg) -> list[str] | None:
    """The overrides of the command line (``key=value`` strings), or None when they are not known.

    From Hydra's runtime (``python train.py ...``), else from a config composed with ``return_hydra_config``.
    """
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        return list(HydraConfig.get().overrides.task)
    node = cfg.get("hydra") if hasattr(cfg, "get") else None
    if node is not None and node.get("overrides") is not None:
        return list(node.overrides.task)
    return None


def model_request(cfg) -> tuple[Any, dict[str, Any]]:
    """What the command asks of a checkpoint's model: ``(requested model node or None, overrides)``.

    The requested node is ``cfg.model`` when the command line selects a model (``model=<name>``; when the command
    line is not known: whenever ``cfg.model`` has a ``_target_``), else None (the checkpoint's own model). The
    overrides are the command line's ``model.<key>=``, ``+model.<key>=``, ``~model.<key>`` and ``model/<group>=``
    options: ``{key relative to the model node: its value in cfg.model}`` (resolved;
    :data:`shapecorr.models.recipe.DELETE` for a removed key), for
    :func:`shapecorr.models.recipe.merge_overrides`.
    """
    from omegaconf import OmegaConf

    from shapecorr.models.recipe import DELETE

    model = cfg.get("model")
    overrides = command_line_overrides(cfg)
    keys: list[str] = []
    selects = overrides is None
    for item in overrides or ():
        key = item.lstrip("+~").split("=", 1)[0].split("@", 1)[0]
        if key == "model":
            selects = True
        elif key.startswith("model.") or key.startswith("model/"):
            keys.append(key[len("model."):].replace("/", "."))
    values: dict[str, Any] = {}
    for key in keys:
        value = DELETE if model is None else OmegaConf.select(model, key, default=DELETE)
        values[key] = OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value
    requested = model if selects and model is not None and "_target_" in model else None
    return requested, values
