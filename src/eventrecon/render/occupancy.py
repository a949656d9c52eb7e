"""A time-aware occupancy grid: which space-time cells can hold density.

The clipping cylinder's bounding box is divided into ``G³`` cells and the segment's
normalised time into ``B`` bins. Cell ``(b, i, j, k)`` holds an upper estimate of the
field's density over its volume and time bin,

.. math:: D_{b,ijk} \\leftarrow \\max\\big(\\gamma\\, D_{b,ijk},\\ \\sigma(\\mathbf{x}, t)\\big),
          \\quad \\mathbf{x} \\sim U(\\text{cell}),\\ t \\sim U(\\text{bin}),

an exponential moving maximum of the field's own density at jittered points (instant-NGP's
rule, decay ``γ``), with ``σ = 0`` outside the cylinder. A cell starts *unasked*: it
counts as occupied (nothing is skipped before the field has been asked about it) until
its first update, which sets ``D`` to the sampled density. A cell is *occupied* when it
or one of its neighbours has ``D > τ``: with ``dilation = (s, b)``, the
``(2s + 1)³`` cells around it in space, in its own and the ``b`` bins on either side in
time (default ``(1, 1)``: 3×3×3 cells in three bins). The effective threshold is

.. math:: τ = \\min\\big(\\text{threshold},\\ \\overline{D}\\big),

:math:`\\overline{D}` being the mean over the asked cells (nerfacc's rule): while the
field is still a thin fog everywhere, its denser half stays occupied instead of the whole
grid going empty, which would lock the field out of space it has not learnt yet.
The dilation is there because one jittered point per cell and update can miss the
peak of a feature that spans a few cells, and the dilation keeps its surroundings. In
time it is costly for a moving subject: one bin on either side triples the time span over
which the subject's path counts as occupied (``dilation = (1, 0)`` with more bins keeps
less; ``docs/results/history.md``, "Session 49"). The
renderer evaluates the field only at samples in occupied cells
(:meth:`OccupancyGrid.occupied`); a sample whose density is below the threshold adds at
most ``1 − exp(−threshold · δ)`` of opacity over a step ``δ``.

Updates (:class:`OccupancyUpdate`, a Lightning callback, every ``every`` steps) ask every
unasked cell, a random share ``recheck`` of the cells above the threshold and a random
share ``fraction`` of the empty ones, with a generator seeded by the step, so a resumed
run updates exactly as an uninterrupted one; the grid is a buffer of the renderer and is
saved in checkpoints. A cell above the threshold is asked once in ``1/recheck`` updates
on average, so its decay per ask is :math:`γ^{1/\text{recheck}}`: the moving maximum
forgets at the rate ``γ`` per update whatever the share. Only asked cells change, and an
asked cell keeps at least the density just sampled, so asking fewer cells can leave a
cell occupied longer but never empties one the field fills. While the field is a fog
(early training: nearly every cell above the threshold) this makes an update about
``1/recheck`` times cheaper (``recheck = 1``: every such cell at every update).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from typing import Any

import lightning.pytorch as pl
import torch
from torch import Tensor, nn

from eventrecon.common.errors import InputError

__all__ = ["OccupancyGrid", "OccupancyUpdate", "dilate"]

log = logging.getLogger(__name__)

#: ``σ(x [N, 3], t [N, 1]) -> [N]`` density of the field with the clipping mask applied.
DensityFn = Callable[[Tensor, Tensor], Tensor]


def dilate(core: Tensor, s: int, b: int) -> Tensor:
    """``[B, G, G, G]`` bool: ``core`` widened by ``s`` cells on either side along each
    spatial axis (a ``(2s + 1)³`` cube) and ``b`` bins on either side in time (at most
    ``B − 1``), the OR over the neighbourhood, one axis at a time."""
    out = core
    for axis, reach in ((1, s), (2, s), (3, s), (0, min(b, core.shape[0] - 1))):
        n = out.shape[axis]
        for _ in range(min(reach, n - 1)):
            grown = out.clone()
            grown.narrow(axis, 1, n - 1).logical_or_(out.narrow(axis, 0, n - 1))
            grown.narrow(axis, 0, n - 1).logical_or_(out.narrow(axis, 1, n - 1))
            out = grown
    return out


class OccupancyGrid(nn.Module):
    """``[B, G, G, G]`` space-time occupancy over a box (maths in the module docstring).

    Args:
        lo, hi: ``[3]`` corners of the box (the clipping cylinder's bounding box).
        resolution: cells ``G`` per spatial axis.
        time_bins: bins ``B`` of the segment's normalised time ``[0, 1]``.
        threshold: density above which a cell is occupied.
        decay: ``γ`` of the moving maximum.
        every: steps between updates; fraction: share of the empty cells re-asked.
        recheck: share of the cells above the threshold re-asked at each update.
        start_step: no sample is skipped before this step (the grid is updated).
        chunk: points per field call during an update.
        dilation: ``(s, b)``: cells in space and bins in time by which occupancy is
            widened on either side (``(0, 0)``: none).

    >>> g = OccupancyGrid([-1, -1, -1], [1, 1, 1], resolution=2, time_bins=1, threshold=0.5)
    >>> bool(g.occupied(torch.zeros(1, 3), torch.zeros(1, 1)).item())  # unasked: occupied
    True
    >>> g.update(lambda x, t: (x[:, 0] > 0).float(), torch.Generator().manual_seed(0))
    8
    >>> g.occupied(torch.tensor([[-0.5, 0, 0], [0.5, 0, 0]]), torch.zeros(2, 1)).tolist()
    [True, True]
    >>> g4 = OccupancyGrid([-1, -1, -1], [1, 1, 1], resolution=4, time_bins=1, threshold=0.5)
    >>> g4.update(lambda x, t: (x[:, 0] > 0.5).float(), torch.Generator().manual_seed(0))
    64
    >>> g4.occupied(torch.tensor([[-0.9, 0, 0], [0.1, 0, 0], [0.9, 0, 0]]),
    ...             torch.zeros(3, 1)).tolist()  # the dilation keeps the cell next to x > 0.5
    [False, True, True]
    """

    def __init__(self, lo: Sequence[float], hi: Sequence[float], resolution: int = 32,
                 time_bins: int = 8, threshold: float = 0.01, decay: float = 0.95,
                 every: int = 16, fraction: float = 0.25, start_step: int = 0,
                 chunk: int = 65536, recheck: float = 0.25,
                 dilation: Sequence[int] = (1, 1)) -> None:
        super().__init__()
        if resolution < 1 or time_bins < 1 or threshold < 0 or not 0 < decay <= 1 \
                or every < 1 or not 0 <= fraction <= 1 or not 0 < recheck <= 1:
            raise InputError("config", "render.occupancy",
                             "resolution >= 1, time_bins >= 1, threshold >= 0, decay in (0, 1], "
                             "every >= 1, fraction in [0, 1], recheck in (0, 1]",
                             (resolution, time_bins, threshold, decay, every, fraction,
                              recheck))
        dil = (list(dilation) if isinstance(dilation, Sequence)
               and not isinstance(dilation, (str, bytes)) else [])
        if len(dil) != 2 or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 0
                                    for v in dil):
            raise InputError("config", "render.occupancy.dilation",
                             "[cells in space, bins in time], two integers >= 0", dilation)
        self.dilation = (int(dil[0]), int(dil[1]))
        self.resolution, self.time_bins = int(resolution), int(time_bins)
        self.threshold, self.decay = float(threshold), float(decay)
        self.every, self.fraction, self.recheck = int(every), float(fraction), float(recheck)
        self.start_step, self.chunk = int(start_step), int(chunk)
        self.active = True  # skipping on (the renderer sets it from start_step)
        shape = (self.time_bins, *(self.resolution,) * 3)
        self.register_buffer("density", torch.zeros(shape))
        self.register_buffer("asked", torch.zeros(shape, dtype=torch.bool))
        self.register_buffer("occ", torch.ones(shape, dtype=torch.bool), persistent=False)
        self.register_buffer("lo", torch.as_tensor(lo, dtype=torch.float32).reshape(3))
        self.register_buffer("hi", torch.as_tensor(hi, dtype=torch.float32).reshape(3))

    def extra_repr(self) -> str:
        return (f"resolution={self.resolution}, time_bins={self.time_bins}, "
                f"threshold={self.threshold}, decay={self.decay}, every={self.every}, "
                f"dilation={self.dilation}")

    @property
    def occupancy(self) -> Tensor:
        """``[B, G, G, G]`` bool: occupied (dilated) or not yet asked."""
        return self.occ

    def effective_threshold(self) -> Tensor:
        """Scalar ``τ = min(threshold, mean density of the asked cells)`` (``threshold``
        while no cell has been asked)."""
        thr = torch.tensor(self.threshold, device=self.density.device)
        n = self.asked.sum()
        mean = (self.density * self.asked).sum() / n.clamp_min(1)
        return torch.where(n > 0, torch.minimum(thr, mean), thr)  # no host sync

    def _dense(self) -> Tensor:
        """``[B, G, G, G]`` bool: above the effective threshold, or unasked (undilated)."""
        return (self.density > self.effective_threshold()) | ~self.asked

    def refresh(self) -> None:
        """Recompute :attr:`occupancy` from the densities: above the effective threshold or
        unasked, dilated by :attr:`dilation` (cells in space, bins in time)."""
        self.occ.copy_(dilate(self._dense(), *self.dilation))

    def _load_from_state_dict(self, *args: Any, **kwargs: Any) -> None:  # type: ignore[override]
        super()._load_from_state_dict(*args, **kwargs)
        self.refresh()

    def cell_index(self, x: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        """Flat cell index of points ``x [..., 3]`` at times ``t [..., 1]``, and whether the
        point lies in the box (``[...]`` each)."""
        u = (x - self.lo.to(x)) / (self.hi - self.lo).to(x)
        inside = ((u >= 0) & (u <= 1)).all(-1)
        b, g = self.occupancy.shape[:2]          # the cells of the mask the renderer reads
        ijk = (u * g).long().clamp(0, g - 1)
        tb = (t[..., 0] * b).long().clamp(0, b - 1)
        return ((tb * g + ijk[..., 0]) * g + ijk[..., 1]) * g + ijk[..., 2], inside

    def occupied(self, x: Tensor, t: Tensor) -> Tensor:
        """``[...]`` bool: whether the field must be evaluated at ``x [..., 3]``, ``t [..., 1]``
        (points outside the box are never occupied: they are outside the cylinder)."""
        idx, inside = self.cell_index(x, t)
        return self.occupancy.reshape(-1)[idx] & inside

    def occupied_rays(self, o: Tensor, d: Tensor, t: Tensor, s: Tensor) -> Tensor:
        """``[n, K]`` bool: :meth:`occupied` at the samples ``o + s d`` of rays ``o, d
        [n, 3]`` at times ``t [n, 1]``, ``s [n, K]``."""
        n, k = s.shape
        return self.occupied(o[:, None, :] + s[..., None] * d[:, None, :],
                             t[:, None, :].expand(n, k, 1))

    @torch.no_grad()
    def update(self, density: DensityFn, gen: torch.Generator) -> int:
        """Ask the field about the unasked cells and random shares ``recheck`` of the
        cells above the threshold and ``fraction`` of the empty ones (one jittered point
        each); returns the number of cells asked."""
        asked = self._update_cells(density, gen)
        self.refresh()
        return asked

    def _update_cells(self, density: DensityFn, gen: torch.Generator) -> int:
        """:meth:`update` without the :meth:`refresh`."""
        flat_occ = self._dense().reshape(-1)
        n = flat_occ.numel()
        pick = torch.rand(n, generator=gen, device=gen.device).to(flat_occ.device)
        unasked = ~self.asked.view(-1)
        chosen = torch.where(flat_occ, pick < self.recheck, pick < self.fraction) | unasked
        cells = chosen.nonzero().squeeze(1)
        if cells.numel():
            decay = torch.where(flat_occ[cells], self.decay ** (1.0 / self.recheck),
                                self.decay)
            self.ask(cells, decay, self.density, self.asked, density, gen)
        return int(cells.numel())

    def ask(self, cells: Tensor, decay: Tensor, values: Tensor, asked: Tensor,
            density: DensityFn, gen: torch.Generator) -> None:
        """The moving maximum of ``values [B', G', G', G']`` (``asked`` alike, bool) at its
        flat ``cells [n]``, from one jittered point each over the box and the time bin:
        ``D ← max(decay·D, σ)`` where asked before, ``D ← σ`` otherwise (``decay [n]``)."""
        b, g = values.shape[:2]
        jitter = torch.rand(cells.numel(), 4, generator=gen, device=gen.device).to(cells.device)
        k = cells % g
        j = (cells // g) % g
        i = (cells // (g * g)) % g
        tb = cells // (g * g * g)
        u = (torch.stack([i, j, k], -1).float() + jitter[:, :3]) / g
        x = self.lo + u * (self.hi - self.lo)
        t = ((tb.float() + jitter[:, 3]) / b)[:, None]
        new = torch.cat([density(x[a:a + self.chunk], t[a:a + self.chunk]).float()
                         for a in range(0, cells.numel(), self.chunk)])
        flat, seen = values.view(-1), asked.view(-1)
        old = flat[cells]
        flat[cells] = torch.where(seen[cells], torch.maximum(decay * old, new), new)
        seen[cells] = True

    def occupied_fraction(self) -> float:
        """Share of the cells that are occupied (or unasked)."""
        return float(self.occupancy.float().mean())


class OccupancyUpdate(pl.Callback):
    """Updates the renderer's :class:`OccupancyGrid` every ``grid.every`` steps from the
    module's field, and switches skipping on from ``grid.start_step``.

    The update's random cells come from a generator seeded by ``(seed, step)``.
    """

    def __init__(self, seed: int = 0) -> None:
        super().__init__()
        self.seed = int(seed)

    def on_train_batch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule,
                             batch: Any, batch_idx: int) -> None:
        renderer = pl_module.renderer
        grid: OccupancyGrid | None = getattr(renderer, "occupancy", None)
        if grid is None:
            return
        step = int(trainer.global_step)
        grid.active = step >= grid.start_step
        if step % grid.every:
            return
        gen = torch.Generator().manual_seed(self.seed * 1_000_003 + step)
        was_training = pl_module.field.training
        pl_module.field.eval()
        asked = grid.update(lambda x, t: renderer.masked_density(pl_module.field, x, t), gen)
        pl_module.field.train(was_training)
        if step % max(grid.every * 16, 1) == 0:
            log.debug("step %d: occupancy grid asked %d cells, %.1f%% occupied", step, asked,
                      100 * grid.occupied_fraction())
        if math.isfinite(grid.occupied_fraction()):
            pl_module.log("train/occupied", grid.occupied_fraction(), on_step=True,
                          on_epoch=False)
