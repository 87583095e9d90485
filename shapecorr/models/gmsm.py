"""G-MSM as a LightningModule: Deep Shells with a DiffusionNet backbone, plus a shape graph over the training set.

Eisenberger, Toker, Leal-Taixé, Cremers, "G-MSM: Unsupervised Multi-Shape Matching with Graph-based Affinity
Priors", CVPR 2023 (docs/gmsm.md). :class:`GMSM` is :class:`~shapecorr.models.deep_shells.DeepShells` (the
backbone injected, ``configs/model/backbone/diffusion_net.yaml`` by default) with:

- :meth:`GMSM.graph_query`: the fast one-level query of a pair (a seeded 2000-vertex sample and the training
  layer, then :func:`~shapecorr.matching.gmsm_query.one_level_query` at full resolution), giving both maps and
  the alignment cost; ``match`` returns its maps (G-MSM's test protocol; ``test_query="deep_shells"`` gives the
  Deep Shells test pipeline instead);
- the graph term of the loss (``model.loss.terms.graph``, :func:`~shapecorr.losses.shells.graph_alignment_loss`,
  weight ``lambda_graph`` = 0.5, times 2000 in the function as in the G-MSM code): when a graph exists,
  :meth:`GMSM.loss_inputs` hands the loss the two-sided mean squared distance between the last level's ``X*`` and
  ``Y_k`` at full resolution over the pseudo-pairs of the composed graph maps (``graph_alignment``); logged as
  ``train/graph``;
- :class:`ShapeGraphCallback` (added by :meth:`GMSM.configure_callbacks` when ``graph.enabled``): (re)builds the
  graph at the end of epoch ``e`` when ``e >= burn_in`` and ``e % update_every == 0`` (0-based epochs, as the
  original's loop), the queries sharded over the DDP ranks and gathered; the graph is written atomically to
  ``<checkpoint dir>/shape_graph.npz`` and read back on resume instead of rebuilt.

With ``graph.enabled=false`` training is exactly pairwise Deep Shells + DiffusionNet (same loss, same samples).
Dropout: queries (graph building, tests) run the backbone in eval mode; ``dropout_at_test=true`` keeps it in
training mode, as the original code does (docs/gmsm.md §6).
"""

from __future__ import annotations

import contextlib
import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytorch_lightning as pl
import torch
from pytorch_lightning.callbacks import Timer

from shapecorr.data.operators import merge_requests
from shapecorr.errors import ConfigError
from shapecorr.eval.multi_shape import (
    PAIR_COST_KEY,
    CollectionGraph,
    GraphQuery,
    build_collection_graph,
    check_variant,
    collection_candidates,
    load_graph,
    query_pairs,
    save_graph,
)
from shapecorr.eval.sharding import shard_pairs
from shapecorr.matching.deep_shells import deep_shells_layer, random_samples, shell_size
from shapecorr.matching.gmsm_query import full_resolution_shells, one_level_query, two_sided_alignment_cost
from shapecorr.matching.result import MatchResult
from shapecorr.models.deep_shells import DeepShells

#: Name of the graph term in ``model.loss`` (its input is not computed while the term's weight is 0).
GRAPH_TERM = "graph"
#: File of the persisted graph, next to the checkpoints.
GRAPH_FILE = "shape_graph.npz"
TEST_QUERIES = ("fast", "deep_shells")


@dataclass(frozen=True)
class GraphOptions:
    """``model.graph`` options (defaults: G-MSM code, docs/gmsm.md §5).

    Attributes
    ----------
    enabled : bool
        Build the graph and add the graph loss (G-MSM: use_graph = True).
    variant : str
        ``full`` (G-MSM default) | ``mst`` | ``star`` | ``tsp`` | ``knn`` (only each shape's ``knn_k`` nearest
        shapes in eigenvalue space are queried; project extension).
    knn_k : int
    burn_in : int
        First epoch (0-based) at whose end the graph is built (G-MSM: 100).
    update_every : int
        Rebuild at the end of epochs ``e >= burn_in`` with ``e % update_every == 0`` (G-MSM: 20).
    progress : bool
        Progress bar over the queries (rank 0).
    """

    enabled: bool = True
    variant: str = "full"
    knn_k: int = 5
    burn_in: int = 100
    update_every: int = 20
    progress: bool = True

    def __post_init__(self):
        check_variant(self.variant)
        if self.burn_in < 0 or self.update_every < 1 or self.knn_k < 1:
            raise ConfigError(f"model.graph: need burn_in >= 0, update_every >= 1, knn_k >= 1; got {self.burn_in}, "
                              f"{self.update_every}, {self.knn_k}")

    def builds_at(self, epoch: int) -> bool:
        """Whether the graph is (re)built at the end of 0-based epoch ``epoch``."""
        return self.enabled and epoch >= self.burn_in and epoch % self.update_every == 0


class PseudoMaps:
    """Composed graph maps by shape names: ``lookup(name_x, name_y) -> (pi_xy, pi_yx)`` torch int64 or None."""

    def __init__(self, names, composed: Mapping[tuple[int, int], np.ndarray], epoch: int):
        self.index = {n: i for i, n in enumerate(names)}
        self.composed = composed
        self.epoch = int(epoch)

    def lookup(self, name_x: str, name_y: str):
        i, j = self.index.get(name_x), self.index.get(name_y)
        if i is None or j is None or i == j or (i, j) not in self.composed or (j, i) not in self.composed:
            return None
        return torch.from_numpy(self.composed[(i, j)]), torch.from_numpy(self.composed[(j, i)])


class GMSM(DeepShells):
    """G-MSM (see the module docstring).

    Parameters
    ----------
    graph : mapping, optional
        :class:`GraphOptions` fields.
    dropout_at_test : bool
        Keep the backbone's dropout on in queries (the original's behaviour); default off (eval mode).
    test_query : {"fast", "deep_shells"}
        What ``match`` runs: the fast one-level query (G-MSM test protocol) or the Deep Shells test pipeline.
    **kwargs
        :class:`~shapecorr.models.deep_shells.DeepShells` options (``backbone``, ``loss``, ``num_samples``,
        ``layer``, ...).
    """

    def __init__(self, *args, graph: Mapping[str, Any] | None = None, dropout_at_test: bool = False,
                 test_query: str = "fast", **kwargs):
        super().__init__(*args, **kwargs)
        try:
            self.graph_options = GraphOptions(**dict(graph or {}))
        except TypeError as err:
            raise ConfigError(f"gmsm: invalid model.graph option: {err}") from None
        if test_query not in TEST_QUERIES:
            raise ConfigError(f"gmsm: test_query must be one of {TEST_QUERIES}, got {test_query!r}")
        self.dropout_at_test = bool(dropout_at_test)
        self.test_query = test_query
        self.pseudo_maps: PseudoMaps | None = None

    @property
    def required_operators(self) -> dict:  # type: ignore[override]
        """The backbone's operators and the eigenpairs of the training levels.

        The refinement schedule's eigenpairs only with ``test_query="deep_shells"`` (the fast query works at the
        last training level).
        """
        if self.test_query == "deep_shells":
            return super().required_operators
        cfg = self.config
        need = max(max(shell_size(k, cfg.smooth_x, cfg.sigmoid_inclusive),
                       shell_size(k, "sigmoid", cfg.sigmoid_inclusive)) for k in cfg.k_array)
        return merge_requests(getattr(self.backbone, "required_operators", {}), {"eigenbasis": {"k": int(need)}})

    # -- graph -------------------------------------------------------------------------------------------------
    def configure_callbacks(self):
        """The shape-graph callback when the graph is enabled (so no ``callbacks:`` config is needed)."""
        return [ShapeGraphCallback()] if self.graph_options.enabled else []

    def set_graph(self, names, composed, epoch: int) -> None:
        """Use composed maps ``{(s, t): (n_s,)}`` over shapes ``names`` as the graph loss's pseudo-pairs."""
        self.pseudo_maps = PseudoMaps(names, composed, epoch)

    @contextlib.contextmanager
    def _query_mode(self):
        was = self.backbone.training
        self.backbone.train(self.dropout_at_test)
        try:
            yield
        finally:
            self.backbone.train(was)

    def query_generator(self, name_x: str, name_y: str) -> torch.Generator:
        """Generator of a query's vertex samples, seeded by (seed, the two names): a graph is reproducible."""
        key = [self.seed, zlib.crc32(name_x.encode()), zlib.crc32(name_y.encode())]
        return torch.Generator().manual_seed(int(np.random.SeedSequence(key).generate_state(1)[0]))

    def graph_query(self, x, y) -> GraphQuery:
        """Fast one-level query of the pair (module docstring): both maps and the alignment cost."""
        gen = self.query_generator(x.name, y.name)
        num = self.config.num_samples
        sx = random_samples(x.shape.n_verts, num, generator=gen).to(x.verts.device)
        sy = random_samples(y.shape.n_verts, num, generator=gen).to(y.verts.device)
        shape_x, shape_y = self.spectral_shape(x), self.spectral_shape(y)
        with torch.no_grad(), self._query_mode():
            out = deep_shells_layer(self.features(x, sx), self.features(y, sy), shape_x, shape_y, sx, sy,
                                    self.config, return_plans=False)
            q = one_level_query(shape_x, shape_y, out.fmap, out.tau, self.config)
        return GraphQuery(q.match.map_x_to_y, q.match.map_y_to_x, float(q.cost))

    def match(self, x, y) -> MatchResult:
        """Maps x -> y and y -> x by the fast one-level query (G-MSM's test protocol).

        With ``test_query="deep_shells"``: Deep Shells' test pipeline with the full refinement instead.
        """
        if self.test_query == "deep_shells":
            return super().match(x, y)
        q = self.graph_query(x, y)
        return MatchResult(p2p=q.map_x_to_y, p2p_inv=q.map_y_to_x, extras={PAIR_COST_KEY: q.cost})

    # -- the graph term --------------------------------------------------------------------------------------
    def graph_alignment(self, x, y, tau: torch.Tensor, pi_xy: torch.Tensor, pi_yx: torch.Tensor) -> torch.Tensor:
        """Input of the graph term: ``mean |X*[a] - Y_k[b]|^2`` over the pseudo-pairs of the composed maps.

        The mean is over ``(i, pi_xy[i])`` and ``(pi_yx[j], j)``, with ``X*`` and ``Y_k`` of shell size
        ``tau.shape[0]`` at full resolution.
        """
        deformed, shell_y = full_resolution_shells(self.spectral_shape(x), self.spectral_shape(y), tau, self.config)
        return two_sided_alignment_cost(deformed, shell_y, pi_xy.to(deformed.device), pi_yx.to(deformed.device))

    def loss_inputs(self, batch, out) -> dict[str, torch.Tensor]:
        """``{"graph_alignment": ...}`` when the graph holds composed maps for this pair, else nothing."""
        if self.pseudo_maps is None or (self.loss is not None and self.loss.weights.get(GRAPH_TERM) == 0.0):
            return {}
        found = self.pseudo_maps.lookup(batch.x.name, batch.y.name)
        if found is None:  # a self pair, or a pair without a path in the graph
            return {}
        return {"graph_alignment": self.graph_alignment(batch.x, batch.y, out.tau, *found)}


# -- the callback ------------------------------------------------------------------------------------------

def _gather(items: list, trainer) -> list:
    """All ranks' lists concatenated in rank order (the list itself in a single process)."""
    import torch.distributed as dist

    if trainer is None or trainer.world_size <= 1 or not (dist.is_available() and dist.is_initialized()):
        return [items]
    out: list = [None] * dist.get_world_size()
    dist.all_gather_object(out, items)
    return out


def graph_path(trainer) -> Path:
    """``<checkpoint dir>/shape_graph.npz`` (the trainer's root dir without a checkpoint callback)."""
    ck = getattr(trainer, "checkpoint_callback", None)
    folder = getattr(ck, "dirpath", None) or trainer.default_root_dir
    return Path(folder) / GRAPH_FILE


class ShapeGraphCallback(pl.Callback):
    """Builds, persists and reloads G-MSM's shape graph over the training shapes (module docstring).

    Attributes
    ----------
    n_builds : int
        Graphs built by this callback (tests: a resumed run must not rebuild).
    n_queries : int
        Pair queries this rank ran.
    """

    def __init__(self):
        self.n_builds = 0
        self.n_queries = 0

    def _shapes(self, trainer):
        dm = trainer.datamodule
        if dm is None or not hasattr(dm, "shapes"):
            raise ConfigError("gmsm: the graph callback needs the ShapePairDataModule (its training shapes)")
        return dm.shapes("train")

    def build(self, trainer, module: GMSM, epoch: int) -> CollectionGraph:
        """Query the training pairs (sharded over ranks), build the graph, persist it and hand it to the model."""
        opts = module.graph_options
        shapes = self._shapes(trainer)
        names = list(shapes.names)
        pairs = collection_candidates(shapes, opts.variant, opts.knn_k)
        rank, world = trainer.global_rank, trainer.world_size
        mine = shard_pairs(list(range(pairs.shape[0])), rank, world)
        results = query_pairs(module.graph_query, shapes, pairs[mine], progress=opts.progress and rank == 0,
                              device=module.device, desc=f"shape graph (epoch {epoch})")
        self.n_queries += len(mine)
        gathered = _gather(list(zip(mine, results)), trainer)
        by_index = dict(item for part in gathered for item in part)
        queries = [by_index[k] for k in range(pairs.shape[0])]
        graph = build_collection_graph(names, pairs, queries, opts.variant)
        self.n_builds += 1
        module.set_graph(names, graph.composed, epoch)
        if trainer.is_global_zero:
            save_graph(graph_path(trainer), graph, epoch)
            self._log(trainer, module, graph, epoch)
        return graph

    def _log(self, trainer, module, graph: CollectionGraph, epoch: int) -> None:
        finite = graph.graph.costs[np.isfinite(graph.graph.costs)]
        module.log_dict({"graph/mean_cost": float(finite.mean()) if finite.size else float("nan"),
                         "graph/unreachable_pairs": float(len(graph.unreachable))}, rank_zero_only=True)
        from shapecorr.viz.shape_graph import log_shape_graph

        log_shape_graph(trainer.logger, graph.graph, graph.names, step=trainer.global_step)

    def on_train_start(self, trainer, pl_module) -> None:
        """On resume: reload the persisted graph, or rebuild the last one the schedule asked for."""
        if not isinstance(pl_module, GMSM):
            raise ConfigError("ShapeGraphCallback needs the G-MSM model (model=gmsm)")
        start = trainer.current_epoch  # the epoch about to run (past ones on resume)
        if start == 0:
            return
        path = graph_path(trainer)
        if path.is_file():
            stored = load_graph(path)
            # a graph built at the end of an epoch the checkpoint has seen; a later one belongs to another run
            if stored.epoch < start and stored.names == list(self._shapes(trainer).names):
                pl_module.set_graph(stored.names, stored.composed, stored.epoch)
                return
        opts = pl_module.graph_options
        last = max((e for e in range(start) if opts.builds_at(e)), default=None)
        if last is not None:  # resuming past the burn-in without a usable file: build it now (as the original)
            self.build(trainer, pl_module, last)

    def on_train_epoch_end(self, trainer, pl_module) -> None:
        """Build the graph at the end of the epochs the schedule names (burn_in, then every update_every).

        Not when training ends with this epoch (stop requested, ``max_epochs`` or ``max_time`` reached): no step
        would use that graph, and a run resumed with a larger budget rebuilds it in :meth:`on_train_start`.
        """
        epoch = trainer.current_epoch
        if pl_module.graph_options.builds_at(epoch) and not training_ends(trainer, epoch):
            self.build(trainer, pl_module, epoch)


def training_ends(trainer, epoch: int) -> bool:
    """Whether no training step follows 0-based ``epoch``.

    True when a stop was requested (e.g. by Lightning's ``Timer`` at a batch end), ``epoch`` is the last of
    ``max_epochs``, or the ``max_time`` budget is spent.
    """
    if getattr(trainer, "should_stop", False):
        return True
    max_epochs = getattr(trainer, "max_epochs", None)
    if max_epochs is not None and max_epochs >= 0 and epoch + 1 >= max_epochs:
        return True
    for callback in getattr(trainer, "callbacks", None) or ():
        if isinstance(callback, Timer):
            remaining = callback.time_remaining()
            if remaining is not None and remaining <= 0:
                return True
    return False


__all__ = [
    "GMSM",
    "GRAPH_FILE",
    "GRAPH_TERM",
    "GraphOptions",
    "ShapeGraphCallback",
    "graph_path",
    "load_graph",
    "save_graph",
    "training_ends",
]
