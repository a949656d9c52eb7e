"""Positional (Fourier) encoding with coarse-to-fine band annealing.

For an input :math:`\\mathbf{x} \\in \\mathbb{R}^D` and ``L`` bands:

.. math::
    \\gamma(\\mathbf{x}) = \\big(\\mathbf{x},\\ w_0 \\sin(2^0 \\mathbf{x}),\\
    w_0 \\cos(2^0 \\mathbf{x}),\\ \\dots,\\ w_{L-1} \\sin(2^{L-1} \\mathbf{x}),\\
    w_{L-1} \\cos(2^{L-1} \\mathbf{x})\\big) \\in \\mathbb{R}^{D(1 + 2L)}

(the raw input kept, then band by band ``sin`` of all D coordinates followed by ``cos``).
Frequencies are ``2^k`` without a factor π, NeRF's code convention (the paper's formula
writes ``2^k π``): the method's bands (2^0..2^13 for position, 2^0..2^6 for time) are
those of the authors' code. A side benefit: ``2^k x`` is exact in floating point, so the
only error is that of ``sin``/``cos`` themselves, even at ``x = ±1`` and beyond.

Band annealing (Nerfies / BARF): with progress :math:`\\alpha = L \\cdot
\\text{step} / \\text{anneal\\_steps}`, band ``k`` is weighted by

.. math:: w_k(\\alpha) = \\tfrac12\\big(1 - \\cos(\\pi\\,\\mathrm{clamp}(\\alpha - k, 0, 1))\\big),

so band ``k`` is off until ``α = k`` and fully on from ``α = k + 1``; all bands are on
after ``anneal_steps`` steps (``anneal_steps = 0``: always on). The window is a buffer,
saved in checkpoints; :class:`BandAnnealing` (a Lightning callback) sets it from the
global step at the start of every training batch.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import lightning.pytorch as pl
import torch
from torch import Tensor, nn

from eventrecon.common.errors import InputError

__all__ = ["PositionalEncoding", "band_window", "BandAnnealing"]


def band_window(n_bands: int, step: float, anneal_steps: int) -> list[float]:
    """Cosine window ``w_k`` for bands ``k = 0..L−1`` at a training step.

    >>> [round(w, 6) for w in band_window(4, 150, 400)]
    [1.0, 0.5, 0.0, 0.0]
    """
    if anneal_steps <= 0:
        return [1.0] * n_bands
    alpha = n_bands * float(step) / anneal_steps
    return [0.5 * (1.0 - math.cos(math.pi * min(max(alpha - k, 0.0), 1.0)))
            for k in range(n_bands)]


class PositionalEncoding(nn.Module):
    """Dimension-agnostic Fourier encoding with annealed bands (maths: module docstring).

    Args:
        in_dim: input dimension ``D`` (3 for position, 1 for time).
        n_bands: number of octaves ``L`` (frequencies ``2^0 .. 2^{L-1}``).
        anneal_steps: steps over which the bands are eased in (0: no annealing).

    Shapes: ``[N, D] -> [N, D (1 + 2L)]``.

    >>> enc = PositionalEncoding(1, 2, anneal_steps=0)
    >>> enc(torch.tensor([[math.pi / 2]]))
    tensor([[ 1.5708e+00,  1.0000e+00, -4.3711e-08, -8.7423e-08, -1.0000e+00]])
    """

    def __init__(self, in_dim: int, n_bands: int, anneal_steps: int = 4000) -> None:
        super().__init__()
        if in_dim < 1:
            raise InputError("encoding", "in_dim", "an integer >= 1", in_dim)
        if n_bands < 0:
            raise InputError("encoding", "n_bands", "an integer >= 0", n_bands)
        if anneal_steps < 0:
            raise InputError("encoding", "anneal_steps", "an integer >= 0", anneal_steps)
        self.in_dim, self.n_bands, self.anneal_steps = int(in_dim), int(n_bands), int(anneal_steps)
        self.register_buffer("freqs", 2.0 ** torch.arange(n_bands, dtype=torch.float32),
                             persistent=False)
        self.register_buffer("window", torch.tensor(band_window(n_bands, 0, anneal_steps)))
        self._window_loaded(self, None)           # _all_on, refreshed on every change
        self.register_load_state_dict_post_hook(PositionalEncoding._window_loaded)

    @staticmethod
    def _window_loaded(module: PositionalEncoding, _keys: Any) -> None:
        """Refresh :attr:`all_on` and :attr:`weights` from the window buffer."""
        module._set_weights(module.window.tolist())

    def _set_weights(self, weights: Sequence[float]) -> None:
        self._weights = tuple(weights)
        self._all_on = all(w == 1.0 for w in self._weights)

    @property
    def all_on(self) -> bool:
        """Whether every band is fully on (the window is then not multiplied in)."""
        return self._all_on

    @property
    def weights(self) -> tuple[float, ...]:
        """The window ``w_0 … w_{L−1}`` as Python floats, the values :meth:`set_progress`
        or a loaded state dict wrote to the buffer (float32): which bands are off, on or
        partly on, known without reading the buffer back from a device."""
        return self._weights

    @property
    def out_dim(self) -> int:
        """``D (1 + 2L)``."""
        return self.in_dim * (1 + 2 * self.n_bands)

    def set_progress(self, step: float) -> None:
        """Set the band window for training step ``step``."""
        window = torch.tensor(band_window(self.n_bands, step, self.anneal_steps))  # float32
        self.window.copy_(window)
        self._set_weights(window.tolist())       # from the host copy: no device sync

    @property
    def bands_on(self) -> int:
        """How many bands have ``w_k > 0``: the window is non-increasing in ``k``, so
        they are the first ones."""
        return sum(w > 0.0 for w in self._weights)

    def forward(self, x: Tensor, dtype: torch.dtype | None = None) -> Tensor:
        """Encode ``x [N, D]`` into ``[N, D (1 + 2L)]`` (layout in the module docstring)
        in ``dtype`` (default ``x``'s; a caller under autocast passes autocast's, the
        cast its first layer would make: the same values, written once at half the size).

        The angles, ``sin`` and ``cos`` are computed in ``x``'s dtype for the bands that
        are on only; the columns of the bands that are off are zeros (early in annealing
        most are)."""
        n, d = x.shape
        out = x.new_zeros(n, self.out_dim, dtype=dtype or x.dtype)
        out[:, :d] = x
        k = self.bands_on
        if k:
            xb = (x[:, :, None] * self.freqs[:k].to(x.dtype)).transpose(1, 2)  # [N, k, D]
            sin, cos = torch.sin(xb), torch.cos(xb)
            if not self._all_on:                 # ×1 is exact: skip the pass once all are on
                w = self.window[:k, None].to(x.dtype)
                sin, cos = sin * w, cos * w
            out[:, d:d + 2 * k * d] = torch.stack([sin, cos], dim=2).view(n, 2 * k * d)
        return out

    def extra_repr(self) -> str:
        return f"in_dim={self.in_dim}, n_bands={self.n_bands}, anneal_steps={self.anneal_steps}"


class BandAnnealing(pl.Callback):
    """Sets every :class:`PositionalEncoding` in the LightningModule to the global step.

    Runs at the start of each training batch, so a resumed run continues the schedule
    from its restored ``global_step``. Idempotent: several fields returning this callback
    (e.g. one per segment) do no harm.
    """

    def on_train_batch_start(self, trainer: Any, pl_module: nn.Module, batch: Any,
                             batch_idx: int) -> None:
        for module in pl_module.modules():
            if isinstance(module, PositionalEncoding):
                module.set_progress(trainer.global_step)
