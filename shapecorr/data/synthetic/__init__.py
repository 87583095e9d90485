"""Procedural deformable creatures with dense ground truth: the embedded default dataset (``data=synthetic``).

Humanoids and quadrupeds, many subjects (body proportions) and poses (linear blend skinning within joint
limits), every shape independently remeshed, written as a FAUST_r-style folder (``off/``, ``corres/*.vts``,
``splits/``). Modules, one concept each:

- ``skeleton``: body plans (bones, joint limits, implicit primitives);
- ``meshing``: implicit field -> marching cubes -> clean closed surface, topology checks;
- ``templates``: canonical template mesh, skinning weights, mirror map;
- ``skinning``: subject proportions and linear blend skinning;
- ``poses``: key poses, random poses, self-contact detection;
- ``groundtruth``: dense trace, reference points, cross-class chart map;
- ``corruptions``: noise, holes, fused self-contacts;
- ``config``: :class:`SyntheticConfig` and presets;
- ``generator``: shapes, files, :func:`ensure_synthetic_dataset`.
"""

from shapecorr.data.synthetic.config import GENERATOR_VERSION, PRESETS, SyntheticConfig, preset
from shapecorr.data.synthetic.generator import (
    SyntheticShape,
    ShapeSpec,
    class_templates,
    ensure_synthetic_dataset,
    generate_dataset,
    generate_shape,
    reference_points,
    shape_specs,
    split_names,
)

__all__ = [
    "GENERATOR_VERSION",
    "PRESETS",
    "ShapeSpec",
    "SyntheticConfig",
    "SyntheticShape",
    "class_templates",
    "ensure_synthetic_dataset",
    "generate_dataset",
    "generate_shape",
    "preset",
    "reference_points",
    "shape_specs",
    "split_names",
]
