"""Density / colour activations of the zoo, and the NGP decoder.

All backbones end in the same activations (:func:`activate`): density
``sigma = trunc_exp(raw_sigma)`` and colour ``rgb = sigmoid(raw_rgb)`` (linear radiance
in [0, 1]). The factorised backbones sum their rank components straight into the raw
values; the hash grid decodes its features with :class:`NGPDecoder`.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from eventrecon.fields.base import trunc_exp

__all__ = ["activate", "activate_density", "bias_free_mlp", "sh4_at_zero_direction", "NGPDecoder"]


def activate(raw_sigma: Tensor, raw_rgb: Tensor) -> tuple[Tensor, Tensor]:
    """``sigma = trunc_exp(raw_sigma)``, ``rgb = sigmoid(raw_rgb)``; float32 outputs even
    under autocast.

    Args:
        raw_sigma: ``[N]``; raw_rgb: ``[N, 3]``.

    Returns:
        ``(sigma [N] >= 0, rgb [N, 3] in [0, 1])``.
    """
    return activate_density(raw_sigma), raw_rgb.float().sigmoid()


def activate_density(raw_sigma: Tensor) -> Tensor:
    """:func:`activate`'s density alone: ``trunc_exp(raw_sigma)`` in float32 (``[N]``)."""
    return trunc_exp(raw_sigma.float())


def bias_free_mlp(in_dim: int, hidden: int, n_hidden: int, out_dim: int) -> nn.Sequential:
    """``in_dim -> [hidden, ReLU] x n_hidden -> out_dim`` without biases, weights
    xavier-uniform (tiny-cuda-nn's fully fused MLP: no biases, that initialisation).

    >>> [m.weight.shape[0] for m in bias_free_mlp(4, 16, 2, 3) if isinstance(m, nn.Linear)]
    [16, 16, 3]
    """
    layers: list[nn.Module] = []
    d = in_dim
    for width in [hidden] * n_hidden + [out_dim]:
        lin = nn.Linear(d, width, bias=False)
        nn.init.xavier_uniform_(lin.weight)
        layers += [lin, nn.ReLU(inplace=True)]
        d = width
    return nn.Sequential(*layers[:-1])


def sh4_at_zero_direction() -> Tensor:
    """The 16 real spherical-harmonics features (degree 4) tiny-cuda-nn gives for the
    authors' zeroed view direction: they map ``d = (0 + 1) / 2`` back to ``2d − 1 = 0``,
    where only the constant ``Y_0^0 = 1 / (2√π)`` and the ``z²`` term of ``Y_2^0``,
    ``−√5 / (4√π)``, are non-zero.

    >>> [round(v, 6) for v in sh4_at_zero_direction().tolist() if v != 0]
    [0.282095, -0.315392]
    """
    sh = torch.zeros(16)
    sh[0] = 0.5 / math.sqrt(math.pi)
    sh[6] = -math.sqrt(5.0) / (4.0 * math.sqrt(math.pi))
    return sh


class NGPDecoder(nn.Module):
    """NGP decoder: ``f [N, F] -> density MLP -> (raw sigma, g [N, G]) -> colour MLP``.

    Supplementary Sec. 10 and the authors' tiny-cuda-nn networks: a density MLP with one
    hidden layer of 16 (1 density + 10 geometry outputs) and a colour MLP with two hidden
    layers of 64 on ``[SH(view direction), g]``, all bias-free. The view direction is
    zeroed (no view dependence), so its 16 SH features are the constant
    :func:`sh4_at_zero_direction`, the only constant input the colour MLP has.

    Args:
        in_dim: encoder feature size ``F``.
        density_hidden: hidden width of the density MLP (one hidden layer).
        geo_features: geometry features ``G`` passed to the colour MLP.
        colour_hidden, colour_layers: colour MLP width and number of hidden layers.
    """

    def __init__(self, in_dim: int, density_hidden: int = 16, geo_features: int = 10,
                 colour_hidden: int = 64, colour_layers: int = 2):
        super().__init__()
        self.density_net = bias_free_mlp(in_dim, density_hidden, 1, 1 + geo_features)
        self.colour_net = bias_free_mlp(16 + geo_features, colour_hidden, colour_layers, 3)
        self.register_buffer("direction_features", sh4_at_zero_direction(), persistent=False)

    def forward(self, feat: Tensor) -> tuple[Tensor, Tensor]:
        """``feat [N, F] -> (sigma [N], rgb [N, 3])``."""
        h = self.density_net(feat)
        sh = self.direction_features.to(h.dtype).expand(h.shape[0], -1)
        return activate(h[:, 0], self.colour_net(torch.cat([sh, h[:, 1:]], dim=-1)))

    def density(self, feat: Tensor) -> Tensor:
        """``feat [N, F] -> sigma [N]``: the density MLP alone, :meth:`forward`'s density
        to the bit without the colour MLP (26 → 64 → 64 → 3, the larger of the two)."""
        return activate_density(self.density_net(feat)[:, 0])
