"""NeuroMorph's EdgeConv feature network as a :class:`~shapecorr.nn.backbone.Backbone` (``model/backbone=edgeconv``).

The network itself is :class:`~shapecorr.nn.neuromorph.NeuroMorphFeatureNet` (Eisenberger et al., CVPR 2021:
ResnetEC on ``[xyz, vertex normal]``, unit-length 128-D rows); this module only adapts it to the backbone
interface: it takes a :class:`~shapecorr.data.datasets.ShapeSample`, builds the mesh's undirected edges itself
and needs no precomputed per-shape operator (``required_operators = {}``: vertices, faces and edges suffice).

The backbone *is* a :class:`NeuroMorphFeatureNet` (a subclass with the backbone's ``forward``), so its
parameters keep their names (``net.*``) and checkpoints written before backbones were injected load unchanged.
"""

from __future__ import annotations

import torch

from shapecorr.errors import ConfigError
from shapecorr.geometry.mesh_graph import undirected_edges
from shapecorr.nn.backbone import Backbone
from shapecorr.nn.edgeconv import DEFAULT_HIDDEN, DEFAULT_N_BLOCKS, POOL_MODES
from shapecorr.nn.neuromorph import DEFAULT_FEATURE_DIM, NeuroMorphFeatureNet

#: Default pooling: our decision, a global max-pool over the vertices (the original code's per-vertex channel
#: max, ``"channel"``, is a left-over of a batched version; see :mod:`shapecorr.nn.edgeconv`).
DEFAULT_POOL = "global"


class EdgeConvBackbone(NeuroMorphFeatureNet, Backbone):
    """Per-vertex EdgeConv features of NeuroMorph (unit-length rows).

    Parameters
    ----------
    feature_dim : int
        Output channels (NeuroMorph: 128).
    hidden_channels : int
        Hidden width of the ResnetEC blocks (NeuroMorph: 128).
    n_blocks : int
        EdgeConv layers (NeuroMorph: 5).
    pool : {"global", "channel"}
        Pooling between layers ("global" our decision, "channel" the original code's).
    residual_init : {"zero", "original"}
        Initialization of the residual blocks' last layer: weight and bias zeroed (ours) or the weight only
        (the original code's; :class:`~shapecorr.nn.edgeconv.ResnetBlockFC`).
    """

    required_operators: dict = {}

    def __init__(
        self,
        feature_dim: int = DEFAULT_FEATURE_DIM,
        hidden_channels: int = DEFAULT_HIDDEN,
        n_blocks: int = DEFAULT_N_BLOCKS,
        pool: str = DEFAULT_POOL,
        residual_init: str = "zero",
    ):
        if int(feature_dim) < 1:
            raise ConfigError(f"model.backbone.feature_dim must be >= 1, got {feature_dim}")
        if pool not in POOL_MODES:
            raise ConfigError(f"model.backbone.pool must be one of {POOL_MODES}, got {pool!r}")
        super().__init__(int(feature_dim), int(hidden_channels), int(n_blocks), str(pool), str(residual_init))
        self.out_channels = int(feature_dim)

    def forward_arrays(self, verts: torch.Tensor, faces: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
        """The network on raw arrays, ``verts (n, 3)``, ``faces (f, 3)``, undirected ``edges (E, 2)``: ``(n, C)``.

        For callers that hold arrays rather than a sample (the parity checks against the original code).
        """
        return NeuroMorphFeatureNet.forward(self, verts, faces, edges)

    def forward(self, sample, rows: torch.Tensor | None = None, edges: torch.Tensor | None = None) -> torch.Tensor:
        """Features of one shape.

        Parameters
        ----------
        sample : ShapeSample
            ``verts (n, 3)``, ``faces (f, 3)``.
        rows : (r,) int64, optional
            Return only these vertices' features (the network still runs on the whole mesh: EdgeConv pools
            over it).
        edges : (E, 2) int64, optional
            The undirected edges of the mesh when the caller has them already
            (:func:`~shapecorr.geometry.mesh_graph.undirected_edges`); computed otherwise.

        Returns
        -------
        (n, feature_dim) or (r, feature_dim) float
            L2-normalized rows.
        """
        if edges is None:
            edges = undirected_edges(sample.faces, sample.shape.n_verts)
        feat = self.forward_arrays(sample.verts, sample.faces, edges)
        return feat if rows is None else feat[rows]
