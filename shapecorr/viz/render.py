"""Headless renders of colored meshes and of correspondences ("texture transfer" images).

A correspondence x -> y is shown by coloring the target y with a smooth function of its position and pulling
the colors back to the source through the map: vertex i of x gets the color of ``p2p[i]``. A correct map
gives x the same smooth color layout as y; errors show as color jumps, and a left/right symmetry flip as
swapped colors on the limbs (the red channel follows the first coordinate).

Rendering uses matplotlib's Agg canvas through :class:`matplotlib.figure.Figure` (no pyplot, no display):
each mesh is drawn as a ``Poly3DCollection`` with per-face colors and a simple two-sided Lambert shading
computed here (mplot3d offers shading only for single-colored surfaces).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

from shapecorr.data.cache import atomic_open
from shapecorr.errors import CorrespondenceError, InvalidMeshError
from shapecorr.geometry.mesh import as_numpy as _np

#: Camera: elevation and azimuth in degrees and the axis pointing up (FAUST/SCAPE shapes stand along +y;
#: azimuth 0 then shows a FAUST person from the front).
DEFAULT_VIEW = (10.0, 0.0, "y")
#: Magnification of the 3-D axes box inside its panel (1 = matplotlib's default, which leaves wide margins).
RENDER_ZOOM = 1.6
#: Light direction in view-independent world coordinates (towards the viewer and slightly from above).
LIGHT_DIRECTION = (0.3, 0.5, 1.0)
#: Shading: ambient fraction of the color, the rest scaled by |cos(normal, light)|.
AMBIENT = 0.45
#: Panel size in inches and the resolution of saved images.
PANEL_SIZE = (3.2, 4.0)
RENDER_DPI = 100


def coordinate_colors(verts) -> np.ndarray:
    """A smooth color per vertex: its coordinates scaled to [0, 1] per axis (x -> red, y -> green, z -> blue).

    Parameters
    ----------
    verts : (n, 3) float

    Returns
    -------
    (n, 3) float64 in [0, 1]
    """
    v = _np(verts, np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    span = np.where(hi - lo > 0, hi - lo, 1.0)
    return (v - lo) / span


def transfer_colors(colors_y, p2p) -> np.ndarray:
    """Pull per-vertex colors of y back to x through a map x -> y.

    Parameters
    ----------
    colors_y : (n_y, c) float
    p2p : (n_x,) int

    Returns
    -------
    (n_x, c) float
    """
    colors_y, p2p = _np(colors_y), _np(p2p).astype(np.int64)
    if p2p.size and (p2p.min() < 0 or p2p.max() >= colors_y.shape[0]):
        raise CorrespondenceError(
            f"map indices in [{p2p.min()}, {p2p.max()}] exceed the {colors_y.shape[0]} target vertices"
        )
    return colors_y[p2p]


def shaded_face_colors(verts, faces, vertex_colors, light=LIGHT_DIRECTION, ambient: float = AMBIENT) -> np.ndarray:
    """Per-face RGB: the mean vertex color times a two-sided Lambert factor.

    Parameters
    ----------
    verts : (n, 3) float
    faces : (f, 3) int
    vertex_colors : (n, 3) float in [0, 1]
    light : (3,) float
    ambient : float in [0, 1]

    Returns
    -------
    (f, 3) float64 in [0, 1]
    """
    v, f = _np(verts, np.float64), _np(faces).astype(np.int64)
    tri = v[f]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    normal = np.divide(normal, length, out=np.zeros_like(normal), where=length > 0)
    light = np.asarray(light, dtype=np.float64)
    light = light / np.linalg.norm(light)
    lambert = np.abs(normal @ light)
    base = _np(vertex_colors, np.float64)[f].mean(axis=1)
    return np.clip(base * (ambient + (1.0 - ambient) * lambert)[:, None], 0.0, 1.0)


def draw_mesh(ax, verts, faces, vertex_colors, view=DEFAULT_VIEW, title: str | None = None) -> None:
    """Draw a colored mesh on a 3-D matplotlib axes with equal aspect and no axis decorations.

    Parameters
    ----------
    ax : mpl_toolkits.mplot3d.Axes3D
    verts : (n, 3) float
    faces : (f, 3) int
    vertex_colors : (n, 3) float in [0, 1]
    view : (elevation, azimuth, vertical axis)
    title : str, optional
    """
    v, f = _np(verts, np.float64), _np(faces).astype(np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise InvalidMeshError(f"cannot render a mesh with verts {v.shape} and faces {f.shape}")
    if not np.isfinite(v).all():
        raise InvalidMeshError("cannot render a mesh with NaN or infinite vertices")
    colors = shaded_face_colors(v, f, vertex_colors)
    ax.add_collection3d(Poly3DCollection(v[f], facecolors=colors, edgecolors="none", linewidths=0.0))
    center = (v.max(0) + v.min(0)) / 2.0
    radius = float((v.max(0) - v.min(0)).max()) / 2.0 or 1.0
    for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), center):
        setter(c - radius, c + radius)
    ax.set_box_aspect((1.0, 1.0, 1.0), zoom=RENDER_ZOOM)
    elev, azim, vertical = view
    ax.view_init(elev=elev, azim=azim, vertical_axis=vertical)
    ax.set_axis_off()
    if title:
        ax.set_title(title, fontsize="small")


def correspondence_figure(
    verts_x, faces_x, verts_y, faces_y, p2p, title: str | None = None, view=DEFAULT_VIEW, names=("source", "target")
) -> Figure:
    """Texture-transfer figure of a map x -> y: source (colors pulled back through the map) | target.

    Parameters
    ----------
    verts_x : (n_x, 3) float
    faces_x : (f_x, 3) int
    verts_y : (n_y, 3) float
    faces_y : (f_y, 3) int
    p2p : (n_x,) int
        Map x -> y.
    title : str, optional
    view : (elevation, azimuth, vertical axis)
    names : (str, str)
        Panel titles.

    Returns
    -------
    matplotlib.figure.Figure
    """
    p2p = _np(p2p)
    if p2p.shape != (_np(verts_x).shape[0],):
        raise CorrespondenceError(f"the map has shape {p2p.shape} but the source has {_np(verts_x).shape[0]} vertices")
    colors_y = coordinate_colors(verts_y)
    colors_x = transfer_colors(colors_y, p2p)
    fig = Figure(figsize=(2 * PANEL_SIZE[0], PANEL_SIZE[1]), dpi=RENDER_DPI)
    panels = ((verts_x, faces_x, colors_x, names[0]), (verts_y, faces_y, colors_y, names[1]))
    for k, (v, f, c, name) in enumerate(panels):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        draw_mesh(ax, v, f, c, view=view, title=name)
    if title:
        fig.suptitle(title, fontsize="small")
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.0, top=0.9, wspace=0.0)
    return fig


def figure_to_rgb(fig: Figure) -> np.ndarray:
    """Rasterize a figure (Agg) to an ``(H, W, 3)`` uint8 array."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def save_figure(fig: Figure, path: str | os.PathLike) -> Path:
    """Save a figure as PNG atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(path) as fh:
        fig.savefig(fh, format="png")
    return path


def render_correspondence(
    path: str | os.PathLike,
    verts_x,
    faces_x,
    verts_y,
    faces_y,
    p2p,
    title: str | None = None,
    view=DEFAULT_VIEW,
    names=("source", "target"),
) -> Path:
    """Write the texture-transfer image of a map x -> y (see :func:`correspondence_figure`) to a PNG."""
    return save_figure(correspondence_figure(verts_x, faces_x, verts_y, faces_y, p2p, title, view, names), path)
