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
from typing import Any, NamedTuple

import lightning.pytorch as pl
import torch
from torch import Tensor, nn

from eventrecon.errors import InputError

__all__ = ["PositionalEncoding", "band_window", "BandAnnealing", "grouped_layout",
           "encode_grouped", "full_precision_products", "ActiveColumns", "active_columns",
           "encode_active"]


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

    def forward(self, x: Tensor) -> Tensor:
        """Encode ``x [N, D]`` into ``[N, D (1 + 2L)]`` (layout in the module docstring)."""
        if self.n_bands == 0:
            return x
        xb = x[:, None, :] * self.freqs[:, None].to(x.dtype)          # [N, L, D]
        feats = torch.cat([torch.sin(xb), torch.cos(xb)], dim=-1)      # [N, L, 2D]
        if not self._all_on:                     # ×1 is exact: skip the pass once all are on
            feats = feats * self.window[:, None].to(x.dtype)
        return torch.cat([x, feats.reshape(x.shape[0], 2 * self.n_bands * self.in_dim)], dim=-1)

    def extra_repr(self) -> str:
        return f"in_dim={self.in_dim}, n_bands={self.n_bands}, anneal_steps={self.anneal_steps}"


def grouped_layout(encodings: Sequence[PositionalEncoding]) -> tuple[Tensor, Tensor]:
    """The grouped layout of several encodings' features, for :func:`encode_grouped`.

    For encodings of ``D_e`` inputs and ``L_e`` bands, the concatenated layout
    ``[γ_1(x_1), γ_2(x_2), …]`` (each band by band, module docstring) holds the same
    features as the grouped one ``[x, sin(A), cos(A)]``, with ``x = [x_1, x_2, …]``
    (``ΣD`` columns) and ``A`` every ``2^k x_{e,d}`` (encoding, then band, then input).

    Returns:
        ``order [ΣD + 2·Σ D_e L_e]`` int64: grouped column ``j`` is concatenated column
        ``order[j]``; ``freqs [ΣD, Σ D_e L_e]``: ``A = x @ freqs`` (one ``2^k`` per
        column, zeros elsewhere).
    """
    raw, sin, cos, rows, cols = [], [], [], [], []
    first_col, first_in = 0, 0
    for enc in encodings:
        d = enc.in_dim
        raw += [first_col + i for i in range(d)]
        for k in range(enc.n_bands):
            sin += [first_col + d + 2 * d * k + i for i in range(d)]
            cos += [first_col + 2 * d + 2 * d * k + i for i in range(d)]
            rows += [first_in + i for i in range(d)]
            cols += [2.0 ** k] * d
        first_col, first_in = first_col + enc.out_dim, first_in + d
    freqs = torch.zeros(first_in, len(rows))
    freqs[rows, range(len(rows))] = torch.tensor(cols)
    return torch.tensor(raw + sin + cos), freqs


def full_precision_products() -> bool:
    """Whether fp32 matrix products on the CPU run in full fp32: no
    ``torch.set_float32_matmul_precision("high"/"medium")`` and no reduced
    ``torch.backends.mkldnn.matmul.fp32_precision`` (bf16, TF32) in effect."""
    onednn = getattr(torch.backends.mkldnn.matmul, "fp32_precision", "none")
    return torch.get_float32_matmul_precision() == "highest" and onednn in ("none", "ieee")


def _angles(x: Tensor, freqs: Tensor) -> Tensor:
    """``A = x @ freqs`` exactly (``x [N, ΣD]``, ``freqs [ΣD, F]`` with one power of two
    per column, :func:`grouped_layout`) → ``[N, F]``. On a CPU with full-precision products
    as one product outside autocast: each column is one input times ``2^k`` plus zeros, so
    the sum is exact (1.2 against 1.7 ms for 16 384 × 49 on 2 cores). Elsewhere (a GPU,
    where TF32 may be on, or reduced CPU product settings) as a gather and a multiply."""
    if x.device.type == "cpu" and full_precision_products():
        with torch.autocast("cpu", enabled=False):
            return torch.mm(x, freqs.to(x.dtype))
    return torch.index_select(x, 1, freqs.argmax(0)) * freqs.amax(0).to(x.dtype)


def encode_grouped(x: Tensor, freqs: Tensor, window: Tensor | None = None,
                   dtype: torch.dtype | None = None,
                   weights: Sequence[float] | None = None) -> Tensor:
    """``[x, w·sin(A), w·cos(A)]`` with ``A = x @ freqs`` (:func:`grouped_layout`).

    ``x [N, ΣD]``, ``freqs [ΣD, F]``, ``window [F]`` (each column's band weight, on ``x``'s
    device; ``None``: all on) → ``[N, ΣD + 2F]`` in ``dtype`` (default ``x``'s; e.g.
    autocast's, so that the first layer reads the features without a cast of its own: the
    same values as casting afterwards). ``A`` is exact in ``x``'s dtype whatever autocast
    is active (:func:`_angles`), so the values equal those of :class:`PositionalEncoding`,
    in other columns (a ``−0`` input may give ``+0`` angles on a CPU). Written as three
    contiguous blocks, at under half the time of the band-by-band layout, whose
    concatenation copies a few elements per row (16 384 rows of the NeRF's 102 features on
    2 cores: 1.1 ms in bf16 against 2.6–2.8 ms, and 0.4 ms for the cast).

    Without gradients, the columns of bands that are off (``w = 0``) are written as zeros
    and their ``sin``, ``cos`` and angles are not computed (:func:`_active_runs`): early in
    annealing most are off (the default job 20 steps in has 4 of the NeRF's 49 columns
    on). ``weights`` (``F`` floats, ``window``'s values on the host) says which, without
    reading ``window`` back from a device (read when not given). The values are those of
    the product ``w·sin(A)`` but for the sign of a zero (``+0`` where ``sin(A)·0`` is
    ``−0``) and a non-finite angle (``0`` where the product is NaN; the raw input column
    then holds the non-finite value)."""
    d, n = x.shape[1], freqs.shape[1]
    if window is not None and tuple(window.shape) != (n,):
        raise InputError("encode_grouped", "window", f"a tensor of shape [{n}]",
                         tuple(window.shape))
    if weights is not None and (window is None or len(weights) != n):
        raise InputError("encode_grouped", "weights", f"{n} floats, with the window",
                         "no window" if window is None else len(weights))
    dtype = dtype or x.dtype
    if x.requires_grad and torch.is_grad_enabled():      # out= is not differentiable
        angles = _angles(x, freqs)
        sin, cos = torch.sin(angles), torch.cos(angles)
        if window is not None:
            sin, cos = sin * window, cos * window
        return torch.cat([x, sin, cos], dim=-1).to(dtype)
    out = x.new_empty(x.shape[0], d + 2 * n, dtype=dtype)
    out[:, :d] = x
    if window is not None and weights is None:
        weights = window.tolist()
    runs = [(0, n)] if weights is None else _active_runs(weights)
    if sum(b - a for a, b in runs) < n:
        out[:, d:].zero_()
    for a, b in runs:
        angles = _angles(x, freqs if (a, b) == (0, n) else freqs[:, a:b])
        ones = weights is None or all(v == 1.0 for v in weights[a:b])
        for fn, first in ((torch.sin, d), (torch.cos, d + n)):
            cols = out[:, first + a:first + b]
            if ones:
                fn(angles, out=cols)
            else:
                torch.mul(fn(angles), window[a:b], out=cols)
    return out


def _active_runs(window: Sequence[float]) -> list[tuple[int, int]]:
    """Maximal runs ``[a, b)`` of columns whose weight is not 0.

    >>> _active_runs([1.0, 0.5, 0.0, 0.0, 1.0, 0.0])
    [(0, 2), (4, 5)]
    """
    runs: list[tuple[int, int]] = []
    for j, w in enumerate(window):
        if w == 0.0:
            continue
        if runs and runs[-1][1] == j:
            runs[-1] = (runs[-1][0], j + 1)
        else:
            runs.append((j, j + 1))
    return runs


class ActiveColumns(NamedTuple):
    """The grouped layout's columns a band window leaves on (:func:`active_columns`), for
    ``k`` angle columns of non-zero weight out of ``F``."""

    columns: Tensor    # [ΣD + 2k] int64: the grouped columns kept, raw, then sin, then cos
    source: Tensor     # [k] int64: each kept angle's input column
    freq: Tensor       # [k]: its frequency, a power of two
    window: Tensor     # [k]: its band weight


def active_columns(freqs: Tensor, weights: Sequence[float]) -> ActiveColumns:
    """The columns of :func:`encode_grouped`'s output that are not zero for every input
    under the band weights ``weights`` (``F`` floats, one per angle column of ``freqs
    [ΣD, F]``): the ``ΣD`` raw inputs and the ``sin`` and ``cos`` of each angle whose
    weight is not 0. Built on ``freqs``' device.

    >>> a = active_columns(grouped_layout([PositionalEncoding(1, 3, 0)])[1], [1.0, 0.5, 0.0])
    >>> a.columns.tolist(), a.source.tolist(), a.freq.tolist(), a.window.tolist()
    ([0, 1, 2, 4, 5], [0, 0], [1.0, 2.0], [1.0, 0.5])
    """
    d, n = freqs.shape
    if len(weights) != n:
        raise InputError("active_columns", "weights", f"{n} floats", len(weights))
    kept = [j for j, w in enumerate(weights) if w != 0.0]
    device = freqs.device
    index = torch.tensor(kept, dtype=torch.int64, device=device)
    columns = [*range(d), *(d + j for j in kept), *(d + n + j for j in kept)]
    return ActiveColumns(torch.tensor(columns, dtype=torch.int64, device=device),
                         freqs[:, index].argmax(0) if kept else index,
                         freqs.amax(0)[index],
                         torch.tensor([weights[j] for j in kept], dtype=freqs.dtype,
                                      device=device))


def encode_active(x: Tensor, active: ActiveColumns, dtype: torch.dtype | None = None) -> Tensor:
    """The kept columns of :func:`encode_grouped` (``x [N, ΣD]`` → ``[N, ΣD + 2k]``,
    ``[x, w·sin(A), w·cos(A)]`` over the ``k`` angles ``A = 2^k x_d`` of non-zero weight,
    :func:`active_columns`), equal to ``encode_grouped(x, freqs, window)[:, columns]``: the
    same angles (a gather times a power of two, exact), ``sin``, ``cos`` and products. Two
    edge cases differ in bits, not in value: a ``−0`` input keeps ``−0`` angles here (the
    product of :func:`_angles` gives ``+0``), and a non-finite input makes only its own
    angle columns NaN here (every angle column of its row there). The window's values are
    the host floats ``weights`` the layout was built from, as :func:`encode_grouped` reads
    them when given.

    A layer reading these through its weight's kept columns sums the same non-zero terms
    as one reading every column; the columns of bands that are off add zeros. Early in
    annealing that is most of the first layer's products (the default job 20 steps in has
    4 of the NeRF's 49 angle columns on: 12 inputs instead of 102), and no zeros are
    written. The sums then run in another order, so the layer's outputs equal the full
    layout's up to rounding."""
    angles = torch.index_select(x, 1, active.source) * active.freq.to(x.dtype)
    window = active.window.to(x.dtype)
    feats = torch.cat([x, torch.sin(angles) * window, torch.cos(angles) * window], dim=-1)
    return feats.to(dtype or x.dtype)


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
