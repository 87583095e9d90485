"""Plumbing shared by the command-line entry points (train, evaluate, prepare)."""

from __future__ import annotations

import functools
import sys
from typing import Any, Callable, TypeVar

from shapecorr.errors import ShapeCorrError

#: Exit status of a command that stopped on invalid input (a ShapeCorrError).
EXIT_INVALID_INPUT = 2
#: Exit status after Ctrl-C (128 + SIGINT, the shell convention).
EXIT_INTERRUPTED = 130

F = TypeVar("F", bound=Callable)


def exit_on_user_error(fn: F) -> F:
    """Run ``fn`` and turn input errors and Ctrl-C into short messages and exit codes.

    On a :class:`ShapeCorrError` print ``error: <message>`` to stderr (no traceback) and exit 2; on Ctrl-C
    print one line (completed work is kept) and exit 130.

    Only deliberate input/config errors are caught; genuine bugs keep their traceback.
    """

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except ShapeCorrError as err:
            print(f"error: {err}", file=sys.stderr)
            sys.exit(EXIT_INVALID_INPUT)
        except KeyboardInterrupt:
            print("interrupted: what was completed is kept (cache entries and results are written atomically); "
                  "run the same command again to continue", file=sys.stderr)
            sys.exit(EXIT_INTERRUPTED)

    return wrapper  # type: ignore[return-value]


def user_config_error(err: Exception) -> ShapeCorrError:
    """Wrap an OmegaConf/Hydra config error (missing mandatory value, bad interpolation) as a ConfigError."""
    from shapecorr.errors import ConfigError

    return ConfigError(f"invalid configuration: {err}")


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
