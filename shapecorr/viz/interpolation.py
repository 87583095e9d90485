"""TensorBoard drawing of interpolation sequences (NeuroMorph, and any matcher returning frames).

:func:`log_interpolation` writes the frames of one pair as TensorBoard meshes (``<tag>/t<k>``, colored by the
coordinates of the first frame) and a rendered strip image (``<tag>/strip``, one panel per frame, then the
target in gray), from plain tensors and a logger; with a logger that is not TensorBoard it does nothing::

    from shapecorr.viz.interpolation import log_interpolation

    log_interpolation(self.logger, result.deformation, x.faces, result.times, y.verts, y.faces, step=self.global_step)
"""

from __future__ import annotations

import numpy as np
import torch
from matplotlib.figure import Figure

from shapecorr.errors import ConfigError
from shapecorr.viz.render import (
    DEFAULT_VIEW,
    PANEL_SIZE,
    RENDER_DPI,
    coordinate_colors,
    draw_mesh,
    figure_to_rgb,
)
from shapecorr.viz.tensorboard import _COLOR_MAX, summary_writer

#: Gray level of the target panel of the interpolation strip.
TARGET_GRAY = 0.7


def interpolation_strip_figure(frames, faces, times, verts_y=None, faces_y=None, view=DEFAULT_VIEW) -> Figure:
    """One panel per frame (colored by the coordinates of the first frame), then the target if given.

    Parameters
    ----------
    frames : (T, n, 3) float
    faces : (f, 3) int
    times : (T,) float
    verts_y : (n_y, 3) float, optional
    faces_y : (f_y, 3) int, optional
    view : (elevation, azimuth, vertical axis)

    Returns
    -------
    matplotlib.figure.Figure
    """
    frames = torch.as_tensor(frames).detach().cpu().numpy()
    times = torch.as_tensor(times).detach().cpu().numpy().reshape(-1)
    if frames.ndim != 3 or frames.shape[0] != times.shape[0]:
        raise ConfigError(f"frames (T, n, 3) and times (T,) do not match: {frames.shape}, {times.shape}")
    colors = coordinate_colors(frames[0])
    panels = [(f, faces, colors, f"t = {t:.2f}") for f, t in zip(frames, times)]
    if verts_y is not None:
        vy = torch.as_tensor(verts_y).detach().cpu().numpy()
        panels.append((vy, faces_y, np.full((vy.shape[0], 3), TARGET_GRAY), "target"))
    fig = Figure(figsize=(PANEL_SIZE[0] * len(panels), PANEL_SIZE[1]), dpi=RENDER_DPI)
    for k, (v, f, c, title) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), k + 1, projection="3d")
        draw_mesh(ax, v, torch.as_tensor(f).detach().cpu().numpy(), c, view=view, title=title)
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.0, top=0.9, wspace=0.0)
    return fig


def log_interpolation(logger, frames, faces, times, verts_y=None, faces_y=None, step: int = 0,
                      tag: str = "val/interpolation") -> bool:
    """Log an interpolation sequence as TensorBoard meshes (``<tag>/t<k>``) and a rendered strip image.

    Parameters
    ----------
    logger
        A ``SummaryWriter``, a Lightning ``TensorBoardLogger`` or another logger (then nothing is logged).
    frames : (T, n, 3) float
        Positions of x's vertices at ``times``.
    faces : (f, 3) int
        Faces of x.
    times : (T,) float
    verts_y : (n_y, 3) float, optional
    faces_y : (f_y, 3) int, optional
        The target, drawn as the last panel of the strip.
    step : int
    tag : str

    Returns
    -------
    bool
        Whether something was logged (False without a TensorBoard logger).
    """
    writer = summary_writer(logger)
    if writer is None:
        return False
    frames_t = torch.as_tensor(frames).detach().cpu().float()
    faces_t = torch.as_tensor(faces).detach().cpu().to(torch.int32)
    colors = torch.as_tensor(np.round(coordinate_colors(frames_t[0].numpy()) * _COLOR_MAX).astype(np.uint8))
    for k in range(frames_t.shape[0]):
        writer.add_mesh(f"{tag}/t{k:02d}", vertices=frames_t[k][None], colors=colors[None], faces=faces_t[None],
                        global_step=step)
    fig = interpolation_strip_figure(frames_t, faces_t, times, verts_y, faces_y)
    writer.add_image(f"{tag}/strip", figure_to_rgb(fig), global_step=step, dataformats="HWC")
    return True
