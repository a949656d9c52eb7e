"""The occupancy grid's lookup along rays, in one compiled pass on the CPU.

For rays ``o, d [n, 3]`` at times ``t [n]`` with samples ``s [n, K]``, a grid
``occ [B, G, G, G]`` (bool) over the box ``[lo, hi]``, the renderer asks

.. math::
    x = o + s\\,d,\\quad u = (x - lo) / (hi - lo),\\quad
    \\text{inside} = \\textstyle\\bigwedge_a (0 \\le u_a \\le 1),

    (i, j, k) = \\mathrm{clamp}(\\lfloor G u \\rfloor, 0, G - 1),\\quad
    b = \\mathrm{clamp}(\\lfloor B t \\rfloor, 0, B - 1),\\quad
    \\text{occupied} = \\text{inside} \\wedge occ[b, i, j, k]

(:meth:`~eventrecon.render.occupancy.OccupancyGrid.cell_index` on the points, then a
gather). In PyTorch that is about twenty passes over ``[n, K, 3]`` tensors: 12.4 ms for
one chunk of an evaluation image (8192 rays × 32 samples, 2 threads), two per chunk,
~11 % of a trained field's 346×260 image (docs/results/history.md, "Session 51"). Here
the points are formed ray by ray and never stored: the cells of a ray's samples in one
loop that LLVM vectorises across the samples (no branch, no gather), then the gather
(0.8 ms for that chunk).

The floating-point operations are PyTorch's, in the same order and the points' dtype
(the product ``s d`` rounded, then the sum, no fused multiply-add; ``u G`` rounded before
it is truncated), so every sample gets the same cell and the mask is the same
(``tests/test_occupancy_lookup.py``, with samples within a few ulps of every cell
boundary). The time bin is PyTorch's own (``⌊B t⌋`` clamped, computed per ray), so even
an undefined conversion (a NaN or infinite time) gives the bin PyTorch gives on that
platform. A sample with a NaN coordinate is outside.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from eventrecon.render.compiled import AVAILABLE, compiled

__all__ = ["AVAILABLE", "lookup_rays", "supported"]


@compiled
def _cells(o: Any, d: Any, tb: Any, s: Any, lo: Any, span: Any, scale: Any, g: int,
           cell: Any) -> None:
    """``cell [n, K]``: the flat cell of sample ``s[r, j]`` of ray ``r``, ``-1`` outside
    the box (module docstring). ``o, d [n, 3]``, ``s [n, K]``, ``lo``, ``span``,
    ``scale = [G]`` in one dtype; ``tb [n]`` int64, each ray's time bin."""
    gs = scale[0]
    zero = gs - gs              # 0 in the points' dtype: with a literal 0, numba would
    lo0, lo1, lo2 = lo[0], lo[1], lo[2]          # multiply u·G in float64
    sp0, sp1, sp2 = span[0], span[1], span[2]
    for r in range(s.shape[0]):
        o0, o1, o2, d0, d1, d2 = o[r, 0], o[r, 1], o[r, 2], d[r, 0], d[r, 1], d[r, 2]
        first = tb[r] * g
        sr, cr = s[r], cell[r]
        for m in range(sr.shape[0]):
            u0 = ((o0 + sr[m] * d0) - lo0) / sp0
            u1 = ((o1 + sr[m] * d1) - lo1) / sp1
            u2 = ((o2 + sr[m] * d2) - lo2) / sp2
            inside = (((u0 >= 0) & (u0 <= 1)) & ((u1 >= 0) & (u1 <= 1))
                      & ((u2 >= 0) & (u2 <= 1)))
            # outside (NaN included) the cell does not matter: cast 0, never a NaN
            i = min(np.int64((u0 if inside else zero) * gs), g - 1)
            j = min(np.int64((u1 if inside else zero) * gs), g - 1)
            k = min(np.int64((u2 if inside else zero) * gs), g - 1)
            cr[m] = ((first + i) * g + j) * g + k if inside else -1


@compiled
def _gather(cell: Any, occ: Any, out: Any) -> None:
    """``out[m] = occ[cell[m]]`` (flat), ``False`` where ``cell[m] < 0``."""
    for m in range(cell.shape[0]):
        c = cell[m]
        out[m] = occ[max(c, 0)] & (c >= 0)


def supported(o: Tensor, d: Tensor, t: Tensor, s: Tensor, lo: Tensor, hi: Tensor,
              occ: Tensor) -> bool:
    """Whether :func:`lookup_rays` serves these inputs: numba; everything on the CPU;
    ``o, d [n, 3]``, ``s [n, K]`` of one dtype, float32 or float64; ``t [n, 1]`` float32
    or float64; ``lo, hi [3]``; ``occ [B, G, G, G]`` bool (the loops check no bounds)."""
    tensors = (o, d, t, s, lo, hi, occ)
    return (AVAILABLE and all(x.device.type == "cpu" for x in tensors)
            and o.dtype in (torch.float32, torch.float64) and d.dtype == o.dtype
            and s.dtype == o.dtype and t.dtype in (torch.float32, torch.float64)
            and s.dim() == 2 and o.shape == d.shape == (s.shape[0], 3)
            and t.shape == (s.shape[0], 1) and lo.shape == hi.shape == (3,)
            and occ.dtype == torch.bool and occ.dim() == 4
            and occ.shape[1] == occ.shape[2] == occ.shape[3])


def lookup_rays(o: Tensor, d: Tensor, t: Tensor, s: Tensor, lo: Tensor, hi: Tensor,
                occ: Tensor) -> Tensor | None:
    """``[n, K]`` bool: sample ``o + s d`` of each ray at its time ``t [n, 1]`` inside the
    box ``[lo, hi]`` and in an occupied cell of ``occ [B, G, G, G]``; ``None`` where not
    :func:`supported` (the caller then takes PyTorch's path)."""
    if not supported(o, d, t, s, lo, hi, occ):
        return None
    n, k = s.shape
    dtype, np_dtype = o.dtype, o.detach().numpy().dtype
    b, g = occ.shape[0], occ.shape[1]
    tb = (t.detach()[:, 0] * b).long().clamp(0, b - 1).contiguous()   # cell_index's bins
    cell = np.empty((n, k), np.int64)
    _cells(o.detach().contiguous().numpy(), d.detach().contiguous().numpy(), tb.numpy(),
           s.detach().contiguous().numpy(), lo.to(dtype).numpy(), (hi - lo).to(dtype).numpy(),
           np.array([g], np_dtype), g, cell)
    out = torch.empty(n, k, dtype=torch.bool)
    _gather(cell.reshape(-1), occ.contiguous().reshape(-1).numpy(), out.numpy().reshape(-1))
    return out
