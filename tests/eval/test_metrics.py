"""Unit tests of shapecorr.eval.metrics against hand-computed values and analytic oracles."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from shapecorr.errors import CorrespondenceError, InvalidMeshError, NumericalError
from shapecorr.eval import metrics


@pytest.fixture(scope="module")
def sphere(unit_sphere):
    """Unit icosphere (642 vertices) with the exact great-circle distance matrix of its vertices."""
    v, f = unit_sphere(3)
    dist = np.arccos(np.clip(v @ v.T, -1.0, 1.0))
    np.fill_diagonal(dist, 0.0)  # arccos(1 - eps) would leave ~1e-8 on the diagonal
    return v, f, dist


def _mirror_index(v: np.ndarray, axis: int) -> np.ndarray:
    """Index of the vertex at the reflection of each vertex across the plane normal to ``axis``."""
    w = v.copy()
    w[:, axis] *= -1
    d, idx = cKDTree(v).query(w)
    assert d.max() < 1e-9, "the icosphere is symmetric under coordinate reflections"
    return idx


# ---------------------------------------------------------------------------------------------- geodesic error
def test_hand_computed_geodesic_errors():
    dist_y = np.array([[0.0, 1.0, 2.0], [1.0, 0.0, 1.5], [2.0, 1.5, 0.0]])
    p2p = np.array([2, 0, 1, 1])  # 4 vertices on X
    ref_x, ref_y = np.array([0, 1, 3]), np.array([2, 1, 0])
    # e = D[p2p[ref_x], ref_y] / 2 = D[2,2], D[0,1], D[1,0] over 2
    np.testing.assert_allclose(metrics.geodesic_errors(p2p, dist_y, ref_x, ref_y, 2.0), [0.0, 0.5, 0.5])


def test_identity_map_has_zero_error(sphere):
    v, f, dist = sphere
    ident = np.arange(len(v))
    errors = metrics.geodesic_errors(ident, dist, ident, ident, math.sqrt(metrics.surface_area(v, f)))
    assert errors.shape == (len(v),)
    assert np.all(errors == 0.0)


def test_antipodal_map_on_sphere_has_known_error(sphere):
    """Every point sent to its antipode is pi away: the error is pi / sqrt(area) at every point."""
    v, f, dist = sphere
    antipode = cKDTree(v).query(-v)[1]
    sqrt_area = math.sqrt(metrics.surface_area(v, f))
    assert sqrt_area == pytest.approx(math.sqrt(4 * math.pi), rel=0.01)  # mesh area is slightly below 4 pi
    ident = np.arange(len(v))
    errors = metrics.geodesic_errors(antipode, dist, ident, ident, sqrt_area)
    np.testing.assert_allclose(errors, math.pi / sqrt_area, rtol=1e-7)


def test_symmetric_flip_is_detected(sphere):
    """A left/right mirrored map is wrong against the ground truth and exact against the mirrored one."""
    v, f, dist = sphere
    mirror = _mirror_index(v, axis=0)
    ident = np.arange(len(v))
    sqrt_area = math.sqrt(metrics.surface_area(v, f))
    errors = metrics.geodesic_errors(mirror, dist, ident, ident, sqrt_area)
    errors_sym = metrics.geodesic_errors(mirror, dist, ident, mirror, sqrt_area)
    assert np.all(errors_sym == 0.0)
    # a point at longitude phi off the mirror plane moves by 2|x|-ish: the mean is far from zero
    assert errors.mean() > 0.2
    off_plane = np.abs(v[:, 0]) > 0.5
    assert np.all(errors[off_plane] > 0.25)


def test_geodesic_error_input_errors(sphere):
    v, f, dist = sphere
    n = len(v)
    ident = np.arange(n)
    with pytest.raises(CorrespondenceError, match="vertices"):
        metrics.geodesic_errors(np.full(n, n), dist, ident, ident, 1.0)  # map points outside Y
    with pytest.raises(CorrespondenceError, match="lengths differ"):
        metrics.geodesic_errors(ident, dist, ident, ident[:-1], 1.0)
    with pytest.raises(CorrespondenceError, match="integer"):
        metrics.geodesic_errors(ident.astype(float), dist, ident, ident, 1.0)
    bad = dist.copy()
    bad[0, 0] = np.inf
    with pytest.raises(NumericalError, match="NaN or infinite"):
        metrics.geodesic_errors(ident, bad, ident, ident, 1.0)


# ---------------------------------------------------------------------------------------------------- PCK
def test_pck_hand_computed():
    t, frac = metrics.pck_curve([0.0, 0.1, 0.2, 0.3], thresholds=[0.0, 0.1, 0.15, 0.25])
    np.testing.assert_allclose(frac, [0.25, 0.5, 0.5, 0.75])
    # trapezoid: 0.1*(0.25+0.5)/2 + 0.05*0.5 + 0.1*(0.5+0.75)/2 = 0.0375 + 0.025 + 0.0625 = 0.125; / 0.25
    assert metrics.pck_auc(t, frac) == pytest.approx(0.5)


def test_pck_defaults_and_auc_extremes():
    t, frac = metrics.pck_curve(np.zeros(10))
    assert t[0] == 0.0 and t[-1] == metrics.PCK_MAX_THRESHOLD and len(t) == metrics.PCK_N_THRESHOLDS
    assert np.all(frac == 1.0) and metrics.pck_auc(t, frac) == pytest.approx(1.0)
    t, frac = metrics.pck_curve(np.full(10, 0.5))
    assert np.all(frac == 0.0) and metrics.pck_auc(t, frac) == 0.0
    rng = np.random.default_rng(0)
    t, frac = metrics.pck_curve(rng.uniform(0, 0.25, 2000))
    assert np.all(np.diff(frac) >= 0)
    assert metrics.pck_auc(t, frac) == pytest.approx(0.5, abs=0.02)  # uniform errors: AUC 1/2


# ------------------------------------------------------------------------------------- conformal distortion
def _dilatation_oracle(rest, faces, deformed):
    """K = s1/s2 of each triangle's Jacobian from an explicit local frame and an SVD."""
    out = []
    for tri in faces:
        a, b, c = rest[tri]
        e1, e2 = b - a, c - a
        u = e1 / np.linalg.norm(e1)
        w = e2 - (e2 @ u) * u
        w /= np.linalg.norm(w)
        rest_2d = np.array([[e1 @ u, e2 @ u], [e1 @ w, e2 @ w]])  # columns: edges in the rest frame
        d1, d2 = deformed[tri[1]] - deformed[tri[0]], deformed[tri[2]] - deformed[tri[0]]
        jac = np.column_stack([d1, d2]) @ np.linalg.inv(rest_2d)  # 3x2
        s = np.linalg.svd(jac, compute_uv=False)
        out.append(s[0] / s[1])
    return np.array(out)


def test_conformal_distortion_single_triangle_stretch():
    rest = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    stretched = rest * [2.0, 1.0, 1.0]
    value = metrics.conformal_distortion(rest, np.array([[0, 1, 2]]), stretched)
    assert value[0] == pytest.approx((2.0 - 0.5) ** 2)  # (K - 1/K)^2 with K = 2


def test_conformal_distortion_matches_svd_oracle():
    rng = np.random.default_rng(1)
    rest = rng.normal(size=(30, 3))
    faces = np.arange(30).reshape(10, 3)
    deformed = rest @ rng.normal(size=(3, 3)) + rng.normal(scale=0.3, size=rest.shape)
    k = _dilatation_oracle(rest, faces, deformed)
    expected = np.minimum((k - 1.0 / k) ** 2, metrics.CONFORMAL_DISTORTION_CLAMP)
    np.testing.assert_allclose(metrics.conformal_distortion(rest, faces, deformed), expected, rtol=1e-8, atol=1e-10)


def test_conformal_distortion_invariances(sphere):
    v, f, _ = sphere
    rng = np.random.default_rng(2)
    rot, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    assert metrics.mean_conformal_distortion(v, f, v) == pytest.approx(0.0, abs=1e-12)
    # similarity transforms (rotation, reflection, any uniform scale, translation) are conformal
    for scale in (1e-3, 0.5, 7.0):
        moved = scale * v @ rot + [3.0, -1.0, 2.0]
        assert metrics.mean_conformal_distortion(v, f, moved) == pytest.approx(0.0, abs=1e-9)
    # an anisotropic stretch is not, and its distortion does not depend on the overall scale
    stretched = v * [1.5, 1.0, 1.0]
    d = metrics.mean_conformal_distortion(v, f, stretched)
    assert d > 0.01
    assert metrics.mean_conformal_distortion(v, f, 10.0 * stretched) == pytest.approx(d, rel=1e-9)
    assert metrics.mean_conformal_distortion(0.1 * v, f, stretched) == pytest.approx(d, rel=1e-9)


def test_conformal_distortion_flat_grid_known_value():
    """Stretching a planar grid by a in x distorts every triangle by (a - 1/a)^2."""
    xs, ys = np.meshgrid(np.linspace(0, 1, 6), np.linspace(0, 1, 5))
    verts = np.column_stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)])
    quads = [(r * 6 + c, r * 6 + c + 1, (r + 1) * 6 + c, (r + 1) * 6 + c + 1) for r in range(4) for c in range(5)]
    faces = np.array([t for a, b, c, d in quads for t in ((a, b, d), (a, d, c))])
    a = 1.7
    values = metrics.conformal_distortion(verts, faces, verts * [a, 1.0, 1.0])
    np.testing.assert_allclose(values, (a - 1 / a) ** 2, rtol=1e-10)


def test_conformal_distortion_collapsed_and_degenerate_are_clamped_finite():
    rest = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0]])
    faces = np.array([[0, 1, 2], [0, 1, 3]])  # the second rest triangle is degenerate (collinear)
    collapsed = rest.copy()
    collapsed[2] = collapsed[1]  # first triangle collapses under the "map"
    values = metrics.conformal_distortion(rest, faces, collapsed, clamp=10.0)
    assert np.all(np.isfinite(values)) and values.tolist() == [10.0, 10.0]
    # the degenerate rest triangle has zero weight in the mean
    assert metrics.mean_conformal_distortion(rest, faces, rest) == 0.0
    with pytest.raises(NumericalError):
        metrics.conformal_distortion(rest, faces, np.full_like(rest, np.nan))


def test_map_conformal_distortion(sphere):
    v, f, _ = sphere
    ident = np.arange(len(v))
    assert metrics.map_conformal_distortion(v, f, v, ident) == pytest.approx(0.0, abs=1e-12)
    mirror = _mirror_index(v, axis=0)
    assert metrics.map_conformal_distortion(v, f, v, mirror) == pytest.approx(0.0, abs=1e-9)  # an isometry
    constant = np.zeros(len(v), dtype=np.int64)  # everything to one vertex: all triangles collapse
    assert metrics.map_conformal_distortion(v, f, v, constant) == pytest.approx(metrics.CONFORMAL_DISTORTION_CLAMP)
    with pytest.raises(CorrespondenceError):
        metrics.map_conformal_distortion(v, f, v, ident[:-1])


# ------------------------------------------------------------------------------------- chamfer, volume, cycle
def test_chamfer_hand_computed():
    a = np.array([[0.0, 0.0, 0.0]])
    b = np.array([[1.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    assert metrics.chamfer_distance(a, b, one_sided=True) == pytest.approx(1.0)
    assert metrics.chamfer_distance(b, a, one_sided=True) == pytest.approx(2.0)
    assert metrics.chamfer_distance(a, b) == pytest.approx(3.0)
    assert metrics.chamfer_distance(b, b) == 0.0


def test_volume_change_of_a_box():
    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    v, f = np.asarray(box.vertices), np.asarray(box.faces)
    assert metrics.mesh_volume(v, f) == pytest.approx(6.0)
    assert metrics.relative_volume_change(v, f, v + 5.0) == pytest.approx(0.0, abs=1e-12)
    assert metrics.relative_volume_change(v, f, v * [2.0, 1.0, 1.0]) == pytest.approx(1.0)
    assert metrics.volume_change_score(v, f, v * [2.0, 1.0, 1.0]) == pytest.approx(0.5)  # 2 + 1/2 - 2
    assert metrics.volume_change_score(v, f, v * [0.5, 1.0, 1.0]) == pytest.approx(0.5)  # symmetric
    with pytest.raises(InvalidMeshError, match="watertight"):
        metrics.mesh_volume(v, f[:-1])


def test_cycle_consistency(sphere):
    v, f, dist = sphere
    n = len(v)
    rng = np.random.default_rng(3)
    p_xy = rng.permutation(n)
    p_yz = rng.permutation(n)
    p_zx = np.argsort(p_yz[p_xy])  # closes the cycle exactly
    sqrt_area = math.sqrt(metrics.surface_area(v, f))
    assert np.all(metrics.cycle_consistency_errors(p_xy, p_yz, p_zx, dist, sqrt_area) == 0.0)
    antipode = cKDTree(v).query(-v)[1]
    errors = metrics.cycle_consistency_errors(p_xy, p_yz, antipode[p_zx], dist, sqrt_area)
    np.testing.assert_allclose(errors, math.pi / sqrt_area, rtol=1e-7)
    assert metrics.compose_maps(np.array([1, 0]), np.array([2, 2]), np.array([0, 1, 1])).tolist() == [1, 1]
    with pytest.raises(CorrespondenceError):
        metrics.compose_maps(np.array([5]), np.array([0, 1]))


def test_accepts_torch_tensors(sphere):
    torch = pytest.importorskip("torch")
    v, f, dist = sphere
    ident = torch.arange(len(v))
    errors = metrics.geodesic_errors(ident, torch.from_numpy(dist), ident, ident, 1.0)
    assert np.all(errors == 0.0)
    vt = torch.from_numpy(v)
    assert metrics.map_conformal_distortion(vt, torch.from_numpy(f), vt, ident) == pytest.approx(0.0, abs=1e-12)
