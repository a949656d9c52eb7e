"""The paper's field: a NeRF MLP on encoded (x, y, z, t), no view directions.

As the authors' code builds it (``docs/method.md`` "Network"):

.. math::
    \\mathbf{h}_0 = [\\gamma_{14}(\\mathbf{x}), \\gamma_7(t)],\\quad
    \\mathbf{h}_{i+1} = 2\\,\\mathrm{ReLU}(W_i \\mathbf{h}_i' + b_i),\\quad
    \\mathbf{h}_i' = [\\mathbf{h}_0, \\mathbf{h}_i]\\ \\text{if}\\ i = \\text{skip} + 1
    \\ \\text{else}\\ \\mathbf{h}_i,

    \\sigma = \\mathrm{softplus}(w_\\sigma^\\top \\mathbf{h}_{depth} + b_\\sigma +
    \\text{density\\_shift}),\\quad
    \\mathbf{c} = \\mathrm{sigmoid}\\big(W_3\\, 2\\mathrm{ReLU}(W_2 (W_1 \\mathbf{h}_{depth}
    + b_1) + b_2) + b_3\\big).

``γ_L`` is :class:`~eventrecon.fields.encoding.PositionalEncoding` (raw input + sin/cos
at 2^0..2^{L−1}, bands eased in over ``anneal_steps``). The activation is ``2·ReLU``
(the authors' ``MyReLU``). The skip concatenates the input encoding to the output of
layer ``skip`` (0-based): with depth 8 and skip 4 the sixth linear layer takes
``in_dim + width`` inputs. Initialisation: hidden and colour layers PyTorch's default;
the density head xavier-uniform with gain ``density_init_gain`` (1) and bias drawn from
``N(0, density_init_gain²)`` — so a fresh field starts with a density that varies
across space, not a uniform fog; no shift (``density_shift = 0``). The colour branch is
a linear remap to 256 features, then ``colour_width`` (2·ReLU), then 3 (sigmoid); in the
authors' network the remap is concatenated with a zeroed view-direction encoding of 27
features before the hidden colour layer, which changes nothing but that layer's default
initialisation range (``1/sqrt(fan_in)`` with ``fan_in = 256 + 27``): it is initialised
with that range here.

The factor 2 of ``2·ReLU`` is not applied as a multiplication over the activations:
the layer after it multiplies its weight instead (``W (2 r) + b = (2W) r + b``, a
product over the ``[out, in]`` weight, not the ``[N, in]`` activations). Scaling by a
power of two is exact in floating point, so outputs and gradients are bit for bit those
of the explicit ``2·ReLU``, in fp32 and under bf16 or fp16 autocast
(``tests/test_nerf_field.py``; in fp16 short of its subnormal and overflow ranges), and
a full-size pass over the activations goes away each way. Folding the factor into
``addmm``'s ``alpha`` instead (the form before) saves the forward pass only: autograd's
backward of ``addmm`` scales the ``[N, in]`` input gradient by ``alpha`` in a pass of
its own, five per step in the 4×64 field (~10 % of its profiled time; measured 1.05× /
1.07× faster at one / two threads, docs/results/history.md, "Session 30"). The linear layers are
therefore applied through their parameters (:mod:`eventrecon.fields.linear`), not called
as modules: hooks registered on them do not run. With grad mode off on a CPU
(evaluation images, the occupancy grid's queries) each hidden layer's ReLU is fused into
oneDNN's linear, in bf16 where the CPU has it natively (the same values) and in fp32 (the
same to float32 rounding; :func:`~eventrecon.fields.linear.linear_relu`).

The input features are read in a grouped column order, ``[x, t, sin(A), cos(A)]``
(:meth:`NeRFField.features`), and the weight columns of the layers that take them are
gathered to match (:meth:`NeRFField.layer_weight`); the parameters stay in the authors'
order. Concatenating the band-by-band layout copied a few elements per row and took ~40 %
of a bf16 forward pass; the function is the same, its first sums run in another order.
With grad mode off (images, curve points, the occupancy grid's queries) while some bands
are off, the layers that read the features read only the columns that are not zero, with
their weight columns (:meth:`NeRFField.active_features`): an untrained field's image at
step 20 (issue 12's 20-step run) has 12 inputs to its first layer instead of 102.
"""

from __future__ import annotations

import math
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from eventrecon.errors import InputError
from eventrecon.fields.base import Field
from eventrecon.fields.encoding import (
    ActiveColumns,
    BandAnnealing,
    PositionalEncoding,
    active_columns,
    encode_active,
    encode_grouped,
    grouped_layout,
)
from eventrecon.fields.linear import linear, linear_relu

__all__ = ["NeRFField"]


#: Zeroed view-direction features the authors concatenate before the hidden colour layer
#: (an Embedder of 3 inputs with 4 bands: 3 + 3·4·2); they set that layer's init range.
ZEROED_VIEWDIR_FEATURES = 27


def _feature_dtype(xyz: Tensor) -> torch.dtype | None:
    """The dtype the features are made in: autocast's where it is active on ``xyz``'s
    device (the cast the first layer would make), else ``None`` (``xyz``'s)."""
    device = xyz.device.type
    return (torch.get_autocast_dtype(device) if torch.amp.is_autocast_available(device)
            and torch.is_autocast_enabled(device) else None)


class NeRFField(Field):
    """The NeRF MLP of Dynamic EventNeRF (maths in the module docstring).

    Args:
        depth: number of hidden linear layers (≥ 1).
        width: hidden width.
        skip: layer index after which the input encoding is concatenated
            (``-1`` or ``≥ depth − 1``: no skip).
        pos_bands: octaves for position (14: 2^0..2^13).
        time_bands: octaves for time (7: 2^0..2^6).
        anneal_steps: steps of coarse-to-fine band annealing (0: none).
        remap_width: width of the colour branch's linear remap (256).
        colour_width: hidden width of the colour branch (128).
        density_shift: added to the raw density before softplus (0).
        density_init_gain: xavier gain and bias standard deviation of the density head (1).

    Shapes: ``forward(xyz [N, 3], t [N, 1]) -> (sigma [N], rgb [N, 3])``.

    >>> f = NeRFField(depth=2, width=16, skip=-1, pos_bands=2, time_bands=1, colour_width=8)
    >>> sigma, rgb = f(torch.zeros(5, 3), torch.zeros(5, 1))
    >>> sigma.shape, rgb.shape, bool((sigma >= 0).all()), bool(((rgb > 0) & (rgb < 1)).all())
    (torch.Size([5]), torch.Size([5, 3]), True, True)
    """

    def __init__(
        self,
        depth: int = 8,
        width: int = 256,
        skip: int = 4,
        pos_bands: int = 14,
        time_bands: int = 7,
        anneal_steps: int = 4000,
        remap_width: int = 256,
        colour_width: int = 128,
        density_shift: float = 0.0,
        density_init_gain: float = 1.0,
    ) -> None:
        super().__init__()
        for name, value, low in (("depth", depth, 1), ("width", width, 1),
                                 ("remap_width", remap_width, 1),
                                 ("colour_width", colour_width, 1)):
            if int(value) < low:
                raise InputError("model", name, f"an integer >= {low}", value)
        self.pos_enc = PositionalEncoding(3, pos_bands, anneal_steps)
        self.time_enc = PositionalEncoding(1, time_bands, anneal_steps)
        in_dim = self.pos_enc.out_dim + self.time_enc.out_dim
        self.skip = int(skip) if 0 <= int(skip) < depth - 1 else -1
        self.density_shift = float(density_shift)
        dims_in = [in_dim] + [width + (in_dim if i - 1 == self.skip else 0)
                              for i in range(1, depth)]
        self.layers = nn.ModuleList(nn.Linear(n, width) for n in dims_in)
        self.density = nn.Linear(width, 1)
        nn.init.xavier_uniform_(self.density.weight, gain=density_init_gain)
        nn.init.normal_(self.density.bias, mean=0.0, std=density_init_gain)
        self.colour_remap = nn.Linear(width, remap_width)
        self.colour_hidden = nn.Linear(remap_width, colour_width)
        bound = 1.0 / math.sqrt(remap_width + ZEROED_VIEWDIR_FEATURES)
        nn.init.uniform_(self.colour_hidden.weight, -bound, bound)
        nn.init.uniform_(self.colour_hidden.bias, -bound, bound)
        self.colour_out = nn.Linear(colour_width, 3)
        order, freqs = grouped_layout([self.pos_enc, self.time_enc])
        self.register_buffer("feature_order", order, persistent=False)
        self.register_buffer("feature_freqs", freqs, persistent=False)
        self.register_buffer("skip_order", torch.cat([order, torch.arange(width) + in_dim]),
                             persistent=False)
        #: the last band window's kept columns (:meth:`active_features`), keyed by window
        self._active: tuple[tuple[tuple[float, ...], torch.device], ActiveColumns] | None = None

    def set_progress(self, step: float) -> None:
        """Set the band-annealing window of both encodings for training ``step``."""
        self.pos_enc.set_progress(step)
        self.time_enc.set_progress(step)

    def encode(self, xyz: Tensor, t: Tensor) -> Tensor:
        """``[N, in_dim]`` input encoding ``[γ(x), γ(t)]`` (the authors' layout; the layers'
        weights are stored for it)."""
        return torch.cat([self.pos_enc(xyz), self.time_enc(t.to(xyz.dtype))], dim=-1)

    def features(self, xyz: Tensor, t: Tensor) -> Tensor:
        """The same features as :meth:`encode`, grouped: ``xyz [N, 3]``, ``t [N, 1]`` →
        ``[N, in_dim]`` = ``[x, t, sin(A), cos(A)]``, ``A`` every ``2^k x_d`` and
        ``2^k t`` (:func:`~eventrecon.fields.encoding.encode_grouped`). Equal in value to
        ``encode(...)[:, feature_order]``, in autocast's dtype where it is active (the
        cast the first layer would make). The forward pass reads these, at under half
        the encoding's time, with the weight columns that take them gathered in the
        same order (:meth:`layer_weight`)."""
        weights = self._column_weights()
        window = None
        if weights is not None:
            window = torch.cat([e.window.repeat_interleave(e.in_dim)
                                for e in (self.pos_enc, self.time_enc)]).to(xyz.dtype)
        return encode_grouped(torch.cat([xyz, t.to(xyz.dtype)], dim=-1), self.feature_freqs,
                              window, _feature_dtype(xyz), weights)

    def active_features(self, xyz: Tensor, t: Tensor) -> tuple[Tensor, ActiveColumns] | None:
        """With grad mode off and some band off: the columns of :meth:`features` that are
        not zero, ``[N, 4 + 2k]`` for ``k`` angle columns on, and which they are
        (:func:`~eventrecon.fields.encoding.encode_active`); ``None`` otherwise. The
        layout is rebuilt only when the band window (or the device) changes."""
        weights = None if torch.is_grad_enabled() else self._column_weights()
        if weights is None:
            return None
        key = (weights, self.feature_freqs.device)
        if self._active is None or self._active[0] != key:
            self._active = (key, active_columns(self.feature_freqs, weights))
        active = self._active[1]
        x = torch.cat([xyz, t.to(xyz.dtype)], dim=-1)
        return encode_active(x, active, _feature_dtype(xyz)), active

    def _column_weights(self) -> tuple[float, ...] | None:
        """The band weight of each angle column of the grouped layout (host floats, the
        order of ``feature_freqs``' columns); ``None`` when every band is on."""
        encs = (self.pos_enc, self.time_enc)
        if all(e.all_on for e in encs):
            return None
        return tuple(w for e in encs for w in e.weights for _ in range(e.in_dim))

    def layer_weight(self, i: int, columns: Tensor | None = None) -> Tensor:
        """Trunk layer ``i``'s weight ``[width, in]`` with its columns in the order of the
        inputs it receives in :meth:`forward`: the features' columns gathered by
        ``feature_order`` (layer 0, and the layer after the skip), the weight as stored
        otherwise. With ``columns`` (grouped feature columns, :meth:`active_features`)
        only those of the features. A gather of the small weight, differentiable."""
        weight = self.layers[i].weight
        if i not in (0, self.skip + 1):
            return weight
        order = self.feature_order if i == 0 else self.skip_order
        if columns is not None:
            n = self.feature_order.numel()
            hidden = torch.arange(n, order.numel(), device=columns.device)
            order = order[columns if i == 0 else torch.cat([columns, hidden])]
        return torch.index_select(weight, 1, order)

    def _trunk(self, xyz: Tensor, t: Tensor) -> tuple[Tensor, float]:
        """The trunk's output ``h [N, width]`` and the scale its activation carries
        (``2·ReLU`` is ``2 h``, applied by the next layer's weight; module docstring).
        With grad mode off and some bands off the layers that read the features read only
        the columns that are not zero (:meth:`active_features`): the same sums up to
        their order."""
        active = self.active_features(xyz, t)
        feats, columns = (self.features(xyz, t), None) if active is None else (
            active[0], active[1].columns)
        h, scale = feats, 1.0
        for i, layer in enumerate(self.layers):
            h, scale = linear_relu(self.layer_weight(i, columns), layer.bias, h, scale), 2.0
            if i == self.skip:
                h, scale = torch.cat([feats, h * 2.0], dim=-1), 1.0
        return h, scale

    def _density(self, h: Tensor, scale: float) -> Tensor:
        """``σ [N] = softplus(w_σᵀ (scale·h) + b_σ + shift)``."""
        sigma = linear(self.density.weight, self.density.bias, h, scale)
        return F.softplus(sigma.squeeze(-1) + self.density_shift)

    def density_only(self, xyz: Tensor, t: Tensor) -> Tensor:
        """``σ [N]`` without the colour branch: the same values as :meth:`forward`'s
        (the same operations on the same trunk output)."""
        return self._density(*self._trunk(xyz, t))

    def forward(self, xyz: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        """Density and linear colour at ``xyz [N, 3]``, ``t [N, 1]``.

        The same function as the authors' layout (:meth:`encode` through the stored
        weights); the sums over the first layer's inputs run in another order, so values
        differ from it in rounding only.

        Returns:
            ``(sigma [N] ≥ 0, rgb [N, 3] in (0, 1))``.
        """
        h, scale = self._trunk(xyz, t)
        sigma = self._density(h, scale)
        remap = linear(self.colour_remap.weight, self.colour_remap.bias, h, scale)
        hidden = linear_relu(self.colour_hidden.weight, self.colour_hidden.bias, remap)
        rgb = torch.sigmoid(linear(self.colour_out.weight, self.colour_out.bias, hidden, 2.0))
        return sigma, rgb

    def callbacks(self) -> list[Any]:
        """The band-annealing schedule (:class:`~eventrecon.fields.encoding.BandAnnealing`)."""
        return [BandAnnealing()]
