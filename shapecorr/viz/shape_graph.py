"""Drawing of a G-MSM shape graph (docs/gmsm.md §4): shapes as nodes, the graph's edges shaded by weight.

    fig = shape_graph_figure(graph, names)          # matplotlib Figure
    write_shape_graph_png(path, graph, names)       # evaluate.py multishape=graph: OUT/shape_graph.png
    log_shape_graph(logger, graph, names, step)     # TensorBoard image "graph/shape_graph"

The layout is networkx's spring layout of the edges with weight-dependent lengths (seeded, so the same graph
is drawn the same way); the hub of a star graph is drawn larger.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import matplotlib
import networkx as nx
import numpy as np
from matplotlib.figure import Figure

from shapecorr.matching.shape_graph import ShapeGraph
from shapecorr.viz.render import save_figure
from shapecorr.viz.tensorboard import summary_writer

#: Node labels are drawn for graphs up to this many shapes.
MAX_LABELLED_SHAPES = 40
LAYOUT_SEED = 0


def shape_graph_figure(graph: ShapeGraph, names: Sequence[str] | None = None, title: str | None = None) -> Figure:
    """Figure of the graph's edges, colored by their symmetrized cost (darker = cheaper).

    Parameters
    ----------
    graph : ShapeGraph
    names : list of str, optional
        Node labels (shape names).
    title : str, optional

    Returns
    -------
    Figure
    """
    g = nx.Graph()
    g.add_nodes_from(range(graph.n))
    w = [float(graph.weights[i, j]) for i, j in graph.edges.tolist()]
    scale = float(np.median(w)) if w and np.median(w) > 0 else 1.0
    for (i, j), wij in zip(graph.edges.tolist(), w):
        g.add_edge(i, j, weight=1.0 / (1e-9 + wij / scale), cost=wij)
    pos = nx.spring_layout(g, seed=LAYOUT_SEED, weight="weight")
    fig = Figure(figsize=(6, 6))  # Agg canvas, no pyplot (as shapecorr.viz.render)
    ax = fig.add_subplot()
    if w:
        nx.draw_networkx_edges(g, pos, ax=ax, edge_color=w, edge_cmap=matplotlib.colormaps["viridis"], width=1.5,
                               alpha=0.8)
    sizes = [300 if graph.hub == i else 80 for i in range(graph.n)]
    nx.draw_networkx_nodes(g, pos, ax=ax, node_size=sizes, node_color="tab:red")
    if names is not None and graph.n <= MAX_LABELLED_SHAPES:
        nx.draw_networkx_labels(g, pos, labels={i: str(n) for i, n in enumerate(names)}, ax=ax, font_size=7)
    ax.set_title(title or f"{graph.variant} shape graph: {graph.n} shapes, {graph.edges.shape[0]} edges")
    ax.set_axis_off()
    return fig


def write_shape_graph_png(path: str | os.PathLike, graph: ShapeGraph, names: Sequence[str] | None = None) -> Path:
    """Save :func:`shape_graph_figure` as a PNG; returns the path."""
    return save_figure(shape_graph_figure(graph, names), path)


def log_shape_graph(logger, graph: ShapeGraph, names: Sequence[str] | None = None, step: int = 0,
                    tag: str = "graph/shape_graph") -> bool:
    """Log the drawing to TensorBoard (nothing with another logger); returns whether it was logged."""
    writer = summary_writer(logger)
    if writer is None:
        return False
    writer.add_figure(tag, shape_graph_figure(graph, names), global_step=step, close=True)
    return True


__all__ = ["log_shape_graph", "shape_graph_figure", "write_shape_graph_png"]
