"""Per-iteration sampling: window law, balanced counts, event-pixel ratio, reference, jitter."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from eventrecon.common.errors import InputError
from eventrecon.data.sampling import (
    jitter,
    pick_reference,
    rays_per_view,
    sample_pixels,
    sample_window,
)
from eventrecon.events.accumulate import DecayedEvents
from eventrecon.events.stream import EventStream


def test_window_bounds_and_moments() -> None:
    gen = torch.Generator().manual_seed(0)
    n = 20000
    w = np.array([sample_window(gen) for _ in range(n)])
    t0, t1 = w[:, 0], w[:, 1]
    assert np.all((0 <= t0) & (t0 <= t1) & (t1 <= 1))
    # E[t1 − t0] = 1/2 − 2·E[(mid + dur/2 − 1)+] = 1/2 − 2/24 = 5/12; E[t1] = 17/24.
    # Var(t1 − t0) ≤ 1/4 (a variable in [0, 1]) → 5 standard errors ≤ 5·0.5/√n.
    tol = 5 * 0.5 / math.sqrt(n)
    assert abs((t1 - t0).mean() - 5 / 12) < tol
    assert abs(t1.mean() - 17 / 24) < tol and abs(t0.mean() - 7 / 24) < tol
    # Clipped at both ends with positive probability: P(t0 = 0) = P(dur/2 > mid) = 1/4.
    assert abs((t0 == 0).mean() - 0.25) < 5 * math.sqrt(0.25 * 0.75 / n)
    assert abs((t1 == 1).mean() - 0.25) < 5 * math.sqrt(0.25 * 0.75 / n)


def test_window_is_a_function_of_the_seed() -> None:
    a = [sample_window(torch.Generator().manual_seed(7)) for _ in range(2)]
    assert a[0] == a[1]


@pytest.mark.parametrize("n_rays,n_views", [(1024, 6), (1024, 5), (7, 3), (2, 5), (0, 2)])
def test_rays_per_view_exact_and_balanced(n_rays: int, n_views: int) -> None:
    gen = torch.Generator().manual_seed(1)
    totals = torch.zeros(n_views, dtype=torch.int64)
    for _ in range(300):
        c = rays_per_view(n_rays, n_views, gen)
        assert int(c.sum()) == n_rays
        assert int(c.max() - c.min()) <= (1 if n_rays % n_views else 0)
        assert int(c.min()) == n_rays // n_views
        totals += c
    # The remainder goes to random views: each view gets it with rate (n % V)/V.
    rem = n_rays % n_views
    if rem:
        extra = (totals - 300 * (n_rays // n_views)).double() / 300
        p = rem / n_views
        assert torch.all((extra - p).abs() < 5 * math.sqrt(p * (1 - p) / 300))


def test_sample_pixels_counts_and_event_ratio() -> None:
    gen = torch.Generator().manual_seed(2)
    V, H, W = 3, 20, 30
    event_map = torch.zeros(V, H, W)
    event_map[0, 2:5, 3:9] = 1.0           # 18 event pixels
    event_map[1, 10, 10] = -2.0            # a single event pixel (negative E counts too)
    # view 2: no events → uniform fallback
    counts = torch.tensor([400, 300, 200])
    view, row, col = sample_pixels(event_map, counts, 0.9, gen)
    assert view.shape == row.shape == col.shape == (900,)
    assert torch.equal(torch.bincount(view, minlength=V), counts)
    assert torch.all((row >= 0) & (row < H) & (col >= 0) & (col < W))
    on_ev = event_map[view, row, col] != 0
    # View 0: ⌊400·(1 − 0.9)⌋ = 39 rays on events (the authors' int(): 1 − 0.9 is
    # 0.0999… in float64) + the uniform ones hitting the 18/600 event pixels.
    n0 = int(on_ev[view == 0].sum())
    exp0 = 39 + 361 * 18 / 600
    assert abs(n0 - exp0) < 5 * math.sqrt(361 * 0.03)
    assert int(on_ev[view == 1].sum()) >= 29  # 29 forced to the single event pixel
    assert int(on_ev[view == 2].sum()) == 0
    # Uniform rays cover the image: mean row/col near the centre.
    v2 = view == 2
    assert abs(row[v2].double().mean().item() - (H - 1) / 2) < 5 * H / math.sqrt(12 * 200)
    assert abs(col[v2].double().mean().item() - (W - 1) / 2) < 5 * W / math.sqrt(12 * 200)


@pytest.mark.parametrize("neg_ratio", [0.0, 0.5, 1.0])
def test_neg_ratio_proportions(neg_ratio: float) -> None:
    gen = torch.Generator().manual_seed(3)
    event_map = torch.zeros(2, 40, 40, dtype=torch.bool)
    event_map[:, 0, 0] = True  # one event pixel out of 1600
    counts = torch.tensor([500, 500])
    view, row, col = sample_pixels(event_map, counts, neg_ratio, gen)
    hits = int(((row == 0) & (col == 0)).sum())
    forced = 2 * math.floor(500 * (1.0 - neg_ratio))
    uniform = 1000 - forced
    assert abs(hits - forced - uniform / 1600) < 5 * math.sqrt(uniform / 1600) + 1


def test_sample_pixels_draw_without_replacement_like_the_authors() -> None:
    """Each view's uniform rays and its event rays are sets (no pixel twice) unless the
    view asks for more than it has; every pixel is equally likely to be in a set."""
    gen = torch.Generator().manual_seed(4)
    V, H, W = 2, 6, 5                      # 30 pixels per view
    event_map = torch.zeros(V, H, W, dtype=torch.bool)
    event_map[0, :2] = True                # 10 event pixels
    event_map[1, 0, :3] = True             # 3 event pixels: fewer than the 4 asked for
    counts = torch.tensor([25, 25])
    inclusion = torch.zeros(H * W)
    trials = 500
    for _ in range(trials):
        view, row, col = sample_pixels(event_map, counts, 0.8, gen)
        flat = row * W + col
        for v in range(V):   # per view: 21 uniform rays first, then ⌊25·(1 − 0.8)⌋ = 4
            uni, pos = flat[view == v][:21], flat[view == v][21:]   # (25·0.1999… in float64)
            assert pos.numel() == 4 and bool(event_map[v].reshape(-1)[pos].all())
            assert uni.unique().numel() == 21
            if v == 0:
                assert pos.unique().numel() == 4
                inclusion[uni] += 1
            else:                          # 4 > 3 event pixels: with replacement
                assert set(pos.tolist()) <= {0, 1, 2}
    # inclusion frequency of each pixel among 21 of 30, binomial spread
    p = 21 / 30
    assert (inclusion / trials - p).abs().max().item() < 5 * math.sqrt(p * (1 - p) / trials)
    # a view asking for more uniform rays than it has pixels draws with replacement
    view, row, col = sample_pixels(torch.zeros(1, 2, 2), torch.tensor([9]), 1.0, gen)
    assert view.numel() == 9 and (row * 2 + col).unique().numel() <= 4


def test_sample_pixels_bad_input() -> None:
    gen = torch.Generator()
    with pytest.raises(InputError, match="counts"):
        sample_pixels(torch.zeros(2, 3, 3), torch.tensor([1, 2, 3]), 0.9, gen)
    with pytest.raises(InputError, match="neg_ratio"):
        sample_pixels(torch.zeros(2, 3, 3), torch.tensor([1, 2]), 1.5, gen)


def test_jitter_range_and_uniformity() -> None:
    gen = torch.Generator().manual_seed(4)
    uv = torch.tensor([[3.0, 7.0]], dtype=torch.float64).expand(20000, 2)
    out = jitter(uv, gen)
    d = out - uv
    assert out.dtype == torch.float64
    assert torch.all(d >= -0.5) and torch.all(d < 0.5)
    assert d.mean(0).abs().max().item() < 5 * math.sqrt(1 / 12 / 20000)
    assert abs(d.var(0).mean().item() - 1 / 12) < 0.005  # U(−½, ½) has variance 1/12


def test_pick_reference_two_nearest_drawn_per_view() -> None:
    gen = torch.Generator().manual_seed(5)
    times = torch.tensor([0.0, 200.0, 400.0, 600.0, 800.0, 1000.0])
    picks = pick_reference(times, 430.0, gen, views=4000)
    assert picks.shape == (4000,) and picks.dtype == torch.int64
    assert set(picks.tolist()) == {2, 3}  # 400 and 600 are the two nearest to 430
    assert abs((picks == 2).double().mean().item() - 0.5) < 5 * math.sqrt(0.25 / 4000)
    # views are drawn independently (the authors draw per view): of 2000 pairs of
    # views, about half disagree
    pairs = pick_reference(times, 430.0, gen, views=4000).reshape(2000, 2)
    differ = (pairs[:, 0] != pairs[:, 1]).double().mean().item()
    assert abs(differ - 0.5) < 5 * math.sqrt(0.25 / 2000)
    # t1 on a frame: that frame or its nearest neighbour (tie → lower index first).
    assert set(pick_reference(times, 1000.0, gen, views=200).tolist()) == {4, 5}
    assert pick_reference(torch.tensor([500.0]), 10.0, gen).tolist() == [0]  # F = 1
    with pytest.raises(InputError, match="frame_times"):
        pick_reference(torch.zeros(0), 1.0, gen)
    with pytest.raises(InputError, match="views"):
        pick_reference(times, 1.0, gen, views=0)


def test_reference_events_sign_rule() -> None:
    """E_ref→1 = E(t_ref, t1), negated if t_ref > t1 — both equal V(t1) − V(t_ref)."""
    s = EventStream(np.zeros(4, np.int16), np.zeros(4, np.int16),
                    np.array([100.0, 200.0, 300.0, 400.0]), np.array([1, 1, 1, -1], np.int8))
    ev = DecayedEvents.from_streams([s], 1, 1, 1.0)
    pix = torch.zeros(1, dtype=torch.int64)
    # t_ref = 150 < t1 = 350: events at 200, 300 → +2 (brightness went up since t_ref).
    assert float(ev.window(pix, 150.0, 350.0)) == 2.0
    # t_ref = 350 > t1 = 150: −E(150, 350) = −2 (going back from t_ref to t1).
    assert float(ev.window(pix, 350.0, 150.0)) == -2.0
    assert float(ev.value(pix, 150.0) - ev.value(pix, 350.0)) == -2.0


def test_sample_pixels_draws_pinned_to_the_tensor_form() -> None:
    """The pixels and the generator's next draws for three fixed seeds, as the tensor
    form of ``sample_pixels`` (``66964ec``) gave them: a group asking most of its pool
    (a ``randperm``), redraws of duplicates, a view without events. The NumPy
    bookkeeping makes the same torch draws in the same order."""
    em = torch.zeros(3, 3, 4)
    em[0, 0, 1], em[0, 1, 2], em[0, 2, 3], em[0, 2, 0] = 2.0, -1.0, 0.5, 1.0
    em[1] = torch.tensor([[0, 1, 0, 1], [1, 1, 0, 0], [0, 0, 1, 1.0]])
    pinned = {
        (0, (4, 9, 5), 0.5): ([0, 0, 0, 0, 1, 1, 1, 1, 1, 1, 1, 1, 1, 2, 2, 2, 2, 2],
                              [2, 2, 1, 2, 1, 2, 1, 2, 0, 2, 2, 0, 0, 1, 1, 0, 1, 0],
                              [3, 0, 2, 0, 1, 3, 3, 1, 2, 2, 3, 3, 1, 0, 2, 3, 1, 2],
                              [0.949266337947, 0.265221338978]),
        (1, (6, 5, 3), 0.2): ([0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 2, 2, 2],
                              [0, 0, 1, 2, 0, 2, 0, 1, 1, 2, 2, 0, 1, 0],
                              [0, 2, 2, 0, 1, 3, 2, 0, 1, 3, 2, 2, 2, 1],
                              [0.512447328152, 0.71183813972]),
        (2, (12, 2, 7), 0.9): ([0] * 12 + [1, 1] + [2] * 7,
                               [2, 1, 0, 1, 2, 1, 2, 0, 0, 0, 1, 2, 2, 1, 0, 2, 1, 2, 0, 1, 2],
                               [2, 1, 3, 3, 3, 0, 0, 0, 2, 1, 2, 0, 0, 3, 0, 1, 1, 2, 2, 3, 3],
                               [0.55297596658, 0.327015778108]),
    }
    for (seed, counts, neg), (view, row, col, after) in pinned.items():
        gen = torch.Generator().manual_seed(seed)
        v, r, c = sample_pixels(em, torch.tensor(counts), neg, gen)
        assert v.dtype == r.dtype == c.dtype == torch.int64
        assert (v.tolist(), r.tolist(), c.tolist()) == (view, row, col)
        nxt = torch.rand(2, generator=gen, dtype=torch.float64).tolist()
        assert nxt == pytest.approx(after, abs=1e-12)
