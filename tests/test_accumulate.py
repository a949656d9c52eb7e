"""Decayed event accumulation against an independent per-event reference loop."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.signal import lfilter

from eventrecon.common.errors import InputError
from eventrecon.events.accumulate import DecayedEvents, decayed_prefix
from eventrecon.events.bayer import bayer_mask, bayer_mask_at
from eventrecon.events.stream import EventStream

H, W = 4, 5


def random_streams(rng: np.random.Generator, n_views: int, n: int) -> list[EventStream]:
    """Streams on a coarse time grid (many ties) that hits 0 and 1000 exactly."""
    out = []
    for _ in range(n_views):
        t = np.sort(rng.integers(0, 51, n) * 20.0)
        t[0], t[-1] = 0.0, 1000.0
        out.append(EventStream(rng.integers(0, W, n).astype(np.int16),
                               rng.integers(0, H, n).astype(np.int16), t,
                               rng.choice(np.array([-1, 1], np.int8), n)))
    return out


def brute_value(streams: list[EventStream], decay: float, view: int, row: int, col: int,
                t: float) -> float:
    """V(t) by the definition: loop over the pixel's events in stream order."""
    s = streams[view]
    v = 0.0
    for k in range(len(s)):
        if s.x[k] == col and s.y[k] == row and s.t[k] <= t:
            v = decay * v + float(s.p[k])
    return v


@pytest.mark.parametrize("decay", [1.0, 0.93, 0.5, 0.0])
def test_value_matches_brute_force_loop(decay: float) -> None:
    rng = np.random.default_rng(1)
    streams = random_streams(rng, 3, 400)
    ev = DecayedEvents.from_streams(streams, H, W, decay)
    times = np.concatenate([[-1.0, 0.0, 1000.0, 1001.0, 500.0], rng.uniform(0, 1000, 20),
                            rng.integers(0, 51, 20) * 20.0])  # exact event times too
    pix, tq, ref = [], [], []
    for v in range(3):
        for r in range(H):
            for c in range(W):
                for t in times[rng.choice(len(times), 6, replace=False)].tolist() + [0.0, 1000.0]:
                    pix.append((v * H + r) * W + c)
                    tq.append(t)
                    ref.append(brute_value(streams, decay, v, r, c, t))
    got = ev.value(torch.tensor(pix), torch.tensor(tq, dtype=torch.float64)).numpy()
    if decay == 1.0:
        np.testing.assert_array_equal(got, np.array(ref))  # exact integer sums
    else:
        np.testing.assert_allclose(got, np.array(ref), rtol=0, atol=1e-12)


def test_ties_keep_stream_order_and_count_at_equal_time() -> None:
    # Two events at the same pixel and time: +1 then -1, b = 0.5 → V = 0.5·1 − 1.
    s = EventStream(np.array([1, 1], np.int16), np.array([0, 0], np.int16),
                    np.array([3.0, 3.0]), np.array([1, -1], np.int8))
    ev = DecayedEvents.from_streams([s], 1, 2, 0.5)
    t = torch.tensor([np.nextafter(3.0, 0.0), 3.0, 1000.0], dtype=torch.float64)
    assert ev.value(torch.tensor([1, 1, 1]), t).tolist() == [0.0, -0.5, -0.5]


def test_unsorted_stream_equals_sorted() -> None:
    rng = np.random.default_rng(2)
    n = 300
    x, y = rng.integers(0, W, n).astype(np.int16), rng.integers(0, H, n).astype(np.int16)
    t = rng.uniform(0, 1000, n)  # distinct times: the event order is well defined
    p = rng.choice(np.array([-1, 1], np.int8), n)
    o = np.argsort(t)
    ordered = DecayedEvents.from_streams([EventStream(x[o], y[o], t[o], p[o])], H, W, 0.9)
    shuffled = DecayedEvents.from_streams([EventStream(x, y, t, p)], H, W, 0.9)
    for q in np.linspace(0, 1000, 7):
        assert torch.equal(ordered.value_all(float(q)), shuffled.value_all(float(q)))


def test_window_rules_and_all_pixel_map() -> None:
    rng = np.random.default_rng(3)
    streams = random_streams(rng, 2, 500)
    ev = DecayedEvents.from_streams(streams, H, W, 0.93)
    pix = torch.arange(ev.n_pixels)
    for t0, t1 in [(0.0, 1000.0), (120.0, 480.0), (480.0, 120.0), (0.0, 0.0)]:
        e = ev.window(pix, t0, t1)
        assert torch.equal(e, ev.value(pix, t1) - ev.value(pix, t0))
        assert torch.equal(ev.window_all(t0, t1).reshape(-1), e)
        assert torch.equal(ev.window(pix, t1, t0), -e)  # negated window (E_ref rule)
    # t0 == t1 is exactly zero at every pixel and time, including event times.
    t = torch.tensor(rng.integers(0, 51, ev.n_pixels) * 20.0)
    assert torch.count_nonzero(ev.window(pix, t, t)) == 0
    # With b = 1, E(0, 1000) is the plain polarity sum per pixel.
    ev1 = DecayedEvents.from_streams(streams, H, W, 1.0)
    ref = np.zeros((2, H, W))
    for v, s in enumerate(streams):
        np.add.at(ref[v], (s.y, s.x), s.p)
    assert np.array_equal(ev1.window_all(-1.0, 1000.0).numpy(), ref)
    assert int(ev1.event_counts().sum()) == 1000


@pytest.mark.parametrize("decay", [0.8, 1.0])
def test_all_pixel_window_equals_the_lookup_on_every_pixel_to_the_bit(decay: float) -> None:
    """``window_all`` reads each pixel's first and last event of the window off the time
    order instead of searching; on windows ending on event times, with shared timestamps,
    in both orders, it equals :meth:`window` on every pixel to the bit, and it is 0
    wherever no event lies between the two times."""
    rng = np.random.default_rng(8)
    streams = []
    for _ in range(3):
        n = 400
        t = rng.integers(0, 60, n) * 10.0                      # many events share a time
        streams.append(EventStream(rng.integers(0, W, n).astype(np.int16),
                                   rng.integers(0, H, n).astype(np.int16), t,
                                   rng.choice(np.array([-1, 1], np.int8), n)))
    ev = DecayedEvents.from_streams(streams, H, W, decay)
    pix = torch.arange(ev.n_pixels)
    for t0, t1 in [(100.0, 300.0), (300.0, 100.0), (95.0, 305.0), (0.0, 590.0), (200.0, 200.0),
                   (-5.0, 0.0), (590.0, 2000.0), *rng.uniform(-10, 600, (40, 2)).tolist()]:
        e = ev.window_all(t0, t1).reshape(-1)
        assert torch.equal(e, ev.window(pix, t0, t1))
        quiet = torch.ones(ev.n_pixels, dtype=torch.bool)
        for v, s in enumerate(streams):
            m = (s.t > min(t0, t1)) & (s.t <= max(t0, t1))
            quiet[v * H * W + torch.from_numpy(s.y[m] * W + s.x[m].astype(np.int64))] = False
        assert torch.count_nonzero(e[quiet]) == 0


def test_zero_events_everywhere_and_in_one_view() -> None:
    ev = DecayedEvents.from_streams([EventStream.empty(), EventStream.empty()], H, W, 0.93)
    assert ev.n_events == 0
    assert torch.count_nonzero(ev.window_all(0.0, 1000.0)) == 0
    with pytest.raises(InputError, match="NaN"):           # a NaN time is an error even here
        ev.window_all(float("nan"), 1000.0)
    rng = np.random.default_rng(4)
    streams = [EventStream.empty()] + random_streams(rng, 1, 50)
    ev = DecayedEvents.from_streams(streams, H, W, 1.0)
    m = ev.window_all(-1.0, 1000.0)
    assert torch.count_nonzero(m[0]) == 0 and float(m[1].abs().sum()) > 0


def _one_pixel_stream(n: int, seed: int) -> EventStream:
    rng = np.random.default_rng(seed)
    t = np.sort(rng.uniform(0, 1000, n))
    t[0], t[-1] = 0.0, 1000.0
    z = np.zeros(n, np.int16)
    return EventStream(z, z, t, rng.choice(np.array([-1, 1], np.int8), n, p=[0.3, 0.7]))


def _check_one_pixel(n: int) -> None:
    s = _one_pixel_stream(n, 5)
    pix = torch.zeros(5, dtype=torch.int64)
    idx = np.array([0, 1, n // 3, n - 2, n - 1])
    tq = torch.from_numpy(s.t[idx])
    for decay, atol in [(1.0, 0.0), (0.93, 1e-11)]:
        ev = DecayedEvents.from_streams([s], 1, 1, decay)
        ref = lfilter([1.0], [1.0, -decay], s.p.astype(np.float64))  # V_k = b V_{k-1} + p_k
        assert np.all(np.isfinite(ev.values.numpy()))
        np.testing.assert_allclose(ev.values.numpy(), ref, rtol=0, atol=atol)
        np.testing.assert_allclose(ev.value(pix, tq).numpy(), ref[idx], rtol=0, atol=atol)
        assert float(ev.window(pix[:1], 0.0, 0.0)) == 0.0
    # Without decay the drift of q+ = 0.7 reaches 0.4·n (finite, exact integer).
    ev = DecayedEvents.from_streams([s], 1, 1, 1.0)
    assert float(ev.value(pix[:1], 1000.0)) == float(s.p.astype(np.int64).sum())


def test_one_pixel_1e6_events() -> None:
    _check_one_pixel(10**6)


@pytest.mark.slow
def test_one_pixel_1e7_events() -> None:
    _check_one_pixel(10**7)


def test_decayed_prefix_long_segment_no_overflow() -> None:
    # b^(-k) would overflow float64 after ~10^4 events at b = 0.93; the scan never forms it.
    n = 200_000
    v = decayed_prefix(torch.ones(n, dtype=torch.int8),
                       torch.tensor([True] + [False] * (n - 1)), 0.93)
    assert torch.isfinite(v).all()
    assert abs(float(v[-1]) - 1 / (1 - 0.93)) < 1e-12


def test_bad_input_raises_input_error() -> None:
    good = EventStream(np.array([0], np.int16), np.array([0], np.int16), np.array([1.0]),
                       np.array([1], np.int8))
    bad_x = EventStream(np.array([W], np.int16), good.y, good.t, good.p)
    bad_p = EventStream(good.x, good.y, good.t, np.array([2], np.int8))
    bad_t = EventStream(good.x, good.y, np.array([np.nan]), good.p)
    for s, field in [(bad_x, "x"), (bad_p, "p"), (bad_t, "t")]:
        with pytest.raises(InputError, match=f"events view 1: {field}:"):
            DecayedEvents.from_streams([good, s], H, W, 1.0)
    with pytest.raises(InputError, match="decay"):
        DecayedEvents.from_streams([good], H, W, 1.5)
    ev = DecayedEvents.from_streams([good], H, W, 1.0)
    with pytest.raises(InputError, match="pix"):
        ev.value(torch.tensor([H * W]), 0.0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu() -> None:
    rng = np.random.default_rng(6)
    streams = random_streams(rng, 2, 2000)
    cpu = DecayedEvents.from_streams(streams, H, W, 0.93)
    gpu = DecayedEvents.from_streams(streams, H, W, 0.93, device="cuda")
    np.testing.assert_allclose(gpu.window_all(100.0, 900.0).cpu().numpy(),
                               cpu.window_all(100.0, 900.0).numpy(), atol=1e-12)


def test_bayer_mask_pattern() -> None:
    m = bayer_mask(4, 6)
    assert m.shape == (4, 6, 3) and torch.all(m.sum(-1) == 1)
    ch = m.argmax(-1)
    assert ch[0::2, 0::2].eq(0).all() and ch[1::2, 1::2].eq(2).all()
    assert ch[0::2, 1::2].eq(1).all() and ch[1::2, 0::2].eq(1).all()
    assert float(m[..., 1].mean()) == 0.5  # half the pixels are green
    rows, cols = torch.tensor([3, 2, 7]), torch.tensor([5, 4, 2])
    assert torch.equal(bayer_mask_at(rows, cols), m[rows % 4, cols % 6])
