"""Tests of the Deep Shells layer, its refinement, the (C, tau) least squares and the nearest neighbours."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree

from shapecorr.errors import ConfigError, InvalidMeshError, NumericalError
from shapecorr.geometry.laplace_beltrami import eigenbasis
from shapecorr.geometry.mesh import triangle_areas
from shapecorr.geometry.normals import vertex_normals
from shapecorr.geometry.remeshing import remesh
from shapecorr.geometry.shot_descriptor import shot
from shapecorr.geometry.spectral_shape import make_spectral_shape, reorder_vertices
from shapecorr.matching.deep_shells import (
    DeepShellsConfig,
    _shell,
    _Stencil,
    deep_shells_layer,
    deep_shells_query,
    deformation_from_pairs,
    deformation_from_plans,
    log_spaced_k,
    product_embedding_maps,
    random_samples,
    refine_deep_shells,
)
from shapecorr.matching.least_squares import ridge_lstsq, solve_normal_equations
from shapecorr.matching.nearest_neighbors import bidirectional_nearest_neighbors, spatial_order

N_EIGS = 60
#: Small refinement schedule for the ~600-vertex test meshes (the published one goes to k = 499).
SMALL_REFINE = dict(refine_k_max=40, refine_levels=12)


# Tiny tensors: one torch thread (OpenMP threading only adds overhead); fixture in tests/conftest.py.
pytestmark = pytest.mark.usefixtures("single_thread")


def _bend(p: np.ndarray) -> np.ndarray:
    """A smooth non-rigid deformation: rotation about the x axis by an angle growing along x."""
    angle = 0.6 * p[:, 0]
    c, s = np.cos(angle), np.sin(angle)
    q = p.copy()
    q[:, 1] = c * p[:, 1] - s * p[:, 2]
    q[:, 2] = s * p[:, 1] + c * p[:, 2]
    return q


def _spectral(verts, faces, name):
    _, evecs, mass = eigenbasis(verts, faces, N_EIGS)
    return make_spectral_shape(torch.tensor(verts, dtype=torch.float32), torch.tensor(faces),
                               torch.tensor(evecs, dtype=torch.float32), torch.tensor(mass, dtype=torch.float32),
                               name=name)


@pytest.fixture(scope="module")
def pair(asymmetric_blob):
    """X: a bumpy blob (642 vertices, area 0.44); Y: X remeshed (~600 vertices) and bent.

    Ground truth: for each vertex of X the nearest vertex of the remeshed (undeformed) Y. "Good features"
    are random Fourier features of the undeformed positions, so they agree on corresponding points.
    """
    rng = np.random.default_rng(0)
    ico = trimesh.creation.icosphere(subdivisions=3)
    faces_x = np.asarray(ico.faces)
    verts_x = asymmetric_blob(np.asarray(ico.vertices), rng)
    verts_x *= np.sqrt(0.44 / triangle_areas(verts_x, faces_x).sum())
    rest_y, faces_y = remesh(verts_x, faces_x, 600)
    gt = cKDTree(rest_y).query(verts_x)[1]
    verts_y = _bend(rest_y)
    freq = rng.normal(size=(3, 16)) * 3.0
    phase = rng.uniform(0.0, 2 * np.pi, 16)
    features = lambda p: torch.tensor(np.sin(p @ freq + phase), dtype=torch.float32)  # noqa: E731
    edge = float(np.linalg.norm(verts_x[faces_x[:, 0]] - verts_x[faces_x[:, 1]], axis=1).mean())
    return dict(
        x=_spectral(verts_x, faces_x, "blob"),
        y=_spectral(verts_y, faces_y, "blob_remeshed_bent"),
        feat_x=features(verts_x),
        feat_y=features(rest_y),
        gt=torch.from_numpy(gt),
        rest_y=rest_y,
        edge=edge,
    )


def _map_error(pair, map_x_to_y) -> float:
    """Mean distance (in mean edge lengths) between predicted and true images, on the undeformed Y."""
    rest = pair["rest_y"]
    return float(np.linalg.norm(rest[map_x_to_y.numpy()] - rest[pair["gt"].numpy()], axis=1).mean() / pair["edge"])


def _samples(pair, num=300, seed=0):
    g = torch.Generator().manual_seed(seed)
    return random_samples(pair["x"].n_verts, num, g), random_samples(pair["y"].n_verts, num, g)


# --------------------------------------------------------------------------------------------------------
# configuration


def test_config_defaults_and_original_flags():
    cfg = DeepShellsConfig()
    assert cfg.k_array == (6, 7, 8, 10, 12, 14, 17, 21)
    assert (cfg.sigma, cfg.num_sinkhorn, cfg.fac_spec, cfg.fac_norm) == (0.1, 3, 0.3, 0.025)
    assert (cfg.refine_fac_spec, cfg.refine_fac_norm) == (0.25, 0.04)
    assert cfg.refine_k_array == (6, 6, 7, 8, 9, 10, 11, 13, 14, 16, 18, 20, 23, 26, 29, 32, 36, 41, 46, 51, 57,
                                  64, 72, 81, 91, 102, 114, 128, 143, 160, 180, 201, 226, 253, 283, 317, 355,
                                  398, 446, 499)
    assert log_spaced_k(6, 21, 8) == cfg.k_array
    orig = DeepShellsConfig.original(sigma=0.2)
    assert (orig.smooth_x, orig.sigmoid_inclusive, orig.normal_norm, orig.sigma) == ("hard", False, "samples", 0.2)
    assert (cfg.smooth_x, cfg.sigmoid_inclusive, cfg.normal_norm) == ("sigmoid", True, "all")


@pytest.mark.parametrize("bad", [dict(k_array=()), dict(sigma=0.0), dict(num_sinkhorn=-1), dict(fac_spec=-1.0),
                                 dict(smooth_x="box"), dict(normal_norm="some"), dict(nn_backend="faiss"),
                                 dict(refine_k_min=10, refine_k_max=5), dict(sinkhorn_impl="slow")])
def test_config_validation(bad):
    with pytest.raises(ConfigError):
        DeepShellsConfig(**bad)


# --------------------------------------------------------------------------------------------------------
# least squares


def test_ridge_lstsq_matches_numpy_and_weights_duplicate_rows():
    g = torch.Generator().manual_seed(0)
    a = torch.randn(40, 6, generator=g)
    b = torch.randn(40, 3, generator=g)
    expected = np.linalg.lstsq(a.double().numpy(), b.double().numpy(), rcond=None)[0]
    got = ridge_lstsq(a, b, ridge=0.0)
    assert got.dtype == torch.float32
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-5, atol=1e-6)
    # integer weights == repeated rows
    w = torch.tensor([1.0, 3.0] * 20)
    rep = torch.repeat_interleave(torch.arange(40), w.long())
    torch.testing.assert_close(ridge_lstsq(a, b, weights=w, ridge=0.0), ridge_lstsq(a[rep], b[rep], ridge=0.0))


def test_ridge_regularizes_rank_deficient_problems_and_errors():
    a = torch.zeros(10, 3, dtype=torch.float64)
    a[:, 0] = 1.0
    a[:, 1] = 1.0  # column 1 duplicates column 0, column 2 is zero
    b = torch.ones(10, 1, dtype=torch.float64)
    sol = ridge_lstsq(a, b)  # solvable thanks to the ridge: minimum-norm-like solution
    torch.testing.assert_close(a @ sol, b, atol=1e-6, rtol=0)
    with pytest.raises(NumericalError, match="not positive definite"):
        ridge_lstsq(a, b, ridge=0.0)
    bad = a.clone()
    bad[0, 0] = float("nan")
    with pytest.raises(NumericalError, match="NaN"):
        ridge_lstsq(bad, b)
    with pytest.raises(ConfigError):
        solve_normal_equations(torch.eye(3), torch.ones(3, 1), ridge=-1.0)


def test_ridge_lstsq_gradcheck():
    g = torch.Generator().manual_seed(1)
    a = torch.randn(12, 4, generator=g, dtype=torch.float64, requires_grad=True)
    b = torch.randn(12, 2, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a_, b_: ridge_lstsq(a_, b_, ridge=1e-3), (a, b))


# --------------------------------------------------------------------------------------------------------
# nearest neighbours


@pytest.mark.parametrize("n, d", [(300, 3), (300, 40), (3000, 12)])
def test_nearest_neighbours_backends_agree_with_naive(n, d):
    """Every backend and thread count finds the exact neighbours (k-d trees of both leaf sizes, queries reordered)."""
    g = torch.Generator().manual_seed(d)
    x, y = torch.randn(n, d, generator=g), torch.randn(n - 43, d, generator=g)
    dist = torch.cat([((rows[:, None].double() - y[None].double()) ** 2).sum(-1) for rows in x.split(100)])
    naive = (dist.argmin(1), dist.argmin(0))
    # workers: 1 is the serial path, >= 2 runs the two directions in two threads (whatever the core count)
    for kwargs in (dict(backend="kdtree"), dict(backend="kdtree", workers=1), dict(backend="kdtree", workers=2),
                   dict(backend="kdtree", workers=3), dict(backend="brute"), dict(backend="brute", block_size=7),
                   dict(backend="auto")):
        nn_y, nn_x = bidirectional_nearest_neighbors(x, y, **kwargs)
        assert nn_y.dtype == torch.int64 and nn_y.shape == (n,) and nn_x.shape == (n - 43,)
        torch.testing.assert_close(nn_y, naive[0])
        torch.testing.assert_close(nn_x, naive[1])


def test_nearest_neighbours_errors():
    x = torch.zeros(4, 3)
    with pytest.raises(ConfigError):
        bidirectional_nearest_neighbors(x, x, backend="ball")
    # non-finite points on either side, every backend (the k-d tree relies on scipy's own check where it has one)
    for value in (float("inf"), float("nan")):
        bad = x.clone()
        bad[0, 0] = value
        for kwargs in (dict(), dict(backend="kdtree", workers=1), dict(backend="kdtree", workers=2),
                       dict(backend="brute")):
            with pytest.raises(NumericalError, match="NaN or Inf"):
                bidirectional_nearest_neighbors(bad, x, **kwargs)
            with pytest.raises(NumericalError, match="NaN or Inf"):
                bidirectional_nearest_neighbors(x, bad, **kwargs)


# --------------------------------------------------------------------------------------------------------
# building blocks of the layer


def test_make_spectral_shape_validates(pair):
    x = pair["x"]
    torch.testing.assert_close(x.coeffs, x.evecs.T @ (x.mass[:, None] * x.verts))
    with pytest.raises(InvalidMeshError, match="operators"):
        make_spectral_shape(x.verts, x.faces, x.evecs[:-1], x.mass)
    with pytest.raises(InvalidMeshError, match="out of range"):
        make_spectral_shape(x.verts, x.faces + 1000, x.evecs, x.mass)
    nan = x.verts.clone()
    nan[3, 1] = float("nan")
    with pytest.raises(InvalidMeshError, match="NaN"):
        make_spectral_shape(nan, x.faces, x.evecs, x.mass)


def test_stencil_normals_equal_full_normals_at_samples(pair):
    x = pair["x"]
    samples = torch.tensor([0, 5, 5, 77, 641, 300])
    stencil = _Stencil(x.faces, samples, x.n_verts)
    assert stencil.verts.numel() < x.n_verts
    torch.testing.assert_close(stencil.normals(x.verts[stencil.verts]), vertex_normals(x.verts, x.faces)[samples])


def test_deformation_from_identity_plan_is_identity(pair):
    # X against itself with the identity soft map: C = I and tau = 0 (both shells sigmoid smoothed).
    x = pair["x"]
    k = 12
    rows = torch.arange(x.n_verts)
    eye = torch.eye(x.n_verts)
    shell = _shell(x, k, "sigmoid", True, rows=rows)
    fmap, tau = deformation_from_plans(eye, eye, x.evecs[:, :k], x.evecs[:, :k], shell, shell)
    torch.testing.assert_close(fmap, torch.eye(k), atol=1e-5, rtol=0)
    assert tau.abs().max() < 1e-6


def test_deformation_solves_match_stacked_least_squares(pair):
    x, y = pair["x"], pair["y"]
    g = torch.Generator().manual_seed(3)
    k = 10
    sx, sy = _samples(pair, 50)
    plan = torch.softmax(torch.randn(50, 50, generator=g, dtype=torch.float64), 1)
    plan_adj = torch.softmax(torch.randn(50, 50, generator=g, dtype=torch.float64), 1)
    px, py = x.evecs[sx, :k].double(), y.evecs[sy, :k].double()
    xs, ys = _shell(x, k, "hard", True, rows=sx).double(), _shell(y, k, "sigmoid", True, rows=sy).double()
    design = torch.cat([px, plan_adj @ px]).numpy()
    tgt = torch.cat([torch.cat([plan @ py, plan @ ys - xs], 1), torch.cat([py, ys - plan_adj @ xs], 1)]).numpy()
    expected = np.linalg.lstsq(design, tgt, rcond=None)[0]
    fmap, tau = deformation_from_plans(plan, plan_adj, px, py, xs, ys, ridge=0.0)
    np.testing.assert_allclose(torch.cat([fmap, tau], 1).numpy(), expected, rtol=1e-8, atol=1e-9)

    # hard pairs: (i, m_xy[i]) for all i and (m_yx[j], j) for all j
    m_xy = torch.randint(0, y.n_verts, (x.n_verts,), generator=g)
    m_yx = torch.randint(0, x.n_verts, (y.n_verts,), generator=g)
    shx, shy = _shell(x, k, "hard", True).double(), _shell(y, k, "sigmoid", True).double()
    phx, phy = x.evecs[:, :k].double(), y.evecs[:, :k].double()
    px_idx = torch.cat([torch.arange(x.n_verts), m_yx])
    py_idx = torch.cat([m_xy, torch.arange(y.n_verts)])
    expected = np.linalg.lstsq(phx[px_idx].numpy(), torch.cat([phy[py_idx], shy[py_idx] - shx[px_idx]], 1).numpy(),
                               rcond=None)[0]
    fmap, tau = deformation_from_pairs(phx, phy, shx, shy, m_xy, m_yx, ridge=0.0)
    np.testing.assert_allclose(torch.cat([fmap, tau], 1).numpy(), expected, rtol=1e-8, atol=1e-9)


# --------------------------------------------------------------------------------------------------------
# the training layer


def test_layer_outputs(pair):
    sx, sy = _samples(pair)
    out = deep_shells_layer(pair["feat_x"][sx], pair["feat_y"][sy], pair["x"], pair["y"], sx, sy)
    assert out.level_energies.shape == (8,)
    torch.testing.assert_close(out.loss, out.level_energies.mean())
    assert (out.level_energies > 0).all()
    assert out.plan.shape == (300, 300) and out.plan_adj.shape == (300, 300)
    torch.testing.assert_close(out.plan.sum(1), torch.ones(300))
    torch.testing.assert_close(out.plan_adj.sum(1), torch.ones(300))
    assert out.fmap.shape == (21, 21) and out.tau.shape == (21, 3)
    assert out.deformed_x.shape == (300, 3) and out.shell_y.shape == (300, 3)


def test_layer_without_plans_has_the_same_loss_and_gradients(pair):
    sx, sy = _samples(pair, 200)
    results = []
    for return_plans in (True, False):
        fx = pair["feat_x"][sx].clone().requires_grad_(True)
        out = deep_shells_layer(fx, pair["feat_y"][sy], pair["x"], pair["y"], sx, sy, return_plans=return_plans)
        out.loss.backward()
        results.append((out.level_energies.detach(), fx.grad))
        assert (out.plan is None) == (not return_plans) and (out.plan_adj is None) == (not return_plans)
        if return_plans:
            assert not out.plan.requires_grad and not out.plan_adj.requires_grad
    assert torch.equal(results[0][0], results[1][0])
    assert torch.equal(results[0][1], results[1][1])


def test_layer_recovers_the_map_from_good_features(pair):
    sx, sy = _samples(pair)
    out = deep_shells_layer(pair["feat_x"][sx], pair["feat_y"][sy], pair["x"], pair["y"], sx, sy)
    hard = sy[out.plan.argmax(1)]
    rest = pair["rest_y"]
    err = np.linalg.norm(rest[hard.numpy()] - rest[pair["gt"][sx].numpy()], axis=1).mean() / pair["edge"]
    # the true image of a sample is usually not among the 300 samples of Y: ~1 edge is the sampling limit
    assert err < 1.6
    # the deformed shell of X lands on the shell of Y
    assert float((out.deformed_x - out.plan @ out.shell_y).norm(dim=1).mean()) < pair["edge"]


def test_hard_maps_from_the_last_training_level(pair):
    # G-MSM style query: nearest neighbours in the full-resolution embedding of the layer's last level
    sx, sy = _samples(pair)
    out = deep_shells_layer(pair["feat_x"][sx], pair["feat_y"][sy], pair["x"], pair["y"], sx, sy)
    match = product_embedding_maps(pair["x"], pair["y"], out.fmap, out.tau)
    assert match.map_x_to_y.shape == (pair["x"].n_verts,) and match.map_y_to_x.shape == (pair["y"].n_verts,)
    assert _map_error(pair, match.map_x_to_y) < 1.0  # one coarse level (k = 21), no refinement
    with pytest.raises(ConfigError):
        product_embedding_maps(pair["x"], pair["y"], out.fmap, out.tau[:5])


def test_loss_decreases_when_features_improve(pair):
    sx, sy = _samples(pair)
    g = torch.Generator().manual_seed(5)
    fx, fy = pair["feat_x"][sx], pair["feat_y"][sy]
    losses = []
    for noise in (0.0, 0.3, 0.8):
        nx, ny = noise * torch.randn(fx.shape, generator=g), noise * torch.randn(fy.shape, generator=g)
        losses.append(float(deep_shells_layer(fx + nx, fy + ny, pair["x"], pair["y"], sx, sy).loss))
    random = float(deep_shells_layer(torch.randn(fx.shape, generator=g), torch.randn(fy.shape, generator=g),
                                     pair["x"], pair["y"], sx, sy).loss)
    assert losses[0] < losses[1] < losses[2] < random


def test_gradients_reach_the_features(pair):
    sx, sy = _samples(pair, 200)
    fx = pair["feat_x"][sx].clone().requires_grad_(True)
    fy = pair["feat_y"][sy].clone().requires_grad_(True)
    deep_shells_layer(fx, fy, pair["x"], pair["y"], sx, sy).loss.backward()
    for grad in (fx.grad, fy.grad):
        assert torch.isfinite(grad).all() and grad.abs().sum() > 0


def test_fast_and_reference_sinkhorn_give_the_same_layer(pair):
    sx, sy = _samples(pair, 150)
    results = []
    for impl in ("fast", "reference"):
        fx = pair["feat_x"][sx].double().requires_grad_(True)
        x = make_spectral_shape(pair["x"].verts.double(), pair["x"].faces, pair["x"].evecs, pair["x"].mass)
        y = make_spectral_shape(pair["y"].verts.double(), pair["y"].faces, pair["y"].evecs, pair["y"].mass)
        out = deep_shells_layer(fx, pair["feat_y"][sy].double(), x, y, sx, sy, DeepShellsConfig(sinkhorn_impl=impl))
        out.loss.backward()
        results.append((out.level_energies.detach(), fx.grad))
    torch.testing.assert_close(results[0][0], results[1][0], rtol=1e-9, atol=0)
    torch.testing.assert_close(results[0][1], results[1][1], rtol=1e-7, atol=1e-10)


def test_layer_gradcheck_float64():
    mesh = trimesh.creation.icosphere(subdivisions=1)
    verts = np.asarray(mesh.vertices) * np.array([1.3, 1.0, 0.8])
    faces = np.asarray(mesh.faces)
    _, evecs, mass = eigenbasis(verts, faces, 20)
    shape = make_spectral_shape(torch.tensor(verts), torch.tensor(faces), torch.tensor(evecs), torch.tensor(mass))
    g = torch.Generator().manual_seed(0)
    sx, sy = random_samples(42, 15, g), random_samples(42, 14, g)
    fx = torch.randn(15, 3, generator=g, dtype=torch.float64, requires_grad=True)
    fy = torch.randn(14, 3, generator=g, dtype=torch.float64, requires_grad=True)
    cfg = DeepShellsConfig(k_array=(3, 5), sigma=0.5, ridge=0.0)
    assert torch.autograd.gradcheck(lambda a, b: deep_shells_layer(a, b, shape, shape, sx, sy, cfg).loss, (fx, fy))


def test_original_flags_change_the_training_embedding(pair):
    sx, sy = _samples(pair)
    args = (pair["feat_x"][sx], pair["feat_y"][sy], pair["x"], pair["y"], sx, sy)
    ours = deep_shells_layer(*args).level_energies
    orig = deep_shells_layer(*args, config=DeepShellsConfig.original()).level_energies
    assert torch.isfinite(orig).all()
    assert not torch.allclose(ours, orig)


def test_no_learning_ablation_raw_shot_into_the_layer(pair):
    """Identity backbone: the 352-D SHOT descriptors go straight into the OT layer, and the query with refinement
    recovers the map far better than nearest neighbours in SHOT space."""
    x, y = pair["x"], pair["y"]
    # Support radius 30 % of sqrt(area) instead of the published 5 %: at 600 vertices (FAUST_r: 5000) a 5 % ball
    # holds ~5 vertices and SHOT is noise (error 8 edge lengths, random maps 8.6).
    shot_x = torch.tensor(shot(x.verts.numpy(), x.faces.numpy(), radius_fraction=0.3), dtype=torch.float32)
    shot_y = torch.tensor(shot(y.verts.numpy(), y.faces.numpy(), radius_fraction=0.3), dtype=torch.float32)
    assert shot_x.shape[1] == 352
    sx, sy = _samples(pair)
    out = deep_shells_layer(shot_x[sx], shot_y[sy], x, y, sx, sy)
    assert torch.isfinite(out.loss) and out.loss > 0
    match = deep_shells_query(shot_x, shot_y, x, y, DeepShellsConfig(**SMALL_REFINE))
    assert match.map_x_to_y.shape == (x.n_verts,) and match.map_y_to_x.shape == (y.n_verts,)
    nearest = torch.cdist(shot_x, shot_y).argmin(dim=1)
    error, error_nearest = _map_error(pair, match.map_x_to_y), _map_error(pair, nearest)
    # measured: 0.87 edge lengths (SHOT nearest neighbours 4.6; without refinement 2.7)
    assert error < 1.5 and error < 0.5 * error_nearest


# --------------------------------------------------------------------------------------------------------
# test time


@pytest.mark.parametrize("original", [False, True])
def test_query_recovers_the_map(pair, original):
    cfg = (DeepShellsConfig.original if original else DeepShellsConfig)(**SMALL_REFINE)
    coarse = deep_shells_query(pair["feat_x"], pair["feat_y"], pair["x"], pair["y"], cfg, refine=False)
    match = deep_shells_query(pair["feat_x"], pair["feat_y"], pair["x"], pair["y"], cfg)
    assert match.map_x_to_y.dtype == torch.int64
    assert int(match.map_x_to_y.max()) < pair["y"].n_verts and int(match.map_y_to_x.max()) < pair["x"].n_verts
    assert _map_error(pair, match.map_x_to_y) < 0.5
    assert _map_error(pair, coarse.map_x_to_y) < 1.0


def test_identity_pair_gives_the_identity_map(pair):
    x = pair["x"]
    match = deep_shells_query(pair["feat_x"], pair["feat_x"], x, x, DeepShellsConfig(**SMALL_REFINE))
    ident = torch.arange(x.n_verts)
    torch.testing.assert_close(match.map_x_to_y, ident)
    torch.testing.assert_close(match.map_y_to_x, ident)


def _perturbed_maps(pair, seed):
    """(X -> Y: the true map with 30 % of its entries random, Y -> X: nearest vertices of the undeformed shapes)."""
    x, y = pair["x"], pair["y"]
    g = torch.Generator().manual_seed(seed)
    noisy = pair["gt"].clone()
    wrong = torch.rand(x.n_verts, generator=g) < 0.3
    noisy[wrong] = torch.randint(0, y.n_verts, (int(wrong.sum()),), generator=g)
    return noisy, torch.from_numpy(cKDTree(x.verts.numpy()).query(pair["rest_y"])[1])


def test_refinement_repairs_a_perturbed_map(pair):
    x, y = pair["x"], pair["y"]
    noisy, inverse = _perturbed_maps(pair, seed=7)
    before = _map_error(pair, noisy)
    match = refine_deep_shells(x, y, noisy, inverse, DeepShellsConfig(**SMALL_REFINE))
    assert before > 2.0
    assert _map_error(pair, match.map_x_to_y) < 0.5


def test_refinement_in_spatial_order_returns_the_same_maps(pair, monkeypatch):
    """Large shapes are refined with their vertices in a spatial order: same maps, original numbering."""
    import shapecorr.matching.deep_shells as ds

    x, y = pair["x"], pair["y"]
    noisy, inverse = _perturbed_maps(pair, seed=8)
    cfg = DeepShellsConfig(**SMALL_REFINE)
    plain = refine_deep_shells(x, y, noisy, inverse, cfg)
    calls = []

    def recording(points):
        calls.append(points.shape[0])
        return spatial_order(points)

    monkeypatch.setattr(ds, "SPATIAL_ORDER_MIN_VERTS", 0)
    monkeypatch.setattr(ds, "spatial_order", recording)
    ordered = refine_deep_shells(x, y, noisy, inverse, cfg)
    assert calls == [x.n_verts, y.n_verts]
    assert not torch.equal(spatial_order(x.verts), torch.arange(x.n_verts))  # really renumbered
    assert torch.equal(ordered.map_x_to_y, plain.map_x_to_y) and torch.equal(ordered.map_y_to_x, plain.map_y_to_x)
    # the sums of the normal equations run in another order: equal up to rounding
    torch.testing.assert_close(ordered.deformed_x, plain.deformed_x, rtol=0, atol=1e-6)
    torch.testing.assert_close(ordered.fmap, plain.fmap, rtol=0, atol=1e-5)
    # brute-force search (GPU default): no reordering
    calls.clear()
    refine_deep_shells(x, y, noisy, inverse, replace(cfg, nn_backend="brute"))
    assert calls == []


def test_reorder_vertices(pair):
    x = pair["x"]
    order = torch.randperm(x.n_verts, generator=torch.Generator().manual_seed(0))
    r = reorder_vertices(x, order)
    assert torch.equal(r.verts, x.verts[order]) and torch.equal(r.evecs, x.evecs[order])
    assert torch.equal(order[r.faces], x.faces)  # the same triangles
    with pytest.raises(InvalidMeshError, match="permutation"):
        reorder_vertices(x, order[:-1])
    with pytest.raises(InvalidMeshError, match="permutation"):
        reorder_vertices(x, torch.zeros_like(order))


def test_query_subsamples_large_shapes_for_the_ot_level(pair):
    cfg = DeepShellsConfig(max_query_points=200, **SMALL_REFINE)
    match = deep_shells_query(pair["feat_x"], pair["feat_y"], pair["x"], pair["y"], cfg)
    assert _map_error(pair, match.map_x_to_y) < 0.5
    # OT on 200 samples, maps at the input resolution
    assert match.map_x_to_y.shape == (pair["x"].n_verts,) and match.map_y_to_x.shape == (pair["y"].n_verts,)
    assert pair["x"].n_verts > 200


def test_bad_inputs_raise(pair):
    x, y = pair["x"], pair["y"]
    sx, sy = _samples(pair, 20)
    fx, fy = pair["feat_x"][sx], pair["feat_y"][sy]
    with pytest.raises(ConfigError, match="out of range"):
        deep_shells_layer(fx, fy, x, y, sx + 10_000, sy)
    with pytest.raises(ConfigError, match="one row per sample"):
        deep_shells_layer(fx[:-1], fy, x, y, sx, sy)
    with pytest.raises(ConfigError, match="widths"):
        deep_shells_layer(fx, fy[:, :5], x, y, sx, sy)
    nan = fx.clone()
    nan[0, 0] = float("nan")
    with pytest.raises(NumericalError):
        deep_shells_layer(nan, fy, x, y, sx, sy)
    with pytest.raises(ConfigError, match="eigenfunctions"):
        deep_shells_layer(fx, fy, x, y, sx, sy, DeepShellsConfig(k_array=(6, 55)))
    with pytest.raises(ConfigError, match="eigenfunctions"):
        deep_shells_query(pair["feat_x"], pair["feat_y"], x, y, replace(DeepShellsConfig(), refine_k_max=500))
    with pytest.raises(ConfigError, match="every vertex"):
        deep_shells_query(fx, fy, x, y)
