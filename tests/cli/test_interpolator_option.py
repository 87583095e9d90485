"""``evaluate.py interpolator=<name>``: an interpolator on top of any model's maps.

A tiny FAUST-style folder: two bent, vertex-permuted icospheres (162 vertices) in different units, with ``.vts``
ground truth on every vertex, evaluated on one pair through ``evaluate()`` (the function ``evaluate.py`` calls).
``model=identity_gt`` (the ground-truth map, which does not interpolate) is wrapped by the interpolators. The
issue's command (``model=descriptor_nn interpolator=hamiltonian``) runs once on the tiny synthetic preset.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from shapecorr.cli.evaluate import evaluate
from shapecorr.cli.matcher_factory import build_matcher, with_interpolator
from shapecorr.data.io import read_mesh
from shapecorr.errors import ConfigError
from shapecorr.eval.export import read_times
from shapecorr.matching.baselines import LinearBlend

pytestmark = pytest.mark.usefixtures("single_thread")

NAMES = ["p0", "p1"]
INTERP_KEYS = ("mean_deformation_conformal_distortion", "mean_chamfer", "mean_chamfer_one_sided",
               "n_pairs_interpolated")
TIMES = [0.0, 0.5, 1.0, 1.5]
# a Hamiltonian fit small enough for a test (published: 8 modes, 2000 samples, 100 iterations, 16 steps)
TINY_HAMILTONIAN = ["interpolator.n_modes=2", "interpolator.iterations=2", "interpolator.samples=60",
                    "interpolator.n_steps=4"]


@pytest.fixture(scope="module")
def folder(tmp_path_factory, evaluate_on_folder, bent_sphere_folder):
    """``(root, cache_dir, evaluate_on_folder)``."""
    root = bent_sphere_folder(tmp_path_factory.mktemp("interpolator_folder"), NAMES)
    return root, tmp_path_factory.mktemp("interpolator_cache"), evaluate_on_folder


def _cfg(folder, out: Path, *overrides: str):
    root, cache, config = folder
    return config(root, cache, out, "max_pairs=1", *overrides)


def _frames(out: Path) -> tuple[str, str, list[np.ndarray]]:
    (seq,) = (out / "interp").iterdir()
    a, b = seq.name.split("__")
    names = sorted(p.name for p in seq.iterdir())
    assert names == [f"t_{i:02d}.ply" for i in range(len(TIMES))] + ["times.txt"]
    assert read_times(seq).tolist() == TIMES
    return a, b, [read_mesh(seq / f"t_{i:02d}.ply")[0] for i in range(len(TIMES))]


def _check_interpolation_metrics(out: Path, result: dict) -> dict:
    on_disk = json.loads((out / "metrics.json").read_text())
    for key in INTERP_KEYS:
        assert key in on_disk and key in result, key
    assert on_disk["n_pairs_interpolated"] == 1 and on_disk["run"]["interp_times"] == TIMES
    return on_disk


def test_linear_blend_on_a_non_interpolating_model(folder, tmp_path):
    out = tmp_path / "gt_blend"
    result = evaluate(_cfg(folder, out, "model=identity_gt", "interpolator=linear_blend",
                           f"interp_times=[{','.join(map(str, TIMES))}]"))
    on_disk = _check_interpolation_metrics(out, result)
    assert on_disk["run"]["interpolator"] == {"_target_": "shapecorr.matching.baselines.LinearBlend"}
    # the ground-truth map is a bijection onto y's vertices: X(1) = y[p2p] covers y exactly
    assert on_disk["mean_chamfer"] == pytest.approx(0.0, abs=1e-6)
    a, _, frames = _frames(out)
    raw_x, _ = read_mesh(folder[0] / "off" / f"{a}.off")
    tol = 1e-5 * np.abs(raw_x).max()
    np.testing.assert_allclose(frames[0], raw_x, rtol=0, atol=tol)  # X(0) = x, in x's input units
    # straight lines x + t (X(1) - x), extrapolated at 1.5 (X(1) = y[p2p] in x's units)
    for t, frame in zip(TIMES, frames):
        np.testing.assert_allclose(frame, raw_x + t * (frames[2] - raw_x), rtol=0, atol=tol)
    assert not np.allclose(frames[2], raw_x, atol=0.1)

    # the same frames as the model that wraps the same matcher
    ref = tmp_path / "model_blend"
    evaluate(_cfg(folder, ref, "model=linear_blend", "model@model.matcher=identity_gt",
                  f"interp_times=[{','.join(map(str, TIMES))}]"))
    for frame, frame_ref in zip(frames, _frames(ref)[2]):
        np.testing.assert_allclose(frame, frame_ref, rtol=0, atol=tol)


def test_hamiltonian_on_a_non_interpolating_model(folder, tmp_path):
    out = tmp_path / "gt_hamiltonian"
    result = evaluate(_cfg(folder, out, "model=identity_gt", "interpolator=hamiltonian", *TINY_HAMILTONIAN,
                           f"interp_times=[{','.join(map(str, TIMES))}]"))
    on_disk = _check_interpolation_metrics(out, result)
    run = on_disk["run"]
    assert run["interpolator"]["_target_"] == "shapecorr.axiomatic.hamiltonian.Hamiltonian"
    assert run["interpolator"]["n_modes"] == 2 and run["matcher"].endswith("Hamiltonian")
    a, _, frames = _frames(out)
    raw_x, _ = read_mesh(folder[0] / "off" / f"{a}.off")
    np.testing.assert_allclose(frames[0], raw_x, rtol=0, atol=1e-5 * np.abs(raw_x).max())  # X(0) = x
    assert all(np.isfinite(f).all() for f in frames)
    assert not np.allclose(frames[3], frames[2])  # t = 1.5 extrapolates beyond X(1)


def test_interpolator_on_a_wrapper_model_is_refused(folder, tmp_path):
    cfg = _cfg(folder, tmp_path / "bad", "model=linear_blend", "interpolator=hamiltonian")
    with pytest.raises(ConfigError, match="model.matcher"):
        build_matcher(cfg, "cpu")


def test_no_interpolator_leaves_the_model_alone(folder, tmp_path):
    cfg = _cfg(folder, tmp_path / "none", "model=identity_gt")
    assert cfg.interpolator is None or len(cfg.interpolator) == 0
    assert type(build_matcher(cfg, "cpu")).__name__ == "IdentityGT"
    # interp_times null: the interpolator's own default frames
    cfg = _cfg(folder, tmp_path / "default", "model=identity_gt", "interpolator=linear_blend", "interp_times=null")
    assert build_matcher(cfg, "cpu").interp_times == (0.0, 0.25, 0.5, 0.75, 1.0)


def test_a_self_interpolating_model_keeps_its_maps_under_the_interpolator(folder, tmp_path):
    class SelfInterpolating:  # stands for NeuroMorph / divfree: match and its own interpolate
        def match(self, x, y):
            raise AssertionError("not called here")

        def interpolate(self, x, y, times):
            raise AssertionError("not called here")

    model = SelfInterpolating()
    cfg = _cfg(folder, tmp_path / "self", "model=identity_gt", "interpolator=linear_blend", "interp_times=[0,1,1.5]")
    wrapped = with_interpolator(cfg, model)
    assert isinstance(wrapped, LinearBlend) and wrapped.matcher is model and wrapped.interp_times == (0.0, 1.0, 1.5)


def test_the_issue_command_on_the_tiny_synthetic_preset(compose_config, tmp_path):
    # python evaluate.py model=descriptor_nn interpolator=hamiltonian interp_times=[0,0.5,1,1.5] (small fit)
    out = tmp_path / "out"
    cfg = compose_config("evaluate", overrides=[
        "data=synthetic", "data.synthetic.preset=tiny", "max_pairs=1", f"paths.cache_dir={tmp_path / 'cache'}",
        f"output_dir={out}", "progress=false", "n_examples=0", "model=descriptor_nn", "interpolator=hamiltonian",
        *TINY_HAMILTONIAN, f"interp_times=[{','.join(map(str, TIMES))}]"])
    result = evaluate(cfg)
    _check_interpolation_metrics(out, result)
    _frames(out)
