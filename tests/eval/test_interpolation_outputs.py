"""Interpolation outputs: sequence files, interpolation times, deformation metrics, LinearBlend.

Uses the sphere dataset of tests/eval/conftest.py (permuted, rotated unit icospheres, 162 vertices).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from shapecorr.data.io import read_mesh
from shapecorr.data.shape import make_shape
from shapecorr.errors import ConfigError, CorrespondenceError, NumericalError
from shapecorr.eval import export, matcher_run, metrics, pair_pool, protocol, records, reports, scoring
from shapecorr.matching.baselines import DescriptorNN, LinearBlend
from shapecorr.matching.result import MatchResult


class FixedMap:
    """Non-interpolating test matcher: a given map per pair (default the exact map), counting its calls."""

    def __init__(self, shapes, maps=None):
        self.shapes, self.maps, self.calls = shapes, maps or {}, 0

    def match(self, x, y):
        self.calls += 1
        i, j = self.shapes.index(x.name), self.shapes.index(y.name)
        p2p = self.maps.get((i, j), self.shapes.true_map(i, j))
        return MatchResult(p2p=torch.as_tensor(p2p, dtype=torch.int64))


class WrongTimes:
    """An interpolating matcher that ignores the requested times."""

    def match(self, x, y):
        return MatchResult(p2p=torch.arange(x.shape.n_verts))

    def interpolate(self, x, y, times):
        return MatchResult(p2p=torch.arange(x.shape.n_verts), deformation=x.verts[None], times=torch.zeros(1))


def _brute_chamfer(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(a -> b one-sided, two-sided) mean nearest-neighbour distances, by an all-pairs distance matrix."""
    d = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2)
    one = d.min(axis=1).mean()
    return float(one), float(one + d.min(axis=0).mean())


# ------------------------------------------------------------------------------------------- export layer
def test_sequence_layout_times_round_trip_and_extrapolation(tmp_path):
    mesh_v = np.random.default_rng(0).normal(size=(5, 3))
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4]])
    times = [0.0, 0.1, 0.5, 1.0, 1.5, 2.0 / 3.0]  # not sorted on purpose: the writer keeps the given order
    frames = np.stack([mesh_v * (1 + t) for t in times])
    paths = export.write_sequence(tmp_path, "a", "b", frames, faces, times)
    folder = tmp_path / "interp" / "a__b"
    assert [p.name for p in paths] == [f"t_{k:02d}.ply" for k in range(6)]
    assert sorted(p.name for p in folder.iterdir()) == sorted([p.name for p in paths] + ["times.txt"])
    back = export.read_times(folder)
    assert back.tolist() == times  # exact: shortest round-trip decimals ("0.1", not 0.10000000149)
    assert (folder / "times.txt").read_text().splitlines()[1] == "0.1"
    assert export.frame_paths(folder) == list(zip(times, paths))
    for path, frame in zip(paths, frames):
        verts, f = read_mesh(path)
        np.testing.assert_array_equal(verts, frame)  # float64 PLY: lossless
        np.testing.assert_array_equal(f, faces)
    # a shorter sequence in the same folder leaves no stale frame behind
    export.write_sequence(tmp_path, "a", "b", frames[:2], faces, times[:2])
    assert sorted(p.name for p in folder.glob("t_*.ply")) == ["t_00.ply", "t_01.ply"]
    assert export.read_times(folder).tolist() == times[:2]


def test_frame_names_widen_beyond_100_frames():
    assert export.frame_name(0, 1) == "t_00.ply" and export.frame_name(99, 100) == "t_99.ply"
    assert export.frame_name(7, 101) == "t_007.ply" and export.frame_name(100, 101) == "t_100.ply"


def test_sequence_writer_errors(tmp_path):
    faces = np.array([[0, 1, 2]])
    good = np.zeros((2, 3, 3))
    with pytest.raises(CorrespondenceError, match="need 2 times"):
        export.write_sequence(tmp_path, "a", "b", good, faces, [0.0])
    with pytest.raises(CorrespondenceError, match=r"\(T, n, 3\)"):
        export.write_sequence(tmp_path, "a", "b", np.zeros((3, 3)), faces, [0.0])
    bad = good.copy()
    bad[1, 0, 0] = np.nan
    with pytest.raises(NumericalError, match="NaN"):
        export.write_sequence(tmp_path, "a", "b", bad, faces, [0.0, 1.0])
    assert not (tmp_path / "interp" / "a__b" / "times.txt").exists()
    with pytest.raises(CorrespondenceError, match="no times.txt"):
        export.read_times(tmp_path / "interp" / "a__b")
    (tmp_path / "times.txt").write_text("0.0\nabc\n")
    with pytest.raises(CorrespondenceError, match="unreadable frame times"):
        export.read_times(tmp_path)
    (tmp_path / "times.txt").write_text("0.0\n1.0\n")
    with pytest.raises(CorrespondenceError, match="missing"):
        export.frame_paths(tmp_path)


def test_frames_are_written_in_input_units(tmp_path):
    rng = np.random.default_rng(1)
    raw = rng.normal(size=(4, 3)) * 30.0 + 100.0
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]])
    shape = make_shape(raw, faces, "a")
    assert shape.scale != 1.0
    export.write_sequence(tmp_path, "a", "b", shape.verts[None], faces, [0.0], shape=shape)
    np.testing.assert_allclose(read_mesh(tmp_path / "interp" / "a__b" / "t_00.ply")[0], raw, rtol=1e-6)


# --------------------------------------------------------------------------------------------- times
def test_interp_times_validation_and_unit_time():
    assert matcher_run.check_interp_times([0, 0.5, 1.5]) == (0.0, 0.5, 1.5)
    for bad in ([], [0.0, 0.0], [1.0, 0.5], [0.0, float("nan")], ["a"], 3.0):
        with pytest.raises(ConfigError, match="interp_times"):
            matcher_run.check_interp_times(bad)
    with pytest.raises(ConfigError, match="interp_times"):
        protocol.EvalSettings(interp_times=(1.0, 0.0))
    all_times, requested = matcher_run.with_unit_time([0.0, 0.5, 1.5])
    assert all_times == (0.0, 0.5, 1.0, 1.5) and requested.tolist() == [0, 1, 3]
    all_times, requested = matcher_run.with_unit_time([0.25, 1.0])
    assert all_times == (0.25, 1.0) and requested.tolist() == [0, 1]
    assert matcher_run.unit_time_index(np.float32([0.0, 1.0])) == 1
    assert matcher_run.unit_time_index([0.0, 0.99]) is None


# ---------------------------------------------------------------------------------------- LinearBlend
def test_linear_blend_frames(spheres):
    x, y = spheres[0], spheres[1]
    blend = LinearBlend(FixedMap(spheres))
    assert matcher_run.interpolates(blend) and not matcher_run.interpolates(FixedMap(spheres))
    p2p = torch.as_tensor(spheres.true_map(0, 1))
    result = blend.interpolate(x, y, torch.tensor([0.0, 0.5, 1.0, 2.0]))
    assert torch.equal(result.p2p, p2p) and result.deformation.shape == (4, x.shape.n_verts, 3)
    assert torch.equal(result.deformation[0], x.verts)  # t = 0 is x, exactly
    torch.testing.assert_close(result.deformation[2], y.verts[p2p])  # t = 1 lands on y's vertices
    torch.testing.assert_close(result.deformation[1], 0.5 * (x.verts + y.verts[p2p]))
    torch.testing.assert_close(result.deformation[3], 2 * y.verts[p2p] - x.verts)  # extrapolation
    default = blend.match(x, y)
    assert default.times.tolist() == [0.0, 0.25, 0.5, 0.75, 1.0] and default.deformation.shape[0] == 5
    assert LinearBlend(FixedMap(spheres), interp_times=[0.0, 1.0]).match(x, y).times.tolist() == [0.0, 1.0]
    assert LinearBlend(DescriptorNN("hks")).required_operators == {"hks": {}}
    with pytest.raises(ConfigError, match="wraps a matcher"):
        LinearBlend(object())
    with pytest.raises(NumericalError, match="finite"):
        blend.interpolate(x, y, torch.tensor([0.0, float("inf")]))


def test_run_matcher_adds_unit_time_and_exports_only_requested(spheres):
    x, y = spheres[0], spheres[1]
    inner = FixedMap(spheres)
    run = matcher_run.run_matcher(LinearBlend(inner), x, y, (0.0, 0.5, 1.5))
    assert run.result.times.tolist() == [0.0, 0.5, 1.0, 1.5]
    frames, times = run.sequence()
    assert times.tolist() == [0.0, 0.5, 1.5] and frames.shape[0] == 3
    torch.testing.assert_close(frames[2], run.result.deformation[3])
    # a non-interpolating matcher ignores interp_times: match() only, no frames
    plain = matcher_run.run_matcher(inner, x, y, (0.0, 0.5, 1.5))
    assert plain.result.deformation is None and plain.sequence() is None
    with pytest.raises(CorrespondenceError, match="was asked for frames at"):
        matcher_run.run_matcher(WrongTimes(), x, y, (0.0, 1.0))


def test_linear_blend_chamfer_and_distortion_by_hand(spheres, tmp_path):
    """A non-surjective map: X(1) = y[p2p] covers part of y, so the two-sided Chamfer distance is not 0."""
    rng = np.random.default_rng(3)
    n = spheres[0].shape.n_verts
    p2p = rng.integers(0, n, n)
    blend = LinearBlend(FixedMap(spheres, {(0, 1): p2p}))
    settings = protocol.EvalSettings(interp_times=(0.0, 0.5, 1.5))
    record = pair_pool.evaluate_pairs(blend, spheres, [(0, 1)], tmp_path, settings, progress=False)[0]
    x, y = spheres[0], spheres[1]
    vy, vx, fx = y.verts.numpy().astype(np.float64), x.verts.numpy().astype(np.float64), x.faces.numpy()
    sqrt_area = np.sqrt(metrics.surface_area(vy, y.faces.numpy()))
    one, two = _brute_chamfer(vy[p2p], vy)
    assert one == 0.0 and two > 0.01
    assert record.chamfer_one_sided == pytest.approx(0.0, abs=1e-7)
    assert record.chamfer == pytest.approx(two / sqrt_area, rel=1e-5)
    # conformal distortion along the sequence: frames t = 0, 0.5 and the added t = 1, not the extrapolated 1.5
    frames = [vx + t * (vy[p2p] - vx) for t in (0.0, 0.5, 1.0)]
    expected = np.mean([metrics.mean_conformal_distortion(vx, fx, f) for f in frames])
    assert record.deformation_conformal_distortion == pytest.approx(expected, rel=1e-5)
    with_extrapolated = np.mean([metrics.mean_conformal_distortion(vx, fx, vx + t * (vy[p2p] - vx))
                                 for t in (0.0, 0.5, 1.0, 1.5)])
    assert record.deformation_conformal_distortion != pytest.approx(with_extrapolated, rel=1e-3)
    folder = tmp_path / "interp" / "s0__s1"
    assert sorted(p.name for p in folder.glob("t_*.ply")) == ["t_00.ply", "t_01.ply", "t_02.ply"]
    assert export.read_times(folder).tolist() == [0.0, 0.5, 1.5]
    np.testing.assert_allclose(read_mesh(folder / "t_02.ply")[0], vx + 1.5 * (vy[p2p] - vx), atol=1e-6)


def test_score_deformation_needs_a_unit_frame(spheres):
    x, y = spheres[0], spheres[1]
    frames = torch.stack([x.verts, x.verts])
    with pytest.raises(CorrespondenceError, match="no frame at t = 1"):
        scoring.score_deformation(frames, x, y, times=[0.0, 0.5])
    with pytest.raises(CorrespondenceError, match="2 frames but 3 times"):
        scoring.score_deformation(frames, x, y, times=[0.0, 0.5, 1.0])
    # without times the last frame is compared with y (frames from match())
    assert scoring.score_deformation(frames, x, y)["chamfer_one_sided"] > 0


def test_write_interp_false_and_non_interpolating_records(spheres, tmp_path):
    settings = protocol.EvalSettings(interp_times=(0.0, 1.0), write_interp=False)
    record = pair_pool.evaluate_pairs(LinearBlend(FixedMap(spheres)), spheres, [(0, 1)], tmp_path / "a", settings,
                                     progress=False)[0]
    assert record.chamfer == pytest.approx(0.0, abs=1e-6) and not (tmp_path / "a" / "interp").exists()
    plain = pair_pool.evaluate_pairs(FixedMap(spheres), spheres, [(0, 1)], tmp_path / "b", settings, progress=False)[0]
    assert plain.chamfer is None and plain.deformation_conformal_distortion is None


# ---------------------------------------------------------------------------------------------- reports
def test_reports_interpolation_keys_and_summary():
    def record(chamfer, distortion):
        return records.PairRecord("a", "b", 0.1, 0.1, 2, 1.0, 0.1, 0.3, chamfer=chamfer, chamfer_one_sided=chamfer,
                                   deformation_conformal_distortion=distortion)

    errors = [np.full(2, 0.1), np.full(2, 0.1)]
    out = reports.aggregate([record(0.02, 0.5), record(0.04, 1.5)], errors)
    assert out["mean_chamfer"] == pytest.approx(0.03) and out["mean_deformation_conformal_distortion"] == 1.0
    assert out["n_pairs_interpolated"] == 2 and "mean_deformation_conformal_distortion" in out["conventions"]
    assert out["mean_conformal_distortion"] == pytest.approx(0.3)  # the map's, unchanged
    text = reports.summary(out, "OUT")
    assert "conformal distortion 1.0000" in text and "Chamfer X(1)-Y 0.0300" in text and text.endswith("-> OUT")
    plain = reports.aggregate([record(None, None)] * 2, errors)
    for key in ("mean_chamfer", "mean_chamfer_one_sided", "mean_deformation_conformal_distortion",
                "n_pairs_interpolated"):
        assert key not in plain
    assert "Chamfer" not in reports.summary(plain)
