"""Random-search initialization of Smooth Shells ("MCMC" in the original; docs/smooth_shells.md §3, step 3)."""

from __future__ import annotations


import torch

from shapecorr.errors import NumericalError
from shapecorr.geometry.normals import vertex_normals
from shapecorr.geometry.shells import sigmoid_shell_weights, spectral_coefficients

from shapecorr.axiomatic.smooth_shells.config import K_START, MCMC_K_MIN, SmoothShellsConfig
from shapecorr.axiomatic.smooth_shells.layers import LayerState, PairTensors, RunSettings, match_layers, shells_of_poses
from shapecorr.axiomatic.smooth_shells.shapes import ShellsShape
from shapecorr.axiomatic.smooth_shells.surrogates import (
    descriptor_block,
    farthest_samples,
    reattach_detail,
    side_by_side,
    surrogate_score,
)


def random_search_init(x: ShellsShape, y: ShellsShape, aligned_x: torch.Tensor,
                       config: SmoothShellsConfig = SmoothShellsConfig(), feats=None,
                       generator: torch.Generator | None = None):
    """The original's "MCMC" initialization: independent random proposals, best score wins (step 3).

    Every proposal perturbs the 6 lowest spectral coordinates of X (``a_i = |xi_i| N(0, I_3)``, none for the
    constant), draws ``lambda_lap`` from ``config.mcmc_lambda_laps``, runs the surrogate layers k = 6..20 on
    farthest-point samples (spectral weight 1.5, no descriptor term, no ARAP), re-attaches the detail and is
    scored by :func:`surrogate_score`. All random numbers are drawn up front, so the result does not depend on
    ``mcmc_batch``.

    Parameters
    ----------
    x, y : ShellsShape
    aligned_x : (n_x, 3) float
        X after the rigid stage.
    config : SmoothShellsConfig
    feats : tuple, optional
        :func:`basis_features`: unused by the proposals (``lambda_feat = 0``), only by the scores when
        ``config.score_descriptors > 0``.
    generator : torch.Generator, optional

    Returns
    -------
    tau_init : (20, 3) float64
    cfix : (29, 29) float64
        Final functional map of the best proposal (fixes that block of C while k <= 20).
    scores : (num_mcmc,) float64
    """
    gen = generator if generator is not None else torch.Generator().manual_seed(config.seed)
    sx, sy = x.spectral, y.spectral
    dev, dtype = sx.verts.device, sx.verts.dtype
    pair = PairTensors(x, y, None, need_arap=False)
    coeffs = spectral_coefficients(sx.evecs, sx.mass, aligned_x)
    samples_x = farthest_samples(aligned_x, config.problem_size_init, gen)
    samples_y = farthest_samples(sy.verts, config.problem_size_init, gen)
    num = config.num_mcmc
    choice = torch.randint(0, len(config.mcmc_lambda_laps), (num,), generator=gen)
    noise = torch.randn(num, MCMC_K_MIN, 3, generator=gen, dtype=torch.float64)
    sigma = coeffs[:MCMC_K_MIN].to(torch.float64).norm(dim=1).cpu()
    sigma[0] = 0.0
    props = (sigma[None, :, None] * noise).to(dev)
    laps = torch.tensor(config.mcmc_lambda_laps, dtype=torch.float64)[choice]
    w20 = sigmoid_shell_weights(K_START, dtype=dtype, device=dev)
    normals_y_full = vertex_normals(shells_of_poses(pair.phi_y, sy.coeffs[None], config.k_max)[0], sy.faces)
    descriptors = descriptor_block(pair, feats, config.score_descriptors)
    def proposals(start: int):
        stop = min(num, start + config.mcmc_batch)
        b = stop - start
        tau = torch.zeros(b, K_START, 3, dtype=torch.float64, device=dev)
        tau[:, :MCMC_K_MIN] = props[start:stop]
        st = LayerState(verts_x=aligned_x[None].expand(b, -1, -1), coeffs_x=coeffs[None].expand(b, -1, -1), tau=tau,
                        fmap=None, k_prev=0, w_prev=w20)
        run = RunSettings(fac_feat=config.mcmc_fac_feat, normal_damping=config.normal_damping, lambda_feat=0.0,
                          lambda_lap=laps[start:stop], lambda_arap_init=0.0, area_preservation=config.area_preservation,
                          num_sub=1, mode=2, samples_x=samples_x, samples_y=samples_y, ridge=config.ridge,
                          nn_backend=config.nn_backend)
        match_layers(pair, run, st, range(MCMC_K_MIN, K_START + 1))
        full = reattach_detail(pair, st.verts_x, st.coeffs_x, st.tau, K_START)
        score = surrogate_score(pair, run, st, full, config.score_fac_feat, config.normal_damping, normals_y_full,
                                descriptors)
        return score, st.tau, st.fmap

    for k in range(MCMC_K_MIN, K_START + 1):
        pair.shell_y(k)  # fill the cache of Y's shells before the batches share it
    scores, taus, fmaps = zip(*side_by_side(proposals, list(range(0, num, config.mcmc_batch)), dev))
    scores_t = torch.cat(scores)
    if not torch.isfinite(scores_t).all():
        raise NumericalError(f"random-search initialization of {sx.name}, {sy.name}: a proposal score is NaN/Inf")
    best = int(torch.argmin(scores_t))
    return torch.cat(taus)[best], torch.cat(fmaps)[best], scores_t.cpu()
