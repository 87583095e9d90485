"""Figures of a comparison of runs (:mod:`shapecorr.eval.compare`): overlaid curves, per-pair plots, examples.

``pck_overlay.png`` (every run's PCK curve, AUC in the legend), ``pairwise.png`` (two runs: a scatter of their
per-pair errors; more: a win/loss matrix), ``mean_error.png`` (mean errors as bars, published numbers as dashed
marks), ``examples_grid.png`` (the same example pairs, one row per run, rendered as ``examples/`` of
``evaluate.py``) and ``interp_overlay.png`` (when several runs interpolate). Drawn with
:class:`matplotlib.figure.Figure` (no pyplot).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure

from shapecorr.data.io import read_mesh
from shapecorr.errors import MeshReadError
from shapecorr.eval import compare, reports
from shapecorr.eval.export import map_paths
from shapecorr.viz.interp_curves import interp_curves_figure
from shapecorr.viz.pck import pck_figure
from shapecorr.viz.render import PANEL_SIZE, RENDER_DPI, coordinate_colors, draw_mesh, save_figure, transfer_colors

PCK_OVERLAY_PNG = "pck_overlay.png"
PAIRWISE_PNG = "pairwise.png"
MEAN_ERROR_PNG = "mean_error.png"
EXAMPLES_GRID_PNG = "examples_grid.png"
INTERP_OVERLAY_PNG = "interp_overlay.png"
#: Mesh file extensions looked up under a run's data folder, in this order.
MESH_EXTENSIONS = (".off", ".ply", ".obj")
#: Panel size (inches) of one cell of the examples grid.
GRID_PANEL = (PANEL_SIZE[0] * 0.75, PANEL_SIZE[1] * 0.75)


def example_pairs(pairs: Sequence[tuple[str, str]], n: int) -> list[tuple[str, str]]:
    """``n`` evenly spaced pairs of ``pairs`` (all when fewer), as ``evaluate.py`` picks its examples."""
    if n <= 0 or not pairs:
        return []
    keep = sorted(set(np.linspace(0, len(pairs) - 1, min(n, len(pairs))).round().astype(int).tolist()))
    return [pairs[k] for k in keep]


def find_mesh(data_root: str | os.PathLike, name: str) -> Path:
    """The mesh file of shape ``name`` under ``data_root`` (searched recursively, ``.off`` first).

    Raises
    ------
    MeshReadError
        No such file.
    """
    root = Path(data_root)
    for ext in MESH_EXTENSIONS:
        direct = [root / "off" / f"{name}{ext}", root / f"{name}{ext}"]
        for path in direct:
            if path.is_file():
                return path
        found = sorted(root.rglob(f"{name}{ext}"))
        if found:
            return found[0]
    raise MeshReadError(f"no mesh file for shape {name!r} ({'/'.join(MESH_EXTENSIONS)})", root)


def load_meshes(data_root: str | os.PathLike, names: Sequence[str]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``name -> (verts (n, 3) float64, faces (f, 3) int64)`` in input units (the maps' vertex order)."""
    return {n: read_mesh(find_mesh(data_root, n), validate=False) for n in dict.fromkeys(names)}


def read_map(run: compare.Run, source: str, target: str) -> np.ndarray | None:
    """The run's point-to-point map ``(n_source,)`` int64 of a pair (``maps/<x>__<y>.npy``), or None if absent."""
    path = map_paths(run.path, source, target)[1]
    return np.load(path, allow_pickle=False).astype(np.int64) if path.is_file() else None


def write_pck_overlay(path: str | os.PathLike, runs: Sequence[compare.Run]) -> Path | None:
    """Every run's PCK curve on one plot (mean error and AUC in the legend); None when no run has one."""
    curves = {r.name: (np.asarray(r.values["pck"]["thresholds"]), np.asarray(r.values["pck"]["fractions"]),
                       float(r.values["mean_geodesic_error"]))
              for r in runs if r.values.get("pck")}
    if not curves:
        return None
    n = max(int(r.values.get("n_pairs") or 0) for r in runs)
    return save_figure(pck_figure(curves, title=f"PCK, {len(curves)} runs on {n} pairs"), path)


def pairwise_figure(names: Sequence[str], errors: np.ndarray) -> Figure:
    """Two runs: per-pair errors of A (x) against B (y), x100; more: the win/loss matrix (row beats column).

    Parameters
    ----------
    names : list of str
        Run names, one per row of ``errors``.
    errors : (r, p) float
        Per-pair mean errors (fractions of sqrt(area)).
    """
    fig = Figure(figsize=(5.0, 4.6) if len(names) == 2 else (1.6 * len(names) + 3.0, 1.2 * len(names) + 2.2),
                 dpi=120)
    ax = fig.add_subplot(1, 1, 1)
    if len(names) == 2:
        a, b = 100 * errors[0], 100 * errors[1]
        ax.scatter(a, b, s=12)
        hi = float(np.nanmax([a.max(), b.max()])) * 1.05
        ax.plot([0, hi], [0, hi], color="0.5", linewidth=0.8)
        ax.set_xlabel(f"{names[0]}: per-pair mean error (x100)")
        ax.set_ylabel(f"{names[1]} (x100)")
        wins = int((errors[0] < errors[1]).sum())
        ax.set_title(f"{wins} of {errors.shape[1]} pairs lower with {names[0]}", fontsize="small")
        ax.set_xlim(0, hi)
        ax.set_ylim(0, hi)
        ax.grid(True, alpha=0.3)
    else:
        wins = compare.win_matrix(errors)
        share = wins / max(errors.shape[1], 1)
        np.fill_diagonal(share, np.nan)  # drawn blank
        ax.imshow(share, cmap="RdYlGn", vmin=0.0, vmax=1.0)
        for i in range(len(names)):
            for j in range(len(names)):
                ax.text(j, i, "" if i == j else str(wins[i, j]), ha="center", va="center", fontsize="small")
        ax.set_xticks(range(len(names)), labels=names, rotation=30, ha="right", fontsize="small")
        ax.set_yticks(range(len(names)), labels=names, fontsize="small")
        ax.set_title(f"pairs (of {errors.shape[1]}) where the row's error is lower than the column's",
                     fontsize="small")
    fig.tight_layout()
    return fig


def write_mean_error_bars(path: str | os.PathLike, runs: Sequence[compare.Run],
                          published: Sequence[tuple[str, float, str]] = ()) -> Path | None:
    """Mean errors (x100) as bars, the published numbers as labelled dashed lines (not bars)."""
    measured = [(r.name, r.values.get("mean_geodesic_error")) for r in runs]
    measured = [(n, float(v)) for n, v in measured if v is not None]
    if not measured:
        return None
    fig = Figure(figsize=(1.3 * len(measured) + 3.5, 4.0), dpi=120)
    ax = fig.add_subplot(1, 1, 1)
    ax.bar(range(len(measured)), [100 * v for _, v in measured], color="tab:blue")
    ax.set_xticks(range(len(measured)), labels=[n for n, _ in measured], rotation=25, ha="right",
                  fontsize="small")
    for k, (name, value, _) in enumerate(published):
        ax.axhline(100 * value, color=f"C{k + 1}", linestyle="--", linewidth=1.0, label=f"{name} (published)")
    ax.set_ylabel("mean geodesic error (x100)")
    ax.set_yscale("log")
    ax.grid(True, axis="y", alpha=0.3)
    if published:
        ax.legend(fontsize="x-small", loc="upper right")
    fig.tight_layout()
    return save_figure(fig, path)


def write_interp_overlay(path: str | os.PathLike, runs: Sequence[compare.Run]) -> Path | None:
    """The interpolation curves of every interpolating run on one figure; None with fewer than two."""
    curves: Mapping[str, Mapping] = {r.name: r.values[reports.CURVES_KEY] for r in runs
                                     if r.values.get(reports.CURVES_KEY)}
    if len(curves) < 2:
        return None
    return save_figure(interp_curves_figure(curves, title="interpolation, overlaid"), path)


def write_examples_grid(path: str | os.PathLike, runs: Sequence[compare.Run], examples: Sequence[tuple[str, str]],
                        meshes: Mapping[str, tuple[np.ndarray, np.ndarray]], view) -> Path | None:
    """The example pairs side by side, rendered as ``evaluate.py``'s ``examples/``.

    The first row shows the targets (coordinate colours), then one row per run the source coloured through
    that run's map (grey where a run has no map for the pair).
    """
    if not examples or not runs:
        return None
    rows, cols = len(runs) + 1, len(examples)
    fig = Figure(figsize=(GRID_PANEL[0] * cols + 1.2, GRID_PANEL[1] * rows), dpi=RENDER_DPI)
    for c, (x, y) in enumerate(examples):
        vy, fy = meshes[y]
        colors_y = coordinate_colors(vy)
        ax = fig.add_subplot(rows, cols, c + 1, projection="3d")
        draw_mesh(ax, vy, fy, colors_y, view=view, title=f"target {y}")
        vx, fx = meshes[x]
        for r, run in enumerate(runs):
            p2p = read_map(run, x, y)
            colors = transfer_colors(colors_y, p2p) if p2p is not None else np.full((len(vx), 3), 0.6)
            ax = fig.add_subplot(rows, cols, (r + 1) * cols + c + 1, projection="3d")
            draw_mesh(ax, vx, fx, colors, view=view, title=f"{x}" if r == 0 else None)
            if c == 0:
                ax.text2D(-0.05, 0.5, run.name, transform=ax.transAxes, rotation=90, va="center", ha="right",
                          fontsize="small")
    fig.subplots_adjust(left=0.06, right=1.0, bottom=0.0, top=0.96, wspace=0.0, hspace=0.05)
    return save_figure(fig, path)


def write_figures(out_dir: str | os.PathLike, runs: Sequence[compare.Run], pairs: Sequence[tuple[str, str]],
                  examples: Sequence[tuple[str, str]], meshes, view,
                  published: Sequence[tuple[str, float, str]] = ()) -> dict[str, Path]:
    """Write every figure that applies to ``out_dir``; returns ``{file name: path}`` of those written."""
    out = Path(out_dir)
    written: dict[str, Path | None] = {
        PCK_OVERLAY_PNG: write_pck_overlay(out / PCK_OVERLAY_PNG, runs),
        MEAN_ERROR_PNG: write_mean_error_bars(out / MEAN_ERROR_PNG, runs, published),
        INTERP_OVERLAY_PNG: write_interp_overlay(out / INTERP_OVERLAY_PNG, runs),
    }
    with_pairs = [r for r in runs if r.has_records]
    if len(with_pairs) >= 2 and pairs:
        errors = compare.per_pair_errors(with_pairs, pairs)
        written[PAIRWISE_PNG] = save_figure(pairwise_figure([r.name for r in with_pairs], errors), out / PAIRWISE_PNG)
    if examples and meshes:
        written[EXAMPLES_GRID_PNG] = write_examples_grid(out / EXAMPLES_GRID_PNG, with_pairs, examples, meshes, view)
    return {k: v for k, v in written.items() if v is not None}

