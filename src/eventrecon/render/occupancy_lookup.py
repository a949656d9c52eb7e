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
gather). In PyTorch that is about twenty passes over ``[n, K, 3]`` tensors: 4.7 ms for
one chunk of an evaluation image (8192 rays × 32 samples, 2 threads), two per chunk,
~10 % of a trained field's 346×260 image (docs/results/history.md, "Session 51"). Here
the points are formed ray by ray and never stored: the cells of a ray's samples in one
loop that LLVM vectorises across the samples (no branch, no gather), then the gather.

The floating-point operations are PyTorch's, in the same order and dtype (the product
``s d`` rounded, then the sum; no fused multiply-add), so every sample gets the same cell
and the mask is the same (``tests/test_occupancy.py``). Where PyTorch's conversion to an
integer is undefined (a NaN or infinite time, or ``|B t| ≥ 2^63``), x86 gives the most
negative integer, which the clamp turns into bin 0; so does this loop. A sample with a
NaN coordinate is outside.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from eventrecon.sim.jit import AVAILABLE, njit_borrowing

__all__ = ["lookup_rays", "supported"]

#: ``float → int64`` is defined on ``[−2^63, 2^63)``.
_TWO63 = 2.0 ** 63


@njit_borrowing
def _cells(o: Any, d: Any, t: Any, s: Any, lo: Any, span: Any, scale: Any, tscale: Any,
           g: int, b: int, cell: Any) -> None:
    """``cell [n, K]``: the flat cell of sample ``s[r, j]`` of ray ``r``, ``-1`` outside
    the box (module docstring). ``o, d [n, 3]``, ``s [n, K]``, ``lo``, ``span``,
    ``scale = [G]`` in one dtype; ``t [n]`` and ``tscale = [B]`` in another."""
    gs, bs = scale[0], tscale[0]
    zero, tzero = scale[0] * 0, tscale[0] * 0
    lo0, lo1, lo2, sp0, sp1, sp2 = lo[0], lo[1], lo[2], span[0], span[1], span[2]
    for r in range(s.shape[0]):
        o0, o1, o2, d0, d1, d2 = o[r, 0], o[r, 1], o[r, 2], d[r, 0], d[r, 1], d[r, 2]
        v = t[r] * bs
        defined = (v >= -_TWO63) & (v < _TWO63)   # else (NaN, ±inf): x86's INT64_MIN, bin 0
        tb = min(max(np.int64(v if defined else tzero), 0), b - 1)
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
            cr[m] = ((tb * g + i) * g + j) * g + k if inside else -1


@njit_borrowing
def _gather(cell: Any, occ: Any, out: Any) -> None:
    """``out[m] = occ[cell[m]]`` (flat), ``False`` where ``cell[m] < 0``."""
    for m in range(cell.shape[0]):
        c = cell[m]
        out[m] = occ[max(c, 0)] & (c >= 0)


def supported(o: Tensor, d: Tensor, t: Tensor, s: Tensor, occ: Tensor) -> bool:
    """Whether :func:`lookup_rays` serves these inputs: numba; everything on the CPU;
    ``o, d [n, 3]`` and ``s [n, K]`` of one dtype, float32 or float64; ``t [n, 1]``
    float32 or float64."""
    tensors = (o, d, t, s, occ)
    return (AVAILABLE and all(x.device.type == "cpu" for x in tensors)
            and o.dtype in (torch.float32, torch.float64) and d.dtype == o.dtype
            and s.dtype == o.dtype and t.dtype in (torch.float32, torch.float64)
            and s.dim() == 2 and o.shape == d.shape == (s.shape[0], 3)
            and t.shape == (s.shape[0], 1))


def lookup_rays(o: Tensor, d: Tensor, t: Tensor, s: Tensor, lo: Tensor, hi: Tensor,
                occ: Tensor) -> Tensor | None:
    """``[n, K]`` bool: sample ``o + s d`` of each ray at its time ``t [n, 1]`` inside the
    box ``[lo, hi]`` and in an occupied cell of ``occ [B, G, G, G]``; ``None`` where not
    :func:`supported` (the caller then takes PyTorch's path)."""
    if not supported(o, d, t, s, occ):
        return None
    n, k = s.shape
    dtype, np_dtype = o.dtype, o.detach().numpy().dtype
    cell = np.empty((n, k), np.int64)
    b, g = occ.shape[0], occ.shape[1]
    tt = t.detach().reshape(-1).contiguous()
    _cells(o.detach().contiguous().numpy(), d.detach().contiguous().numpy(), tt.numpy(),
           s.detach().contiguous().numpy(), lo.to(dtype).numpy(), (hi - lo).to(dtype).numpy(),
           np.array([g], np_dtype), np.array([b], tt.numpy().dtype), g, b, cell)
    out = torch.empty(n, k, dtype=torch.bool)
    _gather(cell.reshape(-1), occ.contiguous().reshape(-1).numpy(), out.numpy().reshape(-1))
    return out
