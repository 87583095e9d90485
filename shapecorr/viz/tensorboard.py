"""TensorBoard helpers shared by every LightningModule: a PCK figure and a colored correspondence.

Both functions take a ``SummaryWriter``, a Lightning ``TensorBoardLogger`` (its ``.experiment`` is the
writer) or anything else with an ``experiment`` attribute; with another logger (CSV, none) they do nothing
and return False, so a module can call them unconditionally::

    from shapecorr.viz.tensorboard import log_correspondence_meshes, log_pck_figure

    def on_validation_epoch_end(self):
        log_pck_figure(self.logger, errors, self.global_step)                # errors: (m,) pooled
        log_correspondence_meshes(self.logger, x.verts, x.faces, y.verts, y.faces, p2p, self.global_step)
"""

from __future__ import annotations

import numpy as np
import torch

from shapecorr.eval import metrics
from shapecorr.viz.pck import pck_figure
from shapecorr.viz.render import DEFAULT_VIEW, coordinate_colors, correspondence_figure, figure_to_rgb, transfer_colors

#: 8-bit color scale of TensorBoard's mesh plugin.
_COLOR_MAX = 255


def summary_writer(logger):
    """The ``SummaryWriter`` behind a logger, or None when it is not a TensorBoard logger."""
    if logger is None:
        return None
    if hasattr(logger, "add_figure") and hasattr(logger, "add_mesh"):
        return logger
    writer = getattr(logger, "experiment", None)
    if writer is not None and hasattr(writer, "add_figure") and hasattr(writer, "add_mesh"):
        return writer
    return None


def log_pck_figure(logger, errors, step: int, tag: str = "val/pck", label: str = "val", thresholds=None) -> bool:
    """Log the PCK curve of pooled per-point errors as a figure.

    Parameters
    ----------
    logger : SummaryWriter | TensorBoardLogger | other
    errors : (m,) float
        Geodesic errors (fractions of sqrt(area)) of all reference points of the validation pairs.
    step : int
    tag, label : str
        Figure tag and curve label.
    thresholds : (t,) float, optional
        Default 0..0.25.

    Returns
    -------
    bool
        Whether something was logged.
    """
    writer = summary_writer(logger)
    if writer is None:
        return False
    errors = metrics.as_numpy(errors, np.float64).ravel()
    t, frac = metrics.pck_curve(errors, thresholds)
    writer.add_figure(tag, pck_figure({label: (t, frac, float(errors.mean()))}), global_step=step, close=True)
    return True


def log_correspondence_meshes(
    logger,
    verts_x,
    faces_x,
    verts_y,
    faces_y,
    p2p,
    step: int,
    tag: str = "val/correspondence",
    render_image: bool = True,
    view=DEFAULT_VIEW,
) -> bool:
    """Log a map x -> y as two colored meshes (``add_mesh``) and, optionally, a rendered image.

    The target is colored by its coordinates and the source gets the colors through the map (see
    :mod:`shapecorr.viz.render`). Tags: ``<tag>/source``, ``<tag>/target`` (meshes), ``<tag>/render`` (image).

    Parameters
    ----------
    logger : SummaryWriter | TensorBoardLogger | other
    verts_x : (n_x, 3) float
    faces_x : (f_x, 3) int
    verts_y : (n_y, 3) float
    faces_y : (f_y, 3) int
    p2p : (n_x,) int
        Map x -> y.
    step : int
    tag : str
    render_image : bool
        Also log the headless texture-transfer render.
    view : (elevation, azimuth, vertical axis)

    Returns
    -------
    bool
        Whether something was logged.
    """
    writer = summary_writer(logger)
    if writer is None:
        return False
    colors_y = coordinate_colors(verts_y)
    colors_x = transfer_colors(colors_y, p2p)
    for name, verts, faces, colors in (("source", verts_x, faces_x, colors_x), ("target", verts_y, faces_y, colors_y)):
        writer.add_mesh(
            f"{tag}/{name}",
            vertices=torch.as_tensor(metrics.as_numpy(verts, np.float32))[None],
            colors=torch.as_tensor(np.round(colors * _COLOR_MAX).astype(np.uint8))[None],
            faces=torch.as_tensor(metrics.as_numpy(faces).astype(np.int32))[None],
            global_step=step,
        )
    if render_image:
        fig = correspondence_figure(verts_x, faces_x, verts_y, faces_y, p2p, view=view)
        writer.add_image(f"{tag}/render", figure_to_rgb(fig), global_step=step, dataformats="HWC")
    return True
