"""``data_prep/prepare.py``: precompute the shape cache of a dataset ahead of time.

Fills the cache entries (eigenbasis, descriptors and, on request, all-pairs geodesics) of every shape of
every split of the configured dataset, in parallel worker processes with a progress bar. Training and
evaluation compute missing entries themselves; this command is for doing it once, e.g. on a cluster node.
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from shapecorr.cli.common import exit_on_user_error, user_config_error
from shapecorr.data.datamodule import SPLITS, ShapePairDataModule


@exit_on_user_error
def prepare(cfg: DictConfig) -> None:
    """Precompute the cache for ``cfg.data``; see configs/prepare.yaml for the options."""
    try:
        dm: ShapePairDataModule = hydra.utils.instantiate(cfg.data, _convert_="object")
        extra = OmegaConf.to_container(cfg.operators, resolve=True) if cfg.get("operators") else {}
    except OmegaConfBaseException as err:
        raise user_config_error(err) from err
    if extra:
        dm.with_operators(**extra)
    dm.ensure_data()
    seen = set()
    for split in SPLITS:
        shapes = dm.shapes(split)
        if tuple(shapes.names) in seen:
            continue
        seen.add(tuple(shapes.names))
        shapes.prepare(num_workers=cfg.workers, geodesics=cfg.geodesics)
    print(f"cache ready in {dm.shapes('train').cache.root} ({dm.operators})")

