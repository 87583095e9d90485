"""End-to-end: ``evaluate.py`` on a tiny FAUST-style folder, in ``model=`` and ``maps_dir=`` modes.

The folder holds four deformed unit spheres whose vertices are permuted independently (so no two shapes share
a vertex order) with ``.vts`` ground truth on 200 reference vertices and a mirrored ``.sym.vts``. The
configs are composed with Hydra's compose API (the same ``configs/`` as the command line); the error case
runs the real entry point in a subprocess to check the exit status and that no traceback is printed.
"""

from __future__ import annotations

import csv
import json
import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from shapecorr.cli.evaluate import evaluate
from shapecorr.data.io import write_mesh, write_vts
from shapecorr.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]
NAMES = [f"blob_{k:02d}" for k in range(4)]
N_REF = 200
N_PAIRS = len(NAMES) * (len(NAMES) - 1)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, evaluate_on_folder):
    """``(root, cache_dir, evaluate_on_folder)`` of the tiny folder; the cache is shared by the tests of this module."""
    root = tmp_path_factory.mktemp("tiny_faust")
    for sub in ("off", "corres", "splits"):
        (root / sub).mkdir()
    mesh = trimesh.creation.icosphere(subdivisions=3)  # 642 vertices
    base = np.asarray(mesh.vertices)
    faces = np.asarray(mesh.faces)
    mirror = cKDTree(base).query(base * [-1.0, 1.0, 1.0])[1]
    rng = np.random.default_rng(0)
    ref = np.sort(rng.choice(len(base), N_REF, replace=False))
    for k, name in enumerate(NAMES):
        perm = rng.permutation(len(base))  # base vertex i becomes vertex perm[i]
        bent = base * [1.0 + 0.15 * k, 1.0, 1.0 - 0.1 * k]
        bent[:, 2] += 0.2 * np.sin(1.5 * bent[:, 1]) * (k % 2)  # a smooth non-rigid bend
        verts = np.empty_like(bent)
        verts[perm] = bent
        write_mesh(root / "off" / f"{name}.off", verts, perm[faces])
        write_vts(root / "corres" / f"{name}.vts", perm[ref])
        write_vts(root / "corres" / f"{name}.sym.vts", perm[mirror[ref]])
    (root / "splits" / "test.txt").write_text("\n".join(NAMES) + "\n")
    (root / "splits" / "train.txt").write_text("\n".join(NAMES[:2]) + "\n")
    return root, tmp_path_factory.mktemp("cache"), evaluate_on_folder


def _cfg(tiny, out: Path, *overrides: str):
    root, cache, config = tiny
    return config(root, cache, out, *overrides, n_examples=2)


def _read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_identity_gt_end_to_end(tiny, tmp_path):
    out = tmp_path / "gt"
    metrics = evaluate(_cfg(tiny, out, "model=identity_gt"))
    on_disk = json.loads((out / "metrics.json").read_text())
    for key in ("n_pairs", "mean_geodesic_error", "median_geodesic_error", "pck_auc", "mean_conformal_distortion",
                "seconds_per_pair", "peak_memory_mb", "mean_geodesic_error_sym"):
        assert key in on_disk, key
    assert on_disk["n_pairs"] == N_PAIRS == metrics["n_pairs"]
    assert on_disk["mean_geodesic_error"] == 0.0 and on_disk["median_geodesic_error"] == 0.0  # the self-check
    assert on_disk["pck_auc"] == pytest.approx(1.0)
    assert on_disk["mean_geodesic_error_sym"] > 0.05  # the mirrored ground truth is a different map
    assert on_disk["peak_memory_mb"] > 0 and on_disk["seconds_per_pair"] >= 0
    rows = _read_csv(out / "per_pair.csv")
    assert len(rows) == N_PAIRS and list(rows[0])[:4] == ["source", "target", "mean_error", "seconds"]
    assert {(r["source"], r["target"]) for r in rows} == {(a, b) for a in NAMES for b in NAMES if a != b}
    assert len(list((out / "maps").glob("*.txt"))) == N_PAIRS and len(list((out / "maps").glob("*.npy"))) == N_PAIRS
    p2p = np.loadtxt(out / "maps" / f"{NAMES[0]}__{NAMES[1]}.txt", dtype=np.int64)
    assert p2p.shape == (642,) and p2p.min() >= 0 and p2p.max() < 642
    assert (out / "pck.png").stat().st_size > 1000
    assert len(list((out / "examples").glob("*.png"))) == 2


def test_maps_dir_mode_reproduces_errors(tiny, tmp_path):
    src = tmp_path / "wrong"
    # deliberately wrong maps: every vertex of x goes to vertex (k * 7) % n of y
    (src).mkdir()
    for a in NAMES:
        for b in NAMES:
            if a != b:
                np.savetxt(src / f"{a}__{b}.txt", (np.arange(642) * 7) % 642, fmt="%d")
    first = evaluate(_cfg(tiny, tmp_path / "eval1", f"maps_dir={src}", "n_examples=0"))
    assert first["mean_geodesic_error"] > 0.1
    # the maps evaluate.py wrote are read back (as .npy, and one-based as .map) to the same numbers
    written = tmp_path / "eval1" / "maps"
    second = evaluate(_cfg(tiny, tmp_path / "eval2", f"maps_dir={written}", "maps_extension=npy", "n_examples=0"))
    assert second["mean_geodesic_error"] == first["mean_geodesic_error"]
    one_based = tmp_path / "one_based"
    one_based.mkdir()
    for f in src.glob("*.txt"):
        np.savetxt(one_based / f"{f.stem}.map", np.loadtxt(f, dtype=np.int64) + 1, fmt="%d")
    options = [f"maps_dir={one_based}", "maps_extension=map", "maps_one_based=true", "n_examples=0"]
    third = evaluate(_cfg(tiny, tmp_path / "eval3", *options))
    assert third["mean_geodesic_error"] == first["mean_geodesic_error"]


def test_reference_points_evaluates_an_even_subset(tiny, tmp_path):
    """``data.reference_points=50`` scores 50 of the 200 ground-truth points of every pair (the same entries of
    both files, so the identity ground truth stays exact) and caches geodesic rows from those points only."""
    from shapecorr.data.datasets import ShapeDataset, reference_subset

    keep = reference_subset(N_REF, 50)
    assert len(keep) == 50 and keep[0] == 0 and keep[-1] == N_REF - 1 and np.all(np.diff(keep) >= 3)
    assert np.array_equal(reference_subset(N_REF, 500), np.arange(N_REF))
    exact = evaluate(_cfg(tiny, tmp_path / "gt", "model=identity_gt", "data.reference_points=50", "n_examples=0"))
    assert exact["n_points"] == 50 * N_PAIRS and exact["mean_geodesic_error"] == 0.0
    root, cache, _ = tiny
    wrong = tmp_path / "wrong"
    wrong.mkdir()
    for a in NAMES:
        for b in NAMES:
            if a != b:
                np.savetxt(wrong / f"{a}__{b}.txt", (np.arange(642) * 7) % 642, fmt="%d")
    both = [evaluate(_cfg(tiny, tmp_path / f"wrong_{n}", f"maps_dir={wrong}", f"data.reference_points={n}",
                          "n_examples=0")) for n in ("null", 50)]
    assert both[0]["n_points"] == N_REF * N_PAIRS and both[1]["n_points"] == 50 * N_PAIRS
    assert both[1]["mean_geodesic_error"] != both[0]["mean_geodesic_error"]
    assert both[1]["mean_geodesic_error"] == pytest.approx(both[0]["mean_geodesic_error"], rel=0.3)
    shapes = ShapeDataset(root, cache_dir=cache, reference_points=50)
    full = ShapeDataset(root, cache_dir=cache)
    assert set(shapes.geodesic_sources(0)) < set(full.geodesic_sources(0))
    assert len(shapes.geodesic_sources(0)) <= 100  # 50 points of the .vts and 50 of the .sym.vts
    for bad in (0, "all", 2.5):
        with pytest.raises(ConfigError, match="data.reference_points"):
            ShapeDataset(root, cache_dir=cache, reference_points=bad)


def test_descriptor_nn_in_parallel_workers(tiny, tmp_path):
    """Two worker processes; fork keeps the test fast, and spawn (the default) only needs the dataset and the
    matcher to pickle, which is checked here directly."""
    import hydra

    from shapecorr.matching.baselines import DescriptorNN

    cfg = _cfg(tiny, tmp_path / "unused")
    shapes = hydra.utils.instantiate(cfg.data, _convert_="object").shapes("test")
    clone = pickle.loads(pickle.dumps(shapes))
    assert clone.names == shapes.names and clone.root == shapes.root
    assert pickle.loads(pickle.dumps(DescriptorNN("hks"))).descriptor == "hks"
    out = tmp_path / "hks"
    metrics = evaluate(_cfg(tiny, out, "model=descriptor_nn", "model.descriptor=hks", "workers=2", "max_pairs=4",
                            "start_method=fork"))
    assert metrics["n_pairs"] == 4
    assert 0.0 < metrics["mean_geodesic_error"] < 1.0
    assert metrics["run"]["workers"] == 2
    assert metrics["peak_memory_children_mb"] > 0  # the workers' memory is accounted for


def test_resume_skips_done_pairs(tiny, tmp_path):
    out = tmp_path / "resume"
    evaluate(_cfg(tiny, out, "model=identity_gt", "n_examples=0"))
    records = sorted((out / "pairs").glob("*.json"))
    assert len(records) == N_PAIRS
    stamps = {p.name: p.stat().st_mtime_ns for p in records}
    redo = out / "pairs" / f"{NAMES[2]}__{NAMES[0]}.json"
    redo.unlink()
    metrics = evaluate(_cfg(tiny, out, "model=identity_gt", "n_examples=0"))
    assert metrics["n_pairs"] == N_PAIRS
    after = {p.name: p.stat().st_mtime_ns for p in sorted((out / "pairs").glob("*.json"))}
    assert after.keys() == stamps.keys()
    changed = [name for name in after if after[name] != stamps[name]]
    assert changed == [redo.name]  # only the missing pair was evaluated again
    # the same folder with a different matcher is refused, not silently mixed
    with pytest.raises(SystemExit) as exc:
        evaluate(_cfg(tiny, out, "model=descriptor_nn", "model.descriptor=hks"))
    assert exc.value.code == 2


def test_size_mismatch_is_a_clear_error(tiny, tmp_path, capsys):
    maps = tmp_path / "maps"
    maps.mkdir()
    for a in NAMES:
        for b in NAMES:
            if a != b:
                np.savetxt(maps / f"{a}__{b}.txt", np.zeros(600, dtype=np.int64), fmt="%d")  # 600 != 642
    with pytest.raises(SystemExit) as exc:
        evaluate(_cfg(tiny, tmp_path / "out", f"maps_dir={maps}"))
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "Traceback" not in err
    assert str(maps) in err and "__" in err and ".txt" in err  # names the file
    assert "600 entries" in err and "642 vertices" in err


@pytest.mark.slow
def test_entry_point_composes_the_configs(tiny, tmp_path):
    """The root ``evaluate.py`` finds configs/evaluate.yaml and its groups (no run: ``--cfg job``)."""
    root = tiny[0]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run(
        [sys.executable, str(REPO / "evaluate.py"), "--cfg", "job", "model=descriptor_nn", "data=folder",
         f"data.root={root}", f"output_dir={tmp_path}"],
        capture_output=True, text=True, cwd=tmp_path, env=env, timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert "shapecorr.matching.baselines.DescriptorNN" in proc.stdout and "descriptor: wks" in proc.stdout


def test_nothing_to_evaluate_is_a_config_error(tiny, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        evaluate(_cfg(tiny, tmp_path / "none"))
    assert exc.value.code == 2
    assert "model=<name>" in capsys.readouterr().err
