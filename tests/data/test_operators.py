"""Operator registry: requests, merging, resolution with the data config, reuse of larger cached eigenbases,
registering a new (sparse) operator."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import torch
import trimesh

from shapecorr.data import operators as ops
from shapecorr.data.cache import ShapeCache
from shapecorr.data.datasets import ShapeSample
from shapecorr.data.operators import (
    OperatorConfig,
    compute_operator,
    compute_operators,
    merge_requests,
    required_request,
)
from shapecorr.data.shape import make_shape
from shapecorr.errors import ConfigError


@pytest.fixture(scope="module")
def mesh():
    sphere = trimesh.creation.icosphere(2)  # 162 vertices
    return np.asarray(sphere.vertices), np.asarray(sphere.faces, dtype=np.int64)


def test_merge_requests_keeps_the_larger_eigenbasis_and_rejects_conflicts():
    merged = merge_requests({"eigenbasis": {"k": 200}, "shot": {}}, {"eigenbasis": {"k": 508}}, None)
    assert merged == {"eigenbasis": {"k": 508}, "shot": {}}
    with pytest.raises(ConfigError, match="laplacian"):
        merge_requests({"eigenbasis": {"laplacian": "cotan"}}, {"eigenbasis": {"laplacian": "robust"}})
    with pytest.raises(ConfigError, match="unknown operator"):
        merge_requests({"eigenbasis_": {}})
    with pytest.raises(ConfigError, match="no parameter"):
        merge_requests({"shot": {"radius": 0.1}})


def test_resolution_order_and_n_eig():
    cfg = OperatorConfig(laplacian="robust", params={"shot": {"radius_factor": 0.25}})
    resolved = cfg.resolve({"shot": {}, "wks": {}, "eigenbasis": {"k": 50}})
    assert resolved["eigenbasis"] == {"k": 200, "laplacian": "robust"}  # the data's default 200 > 50
    assert resolved["shot"] == {"radius_factor": 0.25}  # the dataset's parameter, not the operator default
    assert resolved["wks"] == {"count": 100, "k": 200, "laplacian": "robust"}
    assert cfg.resolve({"shot": {"radius_factor": 0.1}})["shot"]["radius_factor"] == 0.1  # explicit wins
    small = OperatorConfig(n_eig=12, request={"wks": {}, "shot": {}}, params={"wks": {"count": 7}})
    assert small.request == {"eigenbasis": {"k": 12}, "wks": {}, "shot": {}}
    assert small.n_eig == 12 and small.descriptors == ("wks", "shot")
    assert small.resolve()["wks"] == {"count": 7, "k": 12, "laplacian": "cotan"}  # k at most the eigenbasis
    raised = small.with_request({"eigenbasis": {"k": 8}, "hks": {}}, n_eig=10)
    assert raised.request["eigenbasis"] == {"k": 12} and "hks" in raised.request  # n_eig: a lower bound
    assert small.with_request(n_eig=30).n_eig == 30
    with pytest.raises(ConfigError, match="n_eigs"):
        OperatorConfig(n_eigs=3)
    with pytest.raises(ConfigError, match="n_eig must be >= 1"):
        OperatorConfig(n_eig=0)


@pytest.mark.parametrize("key, value, hint", [
    ("descriptors", ["shot"], "request: {<name>: {}}"),
    ("shot_radius_factor", 0.3, "params: {shot: {radius_factor"),
    ("n_wks", 7, "params: {wks: {count"),
    ("n_descriptor_eig", 50, "params: {wks: {k"),
])
def test_keys_that_are_not_options_name_the_option_to_use(key, value, hint):
    with pytest.raises(ConfigError, match="unknown data.operators option") as err:
        OperatorConfig(**{key: value})
    assert hint in str(err.value)
    with pytest.raises(ConfigError, match="unknown with_request option") as err:
        OperatorConfig().with_request(**{key: value})
    assert hint in str(err.value)


def test_required_operators_take_the_request_form_only():
    class Flat:
        required_operators = {"n_eig": 100, "descriptors": ["shot"]}

    class Nested:
        required_operators = {"eigenbasis": {"k": 100}, "shot": {}}

    assert required_request(Nested()) == {"eigenbasis": {"k": 100}, "shot": {}}
    with pytest.raises(ConfigError, match="Flat: .*unknown operator"):
        required_request(Flat())


def test_eigenbasis_request_reuses_a_larger_cached_entry(tmp_path, mesh, monkeypatch):
    calls = []
    original = ops.REGISTRY["eigenbasis"].compute

    def counting(ctx, params):
        calls.append(params["k"])
        return original(ctx, params)

    monkeypatch.setitem(ops.REGISTRY, "eigenbasis", ops.REGISTRY["eigenbasis"].__class__(
        **{**ops.REGISTRY["eigenbasis"].__dict__, "compute": counting}))
    cache = ShapeCache(tmp_path)
    big = compute_operator(cache, *mesh, "eigenbasis", {"k": 20, "laplacian": "cotan"})
    small = compute_operator(cache, *mesh, "eigenbasis", {"k": 8, "laplacian": "cotan"})
    assert calls == [20]  # the 8-request was answered by truncating the cached 20
    np.testing.assert_array_equal(small["evecs"], big["evecs"][:, :8])
    np.testing.assert_array_equal(small["evals"], big["evals"][:8])
    assert small["evecs"].shape == (len(mesh[0]), 8) and small["mass"].shape == (len(mesh[0]),)
    compute_operator(cache, *mesh, "eigenbasis", {"k": 8, "laplacian": "robust"})  # another Laplacian: no reuse
    compute_operator(cache, *mesh, "eigenbasis", {"k": 30, "laplacian": "cotan"})  # larger: computed
    assert calls == [20, 8, 30]
    # WKS built on the eigenbasis reuses it too (the smallest sufficient entry)
    compute_operators(cache, *mesh, OperatorConfig(n_eig=10, request={"wks": {}}))
    assert calls == [20, 8, 30]


def test_registering_a_sparse_operator_reaches_the_sample(tmp_path, mesh, monkeypatch):
    monkeypatch.setattr(ops, "REGISTRY", dict(ops.REGISTRY))

    def gradient_like(ctx, params):
        n = len(ctx.verts)
        rows = np.concatenate([ctx.faces[:, 0], ctx.faces[:, 1]])
        cols = np.concatenate([ctx.faces[:, 1], ctx.faces[:, 2]])
        mat = sp.csr_array((np.full(len(rows), params["scale"]), (rows, cols)), shape=(n, n))
        return {"grad": mat}

    ops.register_operator("toy_gradient", defaults={"scale": 2.0}, version=1, compute=gradient_like)
    with pytest.raises(ConfigError, match="already registered"):
        ops.register_operator("toy_gradient", defaults={}, version=1, compute=gradient_like)
    cache = ShapeCache(tmp_path)
    arrays = compute_operators(cache, *mesh, OperatorConfig(request={"toy_gradient": {}}))
    assert set(arrays) == {"toy_gradient"} and sp.issparse(arrays["toy_gradient"]["grad"])
    sample = ShapeSample(make_shape(*mesh, "s"), operators=arrays)
    grad = sample.operators["toy_gradient"]["grad"]
    assert grad.is_sparse and grad.dtype == torch.float32
    np.testing.assert_allclose(grad.to_dense().numpy(), arrays["toy_gradient"]["grad"].toarray())
    assert sample.features == {} and sample.to("cpu").operators["toy_gradient"]["grad"].is_sparse
    with pytest.raises(ConfigError, match="no eigenbasis"):
        _ = sample.evecs


def test_sample_views_match_the_operators(tmp_path, mesh):
    cache = ShapeCache(tmp_path)
    arrays = compute_operators(cache, *mesh, OperatorConfig(n_eig=6, request={"hks": {}}))
    sample = ShapeSample(make_shape(*mesh, "s"), operators=arrays)
    assert sample.evecs.shape == (len(mesh[0]), 6) and sample.evecs.dtype == torch.float32
    assert torch.equal(sample.evals, torch.from_numpy(arrays["eigenbasis"]["evals"]))
    assert list(sample.features) == ["hks"] and sample.features["hks"].shape[0] == len(mesh[0])
