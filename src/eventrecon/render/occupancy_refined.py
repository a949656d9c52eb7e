"""A two-level occupancy grid: a finer grid asked only where the coarse one is occupied.

The coarse level is the :class:`~eventrecon.render.occupancy.OccupancyGrid` itself
(``B`` bins × ``G³`` cells, its own updates, thresholds and dilation). The refinement
``refine = (r_s, r_t)`` splits each coarse cell into ``r_s³`` cells and each bin into
``r_t`` bins: a fine grid ``[r_t B, r_s G, r_s G, r_s G]`` whose cell ``c`` has the parent
``p(c) = (⌊b / r_t⌋, ⌊i / r_s⌋, ⌊j / r_s⌋, ⌊k / r_s⌋)``. With the coarse (dilated)
occupancy ``O`` upsampled to the fine cells as the *gate* ``O_{p(c)}``, a fine cell is

.. math::
    \\text{occupied}_c = O_{p(c)} \\wedge \\operatorname{dilate}\\big(
        O_{p(\\cdot)} \\wedge (D^f > τ \\,\\vee\\, \\text{unasked})\\big)_c ,

``D^f`` being the fine level's moving maximum (the coarse rule, at the fine cells), ``τ``
the coarse level's effective threshold and the dilation ``refine_dilation`` fine cells in
space and bins in time. So the mask never keeps more than the coarse grid's; it drops
the parts of an occupied coarse cell, or of its coarse dilation, that the finer cells see
empty. A moving subject that fills one coarse cell for a whole coarse bin fills only the
fine bins it passes through.

**Updates.** After the coarse update, the fine cells under a closed gate are forgotten
(marked unasked: when their gate opens again they count as occupied until asked anew, so
a value from an older field never empties a cell). Under an open gate the asked cells
want ``Σp`` asks, ``p`` being the coarse shares (``recheck`` above the threshold,
``fraction`` below); the unasked cells get ``min(n, max(budget − Σp, budget / 2))`` of
the ``refine_budget``, a random share of the ``n`` of them, and the asked ones the rest,
each with probability ``q·p`` (``q ≤ 1``). So the field is asked at most ``refine_budget``
times per update on average, and at least half the budget re-asks cells whenever they
want it. The decay of a cell above the threshold is ``γ^{1/(q·recheck)}`` per ask: while
``q`` stays the same it forgets at the coarse level's rate per update. While the gate
covers more than ``refine_below`` of the fine cells (the field is a fog, occupied at
either level) the fine level is not asked, and it is forgotten, so the mask is the gate
and no value older than the pause survives it. Random numbers come from the update's
generator after the coarse level's, so a resumed run updates as an uninterrupted one.

**Cost.** The field queries are bounded by the budget; the other passes of an update run
over all ``r_s³ r_t`` times the coarse grid's cells (8.4 M at ``[2, 4]`` over 32³×8, about
0.1 s on two CPU cores). The fine state is saved in checkpoints (about 42 MB at ``[2, 4]``);
a run resumed with ``refine`` switched on or off fails on the checkpoint's keys.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from eventrecon.errors import InputError
from eventrecon.render.occupancy import DensityFn, OccupancyGrid, dilate

__all__ = ["RefinedGrid", "build_grid", "config_pair"]


def config_pair(value: Any, key: str, low: int) -> tuple[int, int]:
    """Two integers ``>= low`` from a config value (a list or tuple), else one error."""
    ok = (isinstance(value, Sequence) and not isinstance(value, (str, bytes))
          and len(value) == 2 and all(isinstance(v, int) and not isinstance(v, bool)
                                      and v >= low for v in value))
    if not ok:
        raise InputError("config", f"render.occupancy.{key}",
                         f"[cells in space, bins in time], two integers >= {low}", value)
    return int(value[0]), int(value[1])


class RefinedGrid(OccupancyGrid):
    """An :class:`OccupancyGrid` whose mask is refined by a finer grid (module docstring).

    Args:
        lo, hi: ``[3]`` corners of the box.
        refine: ``(r_s, r_t)``: each coarse cell split ``r_s`` times along each spatial
            axis and each bin ``r_t`` times.
        refine_dilation: ``(s, b)`` of the fine level, in fine cells and fine bins.
        refine_budget: fine cells asked per update, at most (on average).
        refine_below: the fine level is asked only while the gate covers at most this
            share of its cells.
        **grid: the coarse level's :class:`OccupancyGrid` arguments.
    """

    def __init__(self, lo: Sequence[float], hi: Sequence[float],
                 refine: Sequence[int] = (2, 4), refine_dilation: Sequence[int] = (1, 0),
                 refine_budget: int = 65536, refine_below: float = 0.5,
                 **grid: Any) -> None:
        super().__init__(lo, hi, **grid)
        self.refine = config_pair(refine, "refine", 1)
        self.refine_dilation = config_pair(refine_dilation, "refine_dilation", 0)
        if isinstance(refine_budget, bool) or not isinstance(refine_budget, int) \
                or refine_budget < 1:
            raise InputError("config", "render.occupancy.refine_budget",
                             "an integer >= 1 (fine cells asked per update)", refine_budget)
        self.refine_budget = int(refine_budget)
        if isinstance(refine_below, bool) or not isinstance(refine_below, (int, float)) \
                or not 0 < refine_below <= 1:
            raise InputError("config", "render.occupancy.refine_below",
                             "a share in (0, 1] of the fine cells", refine_below)
        self.refine_below = float(refine_below)
        rs, rt = self.refine
        shape = (self.time_bins * rt, *(self.resolution * rs,) * 3)
        self.register_buffer("fine_density", torch.zeros(shape))
        self.register_buffer("fine_asked", torch.zeros(shape, dtype=torch.bool))
        self.register_buffer("fine_occ", torch.ones(shape, dtype=torch.bool),
                             persistent=False)

    def extra_repr(self) -> str:
        return (f"{super().extra_repr()}, refine={self.refine}, "
                f"refine_dilation={self.refine_dilation}, refine_budget={self.refine_budget}")

    @property
    def occupancy(self) -> Tensor:
        """``[r_t B, r_s G, r_s G, r_s G]`` bool: the refined mask the renderer reads."""
        return self.fine_occ

    def gate(self) -> Tensor:
        """``[r_t B, r_s G, r_s G, r_s G]`` bool: each fine cell's parent's (dilated)
        coarse occupancy."""
        rs, rt = self.refine
        b, g = self.time_bins, self.resolution
        up = self.occ[:, None, :, None, :, None, :, None]
        return up.expand(b, rt, g, rs, g, rs, g, rs).reshape(self.fine_occ.shape)

    def refresh(self) -> None:
        """The coarse occupancy, then the refined mask (module docstring)."""
        super().refresh()
        self._refresh_fine(self.gate())

    def _refresh_fine(self, gate: Tensor) -> None:
        """The refined mask from the fine state under ``gate`` (:meth:`gate`, current)."""
        own = (self.fine_density > self.effective_threshold()) | ~self.fine_asked
        self.fine_occ.copy_(dilate(gate & own, *self.refine_dilation) & gate)

    @torch.no_grad()
    def update(self, density: DensityFn, gen: torch.Generator) -> int:
        """The coarse level's update, then the fine cells under an open gate (module
        docstring); returns the number of cells asked at both levels."""
        asked = self._update_cells(density, gen)
        super().refresh()                        # the gate of this update
        gate4 = self.gate()
        per_parent = gate4.numel() // self.occ.numel()
        if int(self.occ.sum()) * per_parent > self.refine_below * gate4.numel():
            self.fine_asked.zero_()              # paused: forgotten, the mask is the gate
            self.fine_occ.copy_(gate4)
            return asked
        gate = gate4.view(-1)
        seen = self.fine_asked.view(-1)
        seen &= gate                             # forget the cells under a closed gate
        cand = gate.nonzero().squeeze(1)
        if cand.numel():
            chosen, decay = self._choose(cand, seen[cand], gen)
            cells = cand[chosen]
            if cells.numel():
                self.ask(cells, decay[chosen], self.fine_density, self.fine_asked, density,
                         gen)
                asked += int(cells.numel())
        self._refresh_fine(gate4)                # the coarse level is refreshed above
        return asked

    def _choose(self, cand: Tensor, seen: Tensor, gen: torch.Generator
                ) -> tuple[Tensor, Tensor]:
        """Which of the gated fine cells ``cand [n]`` (``seen [n]``: asked before) to ask,
        and each one's decay (module docstring). The asked ones want ``Σp`` asks
        (``p = recheck`` above the threshold, ``fraction`` below); the unasked get
        ``min(n_unasked, max(budget − Σp, budget / 2))`` of the budget, a random share of
        them, and the asked ones the rest, each with probability ``q·p``."""
        pick = torch.rand(cand.numel(), generator=gen, device=gen.device).to(cand.device)
        budget = float(self.refine_budget)
        above = seen & (self.fine_density.view(-1)[cand] > self.effective_threshold())
        p = torch.where(above, self.recheck, self.fraction) * seen
        n_fresh, want = (float(v) for v in torch.stack([(~seen).sum(), p.sum()]).tolist())
        take = min(n_fresh, max(budget - want, budget / 2))
        fresh = ~seen & (pick < take / max(n_fresh, 1.0))
        q = min(1.0, (budget - take) / max(want, 1.0))
        chosen = fresh | (pick < p * q)
        rate = self.decay ** (1.0 / (self.recheck * q)) if q > 0 else 0.0
        decay = torch.where(above, rate, self.decay)
        return chosen, decay


def build_grid(lo: Sequence[float], hi: Sequence[float], **cfg: Any) -> OccupancyGrid:
    """The renderer's grid from ``render.occupancy``: a :class:`RefinedGrid` where
    ``refine`` is set (not ``None``), an :class:`OccupancyGrid` otherwise (the
    ``refine_*`` keys are then ignored)."""
    refine = cfg.pop("refine", None)
    extra = {k: cfg.pop(k) for k in ("refine_dilation", "refine_budget", "refine_below")
             if k in cfg}
    if refine is None:
        return OccupancyGrid(lo, hi, **cfg)
    return RefinedGrid(lo, hi, refine=refine, **extra, **cfg)
