"""G-MSM: the diffusion_gradients operator, the GMSM module (graph off = pairwise Deep Shells + DiffusionNet), the
graph loss, the shape-graph callback (build schedule, persistence, resume without rebuilding), DDP sharding, and
``evaluate.py model=gmsm`` writing the multi-shape metrics.

Shapes are small deformed icospheres (162 vertices) built in memory; the network is a narrow DiffusionNet.
"""

from __future__ import annotations

import json
import time
from types import SimpleNamespace

import numpy as np
import pytest
import scipy.sparse as sp
import torch
import trimesh
from pytorch_lightning.callbacks import Timer
from pytorch_lightning.trainer.states import RunningStage

from shapecorr.data.cache import ShapeCache
from shapecorr.data.datasets import PairSample, ShapeSample
from shapecorr.data.operators import DEFAULT_GRADIENT_RIDGE, compute_operator
from shapecorr.data.shape import make_shape
from shapecorr.eval.sharding import shard_pairs
from shapecorr.geometry.diffusion_operators import GRADIENT_RIDGE, diffusion_gradients
from shapecorr.geometry.laplace_beltrami import eigenbasis
from shapecorr.losses.shells import graph_alignment_loss, level_energy_loss
from shapecorr.losses.weighted import WeightedLoss
from shapecorr.matching.gmsm_query import full_resolution_shells
from shapecorr.models.deep_shells import DeepShells
from shapecorr.models.schedules import LossWeightSchedule
from shapecorr.models.gmsm import (
    GMSM,
    GRAPH_FILE,
    GraphOptions,
    ShapeGraphCallback,
    _gather,
    load_graph,
    training_ends,
)
from shapecorr.nn.diffusion_net import DiffusionNetBackbone

pytestmark = [pytest.mark.usefixtures("single_thread"),
              pytest.mark.filterwarnings("ignore:You are trying to `self.log\\(\\)`")]

N_EIG = 40
BACKBONE = {"k_eig": 32, "out_channels": 8, "width": 8, "n_blocks": 1, "dropout": 0.5}
LAYER = {"num_samples": 80, "layer": {"k_array": [6, 10, 14], "refine_k_max": 20, "refine_levels": 2}}


def _sample(verts, faces, name) -> ShapeSample:
    shape = make_shape(verts, faces, name)
    v, f = shape.verts.numpy().astype(np.float64), shape.faces.numpy()
    evals, evecs, mass = eigenbasis(v, f, N_EIG)
    return ShapeSample(shape=shape, operators={"eigenbasis": {"evals": evals, "evecs": evecs, "mass": mass},
                                               "diffusion_gradients": diffusion_gradients(v, f)})


@pytest.fixture(scope="module")
def shapes():
    mesh = trimesh.creation.icosphere(subdivisions=2)
    base, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    out = []
    for k in range(3):
        bent = base * [1.0 + 0.2 * k, 1.0, 1.0 - 0.1 * k]
        bent[:, 2] += 0.15 * np.sin(2.0 * bent[:, 1]) * k
        out.append(_sample(bent, faces, f"s{k}"))
    return out


class _Shapes:
    """ShapeDataset stand-in: names and samples."""

    def __init__(self, samples):
        self.samples, self.names = samples, [s.name for s in samples]

    def __len__(self):
        return len(self.samples)

    def __getitem__(self, i):
        return self.samples[i]


def _loss(graph_weight: float = 0.5) -> WeightedLoss:
    """The G-MSM loss of configs/model/loss/gmsm.yaml (level energies + graph term, lambda_graph 0.5 x 2000)."""
    return WeightedLoss({"shells": {"fn": level_energy_loss, "weight": 1.0},
                         "graph": {"fn": graph_alignment_loss, "weight": graph_weight}})


def _gmsm(**overrides) -> GMSM:
    torch.manual_seed(0)
    return GMSM(**{"backbone": DiffusionNetBackbone(**BACKBONE), "loss": _loss(), **LAYER, **overrides})


def test_diffusion_gradients_operator_registered_and_cached(tmp_path, shapes):
    assert DEFAULT_GRADIENT_RIDGE == GRADIENT_RIDGE
    v, f = shapes[0].shape.verts.numpy(), shapes[0].shape.faces.numpy()
    cache = ShapeCache(tmp_path)
    first = compute_operator(cache, v, f, "diffusion_gradients", {"ridge": DEFAULT_GRADIENT_RIDGE})
    assert any(tmp_path.rglob("*")), "nothing was written to the cache"
    again = compute_operator(ShapeCache(tmp_path, writable=False), v, f, "diffusion_gradients",
                             {"ridge": DEFAULT_GRADIENT_RIDGE})
    for name in ("grad_x", "grad_y"):
        assert sp.issparse(again[name]) and again[name].shape == (len(v), len(v))
        assert abs(again[name] - first[name]).max() == 0
    assert again["frames"].dtype == np.float32 and again["frames"].shape == (len(v), 3, 3)
    np.testing.assert_array_equal(again["frames"], first["frames"])
    # the backbone runs on a sample built from the cached arrays, with more eigenpairs than it uses
    sample = ShapeSample(shape=shapes[0].shape, operators={"eigenbasis": shapes[0].operators["eigenbasis"],
                                                           "diffusion_gradients": again})
    assert sample.operators["diffusion_gradients"]["grad_x"].is_sparse
    feats = DiffusionNetBackbone(**BACKBONE).eval()(sample)
    assert feats.shape == (len(v), BACKBONE["out_channels"]) and torch.isfinite(feats).all()


def test_graph_off_is_pairwise_deep_shells(shapes):
    batch = PairSample(shapes[0], shapes[1])
    gmsm = _gmsm(graph={"enabled": False})
    torch.manual_seed(0)
    pairwise = DeepShells(backbone=DiffusionNetBackbone(**BACKBONE), loss=_loss(), **LAYER)
    assert gmsm.configure_callbacks() == []
    for m in (gmsm, pairwise):
        m.train()
    torch.manual_seed(1)  # dropout draws
    loss_g = gmsm.training_step(batch, 3)
    torch.manual_seed(1)
    loss_p = pairwise.training_step(batch, 3)
    assert torch.equal(loss_g, loss_p)
    # with a graph the loss gains the graph term
    gmsm.set_graph(["s0", "s1"], {(0, 1): torch.randint(0, 162, (162,)).numpy(),
                                  (1, 0): torch.randint(0, 162, (162,)).numpy()}, epoch=0)
    torch.manual_seed(1)
    with_graph = gmsm.training_step(batch, 3)
    assert with_graph > loss_p
    # the graph term is a loss term: its weight scales it (loss.terms.graph.weight=, loss schedules)
    gmsm.loss.set_weight("graph", 1.0)
    torch.manual_seed(1)
    doubled = gmsm.training_step(batch, 3)
    torch.testing.assert_close(doubled - loss_p, 2 * (with_graph - loss_p), rtol=1e-4, atol=0)
    LossWeightSchedule("graph", [[0, 0.5], [2, 0.0]]).apply(gmsm, 2)  # a schedule switches the term off
    assert gmsm.loss.weights["graph"] == 0.0
    torch.manual_seed(1)
    assert torch.equal(gmsm.training_step(batch, 3), loss_p)


def test_graph_loss_hand_computation_and_prediction_beats_random(shapes):
    model = _gmsm().eval()
    x, y = shapes[0], shapes[1]
    tau = torch.randn(14, 3) * 0.01
    q = model.graph_query(x, y)
    loss = model.loss(level_energies=torch.zeros(3),
                      graph_alignment=model.graph_alignment(x, y, tau, q.map_x_to_y, q.map_y_to_x))[1]["graph"]
    deformed, shell_y = full_resolution_shells(model.spectral_shape(x), model.spectral_shape(y), tau, model.config)
    by_hand = torch.cat([((deformed[i] - shell_y[q.map_x_to_y[i]]) ** 2).sum()[None] for i in range(162)] +
                        [((deformed[q.map_y_to_x[j]] - shell_y[j]) ** 2).sum()[None] for j in range(162)]).mean()
    torch.testing.assert_close(loss, 2000.0 * by_hand)  # unweighted term; weight 0.5 = lambda_graph
    # pseudo-pairs equal to the model's own prediction (its last-level tau) cost less than a random map
    sx = torch.arange(162)
    from shapecorr.matching.deep_shells import deep_shells_layer

    with torch.no_grad():
        out = deep_shells_layer(model.features(x, sx), model.features(y, sx), model.spectral_shape(x),
                                model.spectral_shape(y), sx, sx, model.config, return_plans=False)
    rand = torch.randint(0, 162, (162,), generator=torch.Generator().manual_seed(0))
    own = model.graph_alignment(x, y, out.tau, q.map_x_to_y, q.map_y_to_x)
    other = model.graph_alignment(x, y, out.tau, rand, rand)
    assert own < 0.5 * other
    # queries are seeded per pair: the same pair gives the same cost and maps
    q2 = model.graph_query(x, y)
    assert q2.cost == q.cost and torch.equal(q2.map_x_to_y, q.map_x_to_y)


def test_dropout_at_test_flag(shapes):
    x, y = shapes[0], shapes[1]
    det = _gmsm().eval()
    assert det.graph_query(x, y).cost == det.graph_query(x, y).cost
    noisy = _gmsm(dropout_at_test=True).eval()
    torch.manual_seed(0)
    a = noisy.graph_query(x, y).cost
    torch.manual_seed(1)
    assert noisy.graph_query(x, y).cost != a
    assert not noisy.backbone.training  # restored after the query


def _trainer(tmp_path, samples, epoch):
    return SimpleNamespace(current_epoch=epoch, global_rank=0, world_size=1, is_global_zero=True, logger=None,
                           global_step=0, default_root_dir=str(tmp_path),
                           checkpoint_callback=SimpleNamespace(dirpath=str(tmp_path / "checkpoints")),
                           datamodule=SimpleNamespace(shapes=lambda split: _Shapes(samples)))


def test_callback_schedule_persistence_and_resume(tmp_path, shapes):
    opts = GraphOptions(burn_in=2, update_every=2)
    assert [e for e in range(8) if opts.builds_at(e)] == [2, 4, 6]
    model = _gmsm(graph={"burn_in": 2, "update_every": 2, "progress": False})
    cb = ShapeGraphCallback()
    cb.on_train_start(_trainer(tmp_path, shapes, 0), model)
    for epoch in range(5):
        cb.on_train_epoch_end(_trainer(tmp_path, shapes, epoch), model)
        assert (model.pseudo_maps is not None) == (epoch >= 2)
    assert cb.n_builds == 2 and cb.n_queries == 2 * 3 * 2
    path = tmp_path / "checkpoints" / GRAPH_FILE
    stored = load_graph(path)
    assert stored.epoch == 4 and stored.names == ["s0", "s1", "s2"] and len(stored.composed) == 6
    assert np.isfinite(stored.costs[~np.eye(3, dtype=bool)]).all()
    assert all(m.shape == (162,) for m in stored.composed.values())

    # resume at epoch 5 (checkpoint written after epoch 4): the file is read back, nothing is queried
    resumed = _gmsm(graph={"burn_in": 2, "update_every": 2, "progress": False})
    cb2 = ShapeGraphCallback()
    cb2.on_train_start(_trainer(tmp_path, shapes, 5), resumed)
    assert cb2.n_queries == 0 and resumed.pseudo_maps.epoch == 4
    np.testing.assert_array_equal(resumed.pseudo_maps.lookup("s0", "s2")[0].numpy(), stored.composed[(0, 2)])
    # resume from an older checkpoint (epoch 3 about to run): the file is newer, so the graph of epoch 2 is rebuilt
    cb3 = ShapeGraphCallback()
    cb3.on_train_start(_trainer(tmp_path, shapes, 3), _gmsm(graph={"burn_in": 2, "update_every": 2,
                                                                     "progress": False}))
    assert cb3.n_builds == 1 and load_graph(path).epoch == 2


@pytest.mark.parametrize("ending", ["should_stop", "max_epochs", "max_time"])
def test_no_graph_build_when_training_ends_with_the_epoch(tmp_path, shapes, ending):
    """A graph built at the end of the last epoch would train nothing: the build is skipped (a resumed run with a
    larger budget rebuilds it at train start)."""
    model = _gmsm(graph={"burn_in": 2, "update_every": 2, "progress": False})
    cb = ShapeGraphCallback()
    trainer = _trainer(tmp_path, shapes, 2)
    if ending == "should_stop":
        trainer.should_stop = True
    elif ending == "max_epochs":
        trainer.max_epochs = 3
    else:
        timer = Timer(duration={"seconds": 1})
        timer._start_time[RunningStage.TRAINING] = time.monotonic() - 5.0
        trainer.callbacks = [timer]
    assert training_ends(trainer, 2)
    cb.on_train_epoch_end(trainer, model)
    assert cb.n_builds == 0 and model.pseudo_maps is None
    assert not (tmp_path / "checkpoints" / GRAPH_FILE).exists()
    # the same epoch with budget left builds
    going_on = _trainer(tmp_path, shapes, 2)
    going_on.max_epochs, going_on.callbacks = 10, [Timer(duration={"hours": 1})]
    going_on.callbacks[0]._start_time[RunningStage.TRAINING] = time.monotonic()
    assert not training_ends(going_on, 2)
    cb.on_train_epoch_end(going_on, model)
    assert cb.n_builds == 1


def test_sharding_is_disjoint_and_covering():
    pairs = [(i, j) for i in range(5) for j in range(5) if i != j]
    for world in (1, 2, 3, 7):
        shards = [shard_pairs(list(range(len(pairs))), r, world) for r in range(world)]
        flat = [k for s in shards for k in s]
        assert sorted(flat) == list(range(len(pairs))) and len(set(flat)) == len(flat)
    assert _gather([1, 2], None) == [[1, 2]]


def _folder(root):
    from scipy.spatial import cKDTree

    from shapecorr.data.io import write_mesh, write_vts

    for sub in ("off", "corres"):
        (root / sub).mkdir(parents=True)
    mesh = trimesh.creation.icosphere(subdivisions=2)
    base, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    mirror = cKDTree(base).query(base * [-1.0, 1.0, 1.0])[1]
    rng = np.random.default_rng(0)
    ref = np.sort(rng.choice(len(base), 60, replace=False))
    for k in range(4):
        perm = rng.permutation(len(base))
        bent = base * [1.0 + 0.15 * k, 1.0, 1.0 - 0.1 * k]
        verts = np.empty_like(bent)
        verts[perm] = bent
        write_mesh(root / "off" / f"b{k}.off", verts, perm[faces])
        write_vts(root / "corres" / f"b{k}.vts", perm[ref])
        write_vts(root / "corres" / f"b{k}.sym.vts", perm[mirror[ref]])


def test_evaluate_gmsm_writes_multi_shape_metrics(tmp_path, compose_config):
    from shapecorr.cli.evaluate import evaluate

    _folder(tmp_path / "data")
    small = ["model.backbone.k_eig=32", "model.backbone.width=8", "model.backbone.out_channels=8",
             "model.backbone.n_blocks=1", "model.num_samples=80", "model.layer.k_array=[6,10,14]"]
    base = ["model=gmsm", "data=folder", f"data.root={tmp_path / 'data'}", f"paths.cache_dir={tmp_path / 'cache'}",
            "progress=false", "n_examples=1", "data.operators.n_eig=40", *small]
    result = evaluate(compose_config("evaluate", overrides=[*base, "multishape=graph",
                                                            f"output_dir={tmp_path / 'graph'}"]))
    ms = result["multi_shape"]
    assert ms["n_shapes"] == 4 and ms["n_queries"] == 12 and ms["unreachable_pairs"] == 0
    assert ms["cost"] == "matcher" and result["seconds_per_pair"] > 0  # G-MSM's own alignment cost
    for key in ("cycle_consistency", "cycle_consistency_pairwise"):
        assert ms[key]["n_triplets"] == 24 and 0 <= ms[key]["mean"] < 1
    saved = json.loads((tmp_path / "graph" / "metrics.json").read_text())
    assert saved["multi_shape"]["variant"] == "full" and saved["n_pairs"] == 12
    assert (tmp_path / "graph" / "shape_graph.png").stat().st_size > 0
    assert len(list((tmp_path / "graph" / "graph_queries").glob("*.npz"))) == 12
    direct = evaluate(compose_config("evaluate", overrides=[*base, f"output_dir={tmp_path / 'pairwise'}"]))
    assert "multi_shape" not in direct and direct["n_pairs"] == 12


def test_configs_pairwise_and_gmsm_compose(compose_config):
    from hydra.utils import instantiate

    pairwise = instantiate(compose_config("train", ["model=deep_shells", "model/backbone=diffusion_net",
                                                    "debug=tiny"]).model, _convert_="object")
    assert type(pairwise) is DeepShells and isinstance(pairwise.backbone, DiffusionNetBackbone)
    tiny = compose_config("train", ["model=gmsm", "debug=tiny"])
    model = instantiate(tiny.model, _convert_="object")
    assert isinstance(model, GMSM) and model.graph_options.builds_at(0)
    published = compose_config("train", ["experiment=gmsm_faust_r", "data.root=/nonexistent"])
    assert published.model.graph.burn_in == 100 and published.model.graph.update_every == 20
    assert published.model.loss.terms.graph.weight == 0.5 and published.model.num_samples == 2000
    assert published.model.layer == compose_config("evaluate", ["model=deep_shells"]).model.layer  # inherited
    assert compose_config("evaluate", ["model=gmsm", "multishape=graph"]).multishape.variant == "full"
