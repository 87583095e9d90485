"""Rigid pre-alignment of Smooth Shells (docs/smooth_shells.md §3, step 2).

The first non-constant spectral coordinate of X onto that of Y, an ICP about Y's axis, area-weighted centroids,
then surrogate shell runs over 2 rotations about X's 3rd principal axis and 4 about its 1st, keeping the lowest
score.
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch

from shapecorr.errors import NumericalError
from shapecorr.geometry.normals import vertex_normals
from shapecorr.geometry.shells import sigmoid_shell_weights, spectral_coefficients
from shapecorr.geometry.spectral_shape import SpectralShape
from shapecorr.matching.nearest_neighbors import bidirectional_nearest_neighbors

from shapecorr.axiomatic.smooth_shells.config import K_START, RIGID_K_MIN, SmoothShellsConfig
from shapecorr.axiomatic.smooth_shells.layers import (
    LayerState,
    PairTensors,
    RunSettings,
    functional_map,
    match_layers,
    shells_of_poses,
)
from shapecorr.axiomatic.smooth_shells.shapes import ShellsShape
from shapecorr.axiomatic.smooth_shells.surrogates import (
    descriptor_block,
    farthest_samples,
    reattach_detail,
    side_by_side,
    surrogate_score,
)


def _rotation_between(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """The minimal rotation (3, 3) taking direction ``a`` to direction ``b`` (Rodrigues)."""
    a = a / a.norm()
    b = b / b.norm()
    v = torch.linalg.cross(a, b)
    s, c = v.norm(), torch.dot(a, b)
    if float(s) < 1e-12:
        if float(c) > 0:
            return torch.eye(3, dtype=a.dtype, device=a.device)
        # antiparallel: half turn about any axis orthogonal to a
        helper = torch.eye(3, dtype=a.dtype, device=a.device)[int(torch.argmin(a.abs()))]
        axis = torch.linalg.cross(a, helper)
        return _axis_angle(axis / axis.norm(), math.pi)
    return _axis_angle(v / s, float(torch.atan2(s, c)))


def _axis_angle(axis: torch.Tensor, angle: float) -> torch.Tensor:
    """Rotation matrix (3, 3) about the unit ``axis`` by ``angle`` (Rodrigues' formula)."""
    kx = torch.zeros(3, 3, dtype=axis.dtype, device=axis.device)
    kx[0, 1], kx[0, 2], kx[1, 2] = -axis[2], axis[1], -axis[0]
    kx = kx - kx.transpose(0, 1)
    eye = torch.eye(3, dtype=axis.dtype, device=axis.device)
    return eye + math.sin(angle) * kx + (1.0 - math.cos(angle)) * (kx @ kx)


def _axis_icp(src: torch.Tensor, dst: torch.Tensor, axis: torch.Tensor, iterations: int) -> torch.Tensor:
    """Rotation (3, 3) about ``axis`` through the mean of ``src`` that best aligns ``src`` to ``dst``.

    ICP with bidirectional nearest neighbours; for fixed pairs the optimal angle about a fixed axis has the
    closed form ``atan2(sum q . (u x p), sum q . p_perp)`` (the original takes one Gauss-Newton step on the
    angle per iteration instead).
    """
    u = (axis / axis.norm()).to(torch.float64)
    centre = src.mean(0).to(torch.float64)
    p0 = src.to(torch.float64) - centre
    q = dst.to(torch.float64) - centre
    rot = torch.eye(3, dtype=torch.float64, device=src.device)
    for _ in range(iterations):
        p = p0 @ rot.transpose(0, 1)
        a, ai = bidirectional_nearest_neighbors(p, q, backend="kdtree" if p.device.type == "cpu" else "brute",
                                                workers=torch.get_num_threads())
        pp = torch.cat([p, p[ai]], 0)
        qq = torch.cat([q[a], q], 0)
        perp = pp - (pp @ u)[:, None] * u
        num = (qq * torch.linalg.cross(u.expand_as(pp), pp, dim=-1)).sum()
        den = (qq * perp).sum()
        angle = float(torch.atan2(num, den))
        if abs(angle) < 1e-12:
            break
        rot = _axis_angle(u, angle) @ rot
    return rot


def _area_centroid(verts: torch.Tensor, mass: torch.Tensor) -> torch.Tensor:
    return (mass[:, None] * verts).sum(0) / mass.sum()


def rigid_alignment(x: ShellsShape, y: ShellsShape, config: SmoothShellsConfig = SmoothShellsConfig(),
                    feats=None, generator: torch.Generator | None = None):
    """Rigid pre-alignment of X onto Y (module docstring, step 2).

    Parameters
    ----------
    x, y : ShellsShape
    config : SmoothShellsConfig
    feats : tuple of (K, c) tensors, optional
        :func:`basis_features` (for the descriptor-only initial functional map of the surrogate runs).
    generator : torch.Generator, optional
        Farthest-point starts (default: seeded with ``config.seed``).

    Returns
    -------
    rotation : (3, 3) float
    translation : (3,) float
        ``aligned = x.verts @ rotation.T + translation``.
    scores : list of (c,) float64
        Candidate scores of each surrogate set.
    """
    gen = generator if generator is not None else torch.Generator().manual_seed(config.seed)
    sx, sy = x.spectral, y.spectral
    dtype, dev = sx.verts.dtype, sx.verts.device
    # (a) first non-constant spectral coordinate of X onto +-that of Y
    dir_x, dir_y = sx.coeffs[1].to(torch.float64), sy.coeffs[1].to(torch.float64)
    if float(dir_x.norm()) == 0 or float(dir_y.norm()) == 0:
        raise NumericalError(f"rigid alignment of {sx.name}, {sy.name}: zero first spectral coordinate")
    if float(torch.dot(dir_x, dir_y)) < 0:
        dir_y = -dir_y
    rot = _rotation_between(dir_x, dir_y)
    verts0 = sx.verts.to(torch.float64)
    m_x, m_y = sx.mass.to(torch.float64), sy.mass.to(torch.float64)
    # The original centres both shapes on load; here X's area-weighted centroid is moved onto Y's so that the
    # axis ICP below works for any input placement.
    trans = _area_centroid(sy.verts.to(torch.float64), m_y) - rot @ _area_centroid(verts0, m_x)

    def apply(r, t):
        return verts0 @ r.transpose(0, 1) + t

    # (b) ICP about Y's axis on farthest-point samples of the (normalized) 6-eigenfunction hard shells
    def hard6(s: SpectralShape, verts):
        coeffs = spectral_coefficients(s.evecs[:, :6], s.mass, verts.to(s.evecs.dtype))
        v = s.evecs[:, :6] @ coeffs
        v = v - v.mean(0)
        return v / v.square().mean(0).clamp_min(1e-30)

    cur = apply(rot, trans)
    samples_x = farthest_samples(hard6(sx, cur), config.problem_size_init, gen)
    samples_y = farthest_samples(hard6(sy, sy.verts), config.problem_size_init, gen)
    r_icp = _axis_icp(cur[samples_x], sy.verts[samples_y].to(torch.float64), dir_y, config.icp_iterations)
    centre = cur[samples_x].mean(0)
    rot = r_icp @ rot
    trans = r_icp @ trans + centre - r_icp @ centre
    # (c) area-weighted centroids
    trans = trans + _area_centroid(sy.verts.to(torch.float64), m_y) - _area_centroid(apply(rot, trans), m_x)
    # (d) surrogate runs resolving flips
    pair = PairTensors(x, y, feats, need_arap=False)
    samples_x = farthest_samples(apply(rot, trans).to(dtype), config.problem_size_init, gen)
    samples_y = farthest_samples(sy.verts, config.problem_size_init, gen)
    run = RunSettings(fac_feat=config.rigid_fac_feat, normal_damping=config.rigid_normal_damping,
                      lambda_feat=config.lambda_feat, lambda_lap=torch.tensor([config.rigid_lambda_lap]),
                      lambda_arap_init=0.0, area_preservation=config.area_preservation, num_sub=config.rigid_num_sub,
                      mode=1, samples_x=samples_x, samples_y=samples_y, ridge=config.ridge,
                      nn_backend=config.nn_backend)
    w_init = sigmoid_shell_weights(K_START, dtype=dtype, device=dev)
    c_init = functional_map(pair, replace(run, lambda_lap=torch.tensor([0.0])), w_init.shape[0], batch=1)
    normals_y_full = vertex_normals(shells_of_poses(pair.phi_y, sy.coeffs[None], config.k_max)[0], sy.faces)
    y_centroid = _area_centroid(sy.verts.to(torch.float64), m_y)
    descriptors = descriptor_block(pair, feats, config.score_descriptors)
    for k in range(RIGID_K_MIN, K_START + 1):
        pair.shell_y(k)  # fill the cache of Y's shells before the candidates share it

    def principal_axes(r, t):
        aligned = apply(r, t)
        return torch.linalg.svd(aligned - aligned.mean(0), full_matrices=False)[2]  # rows: decreasing variance

    def evaluate(turns, r, t):
        """Score the poses ``turn @ (r, t)`` (re-centred) by a surrogate run each; returns (scores, poses)."""
        poses = []
        for turn in turns:
            r_c, t_c = turn @ r, turn @ t
            t_c = t_c + y_centroid - _area_centroid(verts0 @ r_c.transpose(0, 1) + t_c, m_x)
            poses.append((r_c, t_c))
        def surrogate(chunk):  # a batch of candidate poses
            verts_b = torch.stack([apply(r_c, t_c) for r_c, t_c in chunk]).to(dtype)
            coeffs_b = torch.stack([spectral_coefficients(sx.evecs, sx.mass, v) for v in verts_b])
            b = verts_b.shape[0]
            st = LayerState(verts_x=verts_b, coeffs_x=coeffs_b,
                            tau=torch.zeros(b, K_START, 3, dtype=torch.float64, device=dev),
                            fmap=c_init.expand(b, -1, -1), k_prev=K_START, w_prev=w_init)
            run_b = replace(run, lambda_lap=torch.full((b,), config.rigid_lambda_lap))
            match_layers(pair, run_b, st, range(RIGID_K_MIN, K_START + 1))
            full = reattach_detail(pair, verts_b, coeffs_b, st.tau, K_START)
            return surrogate_score(pair, run_b, st, full, config.rigid_fac_feat, config.rigid_normal_damping,
                                   normals_y_full,
                                   descriptors)

        threads = torch.get_num_threads() if dev.type == "cpu" else 1  # one batch per thread (side by side)
        per_thread = -(-len(poses) // max(1, threads))
        chunks = [poses[i:i + per_thread] for i in range(0, len(poses), per_thread)]
        return torch.cat(side_by_side(surrogate, chunks, dev)), poses

    all_scores = []
    count3, count1 = config.rigid_rotations
    if config.rigid_joint:
        # every combination of the two sets at once (the 3rd and 1st principal axes of the current pose)
        axes = principal_axes(rot, trans)
        turns = [_axis_angle(axes[0], 2.0 * math.pi * j / count1) @ _axis_angle(axes[2], 2.0 * math.pi * i / count3)
                 for i in range(1, count3 + 1) for j in range(1, count1 + 1)]
        scores, poses = evaluate(turns, rot, trans)
        rot, trans = poses[int(torch.argmin(scores))]
        all_scores.append(scores.cpu())
    else:
        # the original: first the turns about the 3rd principal axis, then about the (new) 1st one
        for count, axis_index in ((count3, 2), (count1, 0)):
            axis = principal_axes(rot, trans)[axis_index]
            turns = [_axis_angle(axis, 2.0 * math.pi * i / count) for i in range(1, count + 1)]  # last: current
            scores, poses = evaluate(turns, rot, trans)
            rot, trans = poses[int(torch.argmin(scores))]
            all_scores.append(scores.cpu())
    if config.rigid_keep_input:
        eye = torch.eye(3, dtype=torch.float64, device=dev)
        scores, poses = evaluate([eye], eye, torch.zeros(3, dtype=torch.float64, device=dev))
        all_scores.append(scores.cpu())
        if float(scores[0]) < float(all_scores[-2].min()):
            rot, trans = poses[0]
    return rot.to(dtype), trans.to(dtype), all_scores
