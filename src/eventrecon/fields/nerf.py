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
(the authors' ``MyReLU``), computed as ``ReLU(2 W h + 2 b)``: the layers before it are
:class:`DoubledLinear` modules, whose output ``2 (W h + b)`` costs a product over the
``[out, in]`` weight instead of a pass over the ``[N, out]`` activations each way, and
equals the doubled sum bit for bit (a power of two scales exactly, in fp32 and under bf16
autocast). The skip concatenates the input encoding to the output of
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
"""

from __future__ import annotations

import math
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from eventrecon.common.errors import InputError
from eventrecon.fields.base import Field
from eventrecon.fields.encoding import BandAnnealing, PositionalEncoding

__all__ = ["DoubledLinear", "NeRFField"]


#: Zeroed view-direction features the authors concatenate before the hidden colour layer
#: (an Embedder of 3 inputs with 4 bands: 3 + 3·4·2); they set that layer's init range.
ZEROED_VIEWDIR_FEATURES = 27


class DoubledLinear(nn.Linear):
    """``2 (W h + b)`` → ``[N, out]`` for ``h [N, in]``: a linear layer whose output is
    doubled through its parameters, so that ``relu`` of it is the authors' ``2·ReLU``.

    >>> layer = DoubledLinear(2, 1)
    >>> h = torch.ones(1, 2)
    >>> bool(torch.equal(layer(h), 2 * nn.functional.linear(h, layer.weight, layer.bias)))
    True
    """

    def forward(self, h: Tensor) -> Tensor:
        return F.linear(h, 2.0 * self.weight, 2.0 * self.bias)


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
        self.layers = nn.ModuleList(DoubledLinear(n, width) for n in dims_in)
        self.density = nn.Linear(width, 1)
        nn.init.xavier_uniform_(self.density.weight, gain=density_init_gain)
        nn.init.normal_(self.density.bias, mean=0.0, std=density_init_gain)
        self.colour_remap = nn.Linear(width, remap_width)
        self.colour_hidden = DoubledLinear(remap_width, colour_width)
        bound = 1.0 / math.sqrt(remap_width + ZEROED_VIEWDIR_FEATURES)
        nn.init.uniform_(self.colour_hidden.weight, -bound, bound)
        nn.init.uniform_(self.colour_hidden.bias, -bound, bound)
        self.colour_out = nn.Linear(colour_width, 3)

    def set_progress(self, step: float) -> None:
        """Set the band-annealing window of both encodings for training ``step``."""
        self.pos_enc.set_progress(step)
        self.time_enc.set_progress(step)

    def encode(self, xyz: Tensor, t: Tensor) -> Tensor:
        """``[N, in_dim]`` input encoding ``[γ(x), γ(t)]`` (the authors' layout; the layers'
        weights are stored for it), in autocast's dtype where it is active."""
        device = xyz.device.type
        dtype = torch.get_autocast_dtype(device) if torch.is_autocast_enabled(device) else None
        return torch.cat([self.pos_enc(xyz, dtype), self.time_enc(t.to(xyz.dtype), dtype)],
                         dim=-1)

    def trunk(self, xyz: Tensor, t: Tensor) -> Tensor:
        """``h [N, width]``: the hidden layers on the encoding, the encoding concatenated
        again after layer ``skip``."""
        feats = self.encode(xyz, t)
        h = feats
        for i, layer in enumerate(self.layers):
            h = F.relu(layer(h), inplace=True)            # 2·ReLU(W h + b)
            if i == self.skip:
                h = torch.cat([feats, h], dim=-1)
        return h

    def _density(self, h: Tensor) -> Tensor:
        """``σ [N] = softplus(w_σᵀ h + b_σ + shift)``."""
        return F.softplus(self.density(h).squeeze(-1) + self.density_shift)

    def density_only(self, xyz: Tensor, t: Tensor) -> Tensor:
        """``σ [N]`` without the colour branch (the same values as :meth:`forward`'s)."""
        return self._density(self.trunk(xyz, t))

    def forward(self, xyz: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        """Density and linear colour at ``xyz [N, 3]``, ``t [N, 1]``.

        Returns:
            ``(sigma [N] ≥ 0, rgb [N, 3] in (0, 1))``.
        """
        h = self.trunk(xyz, t)
        hidden = F.relu(self.colour_hidden(self.colour_remap(h)), inplace=True)
        return self._density(h), torch.sigmoid(self.colour_out(hidden))

    def callbacks(self) -> list[Any]:
        """The band-annealing schedule (:class:`~eventrecon.fields.encoding.BandAnnealing`)."""
        return [BandAnnealing()]
