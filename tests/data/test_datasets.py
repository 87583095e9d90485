"""ShapeDataset / PairDataset / ShapePairDataModule on a tiny hand-made folder."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch
import trimesh

from shapecorr.data.datamodule import ShapePairDataModule
from shapecorr.data.datasets import PairDataset, ShapeDataset, read_pair_file
from shapecorr.data.io import write_mesh, write_vts
from shapecorr.data.operators import OperatorConfig
from shapecorr.errors import ConfigError, CorrespondenceError, DatasetError

N_SHAPES = 4
N_REF = 30


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """Four stretched icospheres (162 vertices) with vts files and train/test split files."""
    root = tmp_path_factory.mktemp("tinyset")
    (root / "off").mkdir()
    (root / "corres").mkdir()
    (root / "splits").mkdir()
    base = trimesh.creation.icosphere(subdivisions=2)
    rng = np.random.default_rng(0)
    names = [f"shape_{i:03d}" for i in range(N_SHAPES)]
    for i, name in enumerate(names):
        verts = (base.vertices * np.array([1.0 + 0.2 * i, 1.0, 1.0 - 0.1 * i])
                 + rng.normal(0, 1e-3, (len(base.vertices), 3)))
        write_mesh(root / "off" / f"{name}.off", verts, base.faces)
        write_vts(root / "corres" / f"{name}.vts", np.arange(N_REF))
    (root / "splits" / "train.txt").write_text("\n".join(names[:3]) + "\n")
    (root / "splits" / "test.txt").write_text("\n".join(names[3:] + names[:1]) + "\n")
    return root


def test_shape_dataset_items(folder, tmp_path):
    ds = ShapeDataset(folder, operators=OperatorConfig(n_eig=12), cache_dir=tmp_path)
    assert ds.names == [f"shape_{i:03d}" for i in range(N_SHAPES)]
    s = ds[1]
    n = s.shape.n_verts
    assert s.evecs.shape == (n, 12) and s.evals.shape == (12,) and s.mass.shape == (n,)
    assert s.evecs.dtype == torch.float32
    assert torch.equal(s.corres, torch.arange(N_REF))
    assert s.corres_sym is None
    # normalized: total area = (2/3)^2
    assert float(s.mass.sum()) == pytest.approx(4.0 / 9.0, rel=1e-4)
    # mass-orthonormal basis
    gram = s.evecs.T.double() @ (s.mass.double()[:, None] * s.evecs.double())
    assert torch.allclose(gram, torch.eye(12, dtype=torch.float64), atol=1e-4)


def test_prepare_fills_cache_then_reads(folder, tmp_path, monkeypatch):
    ds = ShapeDataset(folder, split="train", operators=OperatorConfig(n_eig=8), cache_dir=tmp_path)
    ds.prepare(num_workers=1, progress=False)
    import shapecorr.geometry.laplace_beltrami as lap

    def fail(*a, **k):
        raise AssertionError("eigenbasis recomputed although cached")

    monkeypatch.setattr(lap, "eigenbasis", fail)
    for i in range(len(ds)):
        assert ds[i].evecs.shape[1] == 8


def test_splits_and_pairs(folder, tmp_path):
    train = ShapeDataset(folder, split="train", operators=OperatorConfig(n_eig=4), cache_dir=tmp_path)
    assert train.names == ["shape_000", "shape_001", "shape_002"]
    ranged = ShapeDataset(folder, index_range=[1, 3], operators=OperatorConfig(n_eig=4), cache_dir=tmp_path)
    assert ranged.names == ["shape_001", "shape_002"]
    assert len(PairDataset(train, include_self=True)) == 9
    pairs = PairDataset(train)
    assert len(pairs) == 6 and all(i != j for i, j in pairs.pairs)
    sample = pairs[0]
    assert (sample.x.name, sample.y.name) == pairs.names(0)
    assert sample.name == f"{sample.x.name}__{sample.y.name}"
    assert len(PairDataset(train, max_pairs=4)) == 4


def test_pair_file(folder, tmp_path):
    path = tmp_path / "pairs.txt"
    path.write_text("shape_000\tshape_002\nshape_001 shape_000\n")
    assert read_pair_file(path) == [("shape_000", "shape_002"), ("shape_001", "shape_000")]
    ds = ShapeDataset(folder, operators=OperatorConfig(n_eig=4), cache_dir=tmp_path)
    assert PairDataset(ds, pair_file=path).pairs == [(0, 2), (1, 0)]
    path.write_text("shape_000\tnot_a_shape\n")
    with pytest.raises(DatasetError, match="not_a_shape"):
        PairDataset(ds, pair_file=path)


@pytest.mark.parametrize(
    "make, kwargs, error, text",
    [
        (lambda root: None, {}, DatasetError, "does not exist"),
        (lambda root: root.mkdir(), {}, DatasetError, "no mesh sub-folder"),
        (lambda root: (root / "off").mkdir(parents=True), {}, DatasetError, "no mesh files"),
    ],
)
def test_bad_folders(tmp_path, make, kwargs, error, text):
    root = tmp_path / "data"
    make(root)
    with pytest.raises(error, match=text) as info:
        ShapeDataset(root, cache_dir=tmp_path, **kwargs)
    assert "data" in str(info.value)


def test_missing_split_and_bad_range(folder, tmp_path):
    with pytest.raises(DatasetError, match="splits/val.txt"):
        ShapeDataset(folder, split="val", cache_dir=tmp_path)
    with pytest.raises(DatasetError, match="outside"):
        ShapeDataset(folder, index_range=[2, 9], cache_dir=tmp_path)


def _bare_copy(folder, root):
    """The folder without its splits/ directory (off/ + corres/ only)."""
    import shutil

    shutil.copytree(folder, root, ignore=shutil.ignore_patterns("splits"))
    assert not (root / "splits").exists()
    return root


def test_without_splits_folder_every_shape_is_in_every_split(folder, tmp_path, caplog):
    root = _bare_copy(folder, tmp_path / "bare")
    everything = [f"shape_{i:03d}" for i in range(N_SHAPES)]
    with caplog.at_level(logging.INFO, logger="shapecorr.data.datasets"):
        dm = ShapePairDataModule(root, splits={"train": {"split": "train"}, "val": {"split": "test"},
                                               "test": {"split": "test"}}, cache_dir=tmp_path)
        for split in ("train", "val", "test"):
            assert dm.shapes(split).names == everything
        assert ShapeDataset(root, split="anything", cache_dir=tmp_path).names == everything
    announced = [r for r in caplog.records if "no splits/ folder" in r.getMessage()]
    assert len(announced) == 1 and "every shape (4) belongs to every split" in announced[0].getMessage()
    # explicit selectors keep their meaning
    assert ShapeDataset(root, index_range=[1, 3], cache_dir=tmp_path).names == ["shape_001", "shape_002"]
    with pytest.raises(DatasetError, match="split file does not exist"):
        ShapeDataset(root, split_file=root / "splits" / "test.txt", cache_dir=tmp_path)


def test_with_a_splits_folder_a_missing_split_file_is_still_an_error(folder, tmp_path):
    root = _bare_copy(folder, tmp_path / "typo")
    (root / "splits").mkdir()
    (root / "splits" / "train.txt").write_text("shape_000\n")
    with pytest.raises(DatasetError, match="no split file for split 'test'"):
        ShapeDataset(root, split="test", cache_dir=tmp_path)


def test_pair_file_names_any_pair_of_a_bare_folder(folder, tmp_path):
    root = _bare_copy(folder, tmp_path / "bare_pairs")
    (root / "my_pairs.txt").write_text("shape_003 shape_000\nshape_001\tshape_002\n")
    test = ShapeDataset(root, split="test", cache_dir=tmp_path)
    # a relative path that is not in the working directory is read from the dataset folder
    pairs = PairDataset(test, pair_file="my_pairs.txt")
    assert [pairs.names(k) for k in range(len(pairs))] == [("shape_003", "shape_000"), ("shape_001", "shape_002")]


def test_pair_outside_the_split_names_the_split(folder, tmp_path):
    train = ShapeDataset(folder, split="train", cache_dir=tmp_path)  # shape_003 is a test shape
    with pytest.raises(DatasetError, match="'shape_003' is in the folder but not in split 'train'"):
        PairDataset(train, pairs=[("shape_000", "shape_003")])
    with pytest.raises(DatasetError, match="no shape named 'shape_999'"):
        PairDataset(train, pairs=[("shape_000", "shape_999")])


def test_vts_length_mismatch(folder, tmp_path):
    import shutil

    root = tmp_path / "copy"
    shutil.copytree(folder, root)
    write_vts(root / "corres" / "shape_002.vts", np.arange(N_REF - 1))
    with pytest.raises(CorrespondenceError, match="shape_002"):
        ShapeDataset(root, cache_dir=tmp_path)


def test_datamodule_loaders(folder, tmp_path):
    dm = ShapePairDataModule(
        folder,
        splits={"train": {"split": "train"}, "val": {"split": "test"}, "test": {"split": "test"}},
        pairs={"train": {"include_self": True}, "val": {"max_pairs": 1}},
        operators={"n_eig": 6},
        cache_dir=tmp_path,
        prepare_workers=1,
    )
    dm.prepare_data()
    dm.setup("fit")
    batches = list(dm.train_dataloader())
    assert len(batches) == 9
    assert len(list(dm.val_dataloader())) == 1
    moved = dm.transfer_batch_to_device(batches[0], torch.device("cpu"), 0)
    assert moved.x.evecs.device.type == "cpu"
    # the same seed gives the same epoch order
    again = [b.name for b in dm.train_dataloader()]
    dm2 = ShapePairDataModule(folder, splits={"train": {"split": "train"}}, pairs={"train": {"include_self": True}},
                              operators={"n_eig": 6}, cache_dir=tmp_path)
    assert [b.name for b in dm2.train_dataloader()] == again
    dm.with_operators({"wks": {}}, n_eig=8)
    assert dm.operators.n_eig == 8 and dm.operators.descriptors == ("wks",)
    assert dm.shapes("test")[0].features["wks"].shape[0] == dm.shapes("test")[0].shape.n_verts


def test_datamodule_rejects_unknown_options(folder):
    with pytest.raises(ConfigError, match="unknown"):
        ShapePairDataModule(folder, splits={"trian": {}})
    with pytest.raises(ConfigError, match="index_rnage"):
        ShapePairDataModule(folder, splits={"train": {"index_rnage": [0, 1]}})
    with pytest.raises(ConfigError, match="n_eigs"):
        ShapePairDataModule(folder, operators={"n_eigs": 3})


def test_mesh_cache_hit_and_invalidation(folder, tmp_path, monkeypatch):
    import os
    import shutil

    import shapecorr.data.datasets as datasets_module

    root = tmp_path / "copy"
    shutil.copytree(folder, root)
    first = ShapeDataset(root, operators=OperatorConfig(n_eig=4), cache_dir=tmp_path / "cache").load_shape(0)
    calls = []
    real = datasets_module.load_shape
    monkeypatch.setattr(datasets_module, "load_shape", lambda *a, **k: calls.append(a) or real(*a, **k))
    again = ShapeDataset(root, operators=OperatorConfig(n_eig=4), cache_dir=tmp_path / "cache").load_shape(0)
    assert calls == []  # served from the cache, file not parsed
    assert torch.equal(first.verts, again.verts) and torch.equal(first.faces, again.faces)
    assert again.scale == first.scale and np.allclose(again.offset, first.offset)
    # the entry is keyed on the file's content: touching it (new mtime) still hits ...
    path = root / "off" / "shape_000.off"
    stat = path.stat()
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    ShapeDataset(root, operators=OperatorConfig(n_eig=4), cache_dir=tmp_path / "cache").load_shape(0)
    assert calls == []
    # ... and an in-place edit that keeps the size and the modification time misses
    lines = path.read_text().split("\n")
    digit = next(k for k, c in enumerate(lines[2]) if c.isdigit())  # lines[2]: the first vertex
    lines[2] = lines[2][:digit] + str((int(lines[2][digit]) + 1) % 10) + lines[2][digit + 1:]
    path.write_text("\n".join(lines))
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert path.stat().st_size == stat.st_size and path.stat().st_mtime_ns == stat.st_mtime_ns
    moved = ShapeDataset(root, operators=OperatorConfig(n_eig=4), cache_dir=tmp_path / "cache").load_shape(0)
    assert len(calls) == 1
    assert not torch.equal(moved.verts, first.verts)
