"""Aggregation and report files (shapecorr.eval.reports)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from shapecorr.errors import CorrespondenceError
from shapecorr.eval import reports
from shapecorr.eval.records import PairRecord
from shapecorr.viz import pck


def _record(source, target, mean, sym=None, seconds=1.0, chamfer=None):
    return PairRecord(source, target, mean, mean, 4, seconds, 0.5, 0.2, mean_error_sym=sym, chamfer=chamfer)


def test_aggregate_hand_computed():
    errors = [np.array([0.0, 0.0, 0.1, 0.1]), np.array([0.2, 0.2, 0.2, 0.6])]
    records = [_record("a", "b", 0.05, sym=0.3, seconds=1.0), _record("b", "a", 0.3, sym=0.1, seconds=3.0)]
    sym = [np.full(4, 0.3), np.full(4, 0.1)]
    out = reports.aggregate(records, errors, sym)
    assert out["n_pairs"] == 2 and out["n_points"] == 8
    assert out["mean_geodesic_error"] == pytest.approx(0.175)  # mean of the per-pair means
    assert out["median_geodesic_error"] == pytest.approx(0.15)  # pooled: 0,0,.1,.1,.2,.2,.2,.6
    assert out["seconds_per_pair"] == pytest.approx(2.0) and out["median_seconds_per_pair"] == pytest.approx(2.0)
    assert out["mean_conformal_distortion"] == pytest.approx(0.2)
    assert out["mean_geodesic_error_sym"] == pytest.approx(0.2) and out["n_pairs_sym"] == 2
    fractions = np.asarray(out["pck"]["fractions"])
    assert fractions[0] == pytest.approx(0.25) and fractions[-1] == pytest.approx(7 / 8)
    assert 0 < out["pck_auc"] < 1
    assert "mean_chamfer" not in out  # no interpolating matcher
    json.dumps(out)  # serializable


def test_aggregate_symmetric_only_where_present():
    errors = [np.zeros(4), np.zeros(4)]
    records = [_record("a", "b", 0.0, sym=0.5, chamfer=0.1), _record("b", "a", 0.0, chamfer=0.3)]
    out = reports.aggregate(records, errors, [np.full(4, 0.5), None])
    assert out["mean_geodesic_error_sym"] == pytest.approx(0.5) and out["n_pairs_sym"] == 1
    assert out["mean_chamfer"] == pytest.approx(0.2)
    assert out["pck_auc"] == pytest.approx(1.0) and out["mean_geodesic_error"] == 0.0
    no_sym = reports.aggregate(records, errors)
    assert "mean_geodesic_error_sym" not in no_sym
    with pytest.raises(CorrespondenceError):
        reports.aggregate([], [])


def test_per_pair_csv_round_trip(tmp_path):
    records = [_record("a", "b", 0.05, sym=0.3), _record("b", "a", 0.25)]
    path = reports.write_per_pair_csv(tmp_path / "per_pair.csv", records)
    header = path.read_text().splitlines()[0].split(",")
    assert header[:4] == ["source", "target", "mean_error", "seconds"]
    back = reports.read_per_pair_csv(path)
    assert back == records  # floats round-trip through repr, None through empty cells


def test_metrics_json_and_pck_png(tmp_path):
    errors = [np.linspace(0, 0.3, 50)]
    out = reports.aggregate([_record("a", "b", 0.15, sym=0.2)], errors, [np.linspace(0, 0.4, 50)])
    js = reports.write_metrics_json(tmp_path / "metrics.json", out)
    assert json.loads(js.read_text())["mean_geodesic_error"] == pytest.approx(0.15)
    png = pck.write_pck_png(tmp_path / "pck.png", out, label="test")
    with Image.open(png) as img:
        assert img.format == "PNG" and img.size[0] > 200
    fig = pck.pck_figure({"m": (np.asarray(out["pck"]["thresholds"]), np.asarray(out["pck"]["fractions"]), 0.15)})
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert labels == [f"m: mean 0.1500, AUC {out['pck_auc']:.3f}"]  # the mean is in the legend


def test_peak_memory_is_positive():
    mem = reports.peak_memory_mb()
    assert mem["peak_memory_mb"] >= mem["peak_memory_self_mb"] > 10  # a Python process with numpy/torch


def test_interpolation_curves_mean_per_time_skipping_missing_values(tmp_path):
    from shapecorr.viz.interp_curves import write_interp_curves_png

    a = _record("a", "b", 0.1)
    a.curve_times, a.curve_conformal_distortion = [0.0, 0.5, 1.0], [0.0, 1.0, 2.0]
    a.curve_volume_score = [0.0, 0.2, 0.4]
    b = _record("b", "a", 0.2)
    # a second pair with an extra frame at 1.5, a time carried in float32 and an inverted frame (no volume score)
    b.curve_times = [0.0, float(np.float32(0.5)), 1.0, 1.5]
    b.curve_conformal_distortion, b.curve_volume_score = [0.0, 3.0, 4.0, 5.0], [0.0, None, 0.6, 0.8]
    curves = reports.interpolation_curves([a, b, _record("c", "a", 0.3)])
    assert curves["times"] == [0.0, 0.5, 1.0, 1.5] and curves["n_pairs"] == [2, 2, 2, 1]
    assert curves["conformal_distortion"] == pytest.approx([0.0, 2.0, 3.0, 5.0])
    assert curves["volume_score"] == pytest.approx([0.0, 0.2, 0.5, 0.8])
    assert reports.interpolation_curves([_record("c", "a", 0.3)]) is None
    path = write_interp_curves_png(tmp_path / "interp_curves.png", {"interp_curves": curves, "n_pairs": 3})
    assert Image.open(path).size[0] > 100
