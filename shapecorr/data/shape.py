"""The :class:`Shape` record and the normalization every shape goes through on load.

Normalization (CONVENTIONS.md, "Units"): translate so that the centroid is at the origin, then scale uniformly
so that the total surface area equals ``target_area``. The default ``target_area = (2/3)**2`` gives
sqrt(area) = 2/3; the original MATLAB pipeline of Smooth/Deep Shells used ``target_area = 0.44``
with the plain vertex mean as centroid (``center="mean"``) — both are reachable through
:class:`Normalization`. The applied transform is stored on the shape so that results can be written back in
the input units: ``raw = verts / scale + offset``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from shapecorr.errors import ConfigError, InvalidMeshError
from shapecorr.geometry.mesh import triangle_areas

#: Default total area after normalization: sqrt(area) = 2/3 (CONVENTIONS.md; Deep Shells used 0.44 ~ (2/3)^2).
DEFAULT_TARGET_AREA = (2.0 / 3.0) ** 2


@dataclass(frozen=True)
class Normalization:
    """How shapes are normalized on load.

    Attributes
    ----------
    target_area
        Total surface area after scaling; ``None`` disables scaling.
    center
        ``"area"``: area-weighted centroid (of the triangles' barycenters); ``"mean"``: plain vertex mean
        (the MATLAB convention); ``"none"``: no translation.
    """

    target_area: float | None = DEFAULT_TARGET_AREA
    center: str = "area"

    def __post_init__(self):
        if self.center not in ("area", "mean", "none"):
            raise ConfigError(f"normalization.center must be 'area', 'mean' or 'none', got {self.center!r}")
        if self.target_area is not None and not self.target_area > 0:
            raise ConfigError(f"normalization.target_area must be positive, got {self.target_area}")


@dataclass(frozen=True, eq=False)
class Shape:
    """A triangle mesh in normalized coordinates plus the transform that produced them.

    Attributes
    ----------
    verts
        ``(n, 3)`` float32 vertex positions, normalized.
    faces
        ``(f, 3)`` int64 zero-based triangle indices.
    name
        Identifier (file stem), used in pair names and output files.
    path
        File the shape was read from, if any.
    scale
        Uniform factor applied after the translation: ``verts = (raw - offset) * scale``.
    offset
        ``(3,)`` float64 translation subtracted from the raw vertices.
    """

    verts: torch.Tensor
    faces: torch.Tensor
    name: str
    path: Path | None = None
    scale: float = 1.0
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def n_verts(self) -> int:
        """Number of vertices."""
        return int(self.verts.shape[0])

    @property
    def n_faces(self) -> int:
        """Number of faces."""
        return int(self.faces.shape[0])

    def to(self, device: torch.device | str) -> "Shape":
        """Copy of the shape with its tensors on ``device``."""
        return replace(self, verts=self.verts.to(device), faces=self.faces.to(device))

    def denormalize(self, verts: torch.Tensor | np.ndarray) -> np.ndarray:
        """Map normalized positions ``(..., 3)`` back to the input units (float64 numpy)."""
        v = verts.detach().cpu().numpy() if isinstance(verts, torch.Tensor) else np.asarray(verts)
        return v.astype(np.float64) / self.scale + self.offset

    def __repr__(self) -> str:
        return f"Shape(name={self.name!r}, n_verts={self.n_verts}, n_faces={self.n_faces})"


def normalization_transform(
    verts: np.ndarray, faces: np.ndarray, normalization: Normalization = Normalization()
) -> tuple[np.ndarray, float]:
    """Offset and scale that normalize a mesh: ``normalized = (verts - offset) * scale``.

    Parameters
    ----------
    verts : (n, 3) float
    faces : (f, 3) int
    normalization : Normalization

    Returns
    -------
    offset : (3,) float64
    scale : float
    """
    v = np.asarray(verts, dtype=np.float64)
    areas = triangle_areas(v, faces)
    total = float(areas.sum())
    if normalization.center == "area":
        if total <= 0:
            raise InvalidMeshError("mesh has zero total area; cannot compute its area-weighted centroid")
        barycenters = v[np.asarray(faces)].mean(axis=1)
        offset = (areas[:, None] * barycenters).sum(axis=0) / total
    elif normalization.center == "mean":
        offset = v.mean(axis=0)
    else:
        offset = np.zeros(3)
    if normalization.target_area is None:
        scale = 1.0
    else:
        if total <= 0:
            raise InvalidMeshError("mesh has zero total area; cannot scale it to a target area")
        scale = float(np.sqrt(normalization.target_area / total))
    return offset, scale


def make_shape(
    verts: np.ndarray,
    faces: np.ndarray,
    name: str,
    path: Path | None = None,
    normalization: Normalization | None = Normalization(),
) -> Shape:
    """Build a normalized :class:`Shape` from raw arrays.

    Parameters
    ----------
    verts : (n, 3) float
        Raw vertex positions (input units).
    faces : (f, 3) int
        Zero-based triangles.
    name, path
        Identity of the shape.
    normalization
        ``None`` keeps the raw coordinates (scale 1, offset 0).
    """
    v = np.asarray(verts, dtype=np.float64)
    if normalization is None:
        offset, scale = np.zeros(3), 1.0
    else:
        offset, scale = normalization_transform(v, faces, normalization)
    return Shape(
        verts=torch.from_numpy(((v - offset) * scale).astype(np.float32)),
        faces=torch.from_numpy(np.ascontiguousarray(faces, dtype=np.int64)),
        name=name,
        path=None if path is None else Path(path),
        scale=scale,
        offset=offset,
    )
