"""Per-iteration random choices of the training batch (docs/method.md "Per-iteration sampling").

Pure functions of their inputs and an explicit :class:`torch.Generator` (no global RNG
state), so a batch is a function of ``(seed, step)``. Draws happen on the generator's
device; results are moved to the device of the tensors passed in.

1. :func:`sample_window` — one window ``(t0, t1)`` per iteration, normalised times;
2. :func:`rays_per_view` — ``N_rand`` rays split equally over the views (supp. Sec. 9);
3. :func:`sample_pixels` — per view ``⌊n·(1 − neg_ratio)⌋`` rays on pixels with
   ``E(t0, t1) ≠ 0``, the rest uniform over the image, each set without replacement;
4. :func:`jitter` — ±0.5 px inside the pixel;
5. :func:`pick_reference` — per view, one of the two RGB frames nearest ``t1``.

The reference signal ``E_ref→1 = E(t_ref, t1)``, negated when ``t_ref > t1``, is
``V(t1) − V(t_ref)`` for *both* orderings (for ``t_ref > t1``:
``−E(t1, t_ref) = −(V(t_ref) − V(t1))``), i.e.
:meth:`eventrecon.events.accumulate.DecayedEvents.window` ``(pix, t_ref, t1)``.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from eventrecon.common.errors import InputError

__all__ = ["sample_window", "rays_per_view", "sample_pixels", "jitter", "pick_reference"]


def _rand(n: int, gen: torch.Generator, dtype: torch.dtype = torch.float64) -> Tensor:
    return torch.rand(n, generator=gen, dtype=dtype, device=gen.device)


def sample_window(gen: torch.Generator) -> tuple[float, float]:
    """A random window of the segment, in normalised time.

    ``mid ~ U(0,1)``, ``dur ~ U(0,1)``, ``t0 = max(0, mid − dur/2)``,
    ``t1 = min(1, mid + dur/2)``; so ``0 ≤ t0 ≤ t1 ≤ 1`` and
    ``E[t1 − t0] = 5/12`` (the clipped length averaged over mid and dur).

    >>> t0, t1 = sample_window(torch.Generator().manual_seed(0))
    >>> 0.0 <= t0 <= t1 <= 1.0
    True
    """
    mid, dur = _rand(2, gen).tolist()
    return max(0.0, mid - 0.5 * dur), min(1.0, mid + 0.5 * dur)


def rays_per_view(n_rays: int, n_views: int, gen: torch.Generator) -> Tensor:
    """Equal split of ``n_rays`` over ``n_views``; the remainder goes to random views.

    Returns:
        ``[V]`` int64 counts, each ``⌊n/V⌋`` or ``⌊n/V⌋ + 1``, summing to ``n_rays``.

    >>> rays_per_view(10, 4, torch.Generator().manual_seed(0)).sort().values
    tensor([2, 2, 3, 3])
    """
    if n_views < 1 or n_rays < 0:
        raise InputError("sampling", "n_rays/n_views", "n_rays >= 0 and n_views >= 1",
                         f"{n_rays}/{n_views}")
    counts = torch.full((n_views,), n_rays // n_views, dtype=torch.int64)
    extra = torch.randperm(n_views, generator=gen, device=gen.device)[: n_rays % n_views]
    counts[extra.cpu()] += 1
    return counts


def _draws(n: int, gen: torch.Generator) -> np.ndarray:
    """``n`` uniform float64 draws of ``gen`` (on its device), as a CPU array."""
    return _rand(n, gen).cpu().numpy()


def _distinct(pool: np.ndarray, group: np.ndarray, distinct: np.ndarray,
              gen: torch.Generator) -> np.ndarray:
    """Draw ``j`` uniform over ``range(pool[j])``; no index twice within a group flagged
    ``distinct``.

    Duplicates (every occurrence of a ``(group, index)`` after its first) are drawn again
    until none are left. The procedure treats every index alike, so each set of distinct
    indices is equally likely: the same law as drawing without replacement. A group that
    asks for more than half its pool takes the first indices of a random permutation
    instead (redrawing would need about ``pool·ln(pool)`` draws there). The draws come
    from ``gen`` (uniforms, and ``randperm`` for such a group), in that order; the
    bookkeeping of a few hundred indices runs in NumPy, whose calls on small arrays cost
    a microsecond where a tensor operation costs ten.

    Args:
        pool: ``[K]`` int64 sizes (≥ 1); a distinct group must not ask for more than its
            pool holds.
        group: ``[K]`` int64 group ids.
        distinct: ``[K]`` bool, constant within a group.
        gen: random generator.

    Returns:
        ``[K]`` int64 indices.
    """
    idx = np.minimum((_draws(pool.size, gen) * pool).astype(np.int64), pool - 1)
    if idx.size < 2:
        return idx
    asked = np.bincount(group[distinct], minlength=int(group.max()) + 1)   # per group
    heavy = distinct & (2 * asked[group] > pool)
    if heavy.any():                              # most of a pool: a permutation's first k
        distinct = distinct & ~heavy
        for g in np.unique(group[heavy]).tolist():
            members = np.flatnonzero(group == g)
            perm = torch.randperm(int(pool[members[0]]), generator=gen, device=gen.device)
            idx[members] = perm[: members.size].cpu().numpy()
    span = int(pool.max()) + 1
    while True:
        key = group * span + idx
        order = np.argsort(key, kind="stable")
        ordered = key[order]
        again = order[1:][ordered[1:] == ordered[:-1]]
        again = again[distinct[again]]
        if again.size == 0:
            return idx
        idx[again] = np.minimum((_draws(again.size, gen) * pool[again]).astype(np.int64),
                                pool[again] - 1)


def sample_pixels(event_map: Tensor, counts: Tensor, neg_ratio: float,
                  gen: torch.Generator) -> tuple[Tensor, Tensor, Tensor]:
    """Pixels of one batch: per view, rays on event pixels and uniform rays.

    As the authors' ``random_sample`` draws them: view ``v`` gets ``counts[v]`` rays,
    ``⌊counts[v]·(1 − neg_ratio)⌋`` of them on its pixels with ``event_map ≠ 0`` (without
    replacement unless it has fewer such pixels; none if it has none) and the rest uniform
    over its ``H·W`` pixels without replacement (with, where a view asks for more rays than
    it has pixels). The two sets may share pixels. Vectorised over views; the map is read
    once, on the CPU.

    Args:
        event_map: ``[V, H, W]`` E(t0, t1) values or a bool "has events" map.
        counts: ``[V]`` rays per view (:func:`rays_per_view`).
        neg_ratio: fraction of uniform rays, in [0, 1].
        gen: random generator.

    Returns:
        ``(view, row, col)``, each ``[N]`` int64 (``N = Σ counts``) on ``event_map``'s
        device, grouped by view; within a view the uniform rays come first.
    """
    if event_map.dim() != 3:
        raise InputError("sampling", "event_map", "shape [V, H, W]", tuple(event_map.shape))
    if not 0.0 <= neg_ratio <= 1.0:
        raise InputError("sampling", "neg_ratio", "a fraction in [0, 1]", neg_ratio)
    n_views, height, width = event_map.shape
    count = counts.to(torch.int64).cpu().numpy()
    if count.shape != (n_views,) or bool((count < 0).any()):
        raise InputError("sampling", "counts", f"[{n_views}] non-negative counts",
                         count.tolist())
    hw = height * width
    n_pos = np.floor(count.astype(np.float64) * (1.0 - neg_ratio)).astype(np.int64)
    has_ev = (event_map != 0).reshape(n_views, hw).cpu().numpy()
    n_ev = has_ev.sum(1)                         # [V] event pixels per view
    n_pos = np.where(n_ev > 0, n_pos, 0)         # views without events draw uniformly
    n_uni = count - n_pos
    views = np.arange(n_views)
    v_uni, v_pos = np.repeat(views, n_uni), np.repeat(views, n_pos)
    # one draw: uniform rays index the view's pixels (group v), event rays its event
    # pixels (group V + v)
    pool = np.concatenate([np.full(v_uni.size, hw), n_ev[v_pos]])
    group = np.concatenate([v_uni, n_views + v_pos])
    distinct = np.concatenate([(n_uni <= hw)[v_uni], (n_pos <= n_ev)[v_pos]])
    k = _distinct(pool, group, distinct, gen)
    ev_flat = np.flatnonzero(has_ev)             # sorted by view, then pixel
    ev_start = np.cumsum(n_ev) - n_ev
    flat_pos = ev_flat[ev_start[v_pos] + k[v_uni.size:]] - v_pos * hw
    # Group by view, uniform rays first within each view.
    view = np.concatenate([v_uni, v_pos])
    flat = np.concatenate([k[: v_uni.size], flat_pos])
    order = np.argsort(view, kind="stable")
    view, flat = (torch.from_numpy(x[order]).to(event_map.device) for x in (view, flat))
    return view, flat // width, flat % width


def jitter(uv: Tensor, gen: torch.Generator) -> Tensor:
    """``uv + U(−0.5, 0.5)`` per coordinate: a uniform point in each pixel's square.

    Args:
        uv: ``[N, 2]`` pixel-centre coordinates (column, row), floating point.

    Returns:
        ``[N, 2]`` jittered coordinates, same dtype and device.
    """
    if not uv.is_floating_point():
        uv = uv.to(torch.float64)
    noise = torch.rand(uv.shape, generator=gen, dtype=uv.dtype, device=gen.device) - 0.5
    return uv + noise.to(uv.device)


def pick_reference(frame_times: Tensor, t1: float, gen: torch.Generator, views: int = 1
                   ) -> Tensor:
    """Per view, the index of a reference frame: one of the two frames nearest ``t1``, at
    random, drawn independently for each view (the authors' ``random_sample`` draws it
    per view, so one step's views mix both candidates).

    Args:
        frame_times: ``[F]`` frame times (same units as ``t1``), ``F ≥ 1``.
        t1: the window end.
        gen: random generator (``views`` uniform draws).
        views: how many views to draw for.

    Returns:
        ``[views]`` int64 frame indices on ``frame_times``' device (the only frame when
        ``F = 1``). Ties in distance keep the lower index first.

    >>> refs = pick_reference(torch.tensor([0.0, 10.0, 20.0]), 12.0, torch.Generator(), 3)
    >>> set(refs.tolist()) <= {1, 2}
    True
    """
    n = int(frame_times.shape[0])
    if n == 0:
        raise InputError("sampling", "frame_times", "at least one RGB frame", 0)
    if views < 1:
        raise InputError("sampling", "views", "at least one view", views)
    dist = (frame_times.detach().cpu().to(torch.float64) - float(t1)).abs()
    nearest = torch.sort(dist, stable=True).indices[: min(2, n)]
    pick = (_rand(views, gen).cpu() * nearest.shape[0]).long().clamp_max(nearest.shape[0] - 1)
    return nearest[pick].to(frame_times.device)
