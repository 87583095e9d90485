"""DiffusionNet operators: tangent frames and the 1-ring least-squares gradient."""

import numpy as np
import pytest
import scipy.sparse as sp
import trimesh
from scipy.spatial import Delaunay
from scipy.spatial.transform import Rotation

from shapecorr.errors import ConfigError, InvalidMeshError, NumericalError
from shapecorr.geometry.diffusion_operators import (
    diffusion_gradients,
    spatial_gradient,
    tangent_frames,
)


def _planar_patch(seed=0, n=150):
    """Irregular Delaunay triangulation of random points in the unit square, rotated into 3-D."""
    rng = np.random.default_rng(seed)
    pts = np.vstack([rng.random((n, 2)), [[0, 0], [1, 0], [0, 1], [1, 1]]])
    faces = Delaunay(pts).simplices.astype(np.int64)
    verts = np.c_[pts, np.zeros(len(pts))]
    # consistent orientation (+z normals) before rotating
    e1, e2 = verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]]
    flip = np.cross(e1, e2)[:, 2] < 0
    faces[flip] = faces[flip][:, [0, 2, 1]]
    rot = Rotation.random(random_state=seed).as_matrix()
    return verts @ rot.T, faces, rot


def _ellipsoid(subdivisions=2):
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    return np.asarray(m.vertices) * np.array([1.0, 0.8, 0.6]), np.asarray(m.faces)


def test_frames_are_right_handed_orthonormal_with_outward_normals():
    v, f = _ellipsoid()
    fr = tangent_frames(v, f).astype(np.float64)
    assert fr.shape == (len(v), 3, 3)
    gram = np.einsum("nij,nkj->nik", fr, fr)
    assert np.abs(gram - np.eye(3)).max() < 1e-5
    assert np.abs(np.cross(fr[:, 2], fr[:, 0]) - fr[:, 1]).max() < 1e-5  # y = n x x
    assert (np.einsum("ni,ni->n", fr[:, 2], v) > 0).all()  # convex shape: normals point outwards


def test_gradient_is_exact_on_linear_functions_of_a_planar_patch():
    v, f, rot = _planar_patch()
    ops = diffusion_gradients(v, f, ridge=0.0)
    gx, gy, fr = ops["grad_x"], ops["grad_y"], ops["frames"].astype(np.float64)
    assert isinstance(gx, sp.csr_matrix) and gx.dtype == np.float32 and gx.shape == (len(v), len(v))
    rng = np.random.default_rng(1)
    for _ in range(3):
        c = rng.standard_normal(3)  # f(p) = c . p; its surface gradient is c projected onto the plane
        fun = v @ c
        got = np.stack([gx @ fun, gy @ fun], axis=1)
        want = np.stack([fr[:, 0] @ c, fr[:, 1] @ c], axis=1)
        assert np.abs(got - want).max() < 1e-4 * np.abs(c).max()
    # All normals are the plane normal (up to orientation); the in-plane gradient norm is preserved.
    plane_n = rot[:, 2]
    assert np.abs(np.abs(fr[:, 2] @ plane_n) - 1).max() < 1e-5


def test_gradient_kills_constants_and_uses_the_one_ring_only():
    v, f = _ellipsoid()
    gx, gy = spatial_gradient(v, f)
    for g in (gx, gy):
        assert np.abs(g @ np.ones(len(v))).max() < 1e-5
    adj = sp.csr_matrix((np.ones(3 * len(f)), (f[:, [0, 1, 2]].ravel(), f[:, [1, 2, 0]].ravel())), shape=(len(v),) * 2)
    allowed = ((adj + adj.T + sp.eye(len(v))) > 0).astype(np.int8)
    pattern = (abs(gx) + abs(gy) > 0).astype(np.int8)
    assert (pattern.multiply(1 - allowed.toarray())).sum() == 0


def test_gradient_on_a_sphere_approximates_the_tangential_gradient():
    m = trimesh.creation.icosphere(subdivisions=3)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    ops = diffusion_gradients(v, f)
    fr = ops["frames"].astype(np.float64)
    c = np.array([0.3, -1.0, 2.0])
    got = np.stack([ops["grad_x"] @ (v @ c), ops["grad_y"] @ (v @ c)], axis=1)
    want = np.stack([fr[:, 0] @ c, fr[:, 1] @ c], axis=1)
    err = np.linalg.norm(got - want, axis=1).mean() / np.linalg.norm(want, axis=1).mean()
    assert err < 0.02  # first-order fit on a curved surface: small, nonzero error


def test_gradient_is_covariant_under_rotation_and_scale_invariant_in_frame_coordinates():
    v, f = _ellipsoid()
    rng = np.random.default_rng(3)
    fun = rng.standard_normal(len(v))
    gx, gy = spatial_gradient(v, f)
    fr = tangent_frames(v, f).astype(np.float64)
    grad3 = (gx @ fun)[:, None] * fr[:, 0] + (gy @ fun)[:, None] * fr[:, 1]  # gradient as a 3-D vector
    rot = Rotation.random(random_state=4).as_matrix()
    s = 2.5
    gx2, gy2 = spatial_gradient(s * v @ rot.T, f)
    fr2 = tangent_frames(s * v @ rot.T, f).astype(np.float64)
    grad3_b = (gx2 @ fun)[:, None] * fr2[:, 0] + (gy2 @ fun)[:, None] * fr2[:, 1]
    assert np.abs(grad3_b * s - grad3 @ rot.T).max() < 1e-3 * np.abs(grad3).max()


def test_degenerate_one_ring_needs_a_ridge_and_bad_input_raises():
    # Frames given by the caller: vertex 0's tangent axes see both of its edges, (1, 0, 0) and (0, 1, 0), on
    # one line, so its 2 x 2 fit is singular without a ridge.
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=float)
    f = np.array([[0, 1, 2], [1, 3, 2]])
    frames = np.tile(np.eye(3), (4, 1, 1))
    frames[0] = np.array([[0, 0, 1.0], [1, 1, 0] / np.sqrt(2), [1, -1, 0] / np.sqrt(2)])
    with pytest.raises(NumericalError, match="singular"):
        spatial_gradient(v, f, frames=frames, ridge=0.0)
    gx, gy = spatial_gradient(v, f, frames=frames, ridge=1e-5)
    assert np.isfinite(gx.data).all() and np.isfinite(gy.data).all()
    with pytest.raises(ConfigError):
        spatial_gradient(v, f, ridge=-1.0)
    with pytest.raises(ConfigError):
        spatial_gradient(v, f, frames=np.zeros((3, 3, 3)))
    with pytest.raises(InvalidMeshError):
        tangent_frames(np.full((4, 3), np.nan), f)
    with pytest.raises(NumericalError, match="no vertex normal"):
        tangent_frames(np.vstack([v, [[5, 5, 5]]]), f)  # vertex 4 is in no face


def test_frames_where_the_normal_is_the_reference_axis():
    v, f, _ = _planar_patch(seed=5)
    v = v @ np.linalg.inv(_planar_patch(seed=5)[2]).T  # back to the z = 0 plane
    v = v[:, [2, 0, 1]]  # the plane x = 0: every normal is +-e_x, the first reference axis
    ops = diffusion_gradients(v, f, ridge=0.0)
    fr = ops["frames"].astype(np.float64)
    assert np.abs(np.abs(fr[:, 2, 0]) - 1).max() < 1e-6
    assert np.abs(np.einsum("nij,nkj->nik", fr, fr) - np.eye(3)).max() < 1e-5
    c = np.array([0.0, 1.5, -0.5])
    got = np.stack([ops["grad_x"] @ (v @ c), ops["grad_y"] @ (v @ c)], axis=1)
    assert np.abs(got - np.stack([fr[:, 0] @ c, fr[:, 1] @ c], axis=1)).max() < 1e-4


def test_folded_one_ring_takes_the_neighbours_normal():
    # A flap as remeshing leaves it (4 FAUST_r shapes): vertex w lies in two faces with opposite orientation over
    # the same triangle, so its area-weighted normal sums to exactly zero; its frame comes from its neighbours.
    v, f, rot = _planar_patch(seed=3, n=60)
    a, b = f[0, 0], f[0, 1]
    w = len(v)
    v_flap = np.vstack([v, (v[a] + v[b]) / 2 + 0.05 * rot[:, 0]])
    f_flap = np.vstack([f, [[a, w, b], [b, w, a]]])
    fr = tangent_frames(v_flap, f_flap).astype(np.float64)
    assert np.isfinite(fr).all()
    assert np.abs(np.einsum("nij,nkj->nik", fr, fr) - np.eye(3)).max() < 1e-5
    patch_normal = rot[:, 2]
    assert abs(fr[w, 2] @ patch_normal) > 0.99
    # the other vertices keep their libigl normals
    np.testing.assert_allclose(fr[:w], tangent_frames(v, f), atol=1e-6)
    gx, gy = spatial_gradient(v_flap, f_flap, frames=fr.astype(np.float32))
    assert np.isfinite(gx.data).all() and np.isfinite(gy.data).all()
