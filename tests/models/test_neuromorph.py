"""NeuroMorph LightningModule: training step, geodesic lookups, queries and interpolation, configs, CLI smoke run.

The pair is built in memory: a 642-vertex icosphere stretched into an ellipsoid with a bump, and a bent,
vertex-permuted copy (x's vertex i is y's vertex perm[i]). Networks are shrunk (16 channels, 2 EdgeConv
layers) except in the CLI run, which uses the configured model on a 4-shape folder dataset written by the test.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from hydra.utils import instantiate

import shapecorr.models.neuromorph as nm
from shapecorr.data.augmentation import (
    PairAugmenter,
    cached_remesh,
    remeshed_sample,
    rotation_about_axis,
    step_rng,
)
from shapecorr.data.cache import ShapeCache
from shapecorr.data.datasets import PairSample, ShapeSample
from shapecorr.data.shape import make_shape
from shapecorr.errors import ConfigError
from shapecorr.losses.weighted import WeightedLoss
from shapecorr.models.neuromorph import NeuroMorph
from shapecorr.models.schedules import EpochSchedule, LossWeightSchedule
from shapecorr.nn.spectral_conv import SpectralBackbone
from shapecorr.nn.edgeconv_backbone import EdgeConvBackbone
from shapecorr.viz.interpolation import interpolation_strip_figure, log_interpolation

REPO = Path(__file__).resolve().parents[2]
SMALL_NET = dict(hidden_channels=16, n_blocks=2)
#: The published loss weights (configs/model/loss/neuromorph.yaml).
PUBLISHED_WEIGHTS = {"registration": 1.0, "arap": 1.0, "geo": 50.0}


def published_loss():
    """The published loss, built from configs/model/loss/neuromorph.yaml."""
    from omegaconf import OmegaConf

    return instantiate(OmegaConf.load(REPO / "configs" / "model" / "loss" / "neuromorph.yaml"), _convert_="object")


def small() -> dict:
    """Options of a shrunk model: a fresh 16-channel, 2-layer backbone and interpolation network, the loss."""
    return dict(backbone=EdgeConvBackbone(feature_dim=16, **SMALL_NET), interpolation_net=SMALL_NET,
                loss=published_loss())

FINAL_LINE = re.compile(r"^test geodesic error: (\d+\.\d+) \(fraction of sqrt\(area\)\) over (\d+) pairs$")

pytestmark = pytest.mark.filterwarnings("ignore:You are trying to `self.log\\(\\)`", "ignore::DeprecationWarning")


def _base_mesh():
    mesh = trimesh.creation.icosphere(subdivisions=3)
    v, f = np.asarray(mesh.vertices) * [1.4, 1.0, 0.7], np.asarray(mesh.faces)
    v[:, 1] += 0.3 * np.exp(-4.0 * ((v[:, 0] - 0.5) ** 2 + v[:, 2] ** 2))
    return v, f


def _sample(verts, faces, name, corres) -> ShapeSample:
    shape = make_shape(verts, faces, name)
    n = shape.n_verts
    return ShapeSample(
        shape=shape,
        operators={"eigenbasis": {"evals": torch.zeros(0), "evecs": torch.zeros(n, 0), "mass": torch.ones(n)}},
        corres=torch.as_tensor(corres, dtype=torch.int64),
    )


@pytest.fixture(scope="module")
def pair():
    v, f = _base_mesh()
    perm = np.random.default_rng(0).permutation(len(v))
    bent = v.copy()
    bent[:, 2] += 0.25 * np.sin(1.5 * bent[:, 0])
    vy = np.empty_like(bent)
    vy[perm] = bent
    return PairSample(_sample(v, f, "x", np.arange(len(v))), _sample(vy, perm[f], "y", perm))


class LossSpy:
    """Wraps the model's WeightedLoss and records what each call received and returned."""

    def __init__(self, loss: WeightedLoss):
        self.inner, self.calls = loss, []

    @property
    def weights(self):
        return self.inner.weights

    def set_weight(self, name, weight):
        self.inner.set_weight(name, weight)

    def __call__(self, **inputs):
        total, values = self.inner(**inputs)
        self.calls.append((inputs, total.detach(), {k: v.detach() for k, v in values.items()}))
        return total, values


def _model(tmp_path, **kwargs) -> NeuroMorph:
    torch.manual_seed(0)
    options = dict(small(), cache_dir=str(tmp_path), augment=dict(resolution=[200, 400], variants=2))
    return NeuroMorph(**{**options, **kwargs})


def test_training_step_finite_loss_and_gradients_reach_both_networks(pair, tmp_path):
    model = _model(tmp_path, n_intermediate=3)
    spy = model.loss = LossSpy(model.loss)
    loss = model.training_step(pair, 0)
    assert loss.dim() == 0 and torch.isfinite(loss) and loss > 0
    inputs, total, values = spy.calls[-1]
    assert set(values) == {"registration", "arap", "geo"}
    expected = float(values["registration"]) + float(values["arap"]) + 50.0 * float(values["geo"])
    assert float(total) == pytest.approx(expected, rel=1e-5)
    assert inputs["frames"].shape[0] == 3 + 2  # x, then X(t_i) for t = 1/4, 1/2, 3/4, 1
    n_x = inputs["frames"].shape[1]
    assert 190 <= n_x <= 410 and inputs["dist_x"].shape == (n_x, n_x)  # a remesh from the pool, with its geodesics
    # closed mesh: 2 faces per edge, times the default scale 0.5 (the original's number of ARAP residuals)
    torch.testing.assert_close(inputs["edge_weights"].unique(), torch.tensor([1.0]))
    loss.backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    for net in (model.feature_net, model.interpolator):
        assert sum(float(p.grad.abs().sum()) for p in net.parameters()) > 0
    # the same step (same seed, epoch, batch index) draws the same augmentation
    again = model.training_step(pair, 0)
    assert float(again.detach()) == pytest.approx(float(loss.detach()), rel=1e-6)
    assert len(list((tmp_path / "remesh").rglob("*.npz"))) <= 4


def _feature_gradient(model: NeuroMorph, pair, **weights) -> float:
    """Total |gradient| of the feature net after one training step with the given loss weights."""
    for term, weight in weights.items():
        model.loss.set_weight(term, weight)
    model.zero_grad()
    model.training_step(pair, 0).backward()
    return sum(float(p.grad.abs().sum()) for p in model.feature_net.parameters() if p.grad is not None)


def test_map_gradient_geodesic_lets_only_the_geodesic_term_train_the_features(pair, tmp_path):
    published = _model(tmp_path)
    assert published.map_gradient == "all"
    assert _feature_gradient(published, pair, geo=0.0) > 0  # published: registration + ARAP reach the features
    model = _model(tmp_path, map_gradient="geodesic")
    assert _feature_gradient(model, pair, geo=0.0) == 0.0
    assert sum(float(p.grad.abs().sum()) for p in model.interpolator.parameters()) > 0  # still trained
    assert _feature_gradient(model, pair, geo=50.0, registration=0.0, arap=0.0) > 0
    # the geodesic term's own gradient is the same in both modes; and so are the loss values
    only_geo = dict(geo=50.0, registration=0.0, arap=0.0)
    reference = _model(tmp_path)
    _feature_gradient(reference, pair, **only_geo)
    _feature_gradient(model, pair, **only_geo)
    for a, b in zip(reference.feature_net.parameters(), model.feature_net.parameters()):
        torch.testing.assert_close(a.grad, b.grad)
    for term in ("registration", "arap", "geo"):
        reference.loss.set_weight(term, PUBLISHED_WEIGHTS[term])
        model.loss.set_weight(term, PUBLISHED_WEIGHTS[term])
    with torch.no_grad():
        assert float(model.training_step(pair, 0)) == pytest.approx(float(reference.training_step(pair, 0)), rel=1e-5)
    # a schedule can switch it, and a bad value is refused
    EpochSchedule("map_gradient", [[0, "geodesic"], [3, "all"]]).apply(model, 4)
    assert model.map_gradient == "all"
    with pytest.raises(ConfigError, match="map_gradient"):
        model.map_gradient = "registration"
    with pytest.raises(ConfigError, match="map_gradient"):
        NeuroMorph(**small(), map_gradient="none")


def test_geodesics_are_skipped_while_lambda_geo_is_zero(pair, tmp_path, monkeypatch):
    model = _model(tmp_path)
    spy = model.loss = LossSpy(model.loss)
    model.loss.set_weight("geo", 0.0)
    assert model.lambda_geo == 0.0

    def forbidden(self, sample):
        raise AssertionError("geodesics looked up with lambda_geo = 0")

    monkeypatch.setattr(PairAugmenter, "distances", forbidden)
    loss = model.training_step(pair, 1)
    assert torch.isfinite(loss)
    inputs, _, values = spy.calls[-1]
    assert set(values) == {"registration", "arap"} and "dist_x" not in inputs
    assert inputs["frames"].shape[0] == 2  # T = 0: [x, X(1)]
    assert not (tmp_path / "geodesics").exists()


def test_interpolate_frames_maps_and_extrapolation(pair, tmp_path):
    model = _model(tmp_path, match_chunk_size=100).eval()  # several chunks: the chunked query equals the full one
    x, y = pair.x, pair.y
    times = torch.tensor([0.0, 0.5, 1.0, 1.5, 2.0])
    result = model.interpolate(x, y, times)
    result.validate(x.shape.n_verts, y.shape.n_verts)
    assert result.deformation.shape == (5, x.shape.n_verts, 3)
    assert torch.equal(result.deformation[0], x.verts)  # exactly x at t = 0
    torch.testing.assert_close(result.times, times)
    assert not torch.allclose(result.deformation[4], result.deformation[2])  # t = 2 goes beyond t = 1
    with torch.no_grad():
        full = model.forward_pair(x, y, times)
    torch.testing.assert_close(result.deformation, full["frames"], rtol=1e-5, atol=1e-5)
    # hard maps = row argmax of the soft maps (up to float ties of the softmax: the chosen entry is a maximum)
    for p2p, soft in ((result.p2p, full["pi_x_to_y"]), (result.p2p_inv, full["pi_y_to_x"])):
        chosen = soft.gather(1, p2p[:, None]).squeeze(1)
        torch.testing.assert_close(chosen, soft.max(1).values, rtol=1e-5, atol=0.0)
        assert float((p2p == soft.argmax(1)).float().mean()) > 0.95
    match = model.match(x, y)
    torch.testing.assert_close(match.times, torch.tensor(nm.DEFAULT_INTERP_TIMES))
    assert match.deformation.shape == (len(nm.DEFAULT_INTERP_TIMES), x.shape.n_verts, 3)
    assert torch.equal(match.p2p, result.p2p)
    for bad in ([], [0.0, float("nan")], [[0.0, 1.0]]):
        with pytest.raises(ConfigError):
            model.interpolate(x, y, bad)


def test_query_resolution_runs_on_a_remesh_and_carries_back(pair, tmp_path, monkeypatch):
    model = _model(tmp_path, query_resolution=300).eval()
    calls = []
    monkeypatch.setattr(nm, "cached_remesh", lambda *a: calls.append(a[3]) or cached_remesh(*a))
    x, y = pair.x, pair.y
    times = torch.tensor([0.0, 1.0, 1.25])
    result = model.interpolate(x, y, times)
    result.validate(x.shape.n_verts, y.shape.n_verts)
    assert calls == [300, 300]
    assert torch.equal(result.deformation[0], x.verts)
    # oracle: the same network on the remeshed pair, carried back by hand
    cache = ShapeCache(tmp_path)
    rx, ry = cached_remesh(cache, x.verts, x.faces, 300), cached_remesh(cache, y.verts, y.faces, 300)
    low = _plain_copy(model).interpolate(remeshed_sample(x, rx), remeshed_sample(y, ry), times)
    nearest_x, source_y = torch.from_numpy(rx.nearest_vertex), torch.from_numpy(ry.source_vertex)
    assert torch.equal(result.p2p, source_y[low.p2p[nearest_x]])
    source_x, nearest_y = torch.from_numpy(rx.source_vertex), torch.from_numpy(ry.nearest_vertex)
    assert torch.equal(result.p2p_inv, source_x[low.p2p_inv[nearest_y]])
    expected = x.verts + rx.lift(low.deformation - torch.from_numpy(rx.verts))
    torch.testing.assert_close(result.deformation, expected)
    model.interpolate(x, y, times)
    assert calls == [300, 300]  # in-memory LRU: no second lookup


def _plain_copy(model: NeuroMorph) -> NeuroMorph:
    copy = NeuroMorph(**small(), cache_dir=model.cache_dir).eval()
    copy.load_state_dict(model.state_dict())
    return copy


def test_interpolation_metrics_use_the_frame_at_t1(pair, tmp_path, monkeypatch):
    from shapecorr.eval.scoring import score_deformation

    model = _model(tmp_path, interp_times=[0.0, 0.5, 1.5]).eval()  # t = 1 missing: computed for the metrics
    logged = {}
    monkeypatch.setattr(model, "log", lambda name, value, **kw: logged.__setitem__(name, value))
    result = model.match(pair.x, pair.y)
    model._score_interpolation(pair, result, "val")
    expected = score_deformation(model.interpolate(pair.x, pair.y, [0.0, 0.5, 1.0]).deformation, pair.x, pair.y)
    assert {"val/chamfer", "val/chamfer_one_sided", "val/deformation_conformal_distortion"} <= set(logged)
    for key in ("chamfer", "deformation_conformal_distortion"):
        assert logged[f"val/{key}"] == pytest.approx(expected[key], rel=1e-5)


def test_options_are_validated(tmp_path):
    with pytest.raises(TypeError):  # an unknown option (e.g. a Deep Shells key)
        NeuroMorph(**small(), num_samples=3)
    for bad in (dict(sigma=-1.0), dict(query_resolution=2),
                dict(arap_edge_weight_scale=0.0), dict(augment=dict(axis="q")), dict(interp_times=[]),
                dict(interp_times=[1.0, 0.5]),
                dict(loss={"not": "a loss"}), dict(n_intermediate=-1), dict(n_intermediate=1.5)):
        with pytest.raises(ConfigError):
            NeuroMorph(**{**small(), **bad})
    model = NeuroMorph(**small())
    model.n_intermediate = 7
    assert model.n_intermediate == 7
    with pytest.raises(ConfigError):
        model.n_intermediate = -2
    assert model.interpolator.net.pool == "global" and model.backbone.out_channels == 16
    with pytest.raises(ConfigError, match="backbone"):
        NeuroMorph(backbone=torch.nn.Linear(3, 3))
    with pytest.raises(ConfigError, match="per-shape operators"):  # augmented shapes carry none
        NeuroMorph(backbone=SpectralBackbone())
    with pytest.raises(ConfigError, match="interpolation_net"):
        NeuroMorph(interpolation_net=dict(width=3))
    with pytest.raises(ConfigError, match="model.loss"):
        NeuroMorph(**{**small(), "loss": None}).training_step(None, 0)


def test_schedule_callbacks_drive_the_module(tmp_path):
    model = NeuroMorph(**small())
    EpochSchedule("n_intermediate", [[0, 0], [300, 1], [450, 3], [525, 7]]).apply(model, 460)
    LossWeightSchedule("geo", [[0, 50.0], [300, 0.0]]).apply(model, 460)
    assert model.n_intermediate == 3 and model.lambda_geo == 0.0


def test_configs_compose_with_the_published_settings(tmp_path, compose_config):
    cfg = compose_config("train", ["model=neuromorph", "debug=tiny", f"paths.cache_dir={tmp_path}",
                                   f"paths.output_dir={tmp_path}"])
    # the run configs' Deep Shells settings (configs/quick/) do not reach another model
    assert not {"num_samples", "val_refine_levels", "layer"} & set(cfg.model)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model = instantiate(cfg.model, _convert_="object")
    assert isinstance(model, NeuroMorph) and model.loss.weights == {"registration": 1.0, "arap": 1.0, "geo": 50.0}
    assert model.sigma == 100.0 and model.augment.resolution == (200, 2000)
    assert isinstance(model.backbone, EdgeConvBackbone) and model.backbone.out_channels == 128
    assert model.backbone.required_operators == {}
    assert model.interpolator.net.fc_out.in_features == 128 and len(model.interpolator.net.blocks) == 5
    optimizer = model.configure_optimizers()
    assert isinstance(optimizer, torch.optim.Adam) and optimizer.defaults["lr"] == 1e-4
    assert model.interp_times == nm.DEFAULT_INTERP_TIMES
    callbacks = {name: instantiate(node, _convert_="object") for name, node in cfg.callbacks.items()}
    assert callbacks["neuromorph_T"].schedule.values == [0, 1, 3, 7]
    assert callbacks["neuromorph_T"].schedule.epochs == [0, 300, 450, 525]
    assert callbacks["neuromorph_lambda_geo"].schedule.epochs == [0, 300]
    exp = compose_config("train", ["experiment=neuromorph_faust_r", f"paths.cache_dir={tmp_path}",
                                   f"paths.output_dir={tmp_path}", f"data.root={tmp_path}"])
    assert exp.model._target_ == "shapecorr.models.neuromorph.NeuroMorph" and exp.model.query_resolution == 2000
    assert exp.trainer.accumulate_grad_batches == 16 and exp.trainer.max_epochs == 600
    assert exp.trainer.check_val_every_n_epoch == 10 and exp.checkpoint.every_n_epochs == 10
    assert exp.data.pairs.train.include_self and exp.data.splits.train.index_range == [0, 80]
    assert list(exp.callbacks.neuromorph_T.milestones) == [[0, 0], [300, 1], [450, 3], [525, 7]]


def test_log_interpolation_writes_meshes_and_a_strip(pair, tmp_path):
    from torch.utils.tensorboard import SummaryWriter

    x, y = pair.x, pair.y
    frames = torch.stack([x.verts, x.verts * 1.1, x.verts * 1.2])
    times = torch.tensor([0.0, 0.5, 1.0])
    assert len(interpolation_strip_figure(frames, x.faces, times, y.verts, y.faces).axes) == 4
    writer = SummaryWriter(str(tmp_path))
    assert log_interpolation(writer, frames, x.faces, times, y.verts, y.faces, step=3)
    writer.close()
    assert list(tmp_path.glob("events.out.tfevents.*"))
    assert not log_interpolation(None, frames, x.faces, times)
    with pytest.raises(ConfigError):
        interpolation_strip_figure(frames, x.faces, times[:2])


# -- CLI smoke run -------------------------------------------------------------------------------------------
def _write_off(path: Path, verts: np.ndarray, faces: np.ndarray) -> None:
    lines = ["OFF", f"{len(verts)} {len(faces)} 0"]
    lines += [" ".join(f"{c:.6f}" for c in v) for v in verts]
    lines += ["3 " + " ".join(str(int(i)) for i in f) for f in faces]
    path.write_text("\n".join(lines) + "\n")


def _folder_dataset(root: Path) -> None:
    """Four deformed, vertex-permuted ellipsoids with .vts ground truth; train a, b; test c, d."""
    v, f = _base_mesh()
    rng = np.random.default_rng(1)
    for sub in ("off", "corres", "splits"):
        (root / sub).mkdir(parents=True)
    for k, name in enumerate("abcd"):
        perm = rng.permutation(len(v))
        posed = v.copy()
        posed[:, 2] += 0.2 * np.sin((1.0 + 0.3 * k) * posed[:, 0])
        verts = np.empty_like(posed)
        verts[perm] = posed
        _write_off(root / "off" / f"{name}.off", verts, perm[f])
        (root / "corres" / f"{name}.vts").write_text("\n".join(str(i + 1) for i in perm) + "\n")
    (root / "splits" / "train.txt").write_text("a\nb\n")
    (root / "splits" / "test.txt").write_text("c\nd\n")


@pytest.mark.slow
def test_train_cli_tiny_smoke_run(tmp_path):
    data, run_dir = tmp_path / "data", tmp_path / "run"
    _folder_dataset(data)
    args = ["model=neuromorph", "debug=tiny", f"data.root={data}", "~data.synthetic",  # a folder, not generated
            "data.operators.n_eig=16", "data.prepare_workers=1", f"paths.cache_dir={tmp_path / 'cache'}",
            f"hydra.run.dir={run_dir}", "trainer.limit_train_batches=2", "trainer.limit_val_batches=1",
            "trainer.limit_test_batches=2", "trainer.num_sanity_val_steps=0", "trainer.enable_progress_bar=false",
            "model.augment.resolution=[300,500]", "model.augment.variants=2"]
    env = {**os.environ, "PYTHONWARNINGS": "ignore", "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, str(REPO / "train.py"), *args], cwd=REPO, capture_output=True, text=True,
                          timeout=600, env=env, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = [line for line in proc.stdout.strip().splitlines() if line.strip()]
    match = FINAL_LINE.match(lines[-1])
    assert match, proc.stdout[-2000:]
    assert 0.0 <= float(match.group(1)) < 1.0 and int(match.group(2)) == 2
    last = run_dir / "checkpoints" / "last.ckpt"
    assert last.is_file() and list((run_dir / "tensorboard").glob("events.out.tfevents.*"))
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run_dir / "tensorboard")).Reload()
    scalars = set(events.Tags()["scalars"])
    for tag in ("train/loss_step", "train/registration_step", "train/arap_step", "train/geo_step", "schedule/T",
                "schedule/lambda_geo", "schedule/map_gradient_all", "val/geodesic_error", "val/chamfer",
                "val/deformation_conformal_distortion"):
        assert tag in scalars, (tag, sorted(scalars))
    assert "val/interpolation/strip" in events.Tags()["images"]
    assert "neuromorph: mapping old option" not in proc.stderr
    state = torch.load(last, map_location="cpu", weights_only=False)
    assert state["global_step"] == 2 and state["model_recipe"]["augment"]["variants"] == 2
    # the evaluation path: the checkpoint's recipe (with its loss) and weights
    from shapecorr.models.recipe import load_model

    model = load_model(last).eval()
    assert isinstance(model, NeuroMorph) and model.loss.weights["geo"] == 50.0
    v, f = _base_mesh()
    x = _sample(v, f, "a", np.arange(len(v)))
    assert model.match(x, x).p2p.shape == (len(v),)
    assert len(list((tmp_path / "cache" / "remesh").rglob("*.npz"))) <= 4  # 2 train shapes x 2 variants


# -- config nodes: backbone, loss, optimizer ------------------------------------------------------------------
def test_backbone_and_optimizer_nodes_are_selectable(tmp_path, compose_config):
    base = ["model=neuromorph", "debug=tiny", f"paths.cache_dir={tmp_path}", f"paths.output_dir={tmp_path}"]
    cfg = compose_config("train", [*base, "model/backbone=edgeconv", "model.backbone.feature_dim=24",
                                   "model/scheduler=step", "model.optimizer.lr=2e-4"])
    assert cfg.model.backbone._target_ == "shapecorr.nn.edgeconv_backbone.EdgeConvBackbone"
    model = instantiate(cfg.model, _convert_="object")
    assert model.backbone.out_channels == 24 and model.feature_net is model.backbone
    conf = model.configure_optimizers()
    assert conf["optimizer"].defaults["lr"] == 2e-4
    assert isinstance(conf["lr_scheduler"]["scheduler"], torch.optim.lr_scheduler.StepLR)
    assert model.loss.weights == {"registration": 1.0, "arap": 1.0, "geo": 50.0}  # the model node's loss
    assert "interpolation_net" in cfg.model and "interpolator" not in cfg.model  # no clash with interpolator=


# -- augmentation on the data side ------------------------------------------------------------------------
def test_data_side_augmentation_equals_the_in_step_augmentation(pair, tmp_path):
    from shapecorr.data.augmentation import AugmentedPairDataset, SampleKey

    class Pairs:  # a PairDataset stand-in of one pair
        def __len__(self):
            return 1

        def __getitem__(self, k):
            return pair

    model = _model(tmp_path)
    dataset = AugmentedPairDataset(Pairs(), model.augmenter, geodesics=model.geodesic_epochs())
    batch = dataset[SampleKey(epoch=0, position=3, index=0)]
    assert batch.dist_x is not None  # lambda_geo = 50: geodesics come with the sample
    torch.manual_seed(1)
    from_data = model.training_step(batch, 3)
    torch.manual_seed(1)
    in_step = model.training_step(pair, 3)  # plain pair: augmented in the step with the draws of (seed, 0, 3)
    assert float(from_data.detach()) == pytest.approx(float(in_step.detach()), rel=1e-6)
    other = model.training_step(dataset[SampleKey(0, 4, 0)], 4)
    assert float(other.detach()) != pytest.approx(float(in_step.detach()), rel=1e-6)
    # a sample built without geodesics (the data side expected lambda_geo = 0): looked up in the step
    no_geo = AugmentedPairDataset(Pairs(), model.augmenter, geodesics=False)[SampleKey(0, 3, 0)]
    assert no_geo.dist_x is None
    assert float(model.training_step(no_geo, 3).detach()) == pytest.approx(float(in_step.detach()), rel=1e-6)


def test_geodesic_epochs_follow_the_loss_weight_schedule(tmp_path):
    import pickle

    model = _model(tmp_path)
    schedule = LossWeightSchedule("geo", [[0, 50.0], [300, 0.0]])

    class Trainer:
        callbacks = [EpochSchedule("n_intermediate", [[0, 0]]), schedule]

    model._trainer = Trainer()
    flag = pickle.loads(pickle.dumps(model.geodesic_epochs()))  # travels to DataLoader workers
    assert flag(0) and flag(299) and not flag(300) and not flag(600)
    model._trainer = None
    model.loss.set_weight("geo", 0.0)
    assert model.geodesic_epochs() is False


class Recording(NeuroMorph):
    """Records, per training step, (epoch, batch index, batch type, the rotation of the augmentation)."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.seen = []

    def training_step(self, batch, batch_idx):
        self.seen.append((self.current_epoch, batch_idx, type(batch).__name__, batch.rotation.cpu().clone()))
        return super().training_step(batch, batch_idx)


def test_lightning_fit_augments_on_the_data_side_and_resumes_with_the_same_draws(tmp_path):
    """train_dataloader serves AugmentedPairs (in a worker process); a run resumed mid-epoch draws as the full run."""
    import pytorch_lightning as pl
    from pytorch_lightning.callbacks import ModelCheckpoint

    from shapecorr.data.datamodule import ShapePairDataModule

    data = tmp_path / "data"
    _folder_dataset(data)

    def objects(workers):
        dm = ShapePairDataModule(str(data), splits={"train": {"split": "train"}, "val": {"split": "test"},
                                                    "test": {"split": "test"}},
                                 pairs={"train": {"include_self": True}, "val": {"max_pairs": 1}},
                                 operators={"n_eig": 8}, cache_dir=str(tmp_path / "cache"), num_workers=workers,
                                 prepare_workers=1)
        torch.manual_seed(0)
        model = Recording(**small(), augment=dict(remesh=False, rotate=True), seed=5)
        model.loss.set_weight("geo", 0.0)
        return dm, model

    def trainer(**kwargs):
        options = dict(accelerator="cpu", devices=1, max_epochs=2, limit_val_batches=0, num_sanity_val_steps=0,
                       logger=False, enable_progress_bar=False, enable_model_summary=False,
                       default_root_dir=str(tmp_path))
        return pl.Trainer(**{**options, **kwargs})

    dm, full = objects(workers=1)  # 4 train pairs (a, b with self-pairs) x 2 epochs
    trainer(enable_checkpointing=False).fit(full, datamodule=dm)
    assert [(e, b, kind) for e, b, kind, _ in full.seen] == [(e, b, "AugmentedPair") for e in (0, 1) for b in range(4)]
    for epoch, batch_idx, _, rotation in full.seen:  # the draws of (seed, epoch, batch index)
        angle = float(step_rng(5, epoch, batch_idx).uniform(0.0, 2.0 * np.pi))
        torch.testing.assert_close(rotation, rotation_about_axis(angle, "y"))

    dm, first = objects(workers=0)
    ckpt = ModelCheckpoint(dirpath=str(tmp_path / "ckpt"), every_n_train_steps=6, save_top_k=-1,
                           filename="step{step}", auto_insert_metric_name=False)
    trainer(max_steps=6, callbacks=[ckpt]).fit(first, datamodule=dm)
    dm, resumed = objects(workers=0)
    trainer(enable_checkpointing=False).fit(resumed, datamodule=dm, ckpt_path=str(tmp_path / "ckpt" / "step6.ckpt"))
    assert [s[:2] for s in resumed.seen] == [s[:2] for s in full.seen[6:]]
    for (_, _, _, a), (_, _, _, b) in zip(resumed.seen, full.seen[6:]):
        assert torch.equal(a, b)
