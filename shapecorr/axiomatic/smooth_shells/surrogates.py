"""The short surrogate runs of the rigid stage and of the random search: samples, scores, running side by side.

A surrogate run matches farthest-point samples through the layers k <= 20 (:mod:`.layers`); its result is
scored after re-attaching X's detail (:func:`surrogate_score`, lower is better). Independent batches of surrogate runs
run side by side on the CPU threads (:func:`side_by_side`).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

from shapecorr.errors import ConfigError
from shapecorr.geometry.sampling import farthest_point_sampling
from shapecorr.losses.arap import arap_rotations

from shapecorr.axiomatic.smooth_shells.layers import (
    LayerState,
    PairTensors,
    RunSettings,
    batched_normals,
    embedding_scales,
    gather_rows,
    nearest_pairs,
    product_embeddings,
    shells_of_poses,
)


def side_by_side(fn, items: list, device: torch.device) -> list:
    """``[fn(item) for item in items]``, on the CPU with the items spread over torch's thread count.

    The surrogate runs of the random search and of the rigid stage are independent batches of small tensors,
    for which torch's intra-op threads barely help: whole batches run side by side instead, each thread with
    one intra-op thread (torch and scipy release the GIL). Every item is computed exactly as in the serial loop.
    """
    previous = torch.get_num_threads()
    threads = min(previous, len(items))
    if device.type != "cpu" or threads < 2:
        return [fn(item) for item in items]

    def one(item):
        torch.set_num_threads(1)  # one intra-op thread per worker thread
        return fn(item)

    try:
        with ThreadPoolExecutor(max_workers=threads) as pool:
            return list(pool.map(one, items))
    finally:
        torch.set_num_threads(previous)


def reattach_detail(pair: PairTensors, verts_x, coeffs_x, tau, k):
    """``R_i (X - X_k) + X_k + Phi tau``: the detail of X rotated by the per-vertex ARAP rotations of the shell.

    Returns
    -------
    (B, n, 3) float
    """
    shell_x = shells_of_poses(pair.phi_x, coeffs_x, k)
    shifted = shell_x + torch.matmul(pair.phi_x[:, :k], tau[:, :k].to(pair.dtype))
    rot = arap_rotations(shell_x, shifted, pair.edges_x)
    return torch.matmul(rot, (verts_x - shell_x)[..., None])[..., 0] + shifted


def descriptor_block(pair: PairTensors, feats, weight: float):
    """Per-vertex basis features ``Phi F`` of X (n_x, c) and Y (n_y, c), scaled to ``weight * ||Y||``.

    None when ``weight == 0``; ``feats``: :func:`basis_features` (required otherwise).
    """
    if not weight > 0:
        return None
    if feats is None:
        raise ConfigError("smooth_shells.score_descriptors needs the basis features (lambda_feat > 0)")
    k = feats[0].shape[0]
    desc_x = pair.phi_x[:, :k] @ feats[0].to(pair.dtype)
    desc_y = pair.phi_y[:, :k] @ feats[1].to(pair.dtype)
    scale = weight * pair.verts_y.norm() / desc_y.norm().clamp_min(1e-30)
    return scale * desc_x, scale * desc_y


def surrogate_score(pair: PairTensors, run: RunSettings, st: LayerState, full_x, fac_feat, damping, normals_y_full,
                    descriptors=None):
    """Area-weighted residual of the correspondences of the re-attached shapes (lower is better): (B,).

    ``descriptors`` (:func:`descriptor_block`) add the descriptor disagreement of the pairs to the residual.
    """
    normals_x = batched_normals(full_x, pair.faces_x)
    emb_x, emb_y = product_embeddings(pair, st, full_x, normals_x, pair.verts_y, normals_y_full, fac_feat, damping)
    assign, assign_inv = nearest_pairs(pair, run, emb_x, emb_y)
    _, fac_n = embedding_scales(pair, pair.verts_y, normals_y_full, 0, fac_feat, damping)
    px = torch.cat([full_x, fac_n * normals_x], -1)
    py = torch.cat([pair.verts_y, fac_n * normals_y_full], -1)[None]
    if descriptors is not None:
        desc_x, desc_y = descriptors
        px = torch.cat([px, desc_x[None].expand(px.shape[0], -1, -1)], -1)
        py = torch.cat([py, desc_y[None]], -1)
    b = full_x.shape[0]
    sx, sy = run.samples_x[None].expand(b, -1), run.samples_y[None].expand(b, -1)
    d = (gather_rows(px, sx) - gather_rows(py, assign)).norm(dim=-1)
    d_inv = (gather_rows(px, assign_inv) - gather_rows(py, sy)).norm(dim=-1)
    res = torch.cat([pair.mass_x[run.samples_x][None] * d, pair.mass_y[run.samples_y][None] * d_inv], 1)
    return res.to(torch.float64).mean(1)


def farthest_samples(verts: torch.Tensor, num: int, gen: torch.Generator) -> torch.Tensor:
    """Sorted farthest-point samples from a random start drawn from ``gen`` (the original starts at random)."""
    n = verts.shape[0]
    num = min(num, n)
    start = int(torch.randint(0, n, (1,), generator=gen))
    idx = np.sort(farthest_point_sampling(verts.detach().cpu(), num, start=start))
    return torch.from_numpy(idx).to(verts.device)
