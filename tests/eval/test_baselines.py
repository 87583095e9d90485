"""Baseline matchers and MatchResult (shapecorr.matching.baselines, shapecorr.matching.result)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from shapecorr.errors import ConfigError, CorrespondenceError, NumericalError
from shapecorr.eval import scoring
from shapecorr.matching.baselines import (
    DescriptorNN,
    IdentityGT,
    PrecomputedMaps,
)
from shapecorr.matching.nearest_neighbors import bidirectional_nearest_neighbors
from shapecorr.matching.result import Matcher, MatchResult


def test_match_result_validation():
    ok = MatchResult(p2p=torch.tensor([0, 2, 1]))
    assert ok.validate(3, 3) is ok
    with pytest.raises(CorrespondenceError, match="one entry per source vertex"):
        MatchResult(p2p=torch.tensor([0, 1])).validate(3, 3, "a__b")
    with pytest.raises(CorrespondenceError, match="target has 3 vertices"):
        MatchResult(p2p=torch.tensor([0, 1, 3])).validate(3, 3)
    with pytest.raises(CorrespondenceError, match="integer"):
        MatchResult(p2p=torch.tensor([0.0, 1.0, 2.0])).validate(3, 3)
    with pytest.raises(CorrespondenceError, match="p2p_inv"):
        MatchResult(p2p=torch.tensor([0, 1, 1]), p2p_inv=torch.tensor([0, 5])).validate(3, 2)
    with pytest.raises(CorrespondenceError, match="frame times"):
        MatchResult(p2p=torch.tensor([0]), deformation=torch.zeros(2, 1, 3))
    nan = torch.full((2, 1, 3), float("nan"))
    bad = MatchResult(p2p=torch.tensor([0]), deformation=nan, times=torch.tensor([0.0, 1.0]))
    with pytest.raises(NumericalError):
        bad.validate(1, 1)


def test_baselines_are_matchers(tmp_path):
    assert isinstance(IdentityGT(), Matcher)
    assert isinstance(DescriptorNN(), Matcher)
    assert isinstance(PrecomputedMaps(tmp_path), Matcher)
    assert DescriptorNN("shot").required_operators == {"shot": {}}


def test_identity_gt_has_zero_error(spheres):
    matcher = IdentityGT()
    for i, j in [(0, 1), (2, 0)]:
        x, y = spheres[i], spheres[j]
        p2p = matcher.match(x, y).validate(x.shape.n_verts, y.shape.n_verts).p2p
        scores = scoring.score_map(p2p, x, y, spheres.geodesics(j))
        assert np.all(scores["errors"] == 0.0)
        # reference vertices go exactly to their ground truth; the others to a nearby reference's image
        assert torch.equal(p2p[x.corres], y.corres)


def test_identity_gt_conflicting_ground_truth_keeps_first():
    """Two reference points on one vertex of x but on different vertices of y: the first one listed wins."""
    from shapecorr.data.datasets import ShapeSample
    from shapecorr.data.shape import make_shape

    verts = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]])

    def sample(name, corres):
        shape = make_shape(verts, faces, name, normalization=None)
        return ShapeSample(
            shape=shape,
            operators={"eigenbasis": {"evals": torch.zeros(1), "evecs": torch.ones(4, 1), "mass": torch.ones(4)}},
            corres=torch.tensor(corres),
        )

    x, y = sample("x", [0, 0, 1]), sample("y", [2, 3, 1])
    p2p = IdentityGT().match(x, y).p2p
    assert p2p[0] == 2 and p2p[1] == 1


def test_identity_gt_without_vts_uses_identity(spheres):
    x = replace(spheres[0], corres=None, corres_sym=None)
    assert torch.equal(IdentityGT().match(x, x).p2p, torch.arange(x.shape.n_verts))
    y = replace(spheres[1], corres=None, corres_sym=None)
    with pytest.raises(CorrespondenceError, match="connectivity"):
        IdentityGT().match(x, y)  # same vertex count, different faces: no ground truth


def test_nearest_neighbors_matches_brute_force():
    g = torch.Generator().manual_seed(0)
    a, b = torch.randn(300, 5, generator=g, dtype=torch.float64), torch.randn(200, 5, generator=g, dtype=torch.float64)
    dist = torch.cdist(a, b)
    # DescriptorNN's search: the chunked brute force in the input dtype
    for chunk in (1, 37, 1000):
        ab, ba = bidirectional_nearest_neighbors(a, b, backend="brute", block_size=chunk, exact=False)
        assert torch.equal(ab, dist.argmin(dim=1)) and torch.equal(ba, dist.argmin(dim=0))
    # ties go to the lowest index, across chunks too
    dup = torch.cat([b[:1], b[:1]])
    assert bidirectional_nearest_neighbors(dup, b[:3], backend="brute", block_size=1, exact=False)[1][0] == 0


@pytest.mark.parametrize("normalize", ["none", "l2", "standardize"])
def test_descriptor_nn_recovers_exact_map(spheres, normalize):
    """Descriptors that are equal on corresponding vertices give the exact map, in both directions."""
    x, y = spheres[0], spheres[2]
    result = DescriptorNN("wks", normalize=normalize).match(x, y)
    assert torch.equal(result.p2p, torch.from_numpy(spheres.true_map(0, 2)))
    assert torch.equal(result.p2p_inv, torch.from_numpy(spheres.true_map(2, 0)))


def test_descriptor_nn_errors(spheres):
    with pytest.raises(ConfigError, match="descriptor must be one of"):
        DescriptorNN("sift")
    with pytest.raises(ConfigError, match="normalize"):
        DescriptorNN(normalize="whiten")
    with pytest.raises(ConfigError, match="no 'hks' descriptor"):
        DescriptorNN("hks").match(spheres[0], spheres[1])
    bad = replace(spheres[0], operators={**spheres[0].operators, "wks": {"wks": torch.full((162, 8), float("nan"))}})
    with pytest.raises(NumericalError, match="NaN"):
        DescriptorNN("wks").match(bad, spheres[1])


def test_precomputed_maps(spheres, tmp_path):
    x, y = spheres[0], spheres[1]
    true = spheres.true_map(0, 1)
    (tmp_path / "s0__s1.txt").write_text("\n".join(map(str, true)) + "\n")
    (tmp_path / "s0__s1.map").write_text("\n".join(map(str, true + 1)) + "\n")
    np.save(tmp_path / "s0__s1.npy", true)
    for kwargs in ({}, {"one_based": True, "extension": "map"}, {"extension": "npy"}):
        p2p = PrecomputedMaps(tmp_path, **kwargs).match(x, y).p2p
        assert torch.equal(p2p, torch.from_numpy(true))
    # a map written for another shape size is refused with the file named
    (tmp_path / "s0__s2.txt").write_text("\n".join(map(str, true[:-5])) + "\n")
    with pytest.raises(CorrespondenceError, match=r"s0__s2\.txt.*162 vertices"):
        PrecomputedMaps(tmp_path).match(x, spheres[2])
    np.save(tmp_path / "s0__s2.npy", true[:-5])
    with pytest.raises(CorrespondenceError, match=r"s0__s2\.npy.*157 entries"):
        PrecomputedMaps(tmp_path, extension="npy").match(x, spheres[2])
    with pytest.raises(CorrespondenceError, match=r"s1__s0\.txt"):
        PrecomputedMaps(tmp_path).match(y, x)  # missing file
    with pytest.raises(CorrespondenceError, match="does not exist"):
        PrecomputedMaps(tmp_path / "nope")


@pytest.mark.parametrize("dim", [4, 40])
def test_descriptor_nn_backends_agree_at_input_resolution(spheres, dim):
    """auto (kd-tree for low d, chunks otherwise), kd-tree and small chunks give the dense argmin, at full size."""
    x, y = spheres[0], spheres[2]
    g = torch.Generator().manual_seed(1)
    fx = torch.randn(x.shape.n_verts, dim, generator=g)
    fy = torch.randn(y.shape.n_verts, dim, generator=g)
    x = replace(x, operators={**x.operators, "hks": {"hks": fx}})
    y = replace(y, operators={**y.operators, "hks": {"hks": fy}})
    dense = torch.cdist(fx.double(), fy.double())
    for backend, chunk in (("auto", 1024), ("kdtree", 1024), ("brute", 7)):
        result = DescriptorNN("hks", backend=backend, chunk_rows=chunk).match(x, y)
        assert result.p2p.shape == (x.shape.n_verts,) and result.p2p_inv.shape == (y.shape.n_verts,)
        assert torch.equal(result.p2p, dense.argmin(1)) and torch.equal(result.p2p_inv, dense.argmin(0))
    with pytest.raises(ConfigError, match="backend"):
        DescriptorNN(backend="faiss")
