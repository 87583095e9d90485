"""WeightedLoss: weighted total, input routing by argument name, skipping zero weights, Hydra instantiation,
errors."""

import functools

import pytest
import torch
from hydra.utils import instantiate

from shapecorr.errors import ConfigError, NumericalError
from shapecorr.losses.weighted import WeightedLoss


def _sq(a, scale=1.0):
    return scale * a.square().sum()


def _diff(a, b):
    return (a - b).abs().sum()


def test_total_is_weighted_sum_and_values_are_unweighted():
    a, b = torch.tensor([1.0, 2.0]), torch.tensor([0.5, 0.0])
    loss = WeightedLoss({"sq": {"fn": functools.partial(_sq, scale=2.0), "weight": 0.5},
                         "diff": {"fn": _diff, "weight": 3.0}})
    total, values = loss(a=a, b=b, unused=torch.zeros(1))
    assert set(values) == {"sq", "diff"}
    assert float(values["sq"]) == pytest.approx(10.0) and float(values["diff"]) == pytest.approx(2.5)
    assert float(total) == pytest.approx(0.5 * 10.0 + 3.0 * 2.5)


def test_gradients_flow_through_the_total():
    a = torch.tensor([1.0, -2.0], requires_grad=True)
    total, _ = WeightedLoss({"sq": {"fn": _sq, "weight": 2.0}})(a=a)
    (grad,) = torch.autograd.grad(total, a)
    torch.testing.assert_close(grad, 4.0 * a.detach())


def test_zero_weight_term_is_not_evaluated_and_weights_can_change():
    calls = []

    def expensive(a):
        calls.append(1)
        return a.sum()

    loss = WeightedLoss({"sq": {"fn": _sq, "weight": 1.0}, "geo": {"fn": expensive, "weight": 0.0}})
    total, values = loss(a=torch.ones(3))
    assert calls == [] and "geo" not in values and float(total) == 3.0
    loss.set_weight("geo", 50.0)
    total, values = loss(a=torch.ones(3))
    assert calls == [1] and float(total) == pytest.approx(3.0 + 150.0)
    assert loss.weights == {"sq": 1.0, "geo": 50.0}


def test_kwargs_functions_receive_everything():
    seen = {}

    def spy(**kw):
        seen.update(kw)
        return torch.tensor(0.0)

    WeightedLoss({"spy": {"fn": spy, "weight": 1.0}})(a=torch.ones(1), b=2)
    assert set(seen) == {"a", "b"}


def test_instantiates_from_a_hydra_config():
    cfg = {
        "_target_": "shapecorr.losses.weighted.WeightedLoss",
        "terms": {
            "reg": {"fn": {"_target_": "shapecorr.losses.registration.registration_loss", "_partial_": True,
                           "reduction": "sum"}, "weight": 2.0},
            "geo": {"fn": {"_target_": "shapecorr.losses.geodesic_distortion.geodesic_distortion_loss",
                           "_partial_": True}, "weight": 50.0},
        },
    }
    loss = instantiate(cfg)
    n = 6
    verts = torch.randn(n, 3, generator=torch.Generator().manual_seed(0))
    eye = torch.eye(n)
    dist = torch.cdist(verts, verts)
    total, values = loss(verts_x_deformed=verts + 0.1, verts_y=verts, pi_x_to_y=eye, pi_y_to_x=eye,
                         dist_x=dist, dist_y=dist)
    assert float(values["geo"]) == 0.0
    assert float(values["reg"]) == pytest.approx(2 * n * 3 * 0.01, rel=1e-5)
    assert float(total) == pytest.approx(2.0 * float(values["reg"]), rel=1e-6)


def test_errors():
    with pytest.raises(ConfigError, match="at least one"):
        WeightedLoss({})
    with pytest.raises(ConfigError, match="'fn' and 'weight'"):
        WeightedLoss({"a": {"fn": _sq}})
    with pytest.raises(ConfigError, match="not callable"):
        WeightedLoss({"a": {"fn": 3, "weight": 1.0}})
    with pytest.raises(ConfigError, match="finite"):
        WeightedLoss({"a": {"fn": _sq, "weight": float("nan")}})
    with pytest.raises(ConfigError, match="number"):
        WeightedLoss({"a": {"fn": _sq, "weight": "heavy"}})
    loss = WeightedLoss({"diff": {"fn": _diff, "weight": 1.0}})
    with pytest.raises(ConfigError, match=r"needs the inputs \['b'\]"):
        loss(a=torch.ones(2))
    with pytest.raises(ConfigError, match="unknown loss term"):
        loss.set_weight("nope", 1.0)
    with pytest.raises(NumericalError, match="'diff' is not finite"):
        loss(a=torch.tensor([float("inf")]), b=torch.zeros(1))
    with pytest.raises(ConfigError, match="scalar"):
        WeightedLoss({"v": {"fn": lambda a: a, "weight": 1.0}})(a=torch.ones(3))
    off = WeightedLoss({"diff": {"fn": _diff, "weight": 0.0}})
    with pytest.raises(ConfigError, match="weight 0"):
        off(a=torch.ones(1), b=torch.ones(1))
