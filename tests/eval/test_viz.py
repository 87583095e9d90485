"""Headless renders and TensorBoard helpers (shapecorr.viz)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from shapecorr.errors import CorrespondenceError, InvalidMeshError
from shapecorr.viz import render
from shapecorr.viz.tensorboard import log_correspondence_meshes, log_pck_figure, summary_writer


def test_coordinate_colors_and_transfer():
    verts = np.array([[0.0, 0, 0], [2, 1, 4], [1, 0.5, 2]])
    colors = render.coordinate_colors(verts)
    np.testing.assert_allclose(colors, [[0, 0, 0], [1, 1, 1], [0.5, 0.5, 0.5]])
    np.testing.assert_allclose(render.transfer_colors(colors, [1, 1, 0]), colors[[1, 1, 0]])
    with pytest.raises(CorrespondenceError):
        render.transfer_colors(colors, [3])


def test_shading_is_bounded_and_two_sided():
    verts = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    white = np.ones((3, 3))
    front = render.shaded_face_colors(verts, np.array([[0, 1, 2]]), white)
    back = render.shaded_face_colors(verts, np.array([[0, 2, 1]]), white)
    np.testing.assert_allclose(front, back)
    assert np.all((front >= render.AMBIENT) & (front <= 1.0))


def _halves(path):
    img = np.asarray(Image.open(path).convert("RGB"), dtype=np.float64)
    w = img.shape[1] // 2
    return img, img[:, :w], img[:, w : 2 * w]


def test_render_correspondence_shows_errors(spheres, tmp_path):
    """Identity map of a shape onto itself: both panels are the same picture; a mirrored map is not."""
    x = spheres[0]
    v, f = x.verts.numpy(), x.faces.numpy()
    ident = np.arange(len(v))
    path = render.render_correspondence(tmp_path / "ok.png", v, f, v, f, ident, names=("", ""))
    img, left, right = _halves(path)
    assert img.shape[0] > 100 and img.std() > 10  # something was drawn
    assert np.abs(left - right).mean() < 1.0
    mirror = spheres.mirror_map(0, 0)
    flipped = render.render_correspondence(tmp_path / "flip.png", v, f, v, f, mirror, names=("", ""))
    _, left_m, right_m = _halves(flipped)
    assert np.abs(left_m - right_m).mean() > 5 * max(np.abs(left - right).mean(), 0.1)
    with pytest.raises(CorrespondenceError):
        render.correspondence_figure(v, f, v, f, ident[:-1])
    with pytest.raises(InvalidMeshError):
        render.correspondence_figure(np.full_like(v, np.nan), f, v, f, ident)


def test_figure_to_rgb(spheres):
    x = spheres[0]
    fig = render.correspondence_figure(x.verts, x.faces, x.verts, x.faces, torch.arange(x.shape.n_verts))
    rgb = render.figure_to_rgb(fig)
    assert rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3


def test_tensorboard_helpers(spheres, tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from torch.utils.tensorboard import SummaryWriter

    x, y = spheres[0], spheres[1]
    p2p = torch.from_numpy(spheres.true_map(0, 1))
    with SummaryWriter(tmp_path) as writer:
        assert log_pck_figure(writer, np.linspace(0, 0.2, 100), step=3)
        assert log_correspondence_meshes(writer, x.verts, x.faces, y.verts, y.faces, p2p, step=3)
    acc = EventAccumulator(str(tmp_path), size_guidance={"tensors": 0, "images": 0}).Reload()
    tags = acc.Tags()
    assert {"val/pck", "val/correspondence/render"} <= set(tags["images"])
    mesh_tags = [t for t in tags["tensors"] if t.startswith("val/correspondence/")]
    assert any("source" in t for t in mesh_tags) and any("target" in t for t in mesh_tags)
    assert acc.Images("val/pck")[0].step == 3


def test_tensorboard_helpers_with_other_loggers(spheres, tmp_path):
    """Lightning loggers are recognized by their ``experiment`` (TensorBoardLogger: a SummaryWriter; CSVLogger:
    not one); stand-ins keep this test free of the slow Lightning import."""
    from torch.utils.tensorboard import SummaryWriter

    class LoggerLike:
        def __init__(self, experiment):
            self.experiment = experiment

    x = spheres[0]
    assert log_pck_figure(None, [0.1], step=0) is False
    assert log_pck_figure(LoggerLike(object()), [0.1], step=0) is False  # e.g. CSVLogger's experiment
    with SummaryWriter(tmp_path) as writer:
        tb = LoggerLike(writer)
        assert summary_writer(tb) is writer
        ident = torch.arange(162)
        assert log_correspondence_meshes(tb, x.verts, x.faces, x.verts, x.faces, ident, 0, render_image=False)
