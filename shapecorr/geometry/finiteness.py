"""Finiteness test of tensors by one reduction each.

``torch.isfinite(t).all()`` materializes a boolean tensor through several elementwise passes; on the CPU it
costs ~4 ns per float32 element at one thread (9 ms for a 5000 x 505 embedding, measured; a sum costs 0.4 ms).
A NaN or an infinity among the elements makes their sum NaN or infinite, so a finite sum proves every element
finite; only a non-finite sum (a NaN or Inf, or finite elements whose sum overflows) needs the elementwise test,
which then decides. The result is the same as ``torch.isfinite(t).all()`` for every input.
"""

from __future__ import annotations

import torch


def all_finite(*tensors: torch.Tensor) -> bool:
    """Whether every element of every tensor is finite (no NaN, no +-Inf).

    Parameters
    ----------
    *tensors : torch.Tensor, any shape and dtype (integer and boolean tensors are always finite)

    Returns
    -------
    bool
    """
    for t in tensors:
        if not (t.is_floating_point() or t.is_complex()):
            continue
        t = t.detach()
        if not bool(torch.isfinite(t.sum())) and not bool(torch.isfinite(t).all()):
            return False
    return True
