"""The interpolation-curve figure ``interp_curves.png`` of ``evaluate.py`` (and of the interpolation benchmark).

Two panels over the frame time t: the conformal distortion of each frame against x and the volume score
``V_t/V_0 + V_0/V_t - 2``, one line per method, means over pairs (:func:`shapecorr.eval.reports.interpolation_curves`
computes them; this module only draws). Frames beyond t = 1 (extrapolation) are drawn on a gray background.
Drawn with :class:`matplotlib.figure.Figure` (no pyplot: safe headless and in worker threads).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from matplotlib.figure import Figure

from shapecorr.errors import ConfigError
from shapecorr.viz.render import save_figure

#: File name of the figure under an evaluation output folder.
INTERP_CURVES_PNG = "interp_curves.png"
#: Size of the figure in inches (two panels) and its resolution.
CURVES_FIGSIZE = (9.0, 3.6)
CURVES_DPI = 110
#: Panels: key of the curves dict -> y-axis label.
PANELS = {
    "conformal_distortion": "conformal distortion (K - 1/K)^2",
    "volume_score": "volume score V_t/V_0 + V_0/V_t - 2",
}


def _as_line(times, values) -> tuple[np.ndarray, np.ndarray]:
    """``(t, v)`` float arrays without the entries whose value is None (an open mesh, an inverted frame)."""
    pairs = [(float(t), float(v)) for t, v in zip(times, values) if v is not None]
    if not pairs:
        return np.zeros(0), np.zeros(0)
    t, v = np.asarray(pairs).T
    return t, v


def draw_interp_curves(axes, curves: Mapping[str, Mapping[str, Any]], legend: bool = True) -> None:
    """Draw the panels of :data:`PANELS` into ``axes`` (one per panel, in order), one line per entry of ``curves``.

    Parameters
    ----------
    axes : sequence of matplotlib Axes
        ``len(PANELS)`` axes (one row of a figure).
    curves : dict label -> {"times": (T,), "conformal_distortion": (T,), "volume_score": (T,)}
        Lists or arrays; None entries are left out of the line.
    legend : bool
        Legend in the first panel.
    """
    if not curves:
        raise ConfigError("no interpolation curves to draw")
    t_max = max(max(c["times"]) for c in curves.values())
    for k, (ax, (key, ylabel)) in enumerate(zip(axes, PANELS.items())):
        for label, c in curves.items():
            t, v = _as_line(c["times"], c.get(key) or [])
            if t.size:
                ax.plot(t, v, marker="o", markersize=3, label=label)
        if t_max > 1.0:
            ax.axvspan(1.0, t_max, color="0.92", zorder=0, label="_extrapolation")
        ax.set_xlabel("t")
        ax.set_ylabel(ylabel, fontsize="small")
        ax.grid(True, alpha=0.3)
        if legend and k == 0:
            ax.legend(loc="upper left", fontsize="x-small")


def interp_curves_figure(curves: Mapping[str, Mapping[str, Any]], title: str | None = None) -> Figure:
    """Conformal distortion and volume score against t, one line per entry of ``curves``.

    Parameters
    ----------
    curves : dict label -> {"times": (T,), "conformal_distortion": (T,), "volume_score": (T,)}
        Lists or arrays; None entries are left out of the line.
    title : str, optional

    Returns
    -------
    matplotlib.figure.Figure
    """
    if not curves:
        raise ConfigError("no interpolation curves to draw")
    fig = Figure(figsize=CURVES_FIGSIZE, dpi=CURVES_DPI)
    draw_interp_curves([fig.add_subplot(1, len(PANELS), k + 1) for k in range(len(PANELS))], curves)
    if title:
        fig.suptitle(title, fontsize="medium")
    fig.tight_layout()
    return fig


def write_interp_curves_png(path: str | os.PathLike, metrics_dict: Mapping[str, Any], label: str = "method") -> Path:
    """Write ``interp_curves.png`` from the ``interp_curves`` entry of an evaluation's metrics.

    ``metrics_dict`` is a :func:`shapecorr.eval.reports.aggregate` result (or ``metrics.json``).

    Raises
    ------
    ConfigError
        ``metrics_dict`` has no interpolation curves (the matcher does not interpolate).
    """
    curves = metrics_dict.get("interp_curves")
    if curves is None:
        raise ConfigError("these metrics have no interp_curves (the matcher does not interpolate)")
    n = metrics_dict.get("n_pairs_interpolated", metrics_dict.get("n_pairs"))
    return save_figure(interp_curves_figure({label: curves}, title=f"interpolation, mean over {n} pairs"), path)
