"""Interpolation metrics of ``evaluate.py`` for every interpolating method.

Each of NeuroMorph (untrained, small nets), divfree, Hamiltonian and linear blend runs through ``evaluate()``
(the function ``evaluate.py`` calls) on one pair of the tiny bent-icosphere folder (162 vertices, closed, ``.vts``
ground truth) with tiny settings, at ``interp_times=[0,0.5,1,1.5]``. The run must report the conformal
distortion along t, the volume score ``V_t/V_0 + V_0/V_t - 2`` along t (and at t = 1), the two-sided and
one-sided Chamfer of X(1) to Y, the per-time means in ``metrics.json["interp_curves"]`` and
``interp_curves.png``, all finite. The curves are checked against the frames written to disk.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from shapecorr.cli.evaluate import evaluate
from shapecorr.data.io import read_mesh
from shapecorr.eval import metrics

pytestmark = pytest.mark.usefixtures("single_thread")

NAMES = ["p0", "p1"]
TIMES = [0.0, 0.5, 1.0, 1.5]
SCALARS = ("mean_deformation_conformal_distortion", "mean_volume_score", "mean_chamfer", "mean_chamfer_one_sided")
#: Per method: the overrides of a fit that takes seconds on 162 vertices.
METHODS = {
    "neuromorph": ["model=neuromorph", "model.backbone.feature_dim=8", "model.backbone.hidden_channels=8",
                   "model.backbone.n_blocks=2", "model.interpolation_net.hidden_channels=8",
                   "model.interpolation_net.n_blocks=2"],
    "divfree": ["model=divfree", "model.modes=[2]", "model.samples=[60]", "model.iterations=[3]", "model.lr=[0.01]",
                "model.descriptor_weight=[0]", "model.n_steps=4", "model.prealign=none"],
    "hamiltonian": ["model=hamiltonian", "model.n_modes=2", "model.iterations=3", "model.samples=60",
                    "model.n_steps=4"],
    # the ground-truth map: a map with collapses (descriptor NN) flattens X(1) to zero volume (no volume score)
    "linear_blend": ["model=linear_blend", "model@model.matcher=identity_gt"],
}


@pytest.fixture(scope="module")
def folder(tmp_path_factory, evaluate_on_folder, bent_sphere_folder):
    """``(root, cache_dir, evaluate_on_folder)``."""
    root = bent_sphere_folder(tmp_path_factory.mktemp("interp_methods_folder"), NAMES)
    return root, tmp_path_factory.mktemp("interp_methods_cache"), evaluate_on_folder


@pytest.mark.parametrize("method", list(METHODS))
def test_every_interpolating_method_reports_the_interpolation_metrics(folder, tmp_path, method):
    root, cache, config = folder
    out = tmp_path / method
    cfg = config(root, cache, out, "max_pairs=1", *METHODS[method], f"interp_times=[{','.join(map(str, TIMES))}]")
    result = evaluate(cfg)
    on_disk = json.loads((out / "metrics.json").read_text())
    for key in SCALARS:
        assert key in on_disk and key in result, key
        assert np.isfinite(on_disk[key]) and on_disk[key] >= 0, (key, on_disk[key])
    assert on_disk["mean_chamfer"] >= on_disk["mean_chamfer_one_sided"]

    curves = on_disk["interp_curves"]
    assert curves["times"] == TIMES and curves["n_pairs"] == [1] * len(TIMES)
    for key in ("conformal_distortion", "volume_score"):
        values = curves[key]
        assert len(values) == len(TIMES) and all(v is not None and np.isfinite(v) for v in values), (key, values)
        assert values[0] == pytest.approx(0.0, abs=1e-8)  # X(0) = x
    assert curves["volume_score"][2] == pytest.approx(on_disk["mean_volume_score"], rel=1e-9)
    # the mean along the sequence is over the frames with 0 <= t <= 1 only
    along = np.mean(curves["conformal_distortion"][:3])
    assert on_disk["mean_deformation_conformal_distortion"] == pytest.approx(along)

    # the curves are those of the written frames (x's input units: both measures are scale-invariant)
    (seq,) = (out / "interp").iterdir()
    raw_x, faces = read_mesh(seq / "t_00.ply")
    for k, t in enumerate(TIMES):
        frame, _ = read_mesh(seq / f"t_{k:02d}.ply")
        assert curves["volume_score"][k] == pytest.approx(metrics.volume_change_score(raw_x, faces, frame),
                                                          rel=1e-3, abs=1e-6), t
        assert curves["conformal_distortion"][k] == pytest.approx(
            metrics.mean_conformal_distortion(raw_x, faces, frame), rel=1e-3, abs=1e-6), t

    png = out / "interp_curves.png"
    assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    record = json.loads(next((out / "pairs").glob("*.json")).read_text())
    assert record["curve_times"] == TIMES and len(record["curve_volume_score"]) == len(TIMES)


def test_non_interpolating_matcher_writes_no_curves(folder, tmp_path):
    root, cache, config = folder
    out = tmp_path / "nn"
    result = evaluate(config(root, cache, out, "max_pairs=1", "model=descriptor_nn", "model.descriptor=hks"))
    assert "interp_curves" not in result and "mean_volume_score" not in result
    assert not (out / "interp_curves.png").exists()
    assert isinstance(Path(out / "metrics.json").read_text(), str)
