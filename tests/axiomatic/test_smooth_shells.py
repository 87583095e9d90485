"""Tests of the axiomatic Smooth Shells matcher (shapecorr.axiomatic.smooth_shells)."""

from __future__ import annotations

import itertools
import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree

from shapecorr.axiomatic.smooth_shells import (
    SmoothShells,
    SmoothShellsConfig,
    basis_features,
    k_schedule,
    random_search_init,
    refine,
    rigid_alignment,
    shells_shape,
    smooth_shells,
)
from shapecorr.data.shape import triangle_areas
from shapecorr.errors import ConfigError
from shapecorr.geometry.laplace_beltrami import eigenbasis
from shapecorr.geometry.remeshing import remesh
from shapecorr.geometry.shot_descriptor import shot

#: A small version of the published pipeline for ~400-vertex meshes: same stages, shorter schedules.
SMALL = SmoothShellsConfig(k_max=40, k_array_length=6, num_mcmc=6, problem_size_init=150, mcmc_batch=4)
#: With all 8 rigid candidates scored together: a random rotation can leave a half turn about the 2nd principal
#: axis that the original's greedy 2 + 4 search misses.
SMALL_JOINT = replace(SMALL, rigid_joint=True)


# Small tensors: one torch thread (fixture in tests/conftest.py).
pytestmark = pytest.mark.usefixtures("single_thread")


def _shape(verts, faces, name, config=SMALL):
    evals, evecs, mass = eigenbasis(verts, faces, config.num_eigs)
    def f32(a):
        return torch.tensor(np.asarray(a), dtype=torch.float32)
    return shells_shape(f32(verts), torch.tensor(faces), f32(evals), f32(evecs), f32(mass),
                        shot=f32(shot(verts, faces)), name=name)


def _rotation(rng) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


@pytest.fixture(scope="module")
def base(asymmetric_blob):
    ico = trimesh.creation.icosphere(subdivisions=3)
    blob = asymmetric_blob(np.asarray(ico.vertices), np.random.default_rng(0))
    verts, faces = remesh(blob, np.asarray(ico.faces), 400)
    verts = verts * np.sqrt(0.44 / triangle_areas(verts, faces).sum())
    verts = verts - verts.mean(0)
    edge = float(np.linalg.norm(verts[faces[:, 0]] - verts[faces[:, 1]], axis=1).mean())
    return {"verts": verts, "faces": faces, "x": _shape(verts, faces, "blob"), "edge": edge}


def _permuted_copy(base, rotation, shift, rng, name):
    """Y = rotation X + shift with permuted vertices; gt[i] = vertex of Y of vertex i of X."""
    perm = rng.permutation(len(base["verts"]))  # vertex j of Y is vertex perm[j] of X
    gt = np.argsort(perm)
    verts_y = (base["verts"] @ rotation.T + shift)[perm]
    return {"y": _shape(verts_y, gt[base["faces"]], name), "gt": gt, "perm": perm, "verts_y": verts_y}


@pytest.fixture(scope="module")
def rigid_pair(base):
    rng = np.random.default_rng(1)
    pair = _permuted_copy(base, _rotation(rng), np.array([0.05, -0.02, 0.03]), rng, "blob_moved")
    pair["result"] = smooth_shells(base["x"], pair["y"], SMALL_JOINT)
    assert [len(s) for s in pair["result"].rigid_scores] == [8]
    return pair


def test_k_schedule_is_the_published_quartic_one():
    ks = k_schedule(500, 50)
    assert len(ks) == 51 and ks[0] == 20 and ks[-1] == 500
    assert list(ks[:12]) == [20, 21, 21, 22, 22, 23, 24, 24, 25, 27, 28, 29]
    assert list(ks[-5:]) == [388, 414, 441, 470, 500]
    assert all(b >= a for a, b in itertools.pairwise(ks))
    assert SmoothShellsConfig().num_eigs == 509 and SmoothShellsConfig().k_array == ks


def test_config_validation():
    with pytest.raises(ConfigError):
        SmoothShellsConfig(k_max=10)
    with pytest.raises(ConfigError):
        SmoothShellsConfig(nn_backend="faiss")
    with pytest.raises(ConfigError):
        SmoothShellsConfig(fac_feat=-1.0)


def test_too_few_eigenpairs_is_a_config_error(base, rigid_pair):
    with pytest.raises(ConfigError, match="eigenpairs"):
        smooth_shells(base["x"], rigid_pair["y"], replace(SMALL, k_max=60))


def test_basis_features_are_normalized_per_row(base, rigid_pair):
    fx, fy = basis_features(base["x"], rigid_pair["y"])
    assert fx.shape == fy.shape == (SMALL.num_eigs, 352 + 100)
    row = 0.5 * (fx.norm(dim=1) + fy.norm(dim=1))
    torch.testing.assert_close(row, torch.ones_like(row), rtol=1e-4, atol=1e-5)


def test_recovers_a_rigid_motion_exactly(rigid_pair):
    res = rigid_pair["result"]
    assert (res.map_x_to_y.numpy() == rigid_pair["gt"]).mean() > 0.97
    assert (res.map_y_to_x.numpy() == rigid_pair["perm"]).mean() > 0.97
    # the deformed X lands on Y
    target = rigid_pair["verts_y"][rigid_pair["gt"]]
    spread = np.linalg.norm(target - target.mean(0), axis=1).mean()
    assert np.linalg.norm(res.deformed_x.numpy() - target, axis=1).mean() < 0.05 * spread


def test_each_layer_does_not_increase_its_objective(rigid_pair):
    obj = rigid_pair["result"].level_objectives
    assert obj.shape == (len(SMALL.k_array), 2)
    assert torch.isfinite(obj).all()
    assert (obj[:, 1] <= obj[:, 0] * (1 + 1e-9) + 1e-12).all()
    assert (obj[:, 1] < obj[:, 0]).any()


def test_recovers_a_remeshing(base):
    rng = np.random.default_rng(2)
    rest, faces_y = remesh(base["verts"], base["faces"], 360)
    rot = _rotation(rng)
    y = _shape(rest @ rot.T, faces_y, "blob_remeshed")
    gt = cKDTree(rest).query(base["verts"])[1]
    res = smooth_shells(base["x"], y, SMALL)
    err = np.linalg.norm(rest[res.map_x_to_y.numpy()] - rest[gt], axis=1).mean() / base["edge"]
    assert err < 1.0  # mean error below one edge length


@pytest.mark.parametrize("feature_score", [0.0, 0.3])
def test_rigid_stage_resolves_a_half_turn(base, feature_score):
    rng = np.random.default_rng(3)
    centred = base["verts"] - base["verts"].mean(0)
    axis = np.linalg.svd(centred, full_matrices=False)[2][2]  # 3rd principal axis
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    half_turn = np.eye(3) + 2 * k @ k  # Rodrigues with angle pi
    pair = _permuted_copy(base, half_turn, np.zeros(3), rng, "blob_flipped")
    x = base["x"]
    feats = basis_features(x, pair["y"])
    rot, trans, scores = rigid_alignment(x, pair["y"], replace(SMALL, score_descriptors=feature_score), feats)
    aligned = (x.spectral.verts @ rot.T + trans).numpy()
    target = pair["verts_y"][pair["gt"]]
    err_aligned = np.linalg.norm(aligned - target, axis=1).mean()
    err_unaligned = np.linalg.norm(base["verts"] - target, axis=1).mean()
    assert err_aligned < 0.3 * err_unaligned
    # the half turn is the residual rotation (up to what the axis ICP leaves)
    angle = math.degrees(math.acos(np.clip((np.trace(rot.numpy().astype(float) @ half_turn.T) - 1) / 2, -1, 1)))
    assert angle < 30.0
    assert [len(s) for s in scores] == list(SMALL.rigid_rotations)


def test_feature_score_needs_the_basis_features(base, rigid_pair):
    with pytest.raises(ConfigError, match="score_descriptors needs the basis features"):
        rigid_alignment(base["x"], rigid_pair["y"], replace(SMALL, score_descriptors=0.3), feats=None)
    with pytest.raises(ConfigError, match="score_descriptors needs the basis features"):
        random_search_init(base["x"], rigid_pair["y"], rigid_pair["y"].spectral.verts,
                           replace(SMALL, score_descriptors=0.3), feats=None)
    with pytest.raises(ConfigError, match="score_descriptors"):
        replace(SMALL, score_descriptors=-1.0)


def test_feature_score_widens_the_margin_of_the_correct_pose(base, rigid_pair):
    """The descriptor disagreement is an extra non-negative block of the residual: no score falls, the correct
    candidate (exact pairs of a rigid copy: equal descriptors) keeps its score, the wrong ones rise."""
    x, y = base["x"], rigid_pair["y"]
    feats = basis_features(x, y)
    _, _, plain = rigid_alignment(x, y, SMALL_JOINT, feats)
    _, _, with_features = rigid_alignment(x, y, replace(SMALL_JOINT, score_descriptors=0.3), feats)
    plain, with_features = plain[0], with_features[0]
    best = int(torch.argmin(plain))
    assert int(torch.argmin(with_features)) == best
    assert torch.isclose(with_features[best], plain[best], rtol=1e-6)
    others = torch.arange(len(plain)) != best
    assert (with_features[others] > 2.0 * plain[others]).all()


def test_deterministic_for_a_seed_and_independent_of_the_batch(base, rigid_pair):
    again = smooth_shells(base["x"], rigid_pair["y"], replace(SMALL_JOINT, mcmc_batch=6))
    first = rigid_pair["result"]
    assert torch.equal(first.map_x_to_y, again.map_x_to_y)
    torch.testing.assert_close(first.mcmc_scores, again.mcmc_scores, rtol=1e-6, atol=0)
    torch.testing.assert_close(first.tau, again.tau, rtol=1e-4, atol=1e-6)
    other = smooth_shells(base["x"], rigid_pair["y"], replace(SMALL_JOINT, seed=1, no_rigid=True))
    assert not torch.equal(first.mcmc_scores, other.mcmc_scores)


def test_same_result_with_surrogate_runs_side_by_side(base, rigid_pair):
    # with 2 threads the random-search batches and the rigid candidates run in parallel threads (each with one
    # intra-op thread): every number must be the serial one, and the thread count must be restored
    torch.set_num_threads(2)
    try:
        parallel = smooth_shells(base["x"], rigid_pair["y"], SMALL)
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(1)
    serial = smooth_shells(base["x"], rigid_pair["y"], SMALL)
    assert torch.equal(parallel.mcmc_scores, serial.mcmc_scores)
    assert all(torch.equal(a, b) for a, b in zip(parallel.rigid_scores, serial.rigid_scores))
    assert torch.equal(parallel.rotation, serial.rotation) and torch.equal(parallel.tau, serial.tau)
    assert torch.equal(parallel.map_x_to_y, serial.map_x_to_y)


def test_refine_improves_a_noisy_map(base, rigid_pair):
    rng = np.random.default_rng(4)
    gt = rigid_pair["gt"]
    noisy = gt.copy()
    wrong = rng.random(len(gt)) < 0.3
    noisy[wrong] = rng.integers(0, len(gt), int(wrong.sum()))
    # the deformation must absorb the rigid motion: start at a coarse shell with the X -> Y map only
    res = refine(base["x"], rigid_pair["y"], torch.from_numpy(noisy), k_start=20, config=SMALL)
    acc = (res.map_x_to_y.numpy() == gt).mean()
    assert acc > 0.85 and acc > (noisy == gt).mean() + 0.15
    assert res.k_array[0] == 20 and res.mcmc_scores is None
    with pytest.raises(ConfigError):
        refine(base["x"], rigid_pair["y"], torch.zeros(3, dtype=torch.int64), config=SMALL)


def test_matcher_gives_maps_and_frames(base, rigid_pair):
    settings = {k: getattr(SMALL_JOINT, k) for k in ("k_max", "k_array_length", "num_mcmc", "problem_size_init",
                                                      "mcmc_batch", "rigid_joint")}
    matcher = SmoothShells(interp_times=(0.0, 0.5, 1.0), **settings)
    assert matcher.required_operators == {"eigenbasis": {"k": SMALL.num_eigs}, "shot": {}}

    def sample(s):
        sp = s.spectral
        return SimpleNamespace(name=s.name, verts=sp.verts, faces=sp.faces, evals=s.evals, evecs=sp.evecs,
                               mass=sp.mass, features={"shot": s.shot})

    x, y = sample(base["x"]), sample(rigid_pair["y"])
    out = matcher.match(x, y).validate(len(base["verts"]), len(rigid_pair["verts_y"]))
    torch.testing.assert_close(out.deformation[0], x.verts)
    torch.testing.assert_close(out.deformation[2], rigid_pair["result"].deformed_x)
    torch.testing.assert_close(out.deformation[1], 0.5 * (out.deformation[0] + out.deformation[2]))
    assert torch.equal(out.p2p, rigid_pair["result"].map_x_to_y)
    with pytest.raises(ConfigError):
        SmoothShells(k_maxx=3)


def test_rigid_keep_input_scores_the_input_orientation(base):
    rng = np.random.default_rng(5)
    x = base["x"]
    config = replace(SMALL, score_descriptors=0.3, rigid_keep_input=True)
    # an already aligned copy: the input orientation scores lowest and is kept exactly
    same = _permuted_copy(base, np.eye(3), np.zeros(3), rng, "blob_same")
    rot, _, scores = rigid_alignment(x, same["y"], config, basis_features(x, same["y"]))
    assert [len(s) for s in scores] == [*SMALL.rigid_rotations, 1]
    assert torch.equal(rot.to(torch.float64), torch.eye(3, dtype=torch.float64))
    # a half turn: the input orientation is scored but loses to the rigid stage's pose
    centred = base["verts"] - base["verts"].mean(0)
    axis = np.linalg.svd(centred, full_matrices=False)[2][2]
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    turned = _permuted_copy(base, np.eye(3) + 2 * k @ k, np.zeros(3), rng, "blob_turned")
    rot, _, scores = rigid_alignment(x, turned["y"], config, basis_features(x, turned["y"]))
    assert float(scores[-1][0]) > float(scores[-2].min())
    assert not torch.equal(rot.to(torch.float64), torch.eye(3, dtype=torch.float64))
