"""Sharding the pairs of an evaluation over DDP ranks: every rank evaluates its shard into the same folder."""

from __future__ import annotations

import os
from typing import Any, Sequence


from shapecorr.errors import ConfigError


def distributed_context() -> tuple[int, int]:
    """``(rank, world_size)``: from torch.distributed when initialized, else from the launcher's environment.

    The environment fallback reads ``RANK`` (set by torchrun; ``LOCAL_RANK`` when only that is set) and
    ``WORLD_SIZE``; without them the run is a single process ``(0, 1)``.
    """
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    try:
        world = int(os.environ.get("WORLD_SIZE", "1"))
        rank = int(os.environ.get("RANK", os.environ.get("LOCAL_RANK", "0")))
    except ValueError as err:
        raise ConfigError(f"RANK / LOCAL_RANK / WORLD_SIZE must be integers: {err}") from None
    if world < 1 or not 0 <= rank < world:
        raise ConfigError(f"invalid distributed setting: rank {rank} of world size {world}")
    return rank, world


def shard_pairs(pairs: Sequence[Any], rank: int, world_size: int) -> list[Any]:
    """The pairs a rank evaluates: every ``world_size``-th pair starting at ``rank``.

    The shards are disjoint, cover every pair, keep the input order, and differ in size by at most one.
    """
    if world_size < 1 or not 0 <= rank < world_size:
        raise ConfigError(f"invalid shard: rank {rank} of world size {world_size}")
    return list(pairs[rank::world_size])
