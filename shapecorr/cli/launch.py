"""What the entry scripts (train.py, evaluate.py, data_prep/prepare.py) do before Hydra and torch start.

:func:`check_command_line` answers ``--help`` with the script's own help (its description, the config groups it
composes and its options), and otherwise composes the command line's config once (a fraction of a second,
without torch) to stop early, with one ``error: ...`` line and exit status 2, on

- unknown keys, groups and group options (:mod:`shapecorr.cli.config_errors`, with "did you mean");
- a dataset folder or weights file that is not set or does not exist: the message names the option, the
  environment variable the config reads it from (``SHAPECORR_FAUST_R``, ``SHAPECORR_DEEP_SHELLS_WEIGHTS``)
  and README's "Data and weights" section;

and sets the thread variables of the run (:mod:`shapecorr.cli.threads`) before any library reads them.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from shapecorr.cli.common import EXIT_INVALID_INPUT
from shapecorr.cli.config_errors import check_overrides, missing_value
from shapecorr.cli.threads import available_cores, set_thread_environment, threads_per_process
from shapecorr.errors import ConfigError, ShapeCorrError

#: Where README explains how to get the datasets and the published weights.
DATA_SECTION = 'README.md, "Data and weights"'
#: Hydra flags after which the check stands aside (another config, or Hydra's own information).
HYDRA_ONLY_FLAGS = ("--config-name", "-cn", "--config-path", "-cp", "--config-dir", "-cd", "--info", "-i",
                    "--shell-completion", "-sc", "--hydra-help", "--version", "--experimental-rerun")
#: Hydra flags that take a value (``--cfg job``).
FLAGS_WITH_VALUE = ("--cfg", "-c", "--package", "-p")
#: Config groups composed by every script that the user does not choose (paths, Hydra's settings).
INTERNAL_GROUPS = ("paths", "hydra")
_ENV_DEFAULT = re.compile(r"\$\{oc\.env:([A-Za-z_][A-Za-z0-9_]*)")


def _overrides(argv: list[str]) -> list[str] | None:
    """The overrides of a command line, or None when it carries a flag this check leaves to Hydra."""
    out, skip = [], False
    for arg in argv:
        if skip:
            skip = False
            continue
        if arg.split("=", 1)[0] in HYDRA_ONLY_FLAGS:
            return None
        if arg in FLAGS_WITH_VALUE:
            skip = True
            continue
        if arg.startswith("-"):
            continue
        out.append(arg)
    return out


def check_command_line(script: str | Path, config_name: str, description: str | None,
                       argv: list[str] | None = None) -> None:
    """Run the checks of the module docstring for ``script`` (its ``__file__``) and ``configs/<config_name>``.

    Prints the help and exits 0 on ``--help``; prints ``error: <message>`` and exits 2 on a bad command line;
    returns otherwise (Hydra then runs the script).
    """
    argv = sys.argv[1:] if argv is None else argv
    config_dir = _config_dir(Path(script))
    if "--help" in argv or "-h" in argv:
        print(script_help(config_dir, config_name, description, Path(script).name))
        sys.exit(0)
    overrides = _overrides(argv)
    if overrides is None:
        return
    try:
        choices: dict[str, str] = {}
        cfg = check_overrides(config_dir, config_name, overrides, choices)
        early_checks(cfg, config_name, choices)
    except ShapeCorrError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(EXIT_INVALID_INPUT)


def _config_dir(script: Path) -> Path:
    for candidate in (script.resolve().parent / "configs", script.resolve().parent.parent / "configs"):
        if candidate.is_dir():
            return candidate
    raise FileNotFoundError(f"no configs/ folder next to {script}")


def early_checks(cfg: DictConfig, config_name: str, choices: dict[str, str]) -> None:
    """The dataset folder and weights are set and exist; set the thread variables (module docstring).

    Raises
    ------
    ConfigError
        A required path is not set or does not exist; the message names the option, the environment variable
        the config falls back to, and :data:`DATA_SECTION`.
    """
    task = str(cfg.get("task") or "match")
    if "data" in cfg and cfg.data is not None and (config_name != "evaluate" or task == "match"):
        # the synthetic dataset is generated into data.root on first use
        _check_path(cfg, "data.root", f"data={choices.get('data', '?')}", folder=True,
                    must_exist="synthetic" not in cfg.data)
    model = cfg.get("model") if "model" in cfg else None
    if isinstance(model, DictConfig) and "pretrained" in model and not cfg.get("ckpt_path"):
        _check_path(cfg, "model.pretrained", f"model={choices.get('model', '?')}", folder=False,
                    allow_null=True)
    workers = cfg.get("workers") if "workers" in cfg else 0
    if config_name == "prepare" and workers is None:
        workers = available_cores()  # prepare.py: workers=null starts one process per core
    set_thread_environment(threads_per_process(cfg.get("threads") if "threads" in cfg else None, workers or 0))


def _check_path(cfg: DictConfig, key: str, selected: str, folder: bool, allow_null: bool = False,
                must_exist: bool = True) -> None:
    parent, _, leaf = key.rpartition(".")
    raw = OmegaConf.select(cfg, parent)._get_node(leaf)._value()
    env = _ENV_DEFAULT.search(str(raw))
    env_hint = f" or set {env.group(1)}" if env else ""
    kind = "folder" if folder else "file"
    if missing_value(cfg, key):
        raise ConfigError(f"{key} is not set: {selected} needs a {kind}; give {key}=PATH{env_hint} "
                          f"(where to get it: {DATA_SECTION})")
    try:
        value = OmegaConf.select(cfg, parent)[leaf]
    except Exception:  # noqa: BLE001 - an interpolation error is reported when the run resolves it
        return
    if value is None or str(value).strip() == "":  # an empty environment variable counts as unset
        if allow_null and value is None:
            return
        raise ConfigError(f"{key} is not set: {selected} needs a {kind}; give {key}=PATH{env_hint} "
                          f"(where to get it: {DATA_SECTION})")
    path = Path(str(value)).expanduser()
    if must_exist and (folder and not path.is_dir()) or (not folder and not path.is_file()):
        source = f" (from {env.group(1)})" if env and _unset(raw) else ""
        raise ConfigError(f"{key}={value}{source}: no such {kind}; {selected} needs a {kind} "
                          f"(give {key}=PATH{env_hint}; where to get it: {DATA_SECTION})", )


def _unset(raw) -> bool:
    return isinstance(raw, str) and raw.startswith("${oc.env:")


def _default_groups(primary: Path) -> list[tuple[str, str]]:
    """(group, default option) of the defaults list of a primary config file (internal groups excluded)."""
    node = OmegaConf.to_container(OmegaConf.load(primary), resolve=False)
    out = []
    for entry in node.get("defaults", []):
        if not isinstance(entry, dict):
            continue
        for key, value in entry.items():
            key = str(key).replace("optional ", "").strip()
            if key.startswith("override") or key in INTERNAL_GROUPS:
                continue
            out.append((key, "null" if value is None else str(value)))
    return out


def script_help(config_dir: Path, config_name: str, description: str | None, script: str) -> str:
    """``--help`` of a script: its description, the config groups it composes, and its options (commented)."""
    primary = config_dir / f"{config_name}.yaml"
    lines = [(description or "").strip(), "", f"Config groups of {script} (group=option; default in brackets):"]
    groups = {}
    for folder in sorted(p for p in config_dir.rglob("*") if p.is_dir()):
        options = sorted(f.stem for f in folder.glob("*.yaml"))
        if options:
            groups[folder.relative_to(config_dir).as_posix()] = options
    for group, default in _default_groups(primary):
        if default.startswith("${"):
            default = "same as model, if it exists"
        for name in [group] + [g for g in groups if g.startswith(group + "/")]:
            if name in groups:
                shown = default if name == group else "set by the model"
                lines.append(f"  {name}: {', '.join(groups[name])}  [{shown}]")
    text = primary.read_text()
    body, in_defaults = [], False
    for line in text.splitlines():
        if line.startswith("defaults:"):
            in_defaults = True
            continue
        if in_defaults and (line.startswith("  ") or not line.strip()):
            continue
        in_defaults = False
        body.append(line)
    lines += ["", f"Options (configs/{config_name}.yaml; key=value, e.g. seed=1; nested keys with dots, "
                  "e.g. data.root=DIR):", *body, "",
              "Unknown keys and options stop the run with the closest names. More: README.md and docs/. "
              "Hydra's own flags: --hydra-help."]
    return "\n".join(lines)
