"""A weighted sum of named loss terms, the one loss object every model uses.

Each term is a pure function (usually a ``functools.partial`` built by Hydra with ``_partial_: true``, its
options bound) and a weight::

    loss:
      _target_: shapecorr.losses.weighted.WeightedLoss
      terms:
        reg:  {fn: {_target_: shapecorr.losses.registration.registration_loss, _partial_: true}, weight: 1.0}
        arap: {fn: {_target_: shapecorr.losses.arap.arap_sequence_loss, _partial_: true}, weight: 1.0}

A model calls ``total, values = loss(**inputs)`` with everything its terms may need, by name. Every term
receives the inputs whose names match its function's parameters (the others are ignored), so models and
loss functions are coupled by argument names only, never by config keys. A missing required input raises
:class:`~shapecorr.errors.ConfigError` naming the term. A term of weight 0 is skipped (not evaluated, and
absent from ``values``), which lets a schedule switch an expensive term off (e.g. NeuroMorph's geodesic
term after epoch 300, :meth:`WeightedLoss.set_weight`). A term whose function returns None does not apply to
these inputs (e.g. G-MSM's graph term for a pair without composed graph maps): it is left out of the total and
of ``values``.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping
from typing import Any

import torch

from shapecorr.errors import ConfigError, NumericalError


def _parameters(fn: Callable) -> tuple[set[str], set[str], bool]:
    """Names a callable accepts, the subset it requires, and whether it takes ``**kwargs``."""
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"cannot inspect the signature of loss function {fn!r}: {err}") from err
    accepted, required, var_kw = set(), set(), False
    for p in sig.parameters.values():
        if p.kind == p.VAR_KEYWORD:
            var_kw = True
        elif p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY):
            accepted.add(p.name)
            if p.default is p.empty:
                required.add(p.name)
    return accepted, required, var_kw


class WeightedLoss:
    """``total = sum_k weight_k * fn_k(**inputs)`` over named terms.

    Parameters
    ----------
    terms : mapping of name -> {"fn": callable, "weight": float}
        The loss terms. ``fn`` returns a scalar tensor; ``weight`` is a finite float (0 skips the term).
    """

    def __init__(self, terms: Mapping[str, Mapping[str, Any]]):
        if not terms:
            raise ConfigError("WeightedLoss needs at least one term")
        self._fns: dict[str, Callable[..., torch.Tensor]] = {}
        self._signatures: dict[str, tuple[set[str], set[str], bool]] = {}
        self._weights: dict[str, float] = {}
        for name, term in terms.items():
            if not isinstance(term, Mapping) or "fn" not in term or "weight" not in term:
                raise ConfigError(f"loss term {name!r} must be a mapping with keys 'fn' and 'weight'")
            fn = term["fn"]
            if not callable(fn):
                raise ConfigError(f"loss term {name!r}: fn is not callable ({fn!r})")
            self._fns[str(name)] = fn
            self._signatures[str(name)] = _parameters(fn)
            self.set_weight(str(name), term["weight"])

    @property
    def weights(self) -> dict[str, float]:
        """Current weight of every term (a copy)."""
        return dict(self._weights)

    def set_weight(self, name: str, weight: float) -> None:
        """Change the weight of a term (e.g. by an epoch schedule)."""
        if name not in self._fns:
            raise ConfigError(f"unknown loss term {name!r}; terms are {sorted(self._fns)}")
        try:
            value = float(weight)
        except (TypeError, ValueError) as err:
            raise ConfigError(f"loss term {name!r}: weight must be a number, got {weight!r}") from err
        if not torch.isfinite(torch.tensor(value)):
            raise ConfigError(f"loss term {name!r}: weight must be finite, got {value}")
        self._weights[name] = value

    def __call__(self, **inputs: Any) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Evaluate every term of non-zero weight.

        Parameters
        ----------
        **inputs
            Everything the terms may need, by argument name.

        Returns
        -------
        total : () tensor
            Weighted sum.
        values : dict of name -> () tensor
            Unweighted value of each evaluated term (for logging).
        """
        values: dict[str, torch.Tensor] = {}
        total = None
        for name, fn in self._fns.items():
            weight = self._weights[name]
            if weight == 0.0:
                continue
            accepted, required, var_kw = self._signatures[name]
            missing = sorted(required - inputs.keys())
            if missing:
                raise ConfigError(f"loss term {name!r} needs the inputs {missing}, which the model did not pass")
            kwargs = dict(inputs) if var_kw else {k: v for k, v in inputs.items() if k in accepted}
            value = fn(**kwargs)
            if value is None:
                continue
            if not isinstance(value, torch.Tensor) or value.numel() != 1:
                raise ConfigError(f"loss term {name!r} must return a scalar tensor, got {type(value).__name__}")
            if not bool(torch.isfinite(value)):
                raise NumericalError(f"loss term {name!r} is not finite ({float(value)})")
            values[name] = value.reshape(())
            total = weight * values[name] if total is None else total + weight * values[name]
        if total is None:
            raise ConfigError("every loss term has weight 0 or does not apply; nothing to optimize")
        return total, values
