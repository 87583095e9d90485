"""Smooth Shells as post-processing of a matcher's map (shapecorr.axiomatic.postprocess; evaluate.py postprocess=)."""

from __future__ import annotations

import json
from dataclasses import asdict
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree

from shapecorr.axiomatic.postprocess import SmoothShellsPostprocess
from shapecorr.axiomatic.smooth_shells import SmoothShellsConfig
from shapecorr.cli.evaluate import evaluate
from shapecorr.data.shape import triangle_areas
from shapecorr.errors import ConfigError
from shapecorr.geometry.laplace_beltrami import eigenbasis
from shapecorr.geometry.remeshing import remesh
from shapecorr.geometry.shot_descriptor import shot
from shapecorr.matching.result import MatchResult

#: A small layered matching for ~400-vertex meshes (the published stages, a shorter schedule).
SMALL = SmoothShellsConfig(k_max=40, k_array_length=6)
SETTINGS = {"k_max": SMALL.k_max, "k_array_length": SMALL.k_array_length}

pytestmark = pytest.mark.usefixtures("single_thread")


def _sample(verts, faces, name):
    evals, evecs, mass = eigenbasis(verts, faces, SMALL.num_eigs)

    def f32(a):
        return torch.tensor(np.asarray(a), dtype=torch.float32)

    return SimpleNamespace(name=name, verts=f32(verts), faces=torch.tensor(faces), evals=f32(evals),
                           evecs=f32(evecs), mass=f32(mass), features={"shot": f32(shot(verts, faces))})


class _Fixed:
    """A matcher returning given maps (and an operator request of its own)."""

    required_operators = {"eigenbasis": {"k": 10}, "wks": {}}
    needs_ground_truth = True

    def __init__(self, p2p, p2p_inv=None):
        self.p2p, self.p2p_inv = p2p, p2p_inv

    def match(self, x, y):
        return MatchResult(p2p=torch.from_numpy(self.p2p),
                           p2p_inv=None if self.p2p_inv is None else torch.from_numpy(self.p2p_inv))


@pytest.fixture(scope="module")
def pair(asymmetric_blob):
    """A blob X and Y = slightly rotated, shifted, vertex-permuted X; gt[i] = vertex of Y of vertex i of X."""
    ico = trimesh.creation.icosphere(subdivisions=3)
    rng = np.random.default_rng(0)
    verts, faces = remesh(asymmetric_blob(np.asarray(ico.vertices), rng), np.asarray(ico.faces), 400)
    verts = verts * np.sqrt(0.44 / triangle_areas(verts, faces).sum())
    verts = verts - verts.mean(0)
    angle = 0.2
    rot = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    perm = rng.permutation(len(verts))  # vertex j of Y is vertex perm[j] of X
    gt = np.argsort(perm)
    verts_y = (verts @ rot.T + [0.03, -0.02, 0.01])[perm]
    return {"x": _sample(verts, faces, "blob"), "y": _sample(verts_y, gt[faces], "blob_moved"), "gt": gt,
            "perm": perm}


def _corrupt(m, verts_target, seed):
    """``m`` with every image moved to one of its 7 nearest neighbours on the target, 10 % of them anywhere."""
    rng = np.random.default_rng(seed)
    _, near = cKDTree(verts_target).query(verts_target, k=8)
    out = near[m, rng.integers(1, 8, len(m))]
    wrong = rng.random(len(m)) < 0.1
    out[wrong] = rng.integers(0, len(verts_target), int(wrong.sum()))
    return out


@pytest.mark.parametrize("both_directions", [False, True])
def test_wrapper_improves_a_corrupted_map(pair, both_directions):
    gt, perm = pair["gt"], pair["perm"]
    vx, vy = pair["x"].verts.numpy(), pair["y"].verts.numpy()
    noisy = _corrupt(gt, vy, 1)
    noisy_inv = _corrupt(perm, vx, 2) if both_directions else None
    wrapper = SmoothShellsPostprocess(_Fixed(noisy, noisy_inv), k_start=20, **SETTINGS)
    out = wrapper.match(pair["x"], pair["y"]).validate(len(gt), len(perm))
    p2p, p2p_inv = out.p2p.numpy(), out.p2p_inv.numpy()

    def error(m):  # mean distance on Y from the true image
        return np.linalg.norm(vy[m] - vy[gt], axis=1).mean()

    assert (noisy == gt).mean() < 0.1 and (p2p == gt).mean() > 0.85 and (p2p_inv == perm).mean() > 0.85
    assert error(p2p) < 0.2 * error(noisy)
    assert out.deformation is None and out.extras["k_array"][0] == 20
    np.testing.assert_array_equal(out.extras["initial_p2p"].numpy(), noisy)


def test_required_operators_merge_and_validation():
    wrapper = SmoothShellsPostprocess(_Fixed(np.zeros(3, dtype=np.int64)), k_start=25, **SETTINGS)
    assert wrapper.required_operators == {"eigenbasis": {"k": SMALL.num_eigs}, "wks": {}, "shot": {}}
    assert wrapper.needs_ground_truth and wrapper.config == SMALL and wrapper.k_start == 25
    big = SimpleNamespace(match=None, required_operators={"eigenbasis": {"k": 600}})
    big.match = lambda x, y: None
    no_feat = SmoothShellsPostprocess(big, lambda_feat=0.0)
    assert no_feat.required_operators == {"eigenbasis": {"k": 600}} and not no_feat.needs_ground_truth
    with pytest.raises(ConfigError, match="k_start"):
        SmoothShellsPostprocess(_Fixed(np.zeros(3, dtype=np.int64)), k_start=41, **SETTINGS)
    with pytest.raises(ConfigError, match="match"):
        SmoothShellsPostprocess(object())
    with pytest.raises(ConfigError):
        SmoothShellsPostprocess(_Fixed(np.zeros(3, dtype=np.int64)), no_such_setting=1)


def test_postprocess_config_defaults_are_the_published_layered_matching(compose_config):
    cfg = compose_config("evaluate", overrides=["model=descriptor_nn", "postprocess=smooth_shells"])
    settings = {k: v for k, v in cfg.postprocess.items()
                if k not in ("_target_", "_partial_", "k_start", "interp_times")}
    published = asdict(SmoothShellsConfig())
    # the settings are model=smooth_shells's (inherited, not restated)
    model = compose_config("evaluate", overrides=["model=smooth_shells"]).model
    assert settings == {k: v for k, v in model.items() if k not in ("_target_", "interp_times")}
    assert settings and all(published[k] == (tuple(v) if isinstance(v, list) else v) for k, v in settings.items())
    assert cfg.postprocess.k_start == 20
    assert compose_config("evaluate", overrides=["model=descriptor_nn"]).get("postprocess") is None


def test_evaluate_with_postprocess_writes_metrics(compose_config, tmp_path):
    common = ["data=synthetic", "data.synthetic.preset=tiny", "max_pairs=1",
              "data.operators.params.shot.radius_factor=0.25", f"paths.cache_dir={tmp_path / 'cache'}",
              "progress=false", "n_examples=0", "model=descriptor_nn"]
    out = tmp_path / "post"
    cfg = compose_config("evaluate", overrides=common + [
        f"output_dir={out}", "postprocess=smooth_shells", "postprocess.k_max=30", "postprocess.k_array_length=3",
    ])
    result = evaluate(cfg)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["n_pairs"] == 1 and np.isfinite(metrics["mean_geodesic_error"])
    run = json.loads((out / "run.json").read_text())
    assert run["matcher"].endswith("SmoothShellsPostprocess") and run["postprocess"]["k_max"] == 30
    assert result is not None
    # the map before the refinement is scored too: it is the wrapped matcher's own result
    alone = tmp_path / "alone"
    evaluate(compose_config("evaluate", overrides=common + [f"output_dir={alone}"]))
    metrics_alone = json.loads((alone / "metrics.json").read_text())
    assert "mean_initial_geodesic_error" not in metrics_alone
    assert metrics["n_pairs_initial"] == 1
    assert metrics["mean_initial_geodesic_error"] == pytest.approx(metrics_alone["mean_geodesic_error"], abs=1e-12)
    assert metrics["mean_initial_geodesic_error"] != metrics["mean_geodesic_error"]
