"""Run identity: the settings of an evaluation that change its numbers, and what changed between two runs.

``run.json`` records them, so that a resumed run never averages pairs computed with different settings.
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Any




def data_settings(shapes) -> dict[str, Any]:
    """The settings of a :class:`~shapecorr.data.datasets.ShapeDataset` that change an evaluation's numbers.

    Folder, normalization, the resolved parameters of every operator it provides (``data.operators.*`` merged with
    the matcher's request), ``data.reference_points`` and ``data.validation.*``: part of ``run.json``, so that a
    resumed run never averages pairs computed with different settings.
    """
    return {
        "data_root": str(Path(shapes.root).resolve()),
        "normalization": repr(shapes.normalization),
        "operators": shapes.operators.resolve(),
        "reference_points": shapes.reference_points,
        "validation": asdict(shapes.validation),
    }


def _flat(value: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(value, dict) and value:
        out: dict[str, Any] = {}
        for key, item in value.items():
            out.update(_flat(item, f"{prefix}.{key}" if prefix else str(key)))
        return out
    return {prefix: value}


def fingerprint_changes(previous: Any, current: dict[str, Any]) -> list[str]:
    """``["key: old -> new", ...]`` for every setting (dotted keys, sorted) that differs between two run records.

    ``previous`` is the parsed ``run.json`` (anything else, e.g. None for an unreadable file, differs in every
    key); ``current`` is compared as JSON stores it (tuples are lists). Missing keys show as ``(unset)``.
    """
    current = json.loads(json.dumps(current))
    old, new = _flat(previous if isinstance(previous, dict) else {}), _flat(current)
    changes = []
    for key in sorted(set(old) | set(new)):
        if old.get(key, _UNSET) != new.get(key, _UNSET):
            show = [_UNSET_TEXT if v is _UNSET else json.dumps(v)[:60] for v in (old.get(key, _UNSET),
                                                                                 new.get(key, _UNSET))]
            changes.append(f"{key}: {show[0]} -> {show[1]}")
    return changes


_UNSET = object()
_UNSET_TEXT = "(unset)"
