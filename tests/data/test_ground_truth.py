"""Pairing of the reference points of two shapes (shapecorr.data.ground_truth)."""

import numpy as np
import pytest

from shapecorr.data.ground_truth import ground_truth_indices
from shapecorr.errors import CorrespondenceError


def test_ground_truth_indices():
    faces = np.array([[0, 1, 2]])
    gx, gy = ground_truth_indices(np.array([2, 0]), np.array([1, 1]), 3, 2)
    assert gx.tolist() == [2, 0] and gy.tolist() == [1, 1]
    gx, gy = ground_truth_indices(None, None, 3, 3, faces, faces)
    assert gx.tolist() == [0, 1, 2] == gy.tolist()
    with pytest.raises(CorrespondenceError, match="connectivity"):
        ground_truth_indices(None, None, 3, 4)
    with pytest.raises(CorrespondenceError, match="connectivity"):
        ground_truth_indices(None, None, 3, 3, faces, faces[:, ::-1])
    with pytest.raises(CorrespondenceError, match="missing for Y"):
        ground_truth_indices(np.array([0]), None, 3, 3)
    with pytest.raises(CorrespondenceError, match="3 vertices"):
        ground_truth_indices(np.array([3]), np.array([0]), 3, 3)
