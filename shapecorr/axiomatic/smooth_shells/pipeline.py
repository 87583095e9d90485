"""The Smooth Shells pipeline for one ordered pair (:func:`smooth_shells`) and its refinement of a given map."""

from __future__ import annotations

from dataclasses import replace

import torch

from shapecorr.errors import ConfigError, NumericalError
from shapecorr.geometry.shells import spectral_coefficients

from shapecorr.axiomatic.smooth_shells.config import K_START, SmoothShellsConfig, k_schedule
from shapecorr.axiomatic.smooth_shells.layers import LayerState, PairTensors, RunSettings, match_layer, match_layers
from shapecorr.axiomatic.smooth_shells.random_search import random_search_init
from shapecorr.axiomatic.smooth_shells.rigid import rigid_alignment
from shapecorr.axiomatic.smooth_shells.shapes import ShellsShape, SmoothShellsResult, basis_features


def _check_inputs(x: ShellsShape, y: ShellsShape, config: SmoothShellsConfig):
    need = config.num_eigs
    for s in (x, y):
        if s.spectral.n_eigs < need:
            raise ConfigError(f"{s.name}: Smooth Shells up to k_max={config.k_max} needs {need} eigenpairs, the "
                              f"shape has {s.spectral.n_eigs}; compute more (data.operators.n_eig) or lower k_max")
    if x.spectral.verts.device != y.spectral.verts.device:
        raise ConfigError(f"{x.name} and {y.name} are on different devices")


def _main_run(x, y, config, feats, aligned, tau_init, cfix, ks, first_pairs=None):
    pair = PairTensors(x, y, feats if config.lambda_feat > 0 else None, need_arap=config.lambda_arap_init > 0)
    dev = aligned.device
    coeffs = spectral_coefficients(x.spectral.evecs, x.spectral.mass, aligned)
    tau = torch.zeros(1, config.k_max, 3, dtype=torch.float64, device=dev)
    if tau_init is not None:
        tau[0, :tau_init.shape[0]] = tau_init.to(torch.float64)
    st = LayerState(verts_x=aligned[None], coeffs_x=coeffs[None], tau=tau, fmap=None)
    run = RunSettings(fac_feat=config.fac_feat, normal_damping=config.normal_damping, lambda_feat=config.lambda_feat,
                      lambda_lap=torch.tensor([config.lambda_lap]), lambda_arap_init=config.lambda_arap_init,
                      area_preservation=config.area_preservation, num_sub=1, mode=2,
                      samples_x=torch.arange(x.spectral.n_verts, device=dev),
                      samples_y=torch.arange(y.spectral.n_verts, device=dev), ridge=config.ridge,
                      nn_backend=config.nn_backend, cfix=None if cfix is None else cfix[None], record=True)
    match_layers(pair, run, st, ks, first_pairs)
    return st


def _result(x, st, aligned, rot, trans, ks, mcmc_scores=None, rigid_scores=()):
    k = st.tau.shape[1]
    tau = st.tau[0].to(aligned.dtype)
    deformed = aligned + x.spectral.evecs[:, :k] @ tau
    if not torch.isfinite(deformed).all():
        raise NumericalError(f"Smooth Shells: the deformed shape of {x.name} contains NaN or Inf")
    objectives = torch.stack(st.objectives).cpu() if st.objectives else torch.zeros(0, 2, dtype=torch.float64)
    return SmoothShellsResult(map_x_to_y=st.pairs[0][0], map_y_to_x=st.pairs[1][0], tau=tau,
                              fmap=st.fmap[0].to(aligned.dtype), deformed_x=deformed, aligned_x=aligned,
                              rotation=rot, translation=trans, k_array=tuple(ks), level_objectives=objectives,
                              mcmc_scores=mcmc_scores, rigid_scores=list(rigid_scores))


def smooth_shells(x: ShellsShape, y: ShellsShape, config: SmoothShellsConfig = SmoothShellsConfig()
                  ) -> SmoothShellsResult:
    """The full Smooth Shells pipeline for one ordered pair (module docstring).

    Parameters
    ----------
    x, y : ShellsShape
        Normalized shapes with at least ``config.num_eigs`` eigenpairs (509 for k_max = 500); SHOT on both
        unless ``lambda_feat == 0``.
    config : SmoothShellsConfig

    Returns
    -------
    SmoothShellsResult
        Deterministic for a given ``config.seed`` (same device and library versions).
    """
    _check_inputs(x, y, config)
    gen = torch.Generator().manual_seed(config.seed)
    with torch.no_grad():
        feats = basis_features(x, y) if config.lambda_feat > 0 else None
        dtype, dev = x.spectral.verts.dtype, x.spectral.verts.device
        rot = torch.eye(3, dtype=dtype, device=dev)
        trans = torch.zeros(3, dtype=dtype, device=dev)
        rigid_scores = []
        if not config.no_rigid:
            rot, trans, rigid_scores = rigid_alignment(x, y, config, feats, gen)
        aligned = x.spectral.verts @ rot.transpose(0, 1) + trans
        tau_init = cfix = mcmc_scores = None
        if config.num_mcmc > 0:
            tau_init, cfix, mcmc_scores = random_search_init(x, y, aligned, config, feats, gen)
        ks = config.k_array
        st = _main_run(x, y, config, feats, aligned, tau_init, cfix, ks)
        return _result(x, st, aligned, rot, trans, ks, mcmc_scores, rigid_scores)


def refine(x: ShellsShape, y: ShellsShape, initial_map: torch.Tensor, k_start: int = K_START,
           initial_map_inv: torch.Tensor | None = None, config: SmoothShellsConfig = SmoothShellsConfig()
           ) -> SmoothShellsResult:
    """Smooth Shells layered matching initialized from a given map (no rigid stage, no random search).

    The first layer (size ``k_start``) fits ``tau`` and ``C`` to the given pairs instead of searching
    neighbours; the layers of the published schedule above ``k_start`` follow. This is the post-processing
    of a learned matcher's map (NeuroMorph's paper refines its maps this way).

    Parameters
    ----------
    x, y : ShellsShape
    initial_map : (n_x,) int64
        Map X -> Y.
    k_start : int
        Shell size of the first layer (``<= config.k_max``).
    initial_map_inv : (n_y,) int64, optional
        Map Y -> X; without it the first layer uses the X -> Y pairs only.
    config : SmoothShellsConfig
        ``no_rigid`` and ``num_mcmc`` are ignored.

    Returns
    -------
    SmoothShellsResult
    """
    _check_inputs(x, y, config)
    n_x, n_y = x.spectral.n_verts, y.spectral.n_verts
    dev = x.spectral.verts.device
    initial_map = torch.as_tensor(initial_map).to(device=dev, dtype=torch.int64)
    if initial_map.shape != (n_x,) or int(initial_map.min()) < 0 or int(initial_map.max()) >= n_y:
        raise ConfigError(f"refine: initial_map must be ({n_x},) indices into the {n_y} vertices of {y.name}")
    if initial_map_inv is not None:
        initial_map_inv = torch.as_tensor(initial_map_inv).to(device=dev, dtype=torch.int64)
        if initial_map_inv.shape != (n_y,) or int(initial_map_inv.min()) < 0 or int(initial_map_inv.max()) >= n_x:
            raise ConfigError(f"refine: initial_map_inv must be ({n_y},) indices into the {n_x} vertices of {x.name}")
    if not 1 <= k_start <= config.k_max:
        raise ConfigError(f"refine: k_start must be in [1, {config.k_max}], got {k_start}")
    ks = (int(k_start),) + tuple(k for k in k_schedule(config.k_max, config.k_array_length) if k > k_start)
    with torch.no_grad():
        feats = basis_features(x, y) if config.lambda_feat > 0 else None
        dtype = x.spectral.verts.dtype
        rot, trans = torch.eye(3, dtype=dtype, device=dev), torch.zeros(3, dtype=dtype, device=dev)
        aligned = x.spectral.verts
        if initial_map_inv is None:
            first = (initial_map[None], torch.zeros(1, 0, dtype=torch.int64, device=dev))
            samples_y_first = torch.zeros(0, dtype=torch.int64, device=dev)
        else:
            first = (initial_map[None], initial_map_inv[None])
            samples_y_first = None
        pair = PairTensors(x, y, feats if config.lambda_feat > 0 else None, need_arap=config.lambda_arap_init > 0)
        coeffs = spectral_coefficients(x.spectral.evecs, x.spectral.mass, aligned)
        st = LayerState(verts_x=aligned[None], coeffs_x=coeffs[None],
                        tau=torch.zeros(1, config.k_max, 3, dtype=torch.float64, device=dev), fmap=None)
        run = RunSettings(fac_feat=config.fac_feat, normal_damping=config.normal_damping,
                          lambda_feat=config.lambda_feat, lambda_lap=torch.tensor([config.lambda_lap]),
                          lambda_arap_init=config.lambda_arap_init,
                          area_preservation=config.area_preservation, num_sub=1, mode=2,
                          samples_x=torch.arange(n_x, device=dev), samples_y=torch.arange(n_y, device=dev),
                          ridge=config.ridge, nn_backend=config.nn_backend, record=True)
        if samples_y_first is not None:  # one-sided first layer: no Y -> X pairs
            if len(ks) == 1:
                ks = ks + ks  # a second layer searches both directions
            match_layer(pair, replace(run, samples_y=samples_y_first), st, ks[0], first)
            match_layers(pair, run, st, ks[1:])
        else:
            match_layers(pair, run, st, ks, first)
        return _result(x, st, aligned, rot, trans, ks)
