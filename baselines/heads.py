"""Density / colour decoding shared by every baseline backbone.

All backbones end in the same two activations (:func:`activate`): density
``sigma = trunc_exp(raw_sigma + shift)`` (or ``softplus``) and colour
``rgb = sigmoid(raw_rgb)`` (linear radiance in [0, 1]). Two decoders produce the raw
values from encoder features:

- :class:`GeoColourMLP` (NGP): density MLP -> 1 raw density + G geometry features,
  colour MLP on the geometry features -> 3.
- :class:`FactorDecoder` (TensoRF-CP, HexPlane): raw density is the plain sum of the
  density components (a CP/rank sum), colour is a linear basis (TensoRF's "basis
  matrix") or a small MLP on the appearance components.
"""

from __future__ import annotations

from typing import Literal

import torch.nn.functional as F
from torch import Tensor, nn

from eventrecon.errors import InputError
from eventrecon.fields.base import trunc_exp

DensityActivation = Literal["trunc_exp", "softplus"]


def mlp(in_dim: int, hidden: int, n_hidden: int, out_dim: int) -> nn.Sequential:
    """``in_dim -> [hidden, ReLU] x n_hidden -> out_dim`` (no output activation).

    >>> [m.out_features for m in mlp(4, 16, 2, 3) if isinstance(m, nn.Linear)]
    [16, 16, 3]
    """
    layers: list[nn.Module] = []
    d = in_dim
    for _ in range(n_hidden):
        layers += [nn.Linear(d, hidden), nn.ReLU(inplace=True)]
        d = hidden
    layers.append(nn.Linear(d, out_dim))
    return nn.Sequential(*layers)


def activate(raw_sigma: Tensor, raw_rgb: Tensor, shift: float = 0.0,
             density: DensityActivation = "trunc_exp") -> tuple[Tensor, Tensor]:
    """The one density/colour activation of the zoo.

    ``sigma = trunc_exp(raw_sigma + shift)`` (or ``softplus``), ``rgb = sigmoid(raw_rgb)``;
    outputs are float32 even under autocast.

    Args:
        raw_sigma: ``[N]``; raw_rgb: ``[N, 3]``.

    Returns:
        ``(sigma [N] >= 0, rgb [N, 3] in [0, 1])``.
    """
    x = raw_sigma.float() + shift
    sigma = trunc_exp(x) if density == "trunc_exp" else F.softplus(x)
    return sigma, raw_rgb.float().sigmoid()


def _check_activation(density: str) -> None:
    if density not in ("trunc_exp", "softplus"):
        raise InputError("conf/model", "density_activation", "trunc_exp or softplus", density)


class GeoColourMLP(nn.Module):
    """NGP decoder: ``f [N, F] -> density MLP -> (raw sigma, g [N, G]) -> colour MLP``.

    Supplementary Sec. 10: density network of one hidden layer of 16 with 1 density and
    10 geometry outputs; colour network of 2 hidden layers of 64 -> 3.

    Args:
        in_dim: encoder feature size ``F``.
        density_hidden: hidden width of the density MLP (one hidden layer).
        geo_features: geometry features ``G`` passed to the colour MLP.
        colour_hidden, colour_layers: colour MLP width and number of hidden layers.
        density_activation: ``trunc_exp`` (default) or ``softplus``.
    """

    def __init__(self, in_dim: int, density_hidden: int = 16, geo_features: int = 10,
                 colour_hidden: int = 64, colour_layers: int = 2,
                 density_activation: DensityActivation = "trunc_exp"):
        super().__init__()
        _check_activation(density_activation)
        self.density_net = mlp(in_dim, density_hidden, 1, 1 + geo_features)
        self.colour_net = mlp(geo_features, colour_hidden, colour_layers, 3)
        self.density_activation = density_activation

    def forward(self, feat: Tensor) -> tuple[Tensor, Tensor]:
        """``feat [N, F] -> (sigma [N], rgb [N, 3])``."""
        h = self.density_net(feat)
        return activate(h[:, 0], self.colour_net(h[:, 1:]), density=self.density_activation)


class FactorDecoder(nn.Module):
    """Decoder of factorised backbones.

    ``raw_sigma = sum_r d_r`` (the rank sum of the density components) and
    ``raw_rgb = B a`` (``decoder="linear"``, TensoRF's basis matrix, ``B [3, R_a]``) or
    ``raw_rgb = MLP(a)`` (``decoder="mlp"``, one hidden layer of ``hidden``).

    Args:
        app_dim: number of appearance components ``R_a``.
        decoder: ``"linear"`` or ``"mlp"``.
        hidden: MLP width (``decoder="mlp"``).
        density_shift: constant added before the density activation.
        density_activation: ``trunc_exp`` (default) or ``softplus``.
    """

    def __init__(self, app_dim: int, decoder: Literal["linear", "mlp"] = "linear",
                 hidden: int = 64, density_shift: float = 0.0,
                 density_activation: DensityActivation = "trunc_exp"):
        super().__init__()
        _check_activation(density_activation)
        if decoder == "linear":
            self.colour_net: nn.Module = nn.Linear(app_dim, 3)
        elif decoder == "mlp":
            self.colour_net = mlp(app_dim, hidden, 1, 3)
        else:
            raise InputError("conf/model", "decoder", "linear or mlp", decoder)
        self.density_shift = density_shift
        self.density_activation = density_activation

    def forward(self, density_feat: Tensor, app_feat: Tensor) -> tuple[Tensor, Tensor]:
        """Channel-first ``density_feat [R_d, N], app_feat [R_a, N] -> (sigma [N], rgb [N, 3])``."""
        return activate(density_feat.sum(0), self.colour_net(app_feat.t()), self.density_shift,
                        self.density_activation)
