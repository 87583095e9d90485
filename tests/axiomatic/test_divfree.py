"""Tests of the divergence-free matcher (shapecorr.axiomatic.divfree) on a small asymmetric closed surface."""

from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from hydra.utils import instantiate
from omegaconf import OmegaConf
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from shapecorr.axiomatic.divfree import (
    DivFreeMatcher, cycle_consistent, functional_map_from_maps, functional_map_residuals, knn_graph_edges,
    orientation_candidates, principal_frame, rigid_icp, trimmed_functional_map,
)
from shapecorr.data.datasets import ShapeSample
from shapecorr.data.shape import make_shape
from shapecorr.errors import ConfigError
from shapecorr.eval.metrics import relative_volume_change, surface_area
from shapecorr.geometry import divergence_free as df
from shapecorr.geometry.laplace_beltrami import eigenbasis
from shapecorr.geometry.normals import vertex_normals
from shapecorr.geometry.remeshing import remesh
from shapecorr.geometry.shot_descriptor import shot

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "model" / "divfree.yaml"
# A short schedule (two levels, few samples and steps) so that each fit takes a few seconds; SHOT in the product
# space (the small test surfaces carry SHOT, computed here, and no spectral descriptors).
FAST = {"modes": (2, 4), "samples": 150, "iterations": (25, 25), "lr": (0.01, 0.005), "descriptor_weight": (0.2, 0.1),
        "n_steps": 8, "corr_every": 5, "descriptor": "shot"}

# Exact-repeat checks below: one torch thread (parallel reductions may differ in the last bits across runs).
pytestmark = pytest.mark.usefixtures("single_thread")


def _blob(n_verts: int):
    mesh = trimesh.creation.icosphere(subdivisions=3)
    v = np.asarray(mesh.vertices)
    v = v * (1 + 0.25 * np.sin(3 * v[:, 0]) * np.cos(2 * v[:, 1]) + 0.15 * v[:, 2] ** 3)[:, None] * [1.0, 0.7, 0.5]
    return remesh(v, np.asarray(mesh.faces), n_verts)


def _sample(verts, faces, name):
    evals, evecs, mass = eigenbasis(verts, faces, 12)  # the spectral extraction's functional map (k = 10)
    return ShapeSample(
        shape=make_shape(verts, faces, name, normalization=None),
        operators={
            "eigenbasis": {"evals": torch.tensor(evals, dtype=torch.float32),
                           "evecs": torch.tensor(evecs, dtype=torch.float32),
                           "mass": torch.tensor(mass, dtype=torch.float32)},
            "shot": {"shot": torch.tensor(shot(verts, faces), dtype=torch.float32)},
        },
    )


def _rotation(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def rigid_pair():
    v, f = _blob(300)
    perm = np.random.default_rng(0).permutation(len(v))  # vertex i of x is vertex perm[i] of y
    vy = np.empty_like(v)
    vy[perm] = v @ _rotation(0.15).T + [0.05, -0.03, 0.02]
    x, y = _sample(v, f, "x"), _sample(vy, perm[f], "y")
    return x, y, perm


@pytest.fixture(scope="module")
def rigid_result(rigid_pair):
    """The flow alone (no pre-alignment) recovers the small rotation."""
    x, y, _ = rigid_pair
    return DivFreeMatcher(**FAST, prealign="none").match(x, y)


def test_rigid_motion_recovered(rigid_pair, rigid_result):
    x, y, perm = rigid_pair
    r = rigid_result.validate(x.shape.n_verts, y.shape.n_verts)
    vy = y.verts.numpy()
    scale = np.sqrt(surface_area(vy, y.faces.numpy()))
    err = np.linalg.norm(vy[r.p2p.numpy()] - vy[perm], axis=1) / scale
    err_inv = np.linalg.norm(x.verts.numpy()[r.p2p_inv.numpy()[perm]] - x.verts.numpy(), axis=1) / scale
    assert (r.p2p.numpy() == perm).mean() > 0.9 and err.mean() < 0.01
    assert err_inv.mean() < 0.01
    # the deformed x lands on y (the rotation is recovered by the flow, the translation by the box centres)
    frame = r.deformation[-1].numpy()
    assert np.linalg.norm(frame - vy[perm], axis=1).mean() / scale < 0.01
    # without optimization (identity flow) the same product space gets it wrong: the test can fail
    r0 = DivFreeMatcher(**{**FAST, "iterations": (0, 0)}, prealign="none").match(x, y)
    err0 = np.linalg.norm(vy[r0.p2p.numpy()] - vy[perm], axis=1) / scale
    assert err0.mean() > 3 * err.mean() + 0.005
    assert r.extras["fit_seconds"] < 30  # measured ~3-8 s on a shared 2-core CPU


def test_frames_and_volume(rigid_pair, rigid_result):
    x, y, _ = rigid_pair
    r = rigid_result
    assert r.deformation.shape == (5, x.shape.n_verts, 3)
    torch.testing.assert_close(r.times, torch.tensor([0.0, 0.25, 0.5, 0.75, 1.0]))
    torch.testing.assert_close(r.deformation[0], x.verts, atol=1e-5, rtol=0)
    faces = x.faces.numpy()
    for frame in r.deformation[1:]:
        assert abs(relative_volume_change(x.verts.numpy(), faces, frame.numpy())) < 0.01
    # interpolate() at other times, extrapolating, gives the same maps
    matcher = DivFreeMatcher(**FAST, prealign="none")
    r2 = matcher.interpolate(x, y, [0.0, 0.5, 1.0, 1.5])
    assert r2.deformation.shape[0] == 4
    assert torch.equal(r2.p2p, r.p2p)
    torch.testing.assert_close(r2.deformation[2], r.deformation[4])


def test_deterministic(rigid_pair, rigid_result):
    x, y, _ = rigid_pair
    again = DivFreeMatcher(**FAST, prealign="none").match(x, y)
    assert torch.equal(again.p2p, rigid_result.p2p) and torch.equal(again.p2p_inv, rigid_result.p2p_inv)
    torch.testing.assert_close(again.extras["coeffs"], rigid_result.extras["coeffs"], atol=0, rtol=0)


def test_remeshed_self_match():
    vx, fx = _blob(300)
    vy, fy = _blob(450)  # the same surface, another triangulation
    x, y = _sample(vx, fx, "x"), _sample(vy, fy, "y")
    r = DivFreeMatcher(**FAST, prealign="none").match(x, y)
    scale = np.sqrt(surface_area(vy, fy))
    spacing = cKDTree(vy).query(vx)[0].mean() / scale  # error of the best vertex-to-vertex map
    err = np.linalg.norm(vy[r.p2p.numpy()] - vx, axis=1) / scale
    assert err.mean() < max(0.02, 2 * spacing)
    err_inv = np.linalg.norm(vx[r.p2p_inv.numpy()] - vy, axis=1) / scale
    assert err_inv.mean() < 0.03


def test_config_has_published_defaults():
    matcher = instantiate(OmegaConf.load(CONFIG), _convert_="object")
    assert isinstance(matcher, DivFreeMatcher)
    finest = matcher.levels[-1]
    assert (finest.n_modes, finest.n_samples, finest.iterations) == (8, 2000, 100)
    assert (matcher.n_steps, matcher.lambda_reg, matcher.knn, matcher.margin) == (16, 20.0, 5, 0.05)
    assert matcher.prealign == "smooth_shells"
    assert matcher.descriptors == ("wks",) and matcher.levels[0].descriptor_weight == 2.0
    assert matcher.required_operators == {"wks": {}, "shot": {}, "eigenbasis": {"k": 509}}
    assert (matcher.extraction, matcher.extraction_k, matcher.extraction_iterations) == ("spectral", 10, 2)
    assert (matcher.extraction_fit, matcher.extraction_trim, matcher.extraction_trim_steps) == ("orthogonal", 1.0, 10)
    assert DivFreeMatcher(prealign="pca").required_operators == {"wks": {}, "eigenbasis": {"k": 10}}
    assert DivFreeMatcher(prealign="pca", descriptor="shot", extraction="flow").required_operators == {"shot": {}}


def test_bad_input(rigid_pair):
    x, y, _ = rigid_pair
    with pytest.raises(ConfigError):
        DivFreeMatcher(modes=(2, 4), samples=(100, 200, 300))
    with pytest.raises(ConfigError):
        DivFreeMatcher(rule="euler")
    with pytest.raises(ConfigError, match="prealign"):
        DivFreeMatcher(prealign="icp")
    no_shot = ShapeSample(
        shape=x.shape,
        operators={"eigenbasis": {"evals": x.evals, "evecs": x.evecs, "mass": x.mass}},
    )
    with pytest.raises(ConfigError, match="shot"):
        DivFreeMatcher(**FAST).match(no_shot, y)


def test_knn_graph_edges():
    pts = torch.rand(50, 3)
    edges, counts = knn_graph_edges(pts, 5)
    assert (edges[:, 0] < edges[:, 1]).all()
    assert counts.sum() == 50 * 5  # every directed neighbour listed once
    assert set(counts.tolist()) <= {1.0, 2.0}


def _random_rotation(seed):
    q = np.random.default_rng(seed).normal(size=4)
    return torch.from_numpy(Rotation.from_quat(q / np.linalg.norm(q)).as_matrix())


@pytest.mark.parametrize("mode", ["pca", "pca_turns"])
def test_orientation_candidates_contain_the_rotation(mode):
    v, _ = _blob(300)
    x = torch.tensor(v, dtype=torch.float64)
    rot = _random_rotation(3)
    y = (x - x.mean(0)) @ rot.T + torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)
    cands = orientation_candidates(x, y, mode)
    assert cands.shape == ((4 if mode == "pca" else 8), 3, 3)
    torch.testing.assert_close(torch.linalg.det(cands), torch.ones(len(cands), dtype=torch.float64))
    errors = [float(((x - x.mean(0)) @ c.T + y.mean(0) - y).norm(dim=1).max()) for c in cands]
    assert min(errors) < 1e-6 and sorted(errors)[1] > 0.1  # exactly one candidate is the rotation
    mean, axes = principal_frame(y)
    torch.testing.assert_close(mean, y.mean(0))
    torch.testing.assert_close(axes.T @ axes, torch.eye(3, dtype=torch.float64))


def test_pca_turns_contain_pca_and_the_quarter_turns():
    v, _ = _blob(300)
    x = torch.tensor(v, dtype=torch.float64)
    y = x @ _random_rotation(7).T
    pca, turns = orientation_candidates(x, y, "pca"), orientation_candidates(x, y, "pca_turns")
    assert all(min(float((c - t).abs().max()) for t in turns) < 1e-12 for c in pca)
    # turns[k] = turns[0] followed by k quarter turns about y's first principal axis
    axis = principal_frame(y)[1][:, 0]
    for k in range(1, 4):
        rel = turns[k] @ turns[0].T
        torch.testing.assert_close(rel @ axis, axis)
        assert abs(float(torch.trace(rel)) - (1 + 2 * np.cos(k * np.pi / 2))) < 1e-9


def test_prealignment_recovers_a_large_turn():
    v, f = _blob(300)
    perm = np.random.default_rng(1).permutation(len(v))
    rot = _random_rotation(5).numpy()
    vy = np.empty_like(v)
    vy[perm] = v @ rot.T + [0.2, 0.1, -0.1]
    x, y = _sample(v, f, "x"), _sample(vy, perm[f], "y")
    scale = np.sqrt(surface_area(vy, y.faces.numpy()))
    r = DivFreeMatcher(**FAST, prealign="pca_turns").match(x, y)
    err = np.linalg.norm(vy[r.p2p.numpy()] - vy[perm], axis=1) / scale
    assert (r.p2p.numpy() == perm).mean() > 0.9 and err.mean() < 0.01
    # frames: x as given at t = 0, on y at t = 1, the volume kept in between
    torch.testing.assert_close(r.deformation[0], x.verts, atol=1e-5, rtol=0)
    assert np.linalg.norm(r.deformation[-1].numpy() - vy[perm], axis=1).mean() / scale < 0.01
    for frame in r.deformation[1:]:
        assert abs(relative_volume_change(x.verts.numpy(), f, frame.numpy())) < 0.01
    assert len(r.extras["prealign_scores"]) == 8
    # without the pre-alignment the flow cannot turn the shape that far: the test can fail
    r0 = DivFreeMatcher(**FAST, prealign="none").match(x, y)
    err0 = np.linalg.norm(vy[r0.p2p.numpy()] - vy[perm], axis=1) / scale
    assert err0.mean() > 5 * err.mean() + 0.05


def test_rigid_icp_recovers_a_rigid_motion():
    v, f = _blob(300)
    x = torch.tensor(v, dtype=torch.float64)
    nx = torch.tensor(trimesh.Trimesh(v, f, process=False).vertex_normals.copy())
    rot = torch.from_numpy(Rotation.from_rotvec([0.03, -0.05, 0.04]).as_matrix())
    shift = torch.tensor([0.02, 0.0, -0.01], dtype=torch.float64)
    perm = torch.from_numpy(np.random.default_rng(2).permutation(len(v)))
    y, ny = (x @ rot.T + shift)[perm], (nx @ rot.T)[perm]
    r, t = rigid_icp(x, nx, y, ny, iterations=50, normal_weight=0.1)
    torch.testing.assert_close(r, rot, atol=1e-6, rtol=0)
    torch.testing.assert_close(t, shift, atol=1e-6, rtol=0)
    # descriptors that identify the points pair them from the start: one step recovers a large turn
    big = torch.from_numpy(Rotation.from_rotvec([0.0, 0.0, 2.5]).as_matrix())
    feats = torch.eye(len(v), dtype=torch.float64) * 10.0
    r, _ = rigid_icp(x, nx, (x @ big.T)[perm], (nx @ big.T)[perm], iterations=3, features_x=feats,
                     features_y=feats[perm])
    torch.testing.assert_close(r, big, atol=1e-6, rtol=0)


def test_descriptor_option():
    """Several descriptors: each with unit rows, the block with unit rows; names and presence checked."""
    v, f = _blob(300)
    gen = torch.Generator().manual_seed(0)
    shot_rows, wks = torch.rand(len(v), 12, generator=gen) + 0.1, torch.rand(len(v), 7, generator=gen) + 0.1
    sample = ShapeSample(shape=make_shape(v, f, "x", normalization=None),
                         operators={"shot": {"shot": shot_rows}, "wks": {"wks": wks}})
    both = DivFreeMatcher(**{**FAST, "descriptor": ["shot", "wks"]}, prealign="none")
    assert both.required_operators == {"shot": {}, "wks": {}, "eigenbasis": {"k": 10}}
    assert DivFreeMatcher(**{**FAST, "descriptor": "wks"}, prealign="smooth_shells").required_operators.keys() == {
        "wks", "shot", "eigenbasis"}
    block = both._descriptor(sample)
    assert block.shape == (len(v), 12 + 7)
    torch.testing.assert_close(block.norm(dim=1), torch.ones(len(v)))
    torch.testing.assert_close(block[:, -7:] * np.sqrt(2), wks / wks.norm(dim=1, keepdim=True))
    with pytest.raises(ConfigError, match="descriptor"):
        DivFreeMatcher(descriptor="sift")
    with pytest.raises(ConfigError, match="descriptor"):
        DivFreeMatcher(descriptor=["wks", "wks"])
    with pytest.raises(ConfigError, match="hks"):
        DivFreeMatcher(**{**FAST, "descriptor": "hks"}, prealign="none")._descriptor(sample)


def test_spectral_extraction_undoes_a_laid_over_patch():
    """A patch of x that the flow laid onto a neighbouring patch of y (mapped many-to-one, as a swapped limb) is
    pulled back to its own place by the spectral extraction; the rest of the map stays exact."""
    v, f = _blob(300)
    v = v * np.sqrt((4 / 9) / surface_area(v, f))  # FAUST_r's normalized area (the weights' units)
    perm = np.random.default_rng(0).permutation(len(v))  # vertex i of x is vertex perm[i] of y (same surface)
    vy = np.empty_like(v)
    vy[perm] = v
    x, y = _sample(v, f, "x"), _sample(vy, perm[f], "y")
    tx, ty = torch.tensor(v, dtype=torch.float32), torch.tensor(vy, dtype=torch.float32)
    box_x, box_y = df.box_normalization(tx, ty, 0.05)
    bx, by = box_x.to_box(tx), box_y.to_box(ty)
    # the patch R around the +x tip is mapped onto the patch 0.25 away (which keeps its own, right images)
    a = int(np.argmax(v[:, 0]))
    b = int(np.argmin(np.abs(np.linalg.norm(v - v[a], axis=1) - 0.25)))
    patch = np.linalg.norm(v - v[a], axis=1) < 0.1
    p2p = perm.copy()
    p2p[patch] = perm[cKDTree(v).query(v[patch] - v[a] + v[b])[1]]
    p2p, p2p_inv = torch.from_numpy(p2p), torch.from_numpy(np.argsort(perm))
    keep_x, keep_y = cycle_consistent(bx, by, p2p, p2p_inv, 0.03)
    # the patch fails the round trip on both sides (y's uncovered patch returns through x's patch), nothing else
    assert torch.equal(keep_x, torch.from_numpy(~patch)) and torch.equal(keep_y[perm], torch.from_numpy(~patch))
    fmap = functional_map_from_maps(x.evecs[:, :10], y.evecs[:, :10], x.mass, y.mass, p2p, p2p_inv, keep_x, keep_y)
    assert fmap.shape == (10, 10) and fmap.dtype == torch.float64
    # the deformed x lies where the flow's map says: the coordinates alone keep the patch on the wrong place
    moved = by[p2p]
    emb_x, emb_y = torch.cat([moved, 0.1 * vertex_normals(moved, x.faces)], 1), torch.cat([by, 0.1 * vertex_normals(
        by, y.faces)], 1)
    matcher = DivFreeMatcher(prealign="none", descriptor_weight=0.0)
    assert (matcher.extraction, matcher.extraction_k, matcher.required_operators) == ("spectral", 10, {
        "eigenbasis": {"k": 10}})
    new, new_inv = matcher._spectral_maps(bx, by, emb_x, emb_y, p2p, p2p_inv, x, y)
    error = np.linalg.norm(vy[new.numpy()] - vy[perm], axis=1)
    before = np.linalg.norm(vy[p2p.numpy()] - vy[perm], axis=1)
    assert before[patch].mean() > 0.2 and error[patch].mean() < 0.25 * before[patch].mean()
    assert (new.numpy()[~patch] == perm[~patch]).mean() > 0.9 and error.mean() < 0.01
    assert new_inv.shape == (len(v),)
    with pytest.raises(ConfigError, match="extraction"):
        DivFreeMatcher(extraction="zoomout")
    with pytest.raises(ConfigError, match="eigenfunctions"):
        DivFreeMatcher(prealign="none", extraction_k=20)._spectral_maps(bx, by, emb_x, emb_y, p2p, p2p_inv, x, y)


def _permuted_copy(n_verts: int = 300):
    """The test surface at FAUST_r's area and a vertex-permuted copy (x's vertex i is y's ``perm[i]``), in the box."""
    v, f = _blob(n_verts)
    v = v * np.sqrt((4 / 9) / surface_area(v, f))
    perm = np.random.default_rng(0).permutation(len(v))
    vy = np.empty_like(v)
    vy[perm] = v
    x, y = _sample(v, f, "x"), _sample(vy, perm[f], "y")
    tx, ty = torch.tensor(v, dtype=torch.float32), torch.tensor(vy, dtype=torch.float32)
    box_x, box_y = df.box_normalization(tx, ty, 0.05)
    return v, vy, perm, x, y, box_x.to_box(tx), box_y.to_box(ty)


def test_trimmed_extraction_undoes_a_swap_that_passes_the_round_trip():
    """Two patches of x exchanged one-to-one (as a limb laid onto the other side's limb whose own image went the
    other way): the swap passes the round trip, so the consistency filter keeps it and the plain least-squares fit
    inherits it; the trimmed fit leaves its pairs out, and the extraction puts both patches back."""
    v, vy, perm, x, y, bx, by = _permuted_copy()
    a = int(np.argmax(v[:, 0]))
    b = int(np.argmin(np.abs(np.linalg.norm(v - v[a], axis=1) - 0.3)))
    ia = np.flatnonzero(np.linalg.norm(v - v[a], axis=1) < 0.12)
    ib = np.argsort(np.linalg.norm(v - v[b], axis=1))[:len(ia)]
    assert not set(ia) & set(ib)
    ra, rb = linear_sum_assignment(np.linalg.norm((v[ia] - v[a])[:, None] - (v[ib] - v[b])[None], axis=2))
    src = np.arange(len(v))  # x's vertex i -> y's copy of x's vertex src[i]; an involution
    src[ia[ra]], src[ib[rb]] = ib[rb], ia[ra]
    swapped = src != np.arange(len(v))
    inv = np.empty(len(v), dtype=np.int64)
    inv[perm] = src
    p2p, p2p_inv = torch.from_numpy(perm[src]), torch.from_numpy(inv)
    keep_x, keep_y = cycle_consistent(bx, by, p2p, p2p_inv, 0.03)
    assert bool(keep_x.all()) and bool(keep_y.all())  # the round trip cannot see the swap
    phi_x, phi_y = x.evecs[:, :10], y.evecs[:, :10]
    fmap, in_x, in_y = trimmed_functional_map(phi_x, phi_y, x.mass, y.mass, p2p, p2p_inv, keep_x, keep_y, 1.0, 10)
    assert fmap.shape == (10, 10) and fmap.dtype == torch.float64
    torch.testing.assert_close(fmap.T @ fmap, torch.eye(10, dtype=torch.float64))
    # the swapped pairs are left out (on both sides), and the rest is fitted exactly
    assert not bool(in_x[torch.from_numpy(swapped)].any()) and not bool(in_y[torch.from_numpy(swapped[np.argsort(
        perm)])].any())
    assert 0.4 < in_x.float().mean() < 0.6  # the better half
    res_x, _ = functional_map_residuals(phi_x, phi_y, fmap, p2p, p2p_inv)
    assert res_x[~swapped].max() < 1e-6 and res_x[swapped].min() > 1.0
    moved = by[p2p]  # the deformed x where the maps say: the coordinates alone keep the swap
    emb_x = torch.cat([moved, 0.1 * vertex_normals(moved, x.faces)], 1)
    emb_y = torch.cat([by, 0.1 * vertex_normals(by, y.faces)], 1)
    before = np.linalg.norm(vy[p2p.numpy()] - vy[perm], axis=1)
    errors = {}
    for fit, trim in (("least_squares", 0.0), ("orthogonal", 1.0)):  # the earlier extraction, the default
        matcher = DivFreeMatcher(prealign="none", descriptor_weight=0.0, extraction_fit=fit, extraction_trim=trim)
        new, new_inv = matcher._spectral_maps(bx, by, emb_x, emb_y, p2p, p2p_inv, x, y)
        errors[fit] = np.linalg.norm(vy[new.numpy()] - vy[perm], axis=1), new
    assert before[swapped].mean() > 0.25
    assert errors["least_squares"][0][swapped].mean() > 0.5 * before[swapped].mean()  # the swap survives
    err, new = errors["orthogonal"]
    assert err[swapped].mean() < 0.3 * before[swapped].mean()
    assert (new.numpy()[~swapped] == perm[~swapped]).all() and new_inv.shape == (len(v),)
    with pytest.raises(ConfigError, match="extraction_fit"):
        DivFreeMatcher(extraction_fit="lstsq")
    with pytest.raises(ConfigError, match="extraction_trim"):
        DivFreeMatcher(extraction_trim=-1.0)


def test_orthogonal_functional_map_keeps_a_left_out_part_right():
    """Half of the surface left out of the fit, the other half mapped with a few neighbours' noise: the
    least-squares functional map extrapolates wrongly onto the left-out half, the orthogonal one does not."""
    v, vy, perm, x, y, _, _ = _permuted_copy()
    rng = np.random.default_rng(1)
    neighbours = cKDTree(v).query(v, 7)[1]
    src = neighbours[np.arange(len(v)), rng.integers(0, 7, len(v))]
    inv = np.empty(len(v), dtype=np.int64)
    inv[perm] = neighbours[np.arange(len(v)), rng.integers(0, 7, len(v))]
    p2p, p2p_inv = torch.from_numpy(perm[src]), torch.from_numpy(inv)
    out = v[:, 0] > np.median(v[:, 0])
    keep_x, keep_y = torch.from_numpy(~out), torch.from_numpy(~out[np.argsort(perm)])
    phi_x, phi_y = x.evecs[:, :10].to(torch.float64), y.evecs[:, :10]
    errors = {}
    for orthogonal in (False, True):
        fmap = functional_map_from_maps(phi_x, phi_y, x.mass, y.mass, p2p, p2p_inv, keep_x, keep_y, orthogonal)
        pulled = cKDTree(phi_y.numpy()).query((phi_x @ fmap).numpy())[1]  # the spectral map alone
        errors[orthogonal] = np.linalg.norm(vy[pulled] - v, axis=1)
    assert errors[False][out].mean() > 0.05
    assert errors[True][out].mean() < 0.01 and errors[True][~out].mean() < 0.01
    exact = functional_map_from_maps(phi_x, phi_y, x.mass, y.mass, torch.from_numpy(perm),
                                     torch.from_numpy(np.argsort(perm)), orthogonal=True)
    torch.testing.assert_close(exact, functional_map_from_maps(phi_x, phi_y, x.mass, y.mass, torch.from_numpy(perm),
                                                               torch.from_numpy(np.argsort(perm))))
