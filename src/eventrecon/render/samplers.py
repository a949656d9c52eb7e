"""Sample placement along rays: stratified, importance (inverse CDF), interval edges.

Every sampler works on a ray parameter interval ``[near, far]`` per ray and returns
distances ``s [N, K]`` sorted along each ray. The quadrature used by the renderer
assigns each sample the cell between the midpoints to its neighbours
(:func:`interval_edges`), so the cells tile ``[near, far]`` exactly; the same edges are
the histogram bins of the importance sampler.

Randomness only through an optional ``torch.Generator`` (on the rays' device).
"""

from __future__ import annotations

import torch
from torch import Tensor

from eventrecon.errors import InputError

__all__ = ["stratified", "sample_pdf", "interval_edges"]


def uniform(shape: tuple[int, ...], gen: torch.Generator | None, like: Tensor) -> Tensor:
    """``U[0, 1)`` draws of ``shape`` with ``like``'s dtype and device.

    The draws are made on the generator's own device and then moved, so a CPU generator
    (the training step's ``(seed, step)`` generator) works for rays on a GPU and the
    numbers do not depend on where the rays live.
    """
    if gen is None:
        return torch.rand(shape, device=like.device, dtype=like.dtype)
    u = torch.rand(shape, generator=gen, device=gen.device, dtype=like.dtype)
    return u.to(like.device)


def stratified(
    near: Tensor, far: Tensor, n: int, perturb: bool, gen: torch.Generator | None = None,
    copies: int = 1,
) -> Tensor:
    """One sample in each of ``n`` equal bins of ``[near, far]``.

    .. math:: s_i = \\text{near} + (\\text{far} - \\text{near})\\,\\frac{i + u_i}{n},
              \\quad u_i \\sim U[0, 1)\\ \\text{if perturb else}\\ u_i = 1/2

    Args:
        near, far: ``[N]`` interval ends (``far ≥ near``).
        n: samples per ray.
        perturb: jitter within each bin (training) or take bin centres (evaluation).
        gen: optional generator for the jitter.
        copies: the ``N`` rays are ``copies`` stacked blocks of the same ``N / copies``
            rays (one ray rendered at several times); every block gets the same jitter
            ``u``, so a copy's samples are its first block's (the authors' code draws the
            coarse depths once per ray for its ``t0``, ``t1`` and ``t_ref`` renders).

    Returns:
        ``[N, n]`` sorted distances.

    >>> stratified(torch.tensor([0.0]), torch.tensor([1.0]), 4, perturb=False)
    tensor([[0.1250, 0.3750, 0.6250, 0.8750]])
    >>> gen = torch.Generator().manual_seed(0)
    >>> s = stratified(torch.zeros(4), torch.ones(4), 3, True, gen, copies=2)
    >>> bool((s[:2] == s[2:]).all())
    True
    """
    if copies < 1 or near.shape[0] % copies:
        raise InputError("sampler", "copies", f"a divisor of the ray count {near.shape[0]}",
                         copies)
    shape = (near.shape[0] // copies, n)
    if perturb:
        u = uniform(shape, gen, near).repeat(copies, 1)
    else:
        u = torch.full((near.shape[0], n), 0.5, device=near.device, dtype=near.dtype)
    i = torch.arange(n, device=near.device, dtype=near.dtype)
    return near[:, None] + (far - near)[:, None] * ((i + u) / n)


def interval_edges(s: Tensor, near: Tensor, far: Tensor) -> Tensor:
    """Cell edges of sorted samples: ``[near, (s_0+s_1)/2, …, (s_{K-2}+s_{K-1})/2, far]``.

    Args:
        s: ``[N, K]`` sorted distances in ``[near, far]``.
        near, far: ``[N]``.

    Returns:
        ``[N, K+1]`` edges; ``edges.diff(dim=-1)`` are the step sizes ``δ`` (sum
        ``far − near``).

    >>> interval_edges(torch.tensor([[0.25, 0.75]]), torch.tensor([0.0]), torch.tensor([1.0]))
    tensor([[0.0000, 0.5000, 1.0000]])
    """
    mid = 0.5 * (s[:, 1:] + s[:, :-1])
    return torch.cat([near[:, None].to(s.dtype), mid, far[:, None].to(s.dtype)], dim=-1)


def sample_pdf(
    bins: Tensor,
    weights: Tensor,
    n: int,
    deterministic: bool,
    gen: torch.Generator | None = None,
    eps: float = 1e-5,
) -> Tensor:
    """Draw ``n`` samples per ray from the piecewise-constant pdf of ``weights``.

    The pdf is :math:`p_j \\propto w_j + \\epsilon` on bin ``[bins_j, bins_{j+1})``
    (``ε`` keeps an all-zero ray uniform), the CDF :math:`F_j = \\sum_{i<j} p_i`, and a
    sample is :math:`F^{-1}(u)` by linear interpolation inside the bin found by binary
    search. ``u`` are the quantiles ``(k + 1/2)/n`` if ``deterministic`` (then bin ``j``
    receives ``n·p_j`` samples up to ±1), else sorted uniforms. Weights are detached:
    sample positions carry no gradient.

    Args:
        bins: ``[N, M+1]`` increasing bin edges.
        weights: ``[N, M]`` non-negative bin weights (need not be normalised).
        n: samples per ray.
        deterministic: quantiles instead of random draws.
        gen: optional generator (for ``deterministic=False``).
        eps: added to every weight before normalising.

    Returns:
        ``[N, n]`` sorted samples within ``[bins_0, bins_M]``.

    >>> b = torch.tensor([[0.0, 1.0, 2.0]])
    >>> sample_pdf(b, torch.tensor([[0.0, 1.0]]), 2, deterministic=True, eps=0.0)
    tensor([[1.2500, 1.7500]])
    """
    w = weights.detach().to(bins.dtype).clamp(min=0) + eps
    pdf = w / w.sum(dim=-1, keepdim=True).clamp(min=torch.finfo(w.dtype).tiny)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), pdf.cumsum(dim=-1)], dim=-1)
    cdf[:, -1] = 1.0
    n_rays, m = weights.shape
    if deterministic:
        u = (torch.arange(n, device=bins.device, dtype=bins.dtype) + 0.5) / n
        u = u.expand(n_rays, n).contiguous()
    else:
        u = uniform((n_rays, n), gen, bins).sort(dim=-1).values
    hi = torch.searchsorted(cdf.contiguous(), u, right=True).clamp(1, m)
    lo = hi - 1
    cdf_lo, cdf_hi = cdf.gather(1, lo), cdf.gather(1, hi)
    bin_lo, bin_hi = bins.detach().gather(1, lo), bins.detach().gather(1, hi)
    denom = cdf_hi - cdf_lo
    frac = ((u - cdf_lo) / torch.where(denom > 0, denom, torch.ones_like(denom))).clamp(0, 1)
    return bin_lo + frac * (bin_hi - bin_lo)
