"""``evaluate.py`` with an interpolating matcher: frames, times, metrics, resumption.

A tiny FAUST-style folder: three bent, vertex-permuted icospheres (162 vertices) at different sizes and
positions (so that frames in the wrong units would show), with ``.vts`` ground truth on every vertex.
``model=linear_blend`` wraps descriptor NN (an imperfect map, so the Chamfer distance is not trivially 0) and
is compared with descriptor NN alone, which does not interpolate. Configs are composed with Hydra's compose
API and run through ``evaluate()``, the function ``evaluate.py`` calls.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from shapecorr.cli.evaluate import evaluate
from shapecorr.data.io import read_mesh
from shapecorr.eval import metrics
from shapecorr.eval.export import read_times

NAMES = ["p0", "p1", "p2"]
N_PAIRS = len(NAMES) * (len(NAMES) - 1)
INTERP_KEYS = ("mean_deformation_conformal_distortion", "mean_chamfer", "mean_chamfer_one_sided",
               "n_pairs_interpolated")
BLEND = ["model=linear_blend", "model.matcher.descriptor=hks"]


@pytest.fixture(scope="module")
def folder(tmp_path_factory, evaluate_on_folder, bent_sphere_folder):
    """``(root, cache_dir, evaluate_on_folder)``."""
    root = bent_sphere_folder(tmp_path_factory.mktemp("interp_folder"), NAMES)
    return root, tmp_path_factory.mktemp("interp_cache"), evaluate_on_folder


def _cfg(folder, out: Path, *overrides: str):
    root, cache, config = folder
    return config(root, cache, out, *overrides)


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_interpolating_matcher_frames_and_metrics(folder, tmp_path, capsys):
    out = tmp_path / "blend"
    result = evaluate(_cfg(folder, out, *BLEND, "interp_times=[0,0.5,1,1.5]"))
    on_disk = json.loads((out / "metrics.json").read_text())
    for key in INTERP_KEYS + ("mean_conformal_distortion", "mean_geodesic_error"):
        assert key in on_disk and key in result, key
    assert on_disk["n_pairs_interpolated"] == N_PAIRS and on_disk["run"]["interp_times"] == [0.0, 0.5, 1.0, 1.5]
    printed = capsys.readouterr().out
    assert f"Chamfer X(1)-Y {on_disk['mean_chamfer']:.4f}" in printed
    assert f"conformal distortion {on_disk['mean_deformation_conformal_distortion']:.4f}" in printed

    root = folder[0]
    rows = {(r["source"], r["target"]): r for r in _rows(out / "per_pair.csv")}
    assert len(rows) == N_PAIRS
    for (a, b), row in rows.items():
        seq = out / "interp" / f"{a}__{b}"
        assert sorted(p.name for p in seq.iterdir()) == ["t_00.ply", "t_01.ply", "t_02.ply", "t_03.ply", "times.txt"]
        assert read_times(seq).tolist() == [0.0, 0.5, 1.0, 1.5]
        raw_x, faces_x = read_mesh(root / "off" / f"{a}.off")
        frame0, frame_faces = read_mesh(seq / "t_00.ply")
        np.testing.assert_allclose(frame0, raw_x, rtol=0, atol=1e-5 * np.abs(raw_x).max())  # x, input units
        np.testing.assert_array_equal(frame_faces, faces_x)
        # Chamfer at t = 1 by hand: X(1) = y[p2p] (scale-invariant ratio, so y's raw units serve)
        raw_y, faces_y = read_mesh(root / "off" / f"{b}.off")
        p2p = np.loadtxt(out / "maps" / f"{a}__{b}.txt", dtype=np.int64)
        x1 = raw_y[p2p]
        two_sided = cKDTree(raw_y).query(x1)[0].mean() + cKDTree(x1).query(raw_y)[0].mean()
        by_hand = two_sided / np.sqrt(metrics.surface_area(raw_y, faces_y))
        assert float(row["chamfer"]) == pytest.approx(by_hand, rel=1e-4)
        assert float(row["chamfer_one_sided"]) == pytest.approx(0.0, abs=1e-6)
        assert float(row["deformation_conformal_distortion"]) > 0
    assert on_disk["mean_chamfer"] == pytest.approx(np.mean([float(r["chamfer"]) for r in rows.values()]))
    assert on_disk["mean_chamfer"] > 0.01  # descriptor NN is not a bijection

    # resuming the same folder with other times is refused, not mixed
    with pytest.raises(SystemExit) as exc:
        evaluate(_cfg(folder, out, *BLEND, "interp_times=[0,1]"))
    assert exc.value.code == 2 and "interp_times" in capsys.readouterr().err


def test_non_interpolating_matcher_has_no_interpolation_outputs(folder, tmp_path):
    out = tmp_path / "nn"
    result = evaluate(_cfg(folder, out, "model=descriptor_nn", "model.descriptor=hks"))
    on_disk = json.loads((out / "metrics.json").read_text())
    for key in INTERP_KEYS + ("mean_volume_change",):
        assert key not in on_disk and key not in result, key
    assert "mean_conformal_distortion" in on_disk and "interp_times" not in on_disk["run"]
    assert not (out / "interp").exists()
    assert all(r["chamfer"] == "" and r["deformation_conformal_distortion"] == "" for r in _rows(out / "per_pair.csv"))


def test_unit_time_evaluated_but_not_written(folder, tmp_path):
    out = tmp_path / "half"
    result = evaluate(_cfg(folder, out, *BLEND, "interp_times=[0,0.5]", "max_pairs=2"))
    assert result["n_pairs_interpolated"] == 2 and result["mean_chamfer"] > 0
    sequences = sorted((out / "interp").iterdir())
    assert len(sequences) == 2
    for seq in sequences:
        assert sorted(p.name for p in seq.glob("t_*.ply")) == ["t_00.ply", "t_01.ply"]
        assert read_times(seq).tolist() == [0.0, 0.5]
