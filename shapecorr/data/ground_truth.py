"""Ground truth of a pair: which vertex of X corresponds to which vertex of Y.

The readers in :mod:`shapecorr.data.io` give each shape its ``.vts`` reference points; this module pairs them
up. It lives on the data side so that both the matchers (e.g. the ``identity_gt`` baseline in
:mod:`shapecorr.matching.baselines`) and the evaluation protocol (:mod:`shapecorr.eval.scoring`) use it without
the matching layer importing the evaluation layer.
"""

from __future__ import annotations

import numpy as np

from shapecorr.errors import CorrespondenceError
from shapecorr.geometry.mesh import as_numpy, check_index


def ground_truth_indices(corres_x, corres_y, n_x: int, n_y: int, faces_x=None, faces_y=None):
    """Reference-point indices ``(ref_x, ref_y)`` of a pair.

    With ``.vts`` files on both shapes, entry r of each is the same point (FAUST_r/SCAPE_r convention).
    Without ground truth on either shape, two shapes with the same connectivity correspond vertex by vertex
    (Princeton protocol: the ground truth is then the identity).

    Parameters
    ----------
    corres_x, corres_y : (R,) int or None
        Zero-based reference vertices of X and Y.
    n_x, n_y : int
        Vertex counts.
    faces_x, faces_y : (f, 3) int, optional
        Triangles, used to check for shared connectivity when there is no ground truth.

    Returns
    -------
    ref_x, ref_y : (R,) int64
    """
    if corres_x is not None and corres_y is not None:
        ref_x = check_index(corres_x, n_x, "ground truth of X")
        ref_y = check_index(corres_y, n_y, "ground truth of Y")
        if ref_x.shape != ref_y.shape:
            raise CorrespondenceError(
                f"ground truth lengths differ: {ref_x.shape[0]} reference points on X, {ref_y.shape[0]} on Y"
            )
        return ref_x, ref_y
    if corres_x is None and corres_y is None:
        same = n_x == n_y and (
            faces_x is None or faces_y is None or np.array_equal(as_numpy(faces_x), as_numpy(faces_y))
        )
        if same:
            ident = np.arange(n_x, dtype=np.int64)
            return ident, ident.copy()
        raise CorrespondenceError(
            f"no ground truth (.vts) for either shape and they do not share connectivity ({n_x} vs {n_y} "
            "vertices, or different faces): cannot evaluate this pair"
        )
    which = "X" if corres_x is None else "Y"
    raise CorrespondenceError(f"ground truth (.vts) is missing for {which} but present for the other shape")
