"""The Field interface shared by every representation backbone.

A field maps a space-time point to density and linear colour:

.. math:: F_\\Theta : (\\mathbf{x} \\in \\mathbb{R}^3, t \\in [0, 1]) \\mapsto
          (\\sigma \\ge 0, \\mathbf{c} \\in [0, 1]^3)

``x`` is in world units (the scene lies in the unit sphere; the clipping cylinder is
within ``[-1, 1]^3``), ``t`` is normalised to the training segment. The renderer, the
losses and the LightningModule use only this interface and never branch on the class.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor, nn


class Field(nn.Module):
    """Base class: subclasses implement :meth:`forward`.

    Optional hooks, all with neutral defaults:

    - :meth:`density_only` — the density alone, without the colour;
    - :meth:`param_groups` — optimiser groups with per-group learning rates;
    - :meth:`callbacks` — Lightning callbacks with the backbone's own schedule
      (frequency annealing, grid growth with optimiser rebuild, cylinder annealing);
    - :meth:`regularization` — an extra loss term (e.g. total variation), already weighted;
    - :meth:`set_scene_box` — the clipping cylinder's bounding box, for fields whose
      coordinates are normalised to it (the factorised backbones).
    """

    def forward(self, xyz: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        """Evaluate the field.

        Args:
            xyz: ``[N, 3]`` world positions.
            t: ``[N, 1]`` normalised time in [0, 1].

        Returns:
            ``(sigma [N], rgb [N, 3])``: non-negative density and linear colour in [0, 1].
        """
        raise NotImplementedError

    def density_only(self, xyz: Tensor, t: Tensor) -> Tensor:
        """``σ [N]`` alone, the first output of :meth:`forward` (what the occupancy grid
        asks). The default runs the whole forward pass; a field whose colour costs work
        its density does not need overrides it with the same values."""
        return self(xyz, t)[0]

    def param_groups(self, lr: float) -> list[dict[str, Any]]:
        """Optimiser parameter groups; default: one group at ``lr``."""
        return [{"params": [p for p in self.parameters() if p.requires_grad], "lr": lr}]

    def callbacks(self) -> list[Any]:
        """Lightning callbacks implementing this backbone's schedule; default none."""
        return []

    def regularization(self) -> Tensor | None:
        """Extra (weighted) loss on the parameters, or ``None``."""
        return None

    def set_scene_box(self, lo: Sequence[float], hi: Sequence[float]) -> None:
        """The world box ``[lo, hi]`` (``[3]`` each) the scene lives in; default: unused."""
        return None


def trunc_exp(x: Tensor) -> Tensor:
    """``exp(x)`` with the gradient of ``exp(clamp(x, max=15))`` (Instant-NGP's density).

    Forward is ``exp(x)`` clamped at ``exp(15)`` to stay finite in float32.
    """
    return _TruncExp.apply(x)


class _TruncExp(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, x: Tensor) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(x)
        return torch.exp(x.clamp(max=15.0))

    @staticmethod
    def backward(ctx: Any, g: Tensor) -> Tensor:  # type: ignore[override]
        (x,) = ctx.saved_tensors
        return g * torch.exp(x.clamp(min=-15.0, max=15.0))
