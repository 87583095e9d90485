"""Command-line overrides checked before a run starts: unknown keys and group options, with "did you mean".

Hydra accepts ``+key=value`` for any key and reports a mistyped key (``trainer.max_step=3``) or group option
(``model=deep_shell``) in several lines that advise ``+`` even where nothing reads the key. :func:`check_overrides`
composes the config of a command line itself and raises one :class:`~shapecorr.errors.ConfigError` line naming
the closest valid names instead:

- ``group=option`` of a config group (a folder of ``configs/``): the group and the option must exist;
- ``key=value``: the key must exist in the composed config;
- ``+key=value`` / ``++key=value`` of a key that is not in the config: accepted only where something reads it,
  i.e. under an open map (an empty ``{}`` such as ``callbacks`` or ``data.operators.request``, or one of
  :data:`OPEN_MAPS`) or under a node with a ``_target_`` whose constructor takes that argument (``+trainer.
  accumulate_grad_batches=4``); otherwise the closest keys are suggested, never ``+``;
- ``+group.key=value`` of a config group left unselected (``model: null``): accepted, the script builds that
  node itself (a custom ``+model._target_=...``, or a checkpoint's recipe with the keys on top);
- ``~key``: the key must exist.

Keys of Hydra itself (``hydra.*``) are left to Hydra.
"""

from __future__ import annotations

import difflib
import inspect
from pathlib import Path

from omegaconf import DictConfig, ListConfig, OmegaConf, open_dict

from shapecorr.errors import ConfigError

#: Maps whose keys are names chosen by the user (each documented where it is defined).
OPEN_MAPS = ("callbacks", "operators", "operators.request", "operators.params", "data.operators.request",
             "data.operators.params")
#: Maps whose keys are the fields of a dataclass (``+data.synthetic.n_holes=1``: any generator option).
FIELD_MAPS = {"data.synthetic": "shapecorr.data.synthetic.config.SyntheticConfig"}
#: How many close names a message lists at most.
MAX_SUGGESTIONS = 3
#: Similarity (difflib ratio) below which a name is not suggested.
SUGGESTION_CUTOFF = 0.6


def closest(name: str, candidates, n: int = MAX_SUGGESTIONS) -> list[str]:
    """The names of ``candidates`` closest to ``name`` (best first; empty when none is close)."""
    candidates = sorted({str(c) for c in candidates})
    found = difflib.get_close_matches(name, candidates, n=n, cutoff=SUGGESTION_CUTOFF)
    if not found:  # a prefix or an abbreviation, e.g. max_pair -> max_pairs, deep_shell -> deep_shells
        found = [c for c in candidates if c.startswith(name) or name.startswith(c)][:n]
    return found


def _did_you_mean(options: list[str]) -> str:
    if not options:
        return ""
    return "; did you mean " + " or ".join(options) + "?"


def config_groups(config_dir: Path) -> dict[str, list[str]]:
    """Every config group under ``config_dir`` (``model``, ``model/backbone``, ...) with its options."""
    groups: dict[str, list[str]] = {}
    for folder in sorted(p for p in config_dir.rglob("*") if p.is_dir()):
        options = sorted(f.stem for f in folder.glob("*.yaml"))
        if options:
            groups[folder.relative_to(config_dir).as_posix()] = options
    return groups


def _split(override) -> tuple[str, str, list[str]]:
    """(prefix ``+``/``++``/``~``/'', key, the values as strings: several for a sweep)."""
    from hydra.core.override_parser.types import OverrideType

    prefix = {OverrideType.ADD: "+", OverrideType.FORCE_ADD: "++", OverrideType.DEL: "~"}.get(override.type, "")
    key = override.key_or_group
    if override.is_sweep_override():
        try:
            values = [str(v) for v in override.sweep_string_iterator()]
        except Exception:  # noqa: BLE001 - ranges / globs: not expanded here
            values = []
    elif prefix == "~" and override.value() is None:
        values = []
    else:
        values = [override.get_value_element_as_str()]
    return prefix, key, values


def _group_of(key: str, groups: dict[str, list[str]]) -> str | None:
    """The config group an override key names (``model``, ``model/backbone``), else None."""
    return key if key in groups else None


def _node_keys(node) -> list[str]:
    if isinstance(node, DictConfig):
        return [str(k) for k in node.keys()]
    if isinstance(node, ListConfig):
        return [str(i) for i in range(len(node))]
    return []


def _child(node, part: str):
    """The child ``part`` of ``node`` without resolving interpolations; raises KeyError when there is none."""
    if isinstance(node, DictConfig) and part in node.keys():  # `in node` is False for a missing (???) value
        return node._get_node(part)
    if isinstance(node, ListConfig) and part.lstrip("-").isdigit() and -len(node) <= int(part) < len(node):
        return node._get_node(int(part))
    raise KeyError(part)


def _target_parameters(node) -> tuple[str, set[str], bool] | None:
    """(target, its keyword parameters, whether it takes ``**kwargs``) of a node with a ``_target_``, else None."""
    if not isinstance(node, DictConfig) or "_target_" not in node:
        return None
    target = str(node._get_node("_target_")._value())
    try:
        from hydra.utils import get_object

        obj = get_object(target)
        signature = inspect.signature(obj)
    except Exception:  # noqa: BLE001 - an unimportable target is reported when it is built, not here
        return None
    params = {name for name, p in signature.parameters.items()
              if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)}
    return target, params, any(p.kind == p.VAR_KEYWORD for p in signature.parameters.values())


def check_key(cfg: DictConfig, prefix: str, key: str, value: str) -> None:
    """Check one value override ``<prefix><key>=<value>`` against the composed config ``cfg``.

    Raises
    ------
    ConfigError
        The key is unknown (or, with ``+``, nothing reads it), with the closest names.
    """
    parts = key.split(".")
    node = cfg
    for depth, part in enumerate(parts):
        try:
            node = _child(node, part)
            continue
        except KeyError:
            pass
        parent_path = ".".join(parts[:depth])
        is_last = depth == len(parts) - 1
        shown = f"{prefix}{key}" + (f"={value}" if value is not None and prefix != "~" else "")
        if is_last and prefix in ("+", "++"):
            if _accepts(node, parent_path, part):
                return
        names = _node_keys(node)
        # the constructor's arguments (an import, seconds for Lightning) only where the config's keys do not
        # answer: an added key, or an unknown key without a close name in the config
        need_target = is_last and (prefix in ("+", "++") or not closest(part, names))
        target = _target_parameters(node) if need_target else None
        accepted: set[str] = set()
        if target is not None:
            accepted = target[1] - {"self"}
            if not target[2] and part in accepted and prefix == "":
                # the config lacks the key but the constructor takes it: adding it is the fix
                raise ConfigError(f"{shown}: {parent_path} has no key {part!r} in the config, but {target[0]} "
                                  f"takes it: write +{key}={value}")
        if is_last and prefix in ("+", "++"):
            accepted |= _field_names(parent_path)
        matches = closest(part, set(names) | accepted)
        where = f"{parent_path}" if parent_path else "the config"
        rest = parts[depth + 1:]
        fixes = [".".join(parts[:depth] + [m] + rest) for m in matches]
        fixes = [f"{'' if f_in_config(cfg, f) else '+'}{f}" + (f"={value}" if value is not None and prefix != "~"
                                                              else "") for f in fixes]
        what = "key" if prefix != "~" else "key to delete"
        reads = " (nothing reads an added key there)" if prefix in ("+", "++") else ""
        raise ConfigError(f"unknown {what} {shown}: {where} has no {part!r}{reads}{_did_you_mean(fixes)}")


def f_in_config(cfg: DictConfig, key: str) -> bool:
    """Whether the dotted ``key`` exists in ``cfg``."""
    node = cfg
    for part in key.split("."):
        try:
            node = _child(node, part)
        except KeyError:
            return False
    return True


def _field_names(parent_path: str) -> set[str]:
    """The fields of the dataclass behind a map of :data:`FIELD_MAPS` (empty for other paths)."""
    if parent_path not in FIELD_MAPS:
        return set()
    import dataclasses

    from hydra.utils import get_object

    return {f.name for f in dataclasses.fields(get_object(FIELD_MAPS[parent_path]))}


def _accepts(node, parent_path: str, part: str) -> bool:
    """Whether a key ``part`` added under ``node`` (at ``parent_path``) is read by anything."""
    if not isinstance(node, DictConfig):
        return False
    if parent_path in FIELD_MAPS:
        return part in _field_names(parent_path)
    if parent_path in OPEN_MAPS or len(node) == 0:
        return True
    target = _target_parameters(node)
    return target is not None and (target[2] or part in target[1])


def check_overrides(config_dir: str | Path, config_name: str, overrides: list[str],
                    choices: dict[str, str] | None = None) -> DictConfig:
    """Compose ``config_name`` of ``config_dir`` with the command-line ``overrides``; unknown names raise.

    Sweeps (``model=a,b`` with ``-m``) are checked value by value and composed with their first value.
    ``choices``, when given, receives the option selected for every config group (``{"data": "faust_r"}``), as
    Hydra resolved the defaults lists: an experiment's ``override /data: faust_r`` included.

    Returns
    -------
    DictConfig
        The composed config (with the first value of each sweep), unresolved.

    Raises
    ------
    ConfigError
        An unknown key, group or group option (with the closest names), or an override Hydra cannot parse or
        apply (its message on one line).
    """
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    config_dir = Path(config_dir).resolve()
    groups = config_groups(config_dir)
    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
    except HydraException as err:
        raise ConfigError(f"cannot read the command line: {_one_line(err)}") from None
    group_overrides, value_overrides = [], []
    for override, text in zip(parsed, overrides):
        prefix, key, values = _split(override)
        if key.startswith("hydra.") or key.startswith("hydra/") or key == "hydra":
            group_overrides.append(text if not override.is_sweep_override() else None)
            continue
        group = _group_of(key, groups)
        first = values[0] if values else None
        if group is not None:
            for value in values:
                if value not in groups[group] and value not in ("null", "None"):
                    raise ConfigError(f"unknown option {key}={value}: no configs/{group}/{value}.yaml"
                                      f"{_did_you_mean([f'{key}={m}' for m in closest(value, groups[group])])}")
            flat = text if not override.is_sweep_override() or first is None else f"{prefix}{key}={first}"
            group_overrides.append(flat)
        else:
            if "/" in key:
                guesses = closest(key, groups)
                raise ConfigError(f"unknown config group {key} (no folder configs/{key})"
                                  f"{_did_you_mean([f'{g}={first}' for g in guesses])}")
            value_overrides.append((override, prefix, key, first, text))
    group_overrides = [g for g in group_overrides if g is not None]

    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(config_dir), version_base="1.3", job_name=config_name):
            try:
                base = compose(config_name, overrides=group_overrides)
            except HydraException as err:
                raise ConfigError(f"invalid configuration: {_one_line(err)}") from None
            deleted = {key for _, prefix, key, _, _ in value_overrides if prefix == "~"}
            for override, prefix, key, first, _ in value_overrides:
                if prefix in ("+", "++") and any(key == d or key.startswith(d + ".") for d in deleted):
                    continue  # re-added after a deletion (~key +key=...)
                head = key.split(".")[0]
                if prefix in ("+", "++") and head in groups and head not in base:
                    continue  # a node of an unselected group (model: null): a custom `_target_`, or the
                    # checkpoint's recipe with these keys on top (evaluate.py ckpt_path=CKPT +model.refine=false)
                if prefix in ("+", "++") and f_in_config(base, key):
                    if prefix == "+":
                        raise ConfigError(f"+{key}: {key} is already in the config; write {key}={first}")
                    continue
                check_key(base, prefix, key, first)
            flat = group_overrides + [text if not o.is_sweep_override() or first is None
                                      else f"{prefix}{key}={first}" for o, prefix, key, first, text in value_overrides]
            try:
                cfg = compose(config_name, overrides=flat, return_hydra_config=choices is not None)
            except HydraException as err:
                raise ConfigError(f"invalid configuration: {_one_line(err)}") from None
            if choices is not None:
                choices.update({str(k): str(v) for k, v in cfg.hydra.runtime.choices.items()})
                with open_dict(cfg):
                    del cfg["hydra"]
            return cfg
    finally:
        GlobalHydra.instance().clear()


def _one_line(err: Exception) -> str:
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    return "; ".join(lines)


def missing_value(cfg: DictConfig, key: str) -> bool:
    """Whether ``key`` of ``cfg`` is unset (``???``, also through an interpolation such as ``${oc.env:X,???}``)."""
    from omegaconf.errors import MissingMandatoryValue

    parent, _, leaf = key.rpartition(".")
    try:
        value = (OmegaConf.select(cfg, parent) if parent else cfg)[leaf]
    except MissingMandatoryValue:
        return True
    except Exception:  # noqa: BLE001 - other resolution errors surface when the run builds the object
        return False
    return value == "???"


__all__ = ["OPEN_MAPS", "check_overrides", "check_key", "closest", "config_groups", "missing_value"]
