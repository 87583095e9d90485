"""Dropout whose mask can be drawn for a whole tensor and applied to some of its rows.

:class:`RowDropout` computes what :class:`torch.nn.Dropout` computes (the same masks from the same random stream,
the same values, the same gradients) and can in addition apply the mask of a full ``(n, C)`` tensor to a subset
of its rows: ``forward(x_rows, rows=rows, full_rows=n)`` draws the ``(n, C)`` mask exactly as dropout on the full
tensor would (the random stream advances by the same amount) and multiplies ``x_rows`` by its rows ``rows``. A
network can then run per-vertex layers at a few vertices only while training, with the values and random state
of the full computation (DiffusionNet's last block, :mod:`shapecorr.nn.diffusion_net`).

On CPUs PyTorch's dropout is ``x * (bernoulli(1 - p) / (1 - p))`` with the mask drawn element by element from the
default generator: each entry is ``u < 1 - p`` for a float64 uniform ``u`` (two 32-bit Mersenne-Twister outputs).
``torch.rand(..., dtype=float64) < 1 - p`` draws the same uniforms from the same stream in about half the time
(the Bernoulli kernel costs ~10 ns per entry at one thread; a (5000, 128) mask ~6 ms against ~3.5 ms). Whether
the two agree on this build is checked once per process and probability (:func:`rand_mask_matches_bernoulli`,
on a small tensor, with the generator state saved and restored); where they do not, the mask is drawn with
``bernoulli_`` as dropout does. On other devices dropout draws its mask in a fused kernel with its own stream,
which cannot be drawn apart from the values: there :class:`RowDropout` calls :func:`torch.nn.functional.dropout`
on the full tensor (``rows`` are then refused, :meth:`RowDropout.draws_apart` says so beforehand).
"""

from __future__ import annotations

import torch
from torch import nn

from shapecorr.errors import ConfigError

#: Size of the tensor on which the uniform-sample mask is compared with ``bernoulli_`` (a few hundred draws).
_CHECK_SHAPE = (97, 5)
_MATCHES: dict[float, bool] = {}


def _bernoulli_mask(shape, keep: float, dtype, device) -> torch.Tensor:
    """``bernoulli(keep) / keep`` as :func:`torch.nn.functional.dropout` draws it on CPUs."""
    return torch.empty(shape, dtype=dtype, device=device).bernoulli_(keep).div_(keep)


def _uniform_mask(shape, keep: float, dtype, device) -> torch.Tensor:
    """``(u < keep) / keep`` for float64 uniforms ``u``."""
    return (torch.rand(shape, dtype=torch.float64, device=device) < keep).to(dtype).div_(keep)


def rand_mask_matches_bernoulli(p: float) -> bool:
    """Whether, on the CPU, :func:`_uniform_mask` equals dropout's mask for probability ``p`` and draws as much.

    Compares :func:`torch.nn.functional.dropout` of ones with the uniform mask from the same seed, and the
    generator states after both; the default generator's state is restored afterwards. Cached per ``p``.
    """
    p = float(p)
    if p not in _MATCHES:
        ones = torch.ones(_CHECK_SHAPE)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(0)
            reference = nn.functional.dropout(ones, p, training=True)
            state = torch.get_rng_state()
            torch.manual_seed(0)
            mask = _uniform_mask(_CHECK_SHAPE, 1.0 - p, ones.dtype, ones.device)
            _MATCHES[p] = bool(torch.equal(ones * mask, reference)) and bool(torch.equal(torch.get_rng_state(), state))
    return _MATCHES[p]


class RowDropout(nn.Dropout):
    """:class:`torch.nn.Dropout` that can apply the mask of a full tensor to some of its rows (module docstring).

    Parameters
    ----------
    p : float
        Probability of zeroing an entry, in ``[0, 1)``.
    """

    def __init__(self, p: float = 0.5):
        if not 0.0 <= p < 1.0:
            raise ConfigError(f"dropout probability must be in [0, 1), got {p}")
        super().__init__(p)

    @property
    def active(self) -> bool:
        """Whether a forward pass draws a mask (training mode and ``p > 0``)."""
        return self.training and self.p > 0

    def draws_apart(self, device: torch.device) -> bool:
        """Whether the mask on ``device`` can be drawn apart from the values (``rows`` are accepted)."""
        return not self.active or torch.device(device).type == "cpu"

    def forward(self, x: torch.Tensor, rows: torch.Tensor | None = None, full_rows: int | None = None) -> torch.Tensor:
        """Dropout of ``x (n, C)``, or of rows ``rows`` of a ``(full_rows, C)`` tensor given as ``x (len(rows), C)``.

        Without ``rows`` the result equals :func:`torch.nn.functional.dropout`; with them it equals that of the
        full tensor at ``rows``, and the random stream advances as for the full tensor.
        """
        if rows is not None and (full_rows is None or x.shape[0] != rows.shape[0]):
            raise ConfigError(f"RowDropout: rows ({tuple(rows.shape)}) need full_rows and one row of x each, "
                              f"got x {tuple(x.shape)}")
        if not self.active:
            return x
        if x.device.type != "cpu":
            if rows is not None:
                raise ConfigError(f"RowDropout: the mask cannot be drawn apart from the values on {x.device}")
            return nn.functional.dropout(x, self.p, training=True)
        keep = 1.0 - self.p
        shape = (x.shape[0] if rows is None else int(full_rows), *x.shape[1:])
        draw = _uniform_mask if rand_mask_matches_bernoulli(self.p) else _bernoulli_mask
        mask = draw(shape, keep, x.dtype, x.device)
        return x * (mask if rows is None else mask[rows])


__all__ = ["RowDropout", "rand_mask_matches_bernoulli"]
