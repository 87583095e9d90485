"""Comparison of runs from their output folders (shapecorr.eval.compare, compare.py, the multirun callback).

Real ``evaluate.py`` runs on a tiny FAUST-style folder (three bent, vertex-permuted icospheres, 162 vertices):
descriptor NN (an imperfect map), the ground-truth map (error 0) and the linear blend of descriptor NN (it
interpolates), the linear blend of the ground-truth map, plus descriptor NN on 2 of the 6 pairs for the
mismatched-pairs cases.
"""

from __future__ import annotations

import base64
import csv
import json
import re
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from shapecorr.cli.compare import compare_sweep, main, write_comparison
from shapecorr.cli.evaluate import evaluate
from shapecorr.errors import MeshReadError
from shapecorr.eval import compare
from shapecorr.eval.export import map_paths

pytestmark = pytest.mark.usefixtures("single_thread")

REPO = Path(__file__).resolve().parents[2]
NAMES = ["p0", "p1", "p2"]
RUNS = {
    "nn": ["model=descriptor_nn", "model.descriptor=hks"],
    "gt": ["model=identity_gt"],
    "blend": ["model=linear_blend", "model.matcher.descriptor=hks", "interp_times=[0,0.5,1]"],
    "nn_two": ["model=descriptor_nn", "model.descriptor=hks", "max_pairs=2"],
    "gt_blend": ["model=identity_gt", "interpolator=linear_blend", "interp_times=[0,0.5,1]"],
}
OUTPUTS = ("comparison.csv", "comparison.md", "pck_overlay.png", "mean_error.png", "pairwise.png",
           "examples_grid.png", "interp_overlay.png", "report.html")


@pytest.fixture(scope="module")
def folder(tmp_path_factory, bent_sphere_folder) -> tuple[Path, Path]:
    """``(data root, cache folder)``."""
    return bent_sphere_folder(tmp_path_factory.mktemp("compare_folder"), NAMES), tmp_path_factory.mktemp("cache")


@pytest.fixture(scope="module")
def runs(tmp_path_factory, evaluate_on_folder, folder) -> dict[str, Path]:
    """``name -> output folder`` of the evaluations of :data:`RUNS`."""
    root, cache = folder
    base = tmp_path_factory.mktemp("compare_runs")
    out = {}
    for name, overrides in RUNS.items():
        out[name] = base / name
        evaluate(evaluate_on_folder(root, cache, out[name], *overrides))
    return out


def test_rows_are_the_runs_metrics_and_best_is_marked(runs):
    loaded, pairs, note = compare.compare_runs([runs["nn"], runs["gt"], runs["blend"]], names=["nn", "gt", "blend"])
    assert note == "" and len(pairs) == 6
    for run in loaded:
        metrics = json.loads((run.path / "metrics.json").read_text())
        for key in ("mean_geodesic_error", "median_geodesic_error", "pck_auc", "seconds_per_pair", "peak_memory_mb"):
            assert run.values[key] == metrics[key], (run.name, key)
        assert run.values["device"] == "cpu" and run.values["n_pairs"] == 6
    best = compare.best_runs(loaded)
    assert best["mean_geodesic_error"] == {1} and best["pck_auc"] == {1}  # the ground-truth map
    assert loaded[0].values["mean_geodesic_error"] > 0
    assert loaded[2].values["mean_chamfer"] is not None and loaded[0].values["mean_chamfer"] is None
    md = compare.comparison_markdown(loaded)
    gt_row = next(line for line in md.splitlines() if line.startswith("| gt |"))
    assert "**0.00**" in gt_row
    rows = list(csv.DictReader(compare.comparison_csv(loaded).splitlines()))
    assert [r["name"] for r in rows] == ["nn", "gt", "blend"]
    assert "mean_geodesic_error" in rows[1]["best_in"].split() and "mean_geodesic_error" not in rows[0]["best_in"]


def test_names_from_distinguishing_overrides(runs, tmp_path):
    folders = []
    for k, (name, overrides) in enumerate([("nn", ["+method=descriptor_nn", "data=faust_r", "max_pairs=40"]),
                                           ("gt", ["+method=identity_gt", "data=faust_r", "max_pairs=40"])]):
        folder = tmp_path / str(k)
        shutil.copytree(runs[name], folder)
        (folder / ".hydra").mkdir(exist_ok=True)
        (folder / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
        folders.append(folder)
    loaded, _, _ = compare.compare_runs(folders)
    assert [r.name for r in loaded] == ["descriptor_nn", "identity_gt"]
    loaded, _, _ = compare.compare_runs([runs["nn"], runs["gt"]])  # no overrides: from run.json
    assert [r.name for r in loaded] == ["DescriptorNN", "IdentityGT"]


def test_different_pairs_refused_then_compared_on_the_common_ones(runs):
    with pytest.raises(compare.ComparisonError, match="different pairs") as info:
        compare.compare_runs([runs["nn"], runs["nn_two"]])
    assert "2 in common" in str(info.value) and "--allow-different-pairs" in str(info.value)
    loaded, pairs, note = compare.compare_runs([runs["nn"], runs["nn_two"]], allow_different_pairs=True)
    assert len(pairs) == 2 and note == "compared on the 2 pairs common to all 2 runs"
    with open(runs["nn"] / "per_pair.csv", newline="") as fh:
        per_pair = {(r["source"], r["target"]): float(r["mean_error"]) for r in csv.DictReader(fh)}
    expected = np.mean([per_pair[p] for p in pairs])
    for run in loaded:  # the full run recomputed on the 2 pairs equals the 2-pair run
        assert run.values["n_pairs"] == 2
        assert run.values["mean_geodesic_error"] == pytest.approx(expected, rel=1e-12)


def test_different_datasets_refused(runs, tmp_path):
    other = tmp_path / "other"
    shutil.copytree(runs["gt"], other)
    info = json.loads((other / "run.json").read_text())
    (other / "run.json").write_text(json.dumps({**info, "data_root": "/elsewhere/SCAPE_r"}))
    with pytest.raises(compare.ComparisonError, match="different datasets") as err:
        compare.compare_runs([runs["nn"], other], allow_different_pairs=True)
    assert "/elsewhere/SCAPE_r" in str(err.value)


def test_missing_metrics_is_an_error_naming_the_folder(tmp_path):
    with pytest.raises(compare.ComparisonError, match="no metrics.json") as err:
        compare.load_run(tmp_path)
    assert str(tmp_path) in str(err.value)


def test_published_rows_only_for_known_benchmarks(runs):
    run = compare.load_run(runs["nn"])
    assert compare.published_rows([run]) == ("", ())
    run.info["data_root"] = "/data/FAUST_r"
    bench, rows = compare.published_rows([run])
    assert bench == "FAUST_r" and ("Deep Shells", 0.017) in [(m, v) for m, v, _ in rows]
    run.values = {"mean_geodesic_error": 0.2, "n_pairs": 6}
    md = compare.comparison_markdown([run])
    measured, published = md.split("## Published")
    assert "(published)" not in measured and "| Deep Shells (published) | 1.7 |" in published


def test_win_matrix():
    errors = np.array([[0.1, 0.2, 0.3], [0.2, 0.1, 0.3], [0.0, 0.5, 0.5]])
    wins = compare.win_matrix(errors)
    assert wins.tolist() == [[0, 1, 2], [1, 0, 2], [1, 1, 0]]


def test_cli_writes_everything_and_report_holds_the_maps(runs, tmp_path, capsys):
    out = tmp_path / "cmp"
    assert main([str(runs["nn"]), str(runs["gt"]), str(runs["blend"]), str(runs["gt_blend"]), "--out", str(out),
                 "--names", "nn", "gt", "blend", "gt_blend", "--n-examples", "2"]) == 0
    for name in OUTPUTS:
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    assert "| gt | 6 |" in capsys.readouterr().out
    page = (out / "report.html").read_text()
    assert len(re.findall(r'<tr class="run">', page)) == 4
    data = json.loads(re.search(r'<script type="application/json" id="mesh-data">(.*?)</script>', page, re.S)[1])
    assert len(data["pairs"]) == 2
    assert [r["name"] for r in data["pairs"][0]["runs"]] == ["nn", "gt", "blend", "gt_blend"]
    source, target = data["pairs"][0]["source"]["name"], data["pairs"][0]["target"]["name"]
    shown = np.frombuffer(base64.b64decode(data["pairs"][0]["runs"][0]["map"]), dtype=np.int32)
    assert shown.tolist() == np.load(map_paths(runs["nn"], source, target)[1]).tolist()


def test_cli_refusal_exits_2_with_the_difference(runs, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([str(runs["nn"]), str(runs["nn_two"]), "--out", str(tmp_path / "x")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: different pairs") and "6" in err and "2 in common" in err
    assert not (tmp_path / "x").exists()


def test_sweep_folder_and_training_runs(runs, tmp_path):
    sweep = tmp_path / "multirun"
    shutil.copytree(runs["nn"], sweep / "0")
    shutil.copytree(runs["gt"], sweep / "1")
    train = sweep / "2"  # a train.py run: test metrics only, no per-pair records
    train.mkdir()
    (train / "metrics.json").write_text(json.dumps({"mean_geodesic_error": 0.05, "test_pairs": 3}))
    assert compare_sweep(sweep) == sweep / "comparison.md"
    md = (sweep / "comparison.md").read_text()
    assert md.count("\n| ") == 4  # header + 3 runs
    assert (sweep / "report.html").is_file() and (sweep / "pairwise.png").is_file()
    assert compare_sweep(tmp_path / "multirun" / "0" / "maps") is None  # no runs inside: nothing written


def test_write_comparison_without_examples(runs, tmp_path):
    md = write_comparison([runs["nn"], runs["gt"]], tmp_path, n_examples=0)
    assert md.is_file() and not (tmp_path / "examples_grid.png").exists()
    page = (tmp_path / "report.html").read_text()
    assert 'id="mesh-data"' not in page and len(page) < 200_000  # no meshes, no plotly bundle


def test_meshes_from_another_data_root(runs, tmp_path):
    empty = tmp_path / "elsewhere"
    empty.mkdir()
    with pytest.raises(MeshReadError, match="no mesh file for shape") as err:
        write_comparison([runs["nn"], runs["gt"]], tmp_path / "cmp", n_examples=1, data_root=empty)
    assert str(empty) in str(err.value)


@pytest.mark.slow
def test_multirun_ends_with_the_comparison(folder, runs, tmp_path):
    """``evaluate.py -m`` (a real Hydra multirun): the callback writes the comparison into the sweep folder."""
    root, cache = folder
    sweep = tmp_path / "sweep"
    env = {**os.environ, "PYTHONWARNINGS": "ignore", "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(
        [sys.executable, str(REPO / "evaluate.py"), "-m", "model=descriptor_nn,identity_gt",
         "data=folder", f"data.root={root}", f"paths.cache_dir={cache}", "data.operators.n_eig=30", "progress=false",
         "n_examples=0", f"hydra.sweep.dir={sweep}"],
        cwd=REPO, capture_output=True, text=True, timeout=600, env=env, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"comparison of the sweep: {sweep / 'comparison.md'}" in proc.stdout
    rows = list(csv.DictReader((sweep / "comparison.csv").read_text().splitlines()))
    assert [r["name"] for r in rows] == ["descriptor_nn", "identity_gt"]
    assert float(rows[1]["mean_geodesic_error"]) == 0.0 < float(rows[0]["mean_geodesic_error"])
    assert (sweep / "report.html").is_file() and (sweep / "pairwise.png").is_file()
