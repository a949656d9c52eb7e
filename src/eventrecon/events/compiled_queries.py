"""The event store's per-step queries as compiled loops on a CPU: ``V`` at given pixels
and times, and ``E(t0, t1)`` of every pixel (:class:`~eventrecon.events.accumulate.DecayedEvents`).

Each training step asks both: the map of pixels with events in its window, then ``E``
and ``E_ref`` at its rays' pixels. As tensor operations they are searches over all the
keys, scatters and gathers over every event in the window, a few dozen calls of
10–100 µs each (~1.6 ms of a 3.2 ms batch at 130 000 events, 6 × 96 × 72 pixels). Here:

- :func:`lookup` -- for pixel ``p`` and time rank ``r``, the last event of ``p``'s CSR
  row ``offsets[p] … offsets[p+1] − 1`` with key ``≤ p·(U+1) + r``, by a binary search
  of that row alone; its ``V``, or 0 when there is none. The keys of every earlier pixel
  are smaller and of every later one larger, so this is the event the global
  ``searchsorted`` finds, and the same value.
- :func:`window_all` -- for the events of the window in time order (positions ``q`` in
  the CSR arrays), each pixel's first and last position ``lo, hi``; then
  ``E = V[hi] − V[lo − 1]`` (``V[lo − 1]`` taken as 0 when ``lo`` starts the row), negated
  when ``t0 > t1``: the tensor form's scatter of minima and maxima, the same subtraction.

Both give the tensor forms' values to the bit. Where numba is missing or the store is
not on the CPU they return ``None`` and the caller runs the tensor form.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from eventrecon.render.compiled import AVAILABLE, compiled

__all__ = ["lookup", "serves", "window_all"]


@compiled
def _lookup(keys: Any, values: Any, offsets: Any, pix: Any, rank: Any, stride: int,
            out: Any) -> None:
    """``out[i] = V`` of the last event of pixel ``pix[i]`` with key ``≤ pix[i]·stride +
    rank[i]`` (0 if none): a binary search of the pixel's row."""
    for i in range(pix.shape[0]):
        p = pix[i]
        q = p * stride + rank[i]
        a, b = offsets[p], offsets[p + 1]
        first = a
        while a < b:                            # the first key of the row above q
            m = (a + b) >> 1
            if keys[m] <= q:
                a = m + 1
            else:
                b = m
        out[i] = values[a - 1] if a > first else 0.0


@compiled
def _window(pixels: Any, positions: Any, a: int, b: int, values: Any, offsets: Any,
            forward: bool, lo: Any, hi: Any, out: Any) -> None:
    """``out[p] = E`` of every pixel with an event among the time-ordered events
    ``a … b − 1`` (module docstring); ``lo`` starts at the event count and ``hi`` at −1
    (``[n_pixels]`` each, the caller's); ``out`` starts at 0."""
    for e in range(a, b):
        p, q = pixels[e], positions[e]
        if q < lo[p]:
            lo[p] = q
        if q > hi[p]:
            hi[p] = q
    for p in range(out.shape[0]):
        if hi[p] >= 0:
            later = values[hi[p]]
            earlier = values[lo[p] - 1] if lo[p] > offsets[p] else 0.0
            out[p] = later - earlier if forward else earlier - later


def serves(keys: Tensor) -> bool:
    """Whether the compiled loops serve a store whose keys are ``keys``: numba present,
    the store on the CPU."""
    return AVAILABLE and keys.device.type == "cpu"


def lookup(keys: Tensor, values: Tensor, offsets: Tensor, pix: Tensor, rank: Tensor,
           stride: int) -> Tensor | None:
    """``V`` float64 at pixels ``pix`` and time ranks ``rank`` (int64, one shape) of the
    store's ``keys [n]``, ``values [n]`` and ``offsets [n_pixels + 1]`` (``stride = U + 1``);
    ``None`` where :func:`serves` is false."""
    if not serves(keys):
        return None
    out = np.empty(pix.numel())
    _lookup(keys.numpy(), values.numpy(), offsets.numpy(),
            pix.to(torch.int64).reshape(-1).contiguous().numpy(),
            rank.to(torch.int64).reshape(-1).contiguous().numpy(), int(stride), out)
    return torch.from_numpy(out).reshape(pix.shape)


def window_all(time_order: tuple[Tensor, Tensor, Tensor], a: int, b: int, values: Tensor,
               offsets: Tensor, forward: bool, out: Tensor) -> Tensor | None:
    """``out [n_pixels]`` (float64 zeros, the caller's) filled with ``E`` of the
    time-ordered events ``a … b − 1`` (``time_order``: :attr:`DecayedEvents._time_order`'s
    ranks, pixels and positions), ``t0 ≤ t1`` when ``forward``; ``None`` (``out``
    untouched) where :func:`serves` is false."""
    if not serves(values):
        return None
    _, pixels, positions = time_order
    n_pixels = out.shape[0]
    lo = np.full(n_pixels, values.shape[0], dtype=np.int64)
    hi = np.full(n_pixels, -1, dtype=np.int64)
    _window(pixels.numpy(), positions.numpy(), a, b, values.numpy(), offsets.numpy(),
            forward, lo, hi, out.numpy())
    return out
