"""Closed-form statistics of accumulated noise events (supplementary Sec. 15).

A pixel of constant brightness reports noise polarities ``p_i`` i.i.d. with
``q₊ = P(p = +1)``, ``q₋ = P(p = −1)`` (``q₊ + q₋ ≤ 1``; the rest of the mass is
"no event", ``p = 0``, so ``q₊ + q₋ = 1`` is the paper's case). Write
``μ = q₊ − q₋ = E[p]``, ``s = q₊ + q₋ = E[p²]`` and ``σ² = Var(p) = s − μ²``
(``= 4q₊q₋`` when ``s = 1``). After ``n`` events, with decay ``b`` per event:

.. math::
   Ê_n = \\sum_{i=1}^{n} b^{\\,n-i} p_i, \\qquad
   \\mathbb E[Ê_n] = μ\\,g_n(b), \\qquad
   \\mathrm{Var}(Ê_n) = σ^2\\,g_n(b^2), \\qquad
   g_n(x) = \\sum_{k=0}^{n-1} x^k = \\frac{1 - x^n}{1 - x}\\ (g_n(1) = n).

Without decay (``b = 1``): mean ``nμ`` (Eq. 14), variance ``nσ²`` (linear in ``n``), and
second moment — the mean squared deviation from the true level 0 —
``E[E_n²] = ns + n(n−1)μ²``, quadratic in ``n`` whenever ``q₊ ≠ q₋``. With ``b < 1``
every moment converges: mean ``→ μ/(1−b)``, variance ``→ σ²/(1−b²)``.

Note on Eq. (15) of the supplementary: its final expression
``n(n−1)(q₊−q₋)² + 2nq₋`` (:func:`eq15_supplementary`) equals
``E[E_n²] − E[E_n]`` — the derivation subtracts ``E(E_n)`` where ``E(E_n)²`` is meant.
The true variance is ``nσ²`` (e.g. ``q₊ = 1``: ``E_n = n`` surely, variance 0, while
Eq. 15 gives ``n² − n``). The conclusion of Sec. 15 stands for the second moment: without
decay the deviation from the true brightness grows without bound (linearly in
variance, quadratically in mean square when ``q₊ ≠ q₋``); with decay it stays bounded.
Eq. (17) and (18) (the decayed mean and second moment) are correct;
:func:`eq18_supplementary` evaluates Eq. (18) as printed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from eventrecon.common.errors import InputError

__all__ = [
    "NoiseMoments",
    "noise_moments",
    "noise_limits",
    "eq15_supplementary",
    "eq18_supplementary",
    "simulate_noise_accumulation",
    "window_noise_moments",
]


@dataclass(frozen=True)
class NoiseMoments:
    """Moments of the accumulated noise ``Ê_n`` (arrays broadcast like ``n``)."""

    mean: np.ndarray
    variance: np.ndarray
    second_moment: np.ndarray


def _check_q(q_plus: float, q_minus: float) -> None:
    if q_plus < 0 or q_minus < 0 or q_plus + q_minus > 1 + 1e-12:
        raise InputError("noise_theory", "q_plus/q_minus",
                         "probabilities with q_plus + q_minus <= 1", f"{q_plus}/{q_minus}")


def _geometric(n: np.ndarray, x: float) -> np.ndarray:
    """``g_n(x) = Σ_{k<n} x^k`` (``= n`` at ``x = 1``)."""
    n = np.asarray(n, dtype=np.float64)
    if x == 1.0:
        return n
    return (1.0 - x**n) / (1.0 - x)


def noise_moments(n: np.ndarray | int, q_plus: float, q_minus: float,
                  decay: float = 1.0) -> NoiseMoments:
    """Exact mean, variance and second moment of ``Ê_n`` (formulas in the module docstring).

    >>> m = noise_moments(np.array([10, 100]), 0.5, 0.5)
    >>> m.variance.tolist(), m.mean.tolist()
    ([10.0, 100.0], [0.0, 0.0])
    """
    _check_q(q_plus, q_minus)
    if not 0.0 <= decay <= 1.0:
        raise InputError("noise_theory", "decay", "b in [0, 1]", decay)
    mu, s = q_plus - q_minus, q_plus + q_minus
    var_p = s - mu**2
    mean = mu * _geometric(n, decay)
    variance = var_p * _geometric(n, decay**2)
    return NoiseMoments(mean, variance, variance + mean**2)


def noise_limits(q_plus: float, q_minus: float, decay: float) -> tuple[float, float]:
    """``(lim mean, lim variance) = (μ/(1−b), σ²/(1−b²))`` for ``b < 1``.

    >>> [round(v, 4) for v in noise_limits(0.5, 0.5, 0.93)]
    [0.0, 7.4019]
    """
    _check_q(q_plus, q_minus)
    if not 0.0 <= decay < 1.0:
        raise InputError("noise_theory", "decay", "b in [0, 1) for finite limits", decay)
    mu, s = q_plus - q_minus, q_plus + q_minus
    return mu / (1.0 - decay), (s - mu**2) / (1.0 - decay**2)


def _poisson_pgf(lam: float, x: float) -> float:
    """``E[x^N]`` for ``N ~ Poisson(λ)``: ``exp(−λ(1 − x))``."""
    return float(np.exp(-lam * (1.0 - x)))


def window_noise_moments(lam_before: float, lam_window: float, q_plus: float,
                         q_minus: float, decay: float = 1.0) -> tuple[float, float]:
    r"""Mean and second moment of the noise in a *window sum* ``E(t0, t1) = V(t1) − V(t0)``.

    This is what ``L_event`` and ``L_acc`` see (docs/method.md): ``V`` accumulates from the
    start of the recording, so with ``n₀`` noise events before ``t0`` and ``m`` inside the
    window,

    .. math::
       E = \sum_{k=1}^{m} b^{\,m-k} p_k - (1 - b^m)\,Ê_{n_0},

    with mean ``μ(g_m(b) − (1 − bᵐ) g_{n₀}(b))`` and variance
    ``σ²(g_m(b²) + (1 − bᵐ)² g_{n₀}(b²))`` given the counts. Here the counts are Poisson,
    ``n₀ ~ P(λ_before)`` and ``m ~ P(λ_window)``, independent (shot noise). The moments are
    averaged over them in closed form with ``E[x^N] = exp(−λ(1 − x))``.

    Without decay, ``E`` is the window's own sum: mean ``μλ``, second moment
    ``sλ + μ²λ²``, whatever came before. With decay, the history term removes the drift:
    once ``V`` has settled (``λ_before ≫ 1/(1 − b)``) the mean tends to 0 for any
    ``λ_window``. With too few events in and before the window, decay changes nothing.

    Args:
        lam_before: expected noise events of a pixel before ``t0``.
        lam_window: expected noise events in ``(t0, t1]``.
        q_plus, q_minus: ``P(p = +1)``, ``P(p = −1)`` of a noise event.
        decay: ``b ∈ [0, 1]``.

    Returns:
        ``(E[E], E[E²])``: the mean and mean square of the window sum, in events.

    >>> [round(v, 6) for v in window_noise_moments(3.0, 2.0, 0.5, 0.5)]
    [0.0, 2.0]
    """
    _check_q(q_plus, q_minus)
    if not 0.0 <= decay <= 1.0:
        raise InputError("noise_theory", "decay", "b in [0, 1]", decay)
    if lam_before < 0 or lam_window < 0:
        raise InputError("noise_theory", "lam_before/lam_window", "expected counts >= 0",
                         f"{lam_before}/{lam_window}")
    mu, s = q_plus - q_minus, q_plus + q_minus
    var_p = s - mu**2
    b = float(decay)
    if b == 1.0:
        return mu * lam_window, s * lam_window + mu**2 * lam_window**2
    p0, p1 = (lambda x: _poisson_pgf(lam_before, x)), (lambda x: _poisson_pgf(lam_window, x))
    g_m, g_m2 = (1 - p1(b)) / (1 - b), (1 - p1(b * b)) / (1 - b * b)        # E g_m(b), E g_m(b²)
    g_0, g_02 = (1 - p0(b)) / (1 - b), (1 - p0(b * b)) / (1 - b * b)
    cut = 1 - p1(b)                                                          # E(1 − bᵐ)
    cut_sq = 1 - 2 * p1(b) + p1(b * b)                                       # E(1 − bᵐ)²
    g_0_sq = (1 - 2 * p0(b) + p0(b * b)) / (1 - b) ** 2                      # E g_{n₀}(b)²
    mean = mu * (g_m - cut * g_0)
    variance_part = var_p * (g_m2 + cut_sq * g_02)
    mean_sq_part = mu**2 * (cut_sq / (1 - b) ** 2 - 2 * cut_sq / (1 - b) * g_0 + cut_sq * g_0_sq)
    return mean, variance_part + mean_sq_part


def eq15_supplementary(n: np.ndarray | int, q_plus: float, q_minus: float) -> np.ndarray:
    """Eq. (15) as printed: ``n(n−1)(q₊−q₋)² + 2nq₋`` (``= E[E_n²] − E[E_n]``)."""
    n = np.asarray(n, dtype=np.float64)
    return n * (n - 1) * (q_plus - q_minus) ** 2 + 2 * n * q_minus


def eq18_supplementary(n: np.ndarray | int, q_plus: float, q_minus: float,
                       decay: float) -> np.ndarray:
    """The second moment ``E[Ê_n²]`` of Eq. (18) as printed (``b < 1``):

    ``(q₊+q₋)(b^{2n}−1)/(b²−1) + 2(q₊−q₋)²/(b−1)·[(b^{2n}−1)/(b²−1) − (bⁿ−1)/(b−1)]``.
    """
    n = np.asarray(n, dtype=np.float64)
    b = float(decay)
    g2 = (b ** (2 * n) - 1) / (b**2 - 1)
    g1 = (b**n - 1) / (b - 1)
    return (q_plus + q_minus) * g2 + 2 * (q_plus - q_minus) ** 2 / (b - 1) * (g2 - g1)


def simulate_noise_accumulation(n_events: int, n_pixels: int, q_plus: float,
                                q_minus: float, decay: float,
                                gen: torch.Generator) -> Tensor:
    """Monte-Carlo trajectories ``Ê_1 … Ê_n`` of independent noisy pixels.

    The reference is the recurrence itself, a loop over events vectorised over pixels:
    ``Ê_k = b·Ê_{k−1} + p_k``.

    Returns:
        ``[n_events, n_pixels]`` float64; row ``k − 1`` holds ``Ê_k``.
    """
    _check_q(q_plus, q_minus)
    u = torch.rand(n_events, n_pixels, generator=gen, dtype=torch.float64,
                   device=gen.device)
    p = (u < q_plus).double() - ((u >= q_plus) & (u < q_plus + q_minus)).double()
    if decay == 1.0:
        return torch.cumsum(p, 0)
    out = torch.empty_like(p)
    acc = torch.zeros(n_pixels, dtype=torch.float64, device=p.device)
    for k in range(n_events):
        acc = decay * acc + p[k]
        out[k] = acc
    return out
