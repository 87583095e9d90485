"""Per-pair evaluation, resumption, parallel workers and DDP sharding (shapecorr.eval protocol, pair_pool, sharding)."""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest
import torch

from shapecorr.errors import ConfigError, CorrespondenceError
from shapecorr.eval import metrics, pair_pool, scoring, sharding
from shapecorr.eval.records import is_done, load_record, record_paths
from shapecorr.eval.export import map_paths
from shapecorr.matching.result import MatchResult


class MapMatcher:
    """Test matcher: a map chosen by ``kind`` from the sphere dataset's exact maps; counts its calls."""

    def __init__(self, shapes, kind: str = "true", frames: int = 0):
        self.shapes, self.kind, self.frames, self.calls = shapes, kind, frames, 0

    def match(self, x, y):
        self.calls += 1
        i, j = self.shapes.index(x.name), self.shapes.index(y.name)
        p2p = torch.from_numpy(getattr(self.shapes, f"{self.kind}_map")(i, j)).to(x.verts.device)
        if not self.frames:
            return MatchResult(p2p=p2p)
        t = torch.linspace(0.0, 1.0, self.frames)
        target = y.verts[p2p]
        frames = (1 - t)[:, None, None] * x.verts[None] + t[:, None, None] * target[None]
        return MatchResult(p2p=p2p, deformation=frames, times=t)


class BadSizeMatcher:
    def match(self, x, y):
        return MatchResult(p2p=torch.zeros(x.shape.n_verts - 1, dtype=torch.int64))


def test_score_map_exact_mirror_and_antipodal(spheres):
    x, y = spheres[0], spheres[1]
    dist = spheres.geodesics(1)
    exact = scoring.score_map(spheres.true_map(0, 1), x, y, dist)
    assert np.all(exact["errors"] == 0.0) and exact["errors"].shape == (len(x.corres),)
    assert exact["errors_sym"].mean() > 0.1  # the true map is far from the mirrored ground truth
    assert exact["conformal_distortion"] == pytest.approx(0.0, abs=1e-5)  # a rotation is an isometry

    mirrored = scoring.score_map(spheres.mirror_map(0, 1), x, y, dist)
    assert np.all(mirrored["errors_sym"] == 0.0)
    assert mirrored["errors"].mean() > 0.1

    antipodal = scoring.score_map(spheres.antipodal_map(0, 1), x, y, dist)
    sqrt_area = math.sqrt(metrics.surface_area(y.verts.numpy(), y.faces.numpy()))
    np.testing.assert_allclose(antipodal["errors"], math.pi / sqrt_area, rtol=1e-5)


def test_score_map_rejects_wrong_size(spheres):
    with pytest.raises(CorrespondenceError, match="entries but s0 has 162 vertices"):
        scoring.score_map(np.zeros(10, dtype=np.int64), spheres[0], spheres[1], spheres.geodesics(1))


def test_evaluate_pairs_writes_records_and_resumes(spheres, tmp_path):
    pairs = [(0, 1), (1, 0), (2, 0), (1, 2)]
    matcher = MapMatcher(spheres)
    records = pair_pool.evaluate_pairs(matcher, spheres, pairs, tmp_path, progress=False)
    assert matcher.calls == 4
    assert [(r.source, r.target) for r in records] == [("s0", "s1"), ("s1", "s0"), ("s2", "s0"), ("s1", "s2")]
    assert all(r.mean_error == 0.0 and r.median_error == 0.0 and r.n_points == len(spheres[0].corres) for r in records)
    assert all(r.mean_error_sym > 0.1 for r in records)
    # maps: zero-based text, one line per source vertex, and the same array as .npy
    txt, npy = map_paths(tmp_path, "s2", "s0")
    lines = txt.read_text().split()
    assert len(lines) == 162 and [int(a) for a in lines] == spheres.true_map(2, 0).tolist()
    np.testing.assert_array_equal(np.load(npy), spheres.true_map(2, 0))
    record, errors, errors_sym = load_record(tmp_path, "s2", "s0")
    assert record == records[2] and errors.shape == (len(spheres[0].corres),) and errors_sym is not None

    # re-run: everything is done, nothing is matched again
    again = pair_pool.evaluate_pairs(matcher, spheres, pairs, tmp_path, progress=False)
    assert matcher.calls == 4 and again == records
    # delete one record: only that pair is recomputed
    record_paths(tmp_path, "s1", "s0")[0].unlink()
    pair_pool.evaluate_pairs(matcher, spheres, pairs, tmp_path, progress=False)
    assert matcher.calls == 5


def test_geodesics_are_loaded_once_per_target(spheres, tmp_path):
    pairs = [(0, 1), (2, 1), (1, 0), (2, 0)]
    pair_pool.evaluate_pairs(MapMatcher(spheres), spheres, pairs, tmp_path, progress=False)
    assert spheres.geodesic_calls == 2  # pairs are grouped by target


def test_parallel_workers_give_the_same_records(spheres, tmp_path):
    pairs = [(i, j) for i in range(3) for j in range(3) if i != j]
    serial = pair_pool.evaluate_pairs(MapMatcher(spheres, "mirror"), spheres, pairs, tmp_path / "a", progress=False)
    parallel = pair_pool.evaluate_pairs(
        MapMatcher(spheres, "mirror"), spheres, pairs, tmp_path / "b", workers=2, start_method="fork", progress=False
    )
    def strip(rs):
        return [(r.source, r.target, r.mean_error, r.mean_error_sym, r.conformal_distortion) for r in rs]

    assert strip(serial) == strip(parallel)
    assert all(r.mean_error_sym == 0.0 for r in parallel)


class ThreadCountMatcher(MapMatcher):
    """Records the torch thread count it runs with in ``<log_dir>/<pid>.txt``."""

    def __init__(self, shapes, log_dir):
        super().__init__(shapes)
        self.log_dir = log_dir

    def match(self, x, y):
        (self.log_dir / f"{os.getpid()}.txt").write_text(str(torch.get_num_threads()))
        return super().match(x, y)


def test_workers_never_get_more_threads_than_the_parent(spheres, tmp_path, monkeypatch):
    monkeypatch.setattr(os, "cpu_count", lambda: 8)  # a share of 4 CPUs per worker ...
    log = tmp_path / "threads"
    log.mkdir()
    before = torch.get_num_threads()
    torch.set_num_threads(1)  # ... but the parent runs with OMP_NUM_THREADS=1
    try:
        pair_pool.evaluate_pairs(ThreadCountMatcher(spheres, log), spheres, [(0, 1), (1, 0), (0, 2), (2, 0)],
                                tmp_path / "out", workers=2, start_method="fork", progress=False)
    finally:
        torch.set_num_threads(before)
    counts = [int(f.read_text()) for f in log.iterdir()]
    assert counts and all(c == 1 for c in counts)


def test_errors_propagate_from_workers(spheres, tmp_path):
    with pytest.raises(CorrespondenceError, match="one entry per source vertex"):
        pair_pool.evaluate_pairs(BadSizeMatcher(), spheres, [(0, 1)], tmp_path, progress=False)
    with pytest.raises(CorrespondenceError, match="one entry per source vertex"):
        pair_pool.evaluate_pairs(
            BadSizeMatcher(), spheres, [(0, 1), (1, 0)], tmp_path, workers=2, start_method="fork", progress=False
        )
    assert not is_done(tmp_path, "s0", "s1")  # nothing half-written is taken as done
    with pytest.raises(ConfigError, match="start_method"):
        pair_pool.evaluate_pairs(BadSizeMatcher(), spheres, [(0, 1)], tmp_path, start_method="thread", progress=False)


def test_deformation_metrics_and_sequences(spheres, tmp_path):
    records = pair_pool.evaluate_pairs(MapMatcher(spheres, frames=3), spheres, [(0, 1)], tmp_path, progress=False)
    r = records[0]
    # the last frame sits exactly on the target's vertices
    assert r.chamfer_one_sided == pytest.approx(0.0, abs=1e-6)
    assert r.chamfer == pytest.approx(0.0, abs=1e-6)
    # the middle frame (a chord average) shrinks the sphere; the final frame is a rotated copy: no change
    assert r.volume_change == pytest.approx(0.0, abs=1e-4)
    # frames 0 and 2 are rigid copies (distortion 0); the linear blend in the middle is not conformal
    x, y = spheres[0], spheres[1]
    middle = 0.5 * (x.verts.numpy() + y.verts.numpy()[spheres.true_map(0, 1)])
    expected = metrics.mean_conformal_distortion(x.verts.numpy(), x.faces.numpy(), middle) / 3
    assert 0 < r.deformation_conformal_distortion == pytest.approx(expected, rel=1e-4, abs=1e-6)
    frames = sorted((tmp_path / "interp" / "s0__s1").glob("t_*.ply"))
    assert [f.name for f in frames] == ["t_00.ply", "t_01.ply", "t_02.ply"]
    assert (tmp_path / "interp" / "s0__s1" / "times.txt").read_text().split() == ["0.0", "0.5", "1.0"]


def test_record_json_is_readable(spheres, tmp_path):
    pair_pool.evaluate_pairs(MapMatcher(spheres), spheres, [(0, 2)], tmp_path, progress=False)
    data = json.loads(record_paths(tmp_path, "s0", "s2")[0].read_text())
    assert data["source"] == "s0" and data["target"] == "s2" and data["seconds"] >= 0.0


def test_shard_pairs_partition():
    pairs = [(i, j) for i in range(7) for j in range(7) if i != j]  # 42 pairs
    for world in (1, 2, 3, 5, 8):
        shards = [sharding.shard_pairs(pairs, r, world) for r in range(world)]
        flat = [p for s in shards for p in s]
        assert sorted(flat) == sorted(pairs) and len(flat) == len(set(flat))  # disjoint cover
        sizes = [len(s) for s in shards]
        assert max(sizes) - min(sizes) <= 1
        for s in shards:  # input order kept
            assert s == sorted(s, key=pairs.index)
    with pytest.raises(ConfigError):
        sharding.shard_pairs(pairs, 2, 2)


def test_distributed_context_from_environment(monkeypatch):
    for var in ("RANK", "LOCAL_RANK", "WORLD_SIZE"):
        monkeypatch.delenv(var, raising=False)
    assert sharding.distributed_context() == (0, 1)
    monkeypatch.setenv("WORLD_SIZE", "4")
    monkeypatch.setenv("LOCAL_RANK", "3")
    assert sharding.distributed_context() == (3, 4)
    monkeypatch.setenv("RANK", "1")  # the global rank wins over the local one
    assert sharding.distributed_context() == (1, 4)
    monkeypatch.setenv("RANK", "4")
    with pytest.raises(ConfigError, match="rank 4 of world size 4"):
        sharding.distributed_context()
