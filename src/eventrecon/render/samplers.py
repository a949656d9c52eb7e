"""Sample placement along rays: stratified, importance (inverse CDF), step sizes.

Every sampler works on a ray parameter interval ``[near, far]`` per ray and returns
distances ``s [N, K]`` sorted along each ray. The placement and the quadrature are the
authors' (``ddp_train_nerf.py``, ``ddp_sampling.py``, ``ddp_model.py``):

- coarse: ``K`` evenly spaced points from ``near`` to ``far`` (both included), each
  jittered uniformly within the cell between the midpoints to its neighbours, so the
  two end cells are half as wide (:func:`stratified`);
- step sizes: the forward difference to the next sample, the last sample's reaching
  ``far`` (:func:`step_sizes`);
- fine: drawn from the coarse weights ``w_1 … w_{K−2}`` as a histogram over the
  midpoints of the coarse samples (:func:`pdf_bins`, :func:`sample_pdf`); the end
  samples' weights are left out, as in the authors' code.

Randomness only through an optional ``torch.Generator`` (on the rays' device).
"""

from __future__ import annotations

import torch
from torch import Tensor

from eventrecon.common.errors import InputError

__all__ = ["TAU_MAX", "stratified", "sample_pdf", "step_sizes", "pdf_bins"]

#: The quadrature's clamp of the optical thickness ``σ δ`` of one step (``e^{-TAU_MAX}``
#: is 0 in float32; :mod:`eventrecon.render.volume`).
TAU_MAX = 1e4


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
    """``n`` evenly spaced points from ``near`` to ``far``, each jittered within its cell.

    .. math:: z_i = \\text{near} + i\\,\\frac{\\text{far} - \\text{near}}{n - 1},\\quad
              s_i = l_i + u_i\\,(h_i - l_i),\\quad u_i \\sim U[0, 1)

    with ``l_i, h_i`` the midpoints to the neighbours (``l_0 = z_0``, ``h_{n−1} = z_{n−1}``:
    the end cells are half wide, as the authors' ``perturb_samples`` makes them), or
    ``s_i = z_i`` without ``perturb`` (evaluation).

    Args:
        near, far: ``[N]`` interval ends (``far ≥ near``).
        n: samples per ray (≥ 2).
        perturb: jitter within each cell (training) or take the points (evaluation).
        gen: optional generator for the jitter.
        copies: the ``N`` rays are ``copies`` stacked blocks of the same ``N / copies``
            rays (one ray rendered at several times); every block gets the same jitter
            ``u``, so a copy's samples are its first block's (the authors' code draws the
            coarse depths once per ray for its ``t0``, ``t1`` and ``t_ref`` renders).

    Returns:
        ``[N, n]`` sorted distances in ``[near, far]``.

    >>> stratified(torch.tensor([0.0]), torch.tensor([1.5]), 4, perturb=False)
    tensor([[0.0000, 0.5000, 1.0000, 1.5000]])
    >>> gen = torch.Generator().manual_seed(0)
    >>> s = stratified(torch.zeros(4), torch.ones(4), 3, True, gen, copies=2)
    >>> bool((s[:2] == s[2:]).all())
    True
    """
    if n < 2:
        raise InputError("sampler", "n", "at least 2 samples per ray (the authors' linspace)", n)
    if copies < 1 or near.shape[0] % copies:
        raise InputError("sampler", "copies", f"a divisor of the ray count {near.shape[0]}",
                         copies)
    i = torch.arange(n, device=near.device, dtype=near.dtype)
    z = near[:, None] + (far - near)[:, None] * (i / (n - 1))
    if not perturb:
        return z
    mid = 0.5 * (z[:, 1:] + z[:, :-1])
    lower = torch.cat([z[:, :1], mid], dim=-1)
    upper = torch.cat([mid, z[:, -1:]], dim=-1)
    u = uniform((near.shape[0] // copies, n), gen, near).repeat(copies, 1)
    return lower + (upper - lower) * u


def step_sizes(s: Tensor, far: Tensor) -> Tensor:
    """The authors' quadrature steps: ``δ_i = s_{i+1} − s_i``, ``δ_{K−1} = far − s_{K−1}``.

    Args:
        s: ``[N, K]`` sorted distances in ``[near, far]``.
        far: ``[N]``.

    Returns:
        ``[N, K]`` steps (≥ 0), summing to ``far − s_0``.

    >>> step_sizes(torch.tensor([[0.25, 0.75]]), torch.tensor([1.0]))
    tensor([[0.5000, 0.2500]])
    """
    return torch.cat([s[:, 1:] - s[:, :-1], far[:, None].to(s.dtype) - s[:, -1:]], dim=-1)


def pdf_bins(s: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """The fine level's histogram from the coarse level: the ``K − 1`` midpoints of the
    coarse samples as bin edges, the inner weights ``w_1 … w_{K−2}`` as bin weights (each
    inner sample's weight spread over the cell around it; the authors' choice).

    Args:
        s: ``[N, K]`` sorted coarse distances (``K ≥ 3``).
        weights: ``[N, K]`` coarse compositing weights.

    Returns:
        ``(bins [N, K−1], weights [N, K−2])`` for :func:`sample_pdf`.

    >>> b, w = pdf_bins(torch.tensor([[0.0, 1.0, 2.0, 3.0]]), torch.tensor([[9.0, 1.0, 2.0, 9.0]]))
    >>> b.tolist(), w.tolist()
    ([[0.5, 1.5, 2.5]], [[1.0, 2.0]])
    """
    if s.shape[-1] < 3:
        raise InputError("sampler", "n_coarse", "at least 3 coarse samples for a fine level",
                         s.shape[-1])
    return 0.5 * (s[:, 1:] + s[:, :-1]), weights[:, 1:-1]


def sample_pdf(
    bins: Tensor,
    weights: Tensor,
    n: int,
    deterministic: bool,
    gen: torch.Generator | None = None,
    eps: float = 1e-6,
) -> Tensor:
    """Draw ``n`` samples per ray from the piecewise-constant pdf of ``weights``.

    The pdf is :math:`p_j \\propto w_j + \\epsilon` on bin ``[bins_j, bins_{j+1})``
    (``ε`` keeps an all-zero ray uniform), the CDF :math:`F_j = \\sum_{i<j} p_i`, and a
    sample is :math:`F^{-1}(u)` by linear interpolation inside the bin found by binary
    search. ``u`` are ``k/(n − 1)``, evenly from 0 to 1, if ``deterministic`` (the authors'
    evaluation; bin ``j`` then receives ``(n − 1)·p_j`` samples up to ±1), else sorted
    uniforms. Weights are detached: sample positions carry no gradient.

    Args:
        bins: ``[N, M+1]`` increasing bin edges.
        weights: ``[N, M]`` non-negative bin weights (need not be normalised).
        n: samples per ray.
        deterministic: quantiles instead of random draws.
        gen: optional generator (for ``deterministic=False``).
        eps: added to every weight before normalising (the authors' ``TINY_NUMBER``).

    Returns:
        ``[N, n]`` sorted samples within ``[bins_0, bins_M]``.

    >>> b = torch.tensor([[0.0, 1.0, 2.0]])
    >>> sample_pdf(b, torch.tensor([[0.0, 1.0]]), 3, deterministic=True, eps=0.0)
    tensor([[1.0000, 1.5000, 2.0000]])
    """
    w = weights.detach().to(bins.dtype).clamp(min=0) + eps
    pdf = w / w.sum(dim=-1, keepdim=True).clamp(min=torch.finfo(w.dtype).tiny)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), pdf.cumsum(dim=-1)], dim=-1)
    cdf[:, -1] = 1.0
    n_rays, m = weights.shape
    if deterministic:
        u = torch.linspace(0.0, 1.0, n, device=bins.device, dtype=bins.dtype)
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
