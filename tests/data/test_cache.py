"""Shape cache: keys, hits and misses, storage dtypes, corruption, interrupted and concurrent writes,
read-only mode, the upgrade (find) API."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import threading
import time
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest
import trimesh

from shapecorr.data import cache as cache_module
from shapecorr.data.cache import (
    STALE_TEMP_SECONDS,
    TEMP_SUFFIX,
    CacheKey,
    CacheWarning,
    ShapeCache,
    atomic_open,
    content_hash,
    default_cache_root,
)
from shapecorr.errors import CacheError, NumericalError

SEED = 0


@pytest.fixture(scope="module")
def mesh():
    sphere = trimesh.creation.icosphere(1)
    return np.asarray(sphere.vertices), np.asarray(sphere.faces, dtype=np.int64)


class Counting:
    """A compute function that records how often it ran and returns float64 + int arrays."""

    def __init__(self, n: int = 42, k: int = 5, seed: int = SEED):
        self.calls = 0
        rng = np.random.default_rng(seed)
        self.result = {"evecs": rng.standard_normal((n, k)), "evals": np.sort(rng.random(k)), "idx": np.arange(n)}

    def __call__(self):
        self.calls += 1
        return {name: a.copy() for name, a in self.result.items()}


def _entry_files(root: Path) -> list[Path]:
    return sorted(root.rglob("*.npz"))


def _temp_files(root: Path) -> list[Path]:
    return sorted(root.rglob(f"*{TEMP_SUFFIX}"))


# ------------------------------------------------------------------------------------------- keys


def test_content_hash_is_stable_and_sensitive(mesh):
    verts, faces = mesh
    h = content_hash(verts, faces)
    assert len(h) == 64 and h == content_hash(verts.copy(), faces.copy())
    assert h == content_hash(verts.astype(np.float64), faces.astype(np.int32))  # dtype-normalized
    nudged = verts.copy()
    nudged[7, 2] = np.nextafter(nudged[7, 2], np.inf)  # one ulp
    assert content_hash(nudged, faces) != h
    assert content_hash(verts, faces[:, [1, 2, 0]]) != h
    assert content_hash(verts.reshape(-1, 1), faces) != h  # same bytes, different shape
    torch = pytest.importorskip("torch")
    assert content_hash(torch.from_numpy(verts), torch.from_numpy(faces)) == h


def test_key_digest_depends_on_every_part(mesh):
    h = content_hash(*mesh)
    base = CacheKey("eigenbasis", h, {"k": 30, "method": "cot"}, 1)
    variants = [
        CacheKey("descriptors", h, {"k": 30, "method": "cot"}, 1),
        CacheKey("eigenbasis", "0" * 64, {"k": 30, "method": "cot"}, 1),
        CacheKey("eigenbasis", h, {"k": 31, "method": "cot"}, 1),
        CacheKey("eigenbasis", h, {"k": 30, "method": "cot"}, 2),
        CacheKey("eigenbasis", h, {"k": 30, "method": "cot"}, "1"),
        CacheKey("eigenbasis", h, {"k": 30, "method": "cot"}, 1, keep_float64=True),
    ]
    assert len({base.digest} | {v.digest for v in variants}) == 7
    assert CacheKey("eigenbasis", h, {"method": "cot", "k": 30}, 1).digest == base.digest  # key order


def test_key_is_immune_to_later_mutation_of_params(mesh):
    params = {"k": 30, "times": [0.1, 0.2]}
    key = CacheKey("hks", content_hash(*mesh), params, 1)
    digest = key.digest
    params["k"] = 99
    params["times"].append(0.3)
    assert key.digest == digest and key.params == {"k": 30, "times": [0.1, 0.2]}


@pytest.mark.parametrize(
    "name, chash, params, version, match",
    [
        ("../escape", "a" * 64, {}, 1, "name"),
        ("", "a" * 64, {}, 1, "name"),
        ("eig", "not-a-hash", {}, 1, "content_hash"),
        ("eig", "a" * 64, {"solver": object()}, 1, "JSON"),
        ("eig", "a" * 64, {"tol": float("nan")}, 1, "JSON"),
        ("eig", "a" * 64, [("k", 3)], 1, "mapping"),
        ("eig", "a" * 64, {}, 1.5, "version"),
        ("eig", "a" * 64, {}, True, "version"),
    ],
)
def test_invalid_keys_raise_cache_error(name, chash, params, version, match):
    with pytest.raises(CacheError, match=match):
        CacheKey(name, chash, params, version)


def test_default_root_from_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("SHAPECORR_CACHE", str(tmp_path / "c"))
    assert default_cache_root() == tmp_path / "c"
    assert ShapeCache().root == tmp_path / "c"
    monkeypatch.delenv("SHAPECORR_CACHE")
    assert default_cache_root() == Path("~/.cache/shapecorr").expanduser()


# ------------------------------------------------------------------------------------ hit / miss


def test_hit_after_miss_computes_once(tmp_path, mesh):
    cache = ShapeCache(tmp_path)
    compute = Counting()
    first = cache.get_or_compute("eigenbasis", *mesh, {"k": 5}, 1, compute)
    second = cache.get_or_compute("eigenbasis", *mesh, {"k": 5}, 1, compute)
    assert compute.calls == 1
    assert first.keys() == second.keys() == {"evecs", "evals", "idx"}
    for name in first:
        assert first[name].dtype == second[name].dtype
        np.testing.assert_array_equal(first[name], second[name])
    assert len(_entry_files(tmp_path)) == 1 and _temp_files(tmp_path) == []
    # A fresh cache object on the same root (another process) hits too.
    ShapeCache(tmp_path).get_or_compute("eigenbasis", *mesh, {"k": 5}, 1, compute)
    assert compute.calls == 1


def test_params_version_and_mesh_changes_miss(tmp_path, mesh):
    verts, faces = mesh
    cache = ShapeCache(tmp_path)
    compute = Counting()
    cache.get_or_compute("eigenbasis", verts, faces, {"k": 5}, 1, compute)
    cache.get_or_compute("eigenbasis", verts, faces, {"k": 6}, 1, compute)
    assert compute.calls == 2
    cache.get_or_compute("eigenbasis", verts, faces, {"k": 5}, 2, compute)
    assert compute.calls == 3
    cache.get_or_compute("eigenbasis", verts * 2, faces, {"k": 5}, 1, compute)
    assert compute.calls == 4
    cache.get_or_compute("shot", verts, faces, {"k": 5}, 1, compute)
    assert compute.calls == 5
    for params, version in [({"k": 5}, 1), ({"k": 6}, 1), ({"k": 5}, 2)]:
        cache.get_or_compute("eigenbasis", verts, faces, params, version, compute)
    assert compute.calls == 5
    assert len(_entry_files(tmp_path)) == 5


def test_storage_dtypes(tmp_path, mesh):
    cache = ShapeCache(tmp_path)
    compute = Counting()
    compute.result["flags"] = np.array([True, False])
    compute.result["half"] = np.ones(3, dtype=np.float16)
    compute.result["small"] = np.arange(4, dtype=np.int32)
    miss = cache.get_or_compute("ops", *mesh, {}, 1, compute)
    hit = cache.get_or_compute("ops", *mesh, {}, 1, compute)
    for result in (miss, hit):
        assert result["evecs"].dtype == np.float32 and result["evals"].dtype == np.float32
        assert result["idx"].dtype == np.int64 and result["small"].dtype == np.int32
        assert result["flags"].dtype == np.bool_ and result["half"].dtype == np.float16
    np.testing.assert_array_equal(hit["evecs"], compute.result["evecs"].astype(np.float32))
    with np.load(_entry_files(tmp_path)[0], allow_pickle=False) as archive:
        assert archive["evecs"].dtype == np.float32  # on disk too, not only after loading
    kept = cache.get_or_compute("ops", *mesh, {}, 1, compute, keep_float64=True)
    assert compute.calls == 2  # a float64 request is not served by the float32 entry
    assert kept["evecs"].dtype == np.float64
    np.testing.assert_array_equal(kept["evecs"], compute.result["evecs"])


def test_nan_from_compute_raises_and_stores_nothing(tmp_path, mesh):
    cache = ShapeCache(tmp_path)
    with pytest.raises(NumericalError, match="'bad'.*NaN"):
        cache.get_or_compute("x", *mesh, {}, 1, lambda: {"ok": np.ones(3), "bad": np.array([1.0, np.nan])})
    with pytest.raises(NumericalError, match="float32"):  # finite in float64, inf once stored as float32
        cache.get_or_compute("x", *mesh, {}, 1, lambda: {"huge": np.array([1e300])})
    assert _entry_files(tmp_path) == [] and _temp_files(tmp_path) == []


@pytest.mark.parametrize(
    "arrays, match",
    [
        ({}, "non-empty"),
        ({"names": np.array(["a", "b"])}, "numeric"),
        ({"objects": np.array([{}, []], dtype=object)}, "numeric"),
        ({"__meta__": np.ones(2)}, "invalid array name"),
        ({"allow_pickle": np.ones(2)}, "invalid array name"),
        ({"a/b": np.ones(2)}, "invalid array name"),
    ],
)
def test_put_rejects_unstorable_arrays(tmp_path, mesh, arrays, match):
    with pytest.raises(CacheError, match=match):
        ShapeCache(tmp_path).put(CacheKey("x", content_hash(*mesh), {}, 1), arrays)
    assert _entry_files(tmp_path) == []


# ---------------------------------------------------------------------------------- corruption


def _populate(tmp_path, mesh) -> tuple[ShapeCache, Counting, Path]:
    cache = ShapeCache(tmp_path)
    compute = Counting()
    cache.get_or_compute("eigenbasis", *mesh, {"k": 5}, 1, compute)
    (path,) = _entry_files(tmp_path)
    return cache, compute, path


def _rewrite_npz(path: Path, edit) -> None:
    """Rewrite the entry with `edit(members: dict) -> dict` applied (members keep their raw arrays)."""
    with np.load(path, allow_pickle=False) as archive:
        members = {name: archive[name] for name in archive.files}
    members = edit(members)
    with open(path, "wb") as handle:
        np.savez(handle, **members)


def _write_with(path: Path, save, *args, **kwargs) -> None:
    with open(path, "wb") as handle:
        save(handle, *args, **kwargs)


def _edit_meta(members, change):
    meta = json.loads(members["__meta__"].tobytes())
    change(meta)
    members["__meta__"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    return members


def _nan_in_evecs(members):
    members["evecs"] = members["evecs"].copy()
    members["evecs"][0, 0] = np.nan
    return members


CORRUPTIONS = {
    "truncated": lambda p: p.write_bytes(p.read_bytes()[: p.stat().st_size // 2]),
    "truncated-to-zero": lambda p: p.write_bytes(b""),
    "garbage": lambda p: p.write_bytes(b"this is not a zip file at all" * 10),
    "flipped-byte-in-data": lambda p: p.write_bytes(
        (lambda b: b[:200] + bytes([b[200] ^ 0xFF]) + b[201:])(bytearray(p.read_bytes()))
    ),
    "plain-npy": lambda p: _write_with(p, np.save, np.zeros(3)),
    "missing-array": lambda p: _rewrite_npz(p, lambda m: {k: v for k, v in m.items() if k != "evals"}),
    "extra-array": lambda p: _rewrite_npz(p, lambda m: {**m, "junk": np.zeros(2)}),
    "missing-metadata": lambda p: _rewrite_npz(p, lambda m: {k: v for k, v in m.items() if k != "__meta__"}),
    "garbage-metadata": lambda p: _rewrite_npz(p, lambda m: {**m, "__meta__": np.frombuffer(b"{not json", np.uint8)}),
    "wrong-shape": lambda p: _rewrite_npz(p, lambda m: {**m, "evecs": m["evecs"][:-1]}),
    "wrong-dtype": lambda p: _rewrite_npz(p, lambda m: {**m, "idx": m["idx"].astype(np.int32)}),
    "nan-stored": lambda p: _rewrite_npz(p, _nan_in_evecs),
    "old-format": lambda p: _rewrite_npz(p, lambda m: _edit_meta(m, lambda meta: meta.update(format=0))),
    "metadata-array-list-not-a-dict": lambda p: _rewrite_npz(
        p, lambda m: _edit_meta(m, lambda meta: meta.update(arrays=["evecs", "evals", "idx"]))
    ),
    "pickled-object-array": lambda p: _write_with(p, np.savez, evecs=np.array([{"a": 1}], dtype=object)),
}


@pytest.mark.parametrize("corruption", sorted(CORRUPTIONS))
def test_corrupt_entry_is_recomputed_with_warning(tmp_path, mesh, corruption):
    cache, compute, path = _populate(tmp_path, mesh)
    CORRUPTIONS[corruption](path)
    with pytest.warns(CacheWarning, match="corrupt cache entry"):
        result = cache.get_or_compute("eigenbasis", *mesh, {"k": 5}, 1, compute)
    assert compute.calls == 2
    np.testing.assert_array_equal(result["evecs"], compute.result["evecs"].astype(np.float32))
    np.testing.assert_array_equal(result["idx"], compute.result["idx"])
    # Overwritten with a good entry: the next call hits without a warning.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cache.get_or_compute("eigenbasis", *mesh, {"k": 5}, 1, compute)
    assert compute.calls == 2 and _temp_files(tmp_path) == []


def test_stale_entry_with_another_key_is_recomputed(tmp_path, mesh):
    cache, compute, path = _populate(tmp_path, mesh)
    other = CacheKey("eigenbasis", content_hash(*mesh), {"k": 6}, 1)
    cache.path(other).write_bytes(path.read_bytes())  # e.g. copied by hand, or a digest collision
    with pytest.warns(CacheWarning, match="stale"):
        assert cache.get(other) is None
    stored = cache.put(other, {"evecs": np.ones((3, 3))})
    np.testing.assert_array_equal(cache.get(other)["evecs"], stored["evecs"])


# --------------------------------------------------------------------- interrupted and concurrent


def test_failed_rename_keeps_previous_entry_and_leaves_no_temp(tmp_path, mesh, monkeypatch):
    cache, compute, path = _populate(tmp_path, mesh)
    before = path.read_bytes()
    key = CacheKey("eigenbasis", content_hash(*mesh), {"k": 5}, 1)

    def crash(*args, **kwargs):
        raise OSError("simulated crash between write and rename")

    monkeypatch.setattr(cache_module.os, "replace", crash)
    with pytest.raises(CacheError, match="simulated crash") as info:
        cache.put(key, {"evecs": np.zeros((2, 2))})
    assert type(info.value) is CacheError and path.name in str(info.value)
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert _temp_files(tmp_path) == []
    np.testing.assert_array_equal(cache.get(key)["evecs"], compute.result["evecs"].astype(np.float32))


def test_atomic_open_leaves_target_untouched_on_error(tmp_path):
    target = tmp_path / "f.bin"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError):
        with atomic_open(target) as handle:
            handle.write(b"new but incomplete")
            raise RuntimeError("boom")
    assert target.read_bytes() == b"old" and sorted(tmp_path.iterdir()) == [target]
    with atomic_open(target) as handle:
        handle.write(b"new")
    assert target.read_bytes() == b"new" and sorted(tmp_path.iterdir()) == [target]


_CRASHING_WRITER = textwrap.dedent(
    """
    import os, sys
    import numpy as np
    from shapecorr.data.cache import CacheKey, ShapeCache

    root, chash = sys.argv[1], sys.argv[2]
    os.replace = lambda *args, **kwargs: os._exit(3)  # the process dies after the temp file is complete
    ShapeCache(root).put(CacheKey("eigenbasis", chash, {"k": 5}, 1), {"evecs": np.zeros((2, 2))})
    """
)


@pytest.mark.slow
def test_hard_crash_between_write_and_rename(tmp_path, mesh):
    cache, compute, path = _populate(tmp_path, mesh)
    before = path.read_bytes()
    result = subprocess.run(
        [sys.executable, "-c", _CRASHING_WRITER, str(tmp_path), content_hash(*mesh)], capture_output=True, timeout=60
    )
    assert result.returncode == 3, result.stderr.decode()
    (leftover,) = _temp_files(tmp_path)  # the crash left its complete-but-unrenamed temp file
    assert path.read_bytes() == before  # the previous entry is what readers see
    key = CacheKey("eigenbasis", content_hash(*mesh), {"k": 5}, 1)
    np.testing.assert_array_equal(cache.get(key)["evecs"], compute.result["evecs"].astype(np.float32))
    assert cache.find("eigenbasis", key.content_hash, lambda k: True) == [key]  # temp files are not entries

    # A young temp file may belong to a live writer: a write in that directory keeps it ...
    other = CacheKey("eigenbasis", key.content_hash, {"k": 9}, 1)
    cache.put(other, {"evecs": np.ones((2, 2))})
    assert leftover.exists()
    # ... once older than STALE_TEMP_SECONDS it is removed by the next write.
    old = time.time() - STALE_TEMP_SECONDS - 10
    os.utime(leftover, (old, old))
    cache.put(other, {"evecs": np.ones((2, 2))})
    assert not leftover.exists()


def test_clean_temp_walks_the_root(tmp_path):
    cache = ShapeCache(tmp_path)
    (tmp_path / "a" / "b").mkdir(parents=True)
    stale = tmp_path / "a" / "b" / f".x.npz.123{TEMP_SUFFIX}"
    fresh = tmp_path / "a" / f".y.npz.456{TEMP_SUFFIX}"
    stale.write_bytes(b"partial")
    fresh.write_bytes(b"partial")
    old = time.time() - STALE_TEMP_SECONDS - 10
    os.utime(stale, (old, old))
    assert ShapeCache(tmp_path, writable=False).clean_temp() == 0 and stale.exists()
    assert cache.clean_temp() == 1
    assert not stale.exists() and fresh.exists()


def test_concurrent_writers_do_not_corrupt_each_other(tmp_path, mesh):
    key = CacheKey("geodesics", content_hash(*mesh), {}, 1)
    values = [np.full((200, 50), float(i)) for i in range(4)]
    errors = []

    def writer(i):
        try:
            cache = ShapeCache(tmp_path)
            for _ in range(5):
                cache.put(key, {"d": values[i]})
                got = cache.get(key)
                assert got is not None and got["d"][0, 0] in range(4) and np.all(got["d"] == got["d"][0, 0])
        except BaseException as err:  # collected for the main thread to report
            errors.append(err)

    threads = [threading.Thread(target=writer, args=(i,)) for i in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert errors == []
    final = ShapeCache(tmp_path).get(key)["d"]
    assert final.shape == (200, 50) and np.all(final == final[0, 0])
    assert _temp_files(tmp_path) == [] and len(_entry_files(tmp_path)) == 1


# ------------------------------------------------------------------------------- read-only mode


def test_read_only_miss_computes_without_writing(tmp_path, mesh):
    root = tmp_path / "shared"
    cache = ShapeCache(root, writable=False)
    compute = Counting()
    first = cache.get_or_compute("eigenbasis", *mesh, {"k": 5}, 1, compute)
    second = cache.get_or_compute("eigenbasis", *mesh, {"k": 5}, 1, compute)
    assert compute.calls == 2 and not root.exists()
    assert first["evecs"].dtype == np.float32  # same form as a stored entry
    np.testing.assert_array_equal(first["evecs"], second["evecs"])
    with pytest.raises(CacheError, match="read-only"):
        cache.put(CacheKey("x", content_hash(*mesh), {}, 1), {"a": np.ones(2)})


def test_read_only_hits_and_leaves_corrupt_entries_alone(tmp_path, mesh):
    _, compute, path = _populate(tmp_path, mesh)
    reader = ShapeCache(tmp_path, writable=False)
    reader.get_or_compute("eigenbasis", *mesh, {"k": 5}, 1, compute)
    assert compute.calls == 1
    path.write_bytes(b"garbage")
    with pytest.warns(CacheWarning):
        reader.get_or_compute("eigenbasis", *mesh, {"k": 5}, 1, compute)
    assert compute.calls == 2 and path.read_bytes() == b"garbage"


def test_unwritable_root_raises_cache_error(tmp_path, mesh):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    cache = ShapeCache(blocker / "cache")
    with pytest.raises(CacheError, match="cannot write"):
        cache.get_or_compute("x", *mesh, {}, 1, lambda: {"a": np.ones(2)})


# ----------------------------------------------------------------------------- upgrade via find


def test_find_lets_a_larger_eigenbasis_serve_a_smaller_request(tmp_path, mesh):
    cache = ShapeCache(tmp_path)
    h = content_hash(*mesh)
    for k in (8, 20):
        cache.put(CacheKey("eigenbasis", h, {"k": k, "method": "cot"}, 3), {"evecs": np.tile(np.arange(k), (42, 1))})
    cache.put(CacheKey("eigenbasis", h, {"k": 50, "method": "cot"}, 2), {"evecs": np.zeros((42, 50))})  # old version
    cache.put(CacheKey("shot", h, {"k": 50}, 3), {"d": np.zeros(3)})
    (tmp_path / "eigenbasis" / h / f"{'f' * 64}.npz").write_bytes(b"corrupt")  # ignored by find

    def serves(k):
        return lambda key: key.version == 3 and key.params["method"] == "cot" and key.params["k"] >= k

    keys = cache.find("eigenbasis", h, serves(6))
    assert sorted(key.params["k"] for key in keys) == [8, 20]
    best = min(keys, key=lambda key: key.params["k"])
    evecs = cache.get(best)["evecs"][:, :6]
    np.testing.assert_array_equal(evecs[0], np.arange(6))
    assert [key.params["k"] for key in cache.find("eigenbasis", h, serves(10))] == [20]
    assert cache.find("eigenbasis", h, serves(21)) == []
    assert cache.find("eigenbasis", "0" * 64, serves(1)) == []


def test_entries_are_plain_npz_without_pickle(tmp_path, mesh):
    _, _, path = _populate(tmp_path, mesh)
    with zipfile.ZipFile(path) as archive:
        assert sorted(archive.namelist()) == ["__meta__.npy", "evals.npy", "evecs.npy", "idx.npy"]
    with np.load(path, allow_pickle=False) as archive:
        meta = json.loads(archive["__meta__"].tobytes())
    assert json.loads(meta["key"])["params"] == {"k": 5}
    assert meta["arrays"]["evecs"] == ["<f4", [42, 5]]


def test_sparse_round_trip_without_pickle(tmp_path, mesh):
    import scipy.sparse as sp

    rng = np.random.default_rng(SEED)
    dense = rng.standard_normal((7, 5)) * (rng.random((7, 5)) < 0.4)
    csr, csc = sp.csr_array(dense), sp.csc_matrix(dense.T)
    cache = ShapeCache(tmp_path)
    key = CacheKey("grad", content_hash(*mesh), {"k": 3}, 1)
    stored = cache.put(key, {"gx": csr, "gy": csc, "dense": dense})
    again = cache.get(key)
    assert again["gx"].format == "csr" and again["gy"].format == "csc"
    np.testing.assert_array_equal(again["gx"].toarray(), dense.astype(np.float32))
    np.testing.assert_array_equal(again["gy"].toarray(), dense.T.astype(np.float32))
    assert again["gx"].dtype == np.float32 and again["gx"].shape == (7, 5)
    np.testing.assert_array_equal(stored["gy"].toarray(), again["gy"].toarray())
    # plain numeric members only: readable with allow_pickle=False, shape stored as an array
    with np.load(cache.path(key), allow_pickle=False) as archive:
        assert "__sparse__gx__indptr" in archive.files and archive["__sparse__gx__shape"].tolist() == [7, 5]
    # an inconsistent sparse member is corruption: recomputed with a warning
    with np.load(cache.path(key), allow_pickle=False) as archive:
        members = {name: archive[name] for name in archive.files}
    members["__sparse__gx__indices"] = members["__sparse__gx__indices"] + 100
    with open(cache.path(key), "wb") as handle:
        np.savez(handle, **members)
    with pytest.warns(CacheWarning, match="corrupt"):
        assert cache.get(key) is None
