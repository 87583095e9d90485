"""The PCK figure (cumulative geodesic error curve): ``pck.png`` of ``evaluate.py`` and the TensorBoard figure.

Drawn with :class:`matplotlib.figure.Figure` (no pyplot: safe headless and in worker threads). The curve itself
comes from :func:`shapecorr.eval.metrics.pck_curve`; this module only draws it.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from matplotlib.figure import Figure

from shapecorr.eval import metrics
from shapecorr.viz.render import save_figure

#: Size of the PCK figure in inches and its resolution.
PCK_FIGSIZE = (5.0, 4.0)
PCK_DPI = 120


def pck_figure(curves: Mapping[str, tuple[np.ndarray, np.ndarray, float]], title: str | None = None) -> Figure:
    """A PCK figure (no pyplot: safe headless and in worker threads).

    Parameters
    ----------
    curves : dict label -> (thresholds (t,), fractions (t,), mean error)
        One line per entry; the legend shows the mean error and the AUC.
    title : str, optional

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig = Figure(figsize=PCK_FIGSIZE, dpi=PCK_DPI)
    ax = fig.add_subplot(1, 1, 1)
    for label, (t, frac, mean) in curves.items():
        auc = metrics.pck_auc(t, frac)
        ax.plot(t, frac, label=f"{label}: mean {mean:.4f}, AUC {auc:.3f}")
    ax.set_xlabel("geodesic error / sqrt(area)")
    ax.set_ylabel("fraction of correspondences")
    ax.set_ylim(0.0, 1.0)
    ax.set_xlim(float(min(c[0][0] for c in curves.values())), float(max(c[0][-1] for c in curves.values())))
    ax.grid(True, alpha=0.3)
    ax.legend(loc="lower right", fontsize="small")
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return fig


def write_pck_png(path: str | os.PathLike, metrics_dict: Mapping[str, Any], label: str = "map") -> Path:
    """Write ``pck.png`` from a :func:`shapecorr.eval.reports.aggregate` result.

    The symmetric curve is drawn too when present.
    """
    pck = metrics_dict["pck"]
    curves = {label: (np.asarray(pck["thresholds"]), np.asarray(pck["fractions"]), metrics_dict["mean_geodesic_error"])}
    if "pck_sym" in metrics_dict:
        sym = metrics_dict["pck_sym"]
        curves[f"{label} vs mirrored GT"] = (
            np.asarray(sym["thresholds"]),
            np.asarray(sym["fractions"]),
            metrics_dict["mean_geodesic_error_sym"],
        )
    return save_figure(pck_figure(curves, title=f"PCK over {metrics_dict['n_pairs']} pairs"), path)
