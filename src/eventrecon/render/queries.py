"""How the renderer calls a field: row counts padded to a few repeated sizes, and blocks.

With empty-space skipping the number of samples that reach the field changes every call;
on a CPU each new row count of a bf16 linear layer builds a new oneDNN kernel, which costs
more than the layer itself. :func:`query_field` evaluates the field on :func:`padded_rows`
rows and cuts the extra ones off again, so values and gradients are those of the real
samples. Without autograd (images, occupancy updates) the samples go to the field in
blocks of at most ``max_rows``, so that a field's activations stay in cache.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from eventrecon.fields.base import Field

__all__ = ["padded_rows", "query_field", "query_density"]


def padded_rows(m: int, per_octave: int) -> int:
    """The row count a field is called with for ``m`` samples: ``m`` rounded up to the
    next of ``per_octave`` geometric steps per doubling (``2^{⌈k·log2 m⌉/k}``), then to a
    multiple of 64; ``m`` itself when ``per_octave`` is 0 (or ``m`` is 0).

    The padding costs at most ``2^{1/k} − 1`` more samples (9 % at ``k = 8``).

    >>> padded_rows(1000, 8), padded_rows(1000, 0), padded_rows(0, 8)
    (1024, 1000, 0)
    """
    if per_octave <= 0 or m <= 0:
        return m
    size = 2.0 ** (math.ceil(per_octave * math.log2(m) - 1e-9) / per_octave)
    return max(m, 64 * math.ceil(size / 64))


def query_field(field: Field, x: Tensor, t: Tensor, per_octave: int = 8, max_rows: int = 0
                ) -> tuple[Tensor, Tensor]:
    """``field(x [M, 3], t [M, 1])`` → ``σ [M]``, ``rgb [M, 3]``, evaluated on
    :func:`padded_rows` rows: the extra rows repeat the first sample and are cut off
    again, so values and gradients are those of the ``M`` samples alone.

    ``max_rows > 0``: without autograd, the samples go to the field in blocks of at most
    ``max_rows`` (each padded as above). A field's samples are independent, so the values
    are the same up to rounding. With autograd the call is never split: the training
    step's calls are small, and its numerics stay those of one call."""
    return _padded_call(field, x, t, per_octave, max_rows)  # type: ignore[return-value]


def query_density(field: Field, x: Tensor, t: Tensor, per_octave: int = 8,
                  max_rows: int = 0) -> Tensor:
    """``field.density_only(x [M, 3], t [M, 1])`` → ``σ [M]``, padded and split into
    blocks as :func:`query_field` does (a field may skip its colour for it)."""
    return _padded_call(field.density_only, x, t, per_octave, max_rows)[0]


def _padded_call(fn: Callable[[Tensor, Tensor], Tensor | tuple[Tensor, ...]], x: Tensor,
                 t: Tensor, per_octave: int, max_rows: int) -> tuple[Tensor, ...]:
    """``fn(x [M, 3], t [M, 1])`` on :func:`padded_rows` rows (in blocks of ``max_rows``
    without autograd), each output (``[rows, …]``) cut back to ``[M, …]``; always a
    tuple of them."""
    m = x.shape[0]
    if 0 < max_rows < m and not torch.is_grad_enabled():
        parts = [_padded_call(fn, x[a:a + max_rows], t[a:a + max_rows],      # pad the last
                              per_octave if a + max_rows >= m else 0, 0)      # block only
                 for a in range(0, m, max_rows)]
        return tuple(torch.cat(outs) for outs in zip(*parts))
    rows = padded_rows(m, per_octave)
    if rows > m:
        x = torch.cat([x, x[:1].expand(rows - m, -1)])
        t = torch.cat([t, t[:1].expand(rows - m, -1)])
    out = fn(x, t)
    return tuple(o[:m] for o in (out if isinstance(out, tuple) else (out,)))
