"""The matcher an evaluation runs, and the options the ``evaluate.py`` tasks (matching, pose transfer) share.

The matcher is the model (fresh, or from its checkpoint) or a maps folder, wrapped by the ``postprocess=``
refinement and then the ``interpolator=``; the shared options are the device and the interpolation times.
"""

from __future__ import annotations

import os
import sys

import hydra
import torch
from omegaconf import DictConfig, OmegaConf, open_dict

from shapecorr.cli.model_request import model_request
from shapecorr.errors import ConfigError
from shapecorr.eval import matcher_run, multi_shape
from shapecorr.matching.baselines import LinearBlend, PrecomputedMaps
from shapecorr.matching.result import Matcher
from shapecorr.models.recipe import build_model, load_model, untrained_warning


def resolve_device(name: str) -> torch.device:
    """``auto`` -> ``cuda:LOCAL_RANK`` when CUDA is available, else ``cpu``; anything else as given."""
    if name == "auto":
        if torch.cuda.is_available():
            return torch.device(f"cuda:{int(os.environ.get('LOCAL_RANK', '0'))}")
        return torch.device("cpu")
    try:
        device = torch.device(name)
    except RuntimeError as err:
        raise ConfigError(f"invalid device {name!r}: {err}") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"device={name} but CUDA is not available")
    return device


def build_matcher(cfg: DictConfig, device: torch.device):
    """The matcher selected by ``model=`` (+ ``ckpt_path``) or ``maps_dir=`` (see the module docstring).

    Wrapped by the ``postprocess=`` refinement, then by the ``interpolator=`` (both optional).
    """
    model_cfg, matcher = cfg.get("model"), None
    if cfg.get("ckpt_path") and not cfg.get("maps_dir"):
        # the checkpoint's recipe with the command line's model.* overrides on top (shapecorr.models.recipe);
        # the merged recipe replaces cfg.model, so that run.json records what is evaluated
        requested, overrides = model_request(cfg)
        matcher = load_model(str(cfg.ckpt_path), requested, overrides, map_location=device)
        with open_dict(cfg):
            cfg.model = model_cfg = OmegaConf.create(matcher.recipe)
    if cfg.get("maps_dir"):
        if model_cfg is not None:
            raise ConfigError("give either model=<name> or maps_dir=DIR, not both")
        one_based = cfg.get("maps_one_based")
        if one_based is not None and not isinstance(one_based, bool):
            raise ConfigError(f"maps_one_based must be true, false or null (not said), got {one_based!r}")
        # precomputed maps are a matcher like any other: refined (postprocess=) and interpolated (interpolator=)
        matcher = PrecomputedMaps(cfg.maps_dir, one_based=one_based, extension=str(cfg.maps_extension))
        return with_interpolator(cfg, apply_postprocess(cfg, matcher))
    if model_cfg is None:
        raise ConfigError("nothing to evaluate: give model=<name> (e.g. model=descriptor_nn) or maps_dir=DIR")
    if "_target_" not in model_cfg:
        raise ConfigError("the model config has no _target_")
    if matcher is None:  # fresh weights: a learned model gets a warning
        matcher = build_model(model_cfg)
        warning = untrained_warning(matcher)
        if warning:
            print(warning, file=sys.stderr)
    if isinstance(matcher, torch.nn.Module):
        matcher = matcher.eval().to(device)
    if not isinstance(matcher, Matcher):
        raise ConfigError(f"{type(matcher).__name__} has no match(x, y) method; it cannot be evaluated")
    # refine the map first (postprocess=), compose the maps through the shape graph (multishape=), then interpolate
    # the resulting map (interpolator=)
    return with_interpolator(cfg, with_multishape(cfg, apply_postprocess(cfg, matcher)))


def interpolator_config(cfg: DictConfig) -> DictConfig | None:
    """The ``interpolator`` node (``configs/interpolator/<name>.yaml``), or None for ``interpolator=none``."""
    node = cfg.get("interpolator")
    if node is None or len(node) == 0:
        return None
    if "_target_" not in node:
        raise ConfigError("the interpolator config has no _target_ (configs/interpolator/<name>.yaml: "
                          "interpolator=none | linear_blend | hamiltonian)")
    return node


def with_interpolator(cfg: DictConfig, matcher):
    """``matcher`` wrapped in the interpolator selected by ``interpolator=<name>`` (itself when none).

    The interpolator (a :class:`~shapecorr.matching.baselines.LinearBlend` or a subclass, e.g. the Hamiltonian
    interpolation) is instantiated with ``matcher=matcher`` and ``interp_times=cfg.interp_times`` (its own default
    frames when null); it keeps the matcher's maps and computes the frames itself. A model that interpolates by
    itself (NeuroMorph, divfree) may be wrapped: its maps are kept and its own frames replaced. A model that is
    already such a wrapper (``model=linear_blend`` / ``model=hamiltonian``) is refused: wrap its matcher instead.
    """
    node = interpolator_config(cfg)
    if node is None:
        return matcher
    if isinstance(matcher, LinearBlend):
        raise ConfigError(
            f"interpolator={node._target_.rsplit('.', 1)[-1]} on top of {type(matcher).__name__}, which already "
            "interpolates the maps of its model.matcher: use the interpolator on that matcher "
            "(e.g. model=identity_gt interpolator=hamiltonian), or drop interpolator= (interpolator=none)"
        )
    times = interp_times_option(cfg)
    kwargs = {"matcher": matcher} if times is None else {"matcher": matcher, "interp_times": list(times)}
    try:
        wrapped = hydra.utils.instantiate(node, _convert_="object", **kwargs)
    except hydra.errors.InstantiationException as err:
        raise ConfigError(f"cannot build the interpolator: {err}") from None
    if not (isinstance(wrapped, Matcher) and matcher_run.interpolates(wrapped)):
        raise ConfigError(f"interpolator {node._target_} has no interpolate(x, y, times) method")
    return wrapped


def apply_postprocess(cfg: DictConfig, matcher):
    """``matcher`` wrapped by the ``postprocess=`` group's refinement (e.g. ``postprocess=smooth_shells``), if any.

    The group's config is a partial (``_partial_: true``) called with the built matcher as ``matcher``; the
    wrapper's ``required_operators`` then include the refinement's. Only ``evaluate.py`` applies it (training
    validation calls the model's own ``match``).
    """
    post_cfg = cfg.get("postprocess")
    if post_cfg is None:
        return matcher
    if "_target_" not in post_cfg:
        raise ConfigError("the postprocess config has no _target_ (use postprocess=smooth_shells or postprocess=null)")
    wrapped = _wrap(post_cfg, matcher, "the postprocess step")
    if not isinstance(wrapped, Matcher):
        raise ConfigError(f"{type(wrapped).__name__} has no match(x, y) method; it cannot post-process a matcher")
    return wrapped


def with_multishape(cfg: DictConfig, matcher):
    """``matcher`` wrapped in the ``multishape=`` group's :class:`~shapecorr.eval.multi_shape.MultiShapeMatcher`.

    Itself without the group. The wrapper queries the split's pairs in :func:`evaluate` (``prepare``) before the
    per-pair loop scores its composed maps (docs/evaluation.md §7).
    """
    node = cfg.get("multishape")
    if node is None:
        return matcher
    if "_target_" not in node:
        raise ConfigError("the multishape config has no _target_ (use multishape=graph or multishape=null)")
    wrapped = _wrap(node, matcher, "the multishape wrapper")
    if not isinstance(wrapped, multi_shape.MultiShapeMatcher):
        raise ConfigError(f"multishape: {node._target_} is not a MultiShapeMatcher")
    return wrapped


def _wrap(node: DictConfig, matcher, what: str):
    """A wrapper group's partial config (``_partial_: true``) called with ``matcher=matcher``."""
    try:
        return hydra.utils.instantiate(node, _convert_="object", _partial_=True)(matcher=matcher)
    except hydra.errors.InstantiationException as err:
        raise ConfigError(f"cannot build {what}: {err}") from None


def multishape_of(matcher) -> multi_shape.MultiShapeMatcher | None:
    """The multi-shape wrapper in a chain of wrappers (e.g. under ``interpolator=``), or None."""
    while matcher is not None and not isinstance(matcher, multi_shape.MultiShapeMatcher):
        matcher = getattr(matcher, "matcher", None)
    return matcher


def interp_times_option(cfg: DictConfig) -> tuple[float, ...] | None:
    """``cfg.interp_times`` checked (finite, strictly increasing), or None when it is null."""
    value = cfg.get("interp_times")
    if value is None:
        return None
    if not OmegaConf.is_list(value):
        raise ConfigError("interp_times must be a list of times (e.g. interp_times=[0,0.5,1,1.5]) or null, "
                          f"got {value!r}")
    return matcher_run.check_interp_times(OmegaConf.to_container(value, resolve=True))
