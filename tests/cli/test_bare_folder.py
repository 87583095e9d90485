"""``evaluate.py model=descriptor_nn data=folder data.root=DIR`` on a folder with only ``off/`` and ``corres/``.

Without a ``splits/`` folder every shape belongs to every split, so the default ``pairs=test`` evaluates all
ordered pairs, and ``pair_file=`` may name any pair of the folder. Three bent, vertex-permuted icospheres
(162 vertices) with ``.vts`` ground truth on every vertex.
"""

from __future__ import annotations

import csv
import json
import logging

import numpy as np
import pytest
import trimesh

from shapecorr.cli.evaluate import evaluate
from shapecorr.data import datasets
from shapecorr.data.io import write_mesh, write_vts

NAMES = ["a", "b", "c"]


@pytest.fixture(scope="module")
def bare(tmp_path_factory):
    """``(root, cache_dir)`` of a folder with off/ and corres/ only."""
    root = tmp_path_factory.mktemp("bare_folder")
    (root / "off").mkdir()
    (root / "corres").mkdir()
    mesh = trimesh.creation.icosphere(subdivisions=2)
    base, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    rng = np.random.default_rng(0)
    for k, name in enumerate(NAMES):
        perm = rng.permutation(len(base))  # base vertex i becomes vertex perm[i]
        bent = base * [1.0 + 0.2 * k, 1.0, 1.0 - 0.1 * k]
        verts = np.empty_like(bent)
        verts[perm] = bent
        write_mesh(root / "off" / f"{name}.off", verts, perm[faces])
        write_vts(root / "corres" / f"{name}.vts", perm)
    return root, tmp_path_factory.mktemp("bare_cache")


def _evaluate(compose_config, bare, out, *overrides):
    root, cache = bare
    cfg = compose_config("evaluate", ["model=descriptor_nn", "data=folder", f"data.root={root}",
                                      f"paths.cache_dir={cache}", f"output_dir={out}", "progress=false",
                                      "n_examples=0", "data.operators.n_eig=30", "data.prepare_workers=1", *overrides])
    return evaluate(cfg)


def _pairs(out):
    with open(out / "per_pair.csv", newline="") as fh:
        return [(row["source"], row["target"]) for row in csv.DictReader(fh)]


def test_bare_folder_evaluates_all_ordered_pairs(compose_config, bare, tmp_path, caplog, monkeypatch):
    monkeypatch.setattr(datasets, "_ROOTS_WITHOUT_SPLITS", set())  # announced once per folder and process
    with caplog.at_level(logging.INFO, logger="shapecorr.data.datasets"):
        metrics = _evaluate(compose_config, bare, tmp_path / "all")
    assert metrics["n_pairs"] == len(NAMES) * (len(NAMES) - 1)
    assert sorted(_pairs(tmp_path / "all")) == [(x, y) for x in NAMES for y in NAMES if x != y]
    assert json.loads((tmp_path / "all" / "metrics.json").read_text())["n_pairs"] == 6
    assert 0.0 <= metrics["mean_geodesic_error"] < 1.0
    assert (tmp_path / "all" / "pck.png").is_file()
    assert sum("every shape (3) belongs to every split" in r.getMessage() for r in caplog.records) == 1


def test_pair_file_names_any_pair_of_the_folder(compose_config, bare, tmp_path):
    pair_file = tmp_path / "pairs.txt"
    pair_file.write_text("c a\nb\tc\n")
    metrics = _evaluate(compose_config, bare, tmp_path / "some", f"pair_file={pair_file}")
    assert metrics["n_pairs"] == 2 and _pairs(tmp_path / "some") == [("c", "a"), ("b", "c")]
