"""Matchers that need no training.

The evaluation's self-check, a descriptor baseline, maps from files, and the linear-blend interpolation
around any of them.

All implement the matcher protocol of :mod:`shapecorr.matching.result` and are usable as
``evaluate.py model=identity_gt|descriptor_nn|linear_blend`` (``PrecomputedMaps`` backs
``evaluate.py maps_dir=DIR``).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from shapecorr.data.ground_truth import ground_truth_indices
from shapecorr.errors import ConfigError, CorrespondenceError, NumericalError
from shapecorr.matching.nearest_neighbors import NN_BACKENDS, bidirectional_nearest_neighbors
from shapecorr.matching.result import MatchResult

#: Descriptors DescriptorNN can use (computed by the data pipeline, shapecorr.data.operators).
DESCRIPTOR_NAMES = ("wks", "hks", "shot")
#: Row normalizations of DescriptorNN: none, unit L2 rows, or per-channel standardization over both shapes.
DESCRIPTOR_NORMALIZATIONS = ("none", "l2", "standardize")
#: Rows of x processed at once by the brute-force nearest-neighbour search (bounds memory to chunk * n_y).
#: 1024 rows (200 MB of float32 distances for a 50k-vertex y) was faster than 4096 at 50k x 50k on one core.
NN_CHUNK_ROWS = 1024
#: Descriptor dimensions up to this use a kd-tree, larger ones the chunked matrix-product search (measured on
#: random 50k x d descriptors, one core: d = 3 / 8: kd-tree 0.2 / 1.3 s, chunked 9 / 14 s; d = 16: kd-tree 34 s,
#: chunked 13 s; d = 100: chunked 15 s, kd-tree far slower, 17 s already at 10k).
KDTREE_MAX_DIM = 12
#: Default frames of LinearBlend.match: the frame times of NeuroMorph (``interp_times``, as in evaluate.py).
LINEAR_BLEND_TIMES = (0.0, 0.25, 0.5, 0.75, 1.0)


class IdentityGT:
    """Maps x to y through the ground truth: the pipeline's self-check (its geodesic error must be 0).

    Reference point r of x (``x.corres[r]``) goes to ``y.corres[r]``; every other vertex of x goes where its
    Euclidean-nearest reference vertex of x goes. Without ``.vts`` files on either shape, shapes sharing
    their connectivity map by the identity.

    The error is exactly 0 whenever the ground truth is a function of x's vertices. If two reference points
    fall on the same vertex of x but on different vertices of y (a ``.vts`` file that is not injective, as in
    FAUST_r, where 5000 template points land on ~3500 distinct vertices), no vertex map can satisfy both: the
    first one listed wins and the remaining error is the ground-truth floor of the dataset.
    """

    needs_ground_truth = True
    required_operators: dict = {}

    def match(self, x, y) -> MatchResult:
        """Ground-truth map x -> y (see the class docstring)."""
        n_x, n_y = x.shape.n_verts, y.shape.n_verts
        ref_x, ref_y = ground_truth_indices(
            None if x.corres is None else x.corres.cpu().numpy(),
            None if y.corres is None else y.corres.cpu().numpy(),
            n_x,
            n_y,
            x.shape.faces.cpu().numpy(),
            y.shape.faces.cpu().numpy(),
        )
        # First occurrence of each reference vertex of x decides its image.
        uniq_x, first = np.unique(ref_x, return_index=True)
        target_of_ref = ref_y[first]
        verts_x = x.shape.verts.detach().cpu().numpy().astype(np.float64)
        _, nearest = cKDTree(verts_x[uniq_x]).query(verts_x, k=1)
        p2p = target_of_ref[nearest]
        p2p[uniq_x] = target_of_ref  # exact on the reference vertices even with coincident positions
        return MatchResult(p2p=torch.from_numpy(p2p.astype(np.int64)).to(x.shape.verts.device))


class DescriptorNN:
    """Nearest neighbour in descriptor space (WKS, HKS or SHOT), both directions.

    Parameters
    ----------
    descriptor : {"wks", "hks", "shot"}
        Which descriptor operator to match (``ShapeSample.features[descriptor]``); ``required_operators``
        (``{descriptor: {}}``) asks ``evaluate.py`` for it; its parameters come from ``data.operators.params``.
    normalize : {"none", "l2", "standardize"}
        Row transform before the search: none; unit L2 norm per vertex; or per-channel zero mean and unit
        variance using the statistics of both shapes together. On the FAUST_r test pairs with WKS the three
        give mean errors 0.232 (none), 0.235 (standardize), 0.238 (l2)
        (benchmarks/results/eval_baselines.json), hence the default "none".
    chunk_rows : int
        Rows per chunk of the matrix-product search: memory ``chunk_rows x n`` float32 distances.
    backend : {"auto", "kdtree", "brute"}
        Search. ``"auto"``: scipy's ``cKDTree`` when the descriptor dimension is at most
        :data:`KDTREE_MAX_DIM`, the chunked matrix-product search otherwise (on the tensors' device). KD-trees
        degrade with the dimension; measured on random 50k x d descriptors on one core: d = 3 / 8 kd-tree
        0.2 / 1.3 s against 9 / 14 s chunked; d = 16 kd-tree 34 s, chunked 13 s; d = 100 (WKS / HKS default)
        chunked 15 s (kd-tree 17 s already at 10k). Both are exact up to float32 ties; memory is
        O(chunk_rows n), never n x n, so 50k-200k-vertex pairs run at full resolution.
    """

    needs_ground_truth = False

    def __init__(self, descriptor: str = "wks", normalize: str = "none", chunk_rows: int = NN_CHUNK_ROWS,
                 backend: str = "auto"):
        if descriptor not in DESCRIPTOR_NAMES:
            raise ConfigError(f"descriptor must be one of {DESCRIPTOR_NAMES}, got {descriptor!r}")
        if normalize not in DESCRIPTOR_NORMALIZATIONS:
            raise ConfigError(f"normalize must be one of {DESCRIPTOR_NORMALIZATIONS}, got {normalize!r}")
        if chunk_rows < 1:
            raise ConfigError(f"chunk_rows must be positive, got {chunk_rows}")
        if backend not in NN_BACKENDS:
            raise ConfigError(f"descriptor_nn: backend must be one of {NN_BACKENDS}, got {backend!r}")
        self.backend = backend
        self.descriptor = descriptor
        self.normalize = normalize
        self.chunk_rows = int(chunk_rows)
        self.required_operators = {descriptor: {}}

    def _features(self, sample) -> torch.Tensor:
        feats = sample.features.get(self.descriptor)
        if feats is None:
            raise ConfigError(
                f"shape {sample.name!r} has no {self.descriptor!r} descriptor (the data did not compute the "
                f"operator; required_operators = {self.required_operators})"
            )
        if feats.ndim != 2 or feats.shape[0] != sample.shape.n_verts:
            raise ConfigError(
                f"{self.descriptor} of {sample.name!r} has shape {tuple(feats.shape)}, "
                f"expected ({sample.shape.n_verts}, c)"
            )
        if not torch.isfinite(feats).all():
            raise NumericalError(f"the {self.descriptor} descriptor of {sample.name!r} contains NaN or infinite values")
        return feats.to(torch.float32)

    def _transform(self, fx: torch.Tensor, fy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if self.normalize == "l2":
            tiny = torch.finfo(fx.dtype).tiny
            return fx / fx.norm(dim=1, keepdim=True).clamp_min(tiny), fy / fy.norm(dim=1, keepdim=True).clamp_min(tiny)
        if self.normalize == "standardize":
            both = torch.cat([fx, fy], dim=0)
            mean, std = both.mean(0), both.std(0)
            # Constant channels carry no information: leave them at zero instead of dividing by zero.
            std = torch.where(std > 0, std, torch.ones_like(std))
            return (fx - mean) / std, (fy - mean) / std
        return fx, fy

    def match(self, x, y) -> MatchResult:
        """Nearest-neighbour maps x -> y and y -> x in descriptor space."""
        fx, fy = self._transform(self._features(x), self._features(y))
        backend = self.backend
        if backend == "auto":
            backend = "kdtree" if fx.shape[1] <= KDTREE_MAX_DIM else "brute"
        p2p, p2p_inv = bidirectional_nearest_neighbors(fx, fy, backend=backend, block_size=self.chunk_rows, exact=False)
        return MatchResult(p2p=p2p, p2p_inv=p2p_inv)


class PrecomputedMaps:
    """Reads maps computed elsewhere: ``<maps_dir>/<x>__<y>.<extension>``, one target index per source vertex.

    Parameters
    ----------
    maps_dir : path
        Folder of map files.
    one_based : bool or None
        Indices start at 1 (``.map`` / ``.vts``-style files) instead of 0 (shapecorr's ``.txt``). None (not
        said): the folder's ``maps.json`` decides (written by ``evaluate.py`` beside its zero-based maps), else a
        file that never uses index 0 is refused with a message asking for ``maps_one_based``
        (:func:`shapecorr.data.io.read_map`).
    extension : str
        File extension without the dot: ``txt`` / ``map`` / ``vts`` (text, one index per line) or ``npy``
        (an integer array, always zero-based, as written by ``evaluate.py``).
    """

    needs_ground_truth = False
    required_operators: dict = {}

    def __init__(self, maps_dir: str | os.PathLike, one_based: bool | None = None, extension: str = "txt"):
        self.maps_dir = Path(maps_dir)
        if not self.maps_dir.is_dir():
            raise CorrespondenceError("maps folder does not exist", self.maps_dir)
        from shapecorr.data.io import MAPS_MARKER, MAPS_ONE_BASED_OPTION, maps_marker_one_based

        declared = maps_marker_one_based(self.maps_dir)  # evaluate.py's own maps say their base
        if declared is not None and one_based is not None and bool(one_based) != declared:
            raise CorrespondenceError(
                f"{MAPS_MARKER} declares {'one' if declared else 'zero'}-based maps but {MAPS_ONE_BASED_OPTION}="
                f"{str(bool(one_based)).lower()}; drop {MAPS_ONE_BASED_OPTION} (the marker decides)", self.maps_dir)
        self.one_based = declared if one_based is None else bool(one_based)
        self.extension = extension.lstrip(".")

    def path(self, name_x: str, name_y: str) -> Path:
        """File holding the map of pair (x, y)."""
        return self.maps_dir / f"{name_x}__{name_y}.{self.extension}"

    def match(self, x, y) -> MatchResult:
        """The stored map x -> y, checked against the vertex counts of both shapes."""
        path = self.path(x.name, y.name)
        n_x, n_y = x.shape.n_verts, y.shape.n_verts
        if not path.is_file():
            raise CorrespondenceError(f"no map file for pair ({x.name}, {y.name})", path)
        if self.extension == "npy":
            try:
                p2p = np.load(path, allow_pickle=False)
            except (OSError, ValueError) as err:
                raise CorrespondenceError(f"unreadable .npy map: {err}", path) from None
            if p2p.ndim != 1 or not np.issubdtype(p2p.dtype, np.integer):
                raise CorrespondenceError(f"expected a 1-D integer array, got {p2p.dtype} of shape {p2p.shape}", path)
            if p2p.shape[0] != n_x:
                raise CorrespondenceError(f"the map has {p2p.shape[0]} entries but {x.name} has {n_x} vertices", path)
            if p2p.size and (p2p.min() < 0 or p2p.max() >= n_y):
                raise CorrespondenceError(
                    f"map indices in [{p2p.min()}, {p2p.max()}] are outside 0..{n_y - 1} ({y.name} has {n_y} vertices)",
                    path,
                )
        else:
            from shapecorr.data.io import read_map

            p2p = read_map(path, one_based=self.one_based, n_source=n_x, n_target=n_y)
        return MatchResult(p2p=torch.as_tensor(np.asarray(p2p, dtype=np.int64)))


class LinearBlend(torch.nn.Module):
    """The linear-blend interpolation baseline around any matcher (NeuroMorph's interpolation benchmark).

    The maps are those of the wrapped matcher; the deformation moves each vertex of x on a straight line
    towards its image on y: ``X(t) = x + t (y[p2p] - x)``, so X(0) = x, X(1) = y[p2p] (on y's vertices) and
    t > 1 extrapolates along the same lines. It gives any matcher an ``interpolate`` method, which makes the
    whole interpolation path of ``evaluate.py`` (frames, Chamfer distance, conformal distortion along the
    sequence, pose transfer) usable without a learned model.

    It is a ``torch.nn.Module`` only so that ``.eval()`` and ``.to(device)`` reach a wrapped learned model
    (registered as a submodule); it has no parameters of its own.

    Parameters
    ----------
    matcher : Matcher
        Any object with ``match(x, y) -> MatchResult``; its ``required_operators`` and
        ``needs_ground_truth`` are passed through.
    interp_times : sequence of float
        Frames of :meth:`match` (default :data:`LINEAR_BLEND_TIMES`); :meth:`interpolate` takes any times.
    """

    def __init__(self, matcher, interp_times=LINEAR_BLEND_TIMES):
        super().__init__()
        if not callable(getattr(matcher, "match", None)):
            raise ConfigError(f"LinearBlend wraps a matcher (with a match(x, y) method), got {type(matcher).__name__}")
        values = [float(t) for t in interp_times]
        if not values or not all(np.isfinite(values)):
            raise ConfigError(f"LinearBlend interp_times must be a non-empty list of finite numbers, got {values}")
        self.matcher = matcher
        self.interp_times = tuple(values)

    @property
    def required_operators(self) -> dict:
        """The wrapped matcher's operator request."""
        return dict(getattr(self.matcher, "required_operators", {}) or {})

    @property
    def needs_ground_truth(self) -> bool:
        """Whether the wrapped matcher needs the ground truth."""
        return bool(getattr(self.matcher, "needs_ground_truth", False))

    @staticmethod
    def blend(verts_x: torch.Tensor, verts_y: torch.Tensor, p2p: torch.Tensor, times: torch.Tensor) -> torch.Tensor:
        """Frames ``x + t (y[p2p] - x)``.

        Parameters
        ----------
        verts_x : (n_x, 3) float
        verts_y : (n_y, 3) float
        p2p : (n_x,) int64
            Map x -> y.
        times : (T,) float

        Returns
        -------
        (T, n_x, 3) float, dtype and device of ``verts_x``
        """
        times = times.to(device=verts_x.device, dtype=verts_x.dtype)
        step = verts_y[p2p.to(verts_y.device)].to(verts_x.dtype) - verts_x
        return verts_x[None] + times[:, None, None] * step[None]

    def interpolate(self, x, y, times) -> MatchResult:
        """The wrapped matcher's maps and the linear blend at ``times (T,)`` (any finite values)."""
        times = torch.as_tensor(times, dtype=x.verts.dtype, device=x.verts.device).reshape(-1)
        if not torch.isfinite(times).all():
            raise NumericalError(f"interpolation times must be finite, got {times.tolist()}")
        result = self.matcher.match(x, y)
        frames = self.blend(x.verts, y.verts, result.p2p, times)
        return MatchResult(p2p=result.p2p, p2p_inv=result.p2p_inv, deformation=frames, times=times,
                           extras=dict(result.extras))

    def match(self, x, y) -> MatchResult:
        """:meth:`interpolate` at the default frames ``interp_times``."""
        return self.interpolate(x, y, torch.tensor(self.interp_times))
