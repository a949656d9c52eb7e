"""Decayed prefix accumulation of events ("fast event accumulation", docs/method.md).

Per pixel, with its events in time order (ties at equal timestamps keep the order of
the stream),

.. math::
   V_0 = 0, \\qquad V_k = b\\,V_{k-1} + p_k
   \\;\\Longleftrightarrow\\; V_k = \\sum_{j \\le k} b^{\\,k-j} p_j ,

with the decay ``b`` applied per *event*, not per unit of time (``b = 1``: the plain
polarity sum). ``V(t)`` is the value after the last event with ``t_k ≤ t`` (0 before
the first event) and the accumulated signal of a window is

.. math:: E(t_0, t_1) = V(t_1) - V(t_0).

``V`` is computed once for every event at load time; a window query is then two binary
searches per pixel, never a re-summation.

Storage (CSR over the global pixel index ``pix = view·H·W + row·W + col``): the events
are sorted by the composite integer key ``pix·(U+1) + r`` where ``r ∈ [1, U]`` is the
rank of the event's timestamp among the ``U`` distinct timestamps. Ranks are exact
integers (no float64 composite keys, which would lose the low bits of ``t``), so a query
``(pix, t)`` becomes ``pix·(U+1) + #{distinct times ≤ t}`` and one
``torch.searchsorted(..., right=True)`` finds the last event with ``t_k ≤ t`` exactly,
events at ``t_k == t`` included.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from eventrecon.common.errors import InputError
from eventrecon.events.stream import EventStream

__all__ = ["DecayedEvents", "decayed_prefix"]

log = logging.getLogger(__name__)

_KEY_LIMIT = 2**62  # composite keys stay far below int64 overflow


def decayed_prefix(p: Tensor, seg_start: Tensor, decay: float) -> Tensor:
    """Segmented linear recurrence ``V_k = a_k V_{k−1} + p_k`` with ``a_k = 0`` at
    segment starts and ``a_k = b`` elsewhere, for all ``k`` at once.

    ``b = 1`` is an exact integer cumulative sum per segment. ``0 ≤ b < 1`` uses a
    Hillis–Steele doubling scan over pairs ``(A, X)`` with the associative composition
    ``(A₁, X₁) ∘ (A₂, X₂) = (A₁A₂, A₂X₁ + X₂)``: only products of factors ``≤ 1`` appear
    (no ``b^{−k}``, hence no overflow however long a pixel's history), ``⌈log₂ L⌉``
    vectorised passes for a longest segment of ``L`` events, stopping early once every
    product ``A`` has underflowed to 0. The rounding error is a few ``log₂ L`` ulps of
    ``1/(1−b)``.

    Args:
        p: ``[n]`` polarities (any real dtype; integers for the exact ``b = 1`` path).
        seg_start: ``[n]`` bool, True at the first event of each pixel
            (``seg_start[0]`` must be True when ``n > 0``).
        decay: ``b ∈ [0, 1]``.

    Returns:
        ``[n]`` float64 values ``V_k``.

    >>> decayed_prefix(torch.tensor([1, 1, -1, 1]), torch.tensor([True, False, False, True]), 0.5)
    tensor([ 1.0000,  1.5000, -0.2500,  1.0000], dtype=torch.float64)
    """
    n = p.shape[0]
    if n == 0:
        return torch.zeros(0, dtype=torch.float64, device=p.device)
    if decay == 1.0:
        cs = torch.cumsum(p.to(torch.int64), 0)
        seg_id = torch.cumsum(seg_start.to(torch.int64), 0) - 1
        before = (cs - p.to(torch.int64))[seg_start]  # sum of all earlier segments
        return (cs - before[seg_id]).to(torch.float64)
    x = p.to(torch.float64).clone()
    a = torch.full((n,), float(decay), dtype=torch.float64, device=p.device)
    a[seg_start] = 0.0
    d = 1
    while d < n:
        x[d:] = x[d:] + a[d:] * x[:-d]  # RHS is materialised before the write
        a[d:] = a[d:] * a[:-d]
        d *= 2
        if d < n and not bool(a[d:].any()):
            break  # all remaining products underflowed to 0: nothing left to add
    return x


class DecayedEvents:
    """Per-pixel decayed prefix values of all views, queryable at any time.

    Build with :meth:`from_streams`. Attributes (all on one device):

    - ``keys [n]`` int64 sorted composite keys ``pix·(U+1) + rank(t)``;
    - ``values [n]`` float64 ``V`` after each event (same order);
    - ``times [U]`` float64 distinct event timestamps, ascending;
    - ``offsets [V·H·W + 1]`` int64 CSR row pointers: pixel ``pix`` owns events
      ``offsets[pix]:offsets[pix+1]``.

    Query times are in the units of the streams (time units, float64; a float32 query
    is promoted, but its rounding has already happened).

    >>> s = EventStream(np.array([0, 0], np.int16), np.array([0, 0], np.int16),
    ...                 np.array([1.0, 2.0]), np.array([1, 1], np.int8))
    >>> ev = DecayedEvents.from_streams([s], height=1, width=2, decay=0.5)
    >>> ev.value(torch.tensor([0, 0, 0, 1]), torch.tensor([0.5, 1.0, 2.0, 2.0]))
    tensor([0.0000, 1.0000, 1.5000, 0.0000], dtype=torch.float64)
    """

    def __init__(self, keys: Tensor, values: Tensor, times: Tensor, offsets: Tensor,
                 n_views: int, height: int, width: int, decay: float) -> None:
        self.keys = keys
        self.values = values
        self.times = times
        self.offsets = offsets
        self.n_views = n_views
        self.height = height
        self.width = width
        self.decay = float(decay)

    # ------------------------------------------------------------------ build
    @classmethod
    def from_streams(cls, streams: Sequence[EventStream], height: int, width: int,
                     decay: float = 1.0,
                     device: str | torch.device | None = None) -> DecayedEvents:
        """Build from one :class:`EventStream` per view (vectorised; a loop over views).

        Args:
            streams: ``V`` streams; ``x ∈ [0, W)``, ``y ∈ [0, H)``, finite ``t``,
                ``p ∈ {−1, +1}``. Events need not be sorted; equal timestamps of one
                pixel keep their stream order.
            height, width: sensor size ``H, W``.
            decay: ``b ∈ [0, 1]``.
            device: where the buffers live (default CPU).

        Raises:
            InputError: on out-of-range coordinates, polarities, non-finite times or
                a decay outside [0, 1].
        """
        if not 0.0 <= float(decay) <= 1.0:
            raise InputError("events", "decay", "b in [0, 1]", decay)
        if height < 1 or width < 1:
            raise InputError("events", "height/width", "positive sizes", f"{height}x{width}")
        device = torch.device(device) if device is not None else torch.device("cpu")
        hw = height * width
        pix_parts, t_parts, p_parts = [], [], []
        for v, s in enumerate(streams):
            _validate_stream(s, v, height, width)
            x = torch.from_numpy(np.asarray(s.x, dtype=np.int64))
            y = torch.from_numpy(np.asarray(s.y, dtype=np.int64))
            pix_parts.append((v * hw + y * width + x).to(device))
            t_parts.append(torch.from_numpy(np.asarray(s.t, dtype=np.float64)).to(device))
            p_parts.append(torch.from_numpy(np.asarray(s.p, dtype=np.int8)).to(device))
        n_pix = len(streams) * hw
        if n_pix == 0:
            raise InputError("events", "streams", "at least one view", 0)
        pix = torch.cat(pix_parts)
        t = torch.cat(t_parts)
        p = torch.cat(p_parts)
        times, rank = torch.unique(t, sorted=True, return_inverse=True)
        stride = times.shape[0] + 1
        if n_pix * stride >= _KEY_LIMIT:
            raise InputError("events", "size", "views·H·W·(distinct times+1) < 2^62",
                             n_pix * stride)
        keys, order = torch.sort(pix * stride + rank + 1, stable=True)
        p = p[order]
        pix = pix[order]
        seg_start = torch.ones_like(pix, dtype=torch.bool)
        seg_start[1:] = pix[1:] != pix[:-1]
        values = decayed_prefix(p, seg_start, decay)
        offsets = torch.zeros(n_pix + 1, dtype=torch.int64, device=device)
        offsets[1:] = torch.cumsum(torch.bincount(pix, minlength=n_pix), 0)
        log.debug("DecayedEvents: %d events, %d views, %d distinct times, b=%g",
                  keys.shape[0], len(streams), times.shape[0], decay)
        return cls(keys, values, times, offsets, len(streams), height, width, decay)

    def to(self, device: str | torch.device) -> DecayedEvents:
        """A copy with every buffer on ``device``."""
        return DecayedEvents(self.keys.to(device), self.values.to(device),
                             self.times.to(device), self.offsets.to(device),
                             self.n_views, self.height, self.width, self.decay)

    @property
    def device(self) -> torch.device:
        return self.keys.device

    @property
    def n_events(self) -> int:
        return int(self.keys.shape[0])

    @property
    def n_pixels(self) -> int:
        return self.n_views * self.height * self.width

    def __repr__(self) -> str:
        return (f"DecayedEvents(views={self.n_views}, H={self.height}, W={self.width}, "
                f"events={self.n_events}, decay={self.decay}, device={self.device})")

    # ---------------------------------------------------------------- queries
    def value(self, pix: Tensor, t: Tensor | float) -> Tensor:
        """``V(t)`` of the given pixels: the value after their last event with ``t_k ≤ t``.

        Args:
            pix: ``[N]`` int64 global pixel indices ``view·H·W + row·W + col``.
            t: ``[N]`` (or scalar, broadcast) query times in time units.

        Returns:
            ``[N]`` float64; 0 for pixels with no event at or before ``t``.
        """
        pix = self._check_pix(pix)
        return self._lookup(pix, self._rank(t, pix.shape))

    def window(self, pix: Tensor, t0: Tensor | float, t1: Tensor | float) -> Tensor:
        """``E(t0, t1) = V(t1) − V(t0)`` of the given pixels (``[N]`` float64).

        With ``t0 > t1`` this is the negated window ``−E(t1, t0)``; in particular the
        reference signal of docs/method.md, ``E(t_ref, t1)`` negated when ``t_ref > t1``, is
        ``window(pix, t_ref, t1)`` for both orderings. ``t0 == t1`` gives exactly 0.
        """
        pix = self._check_pix(pix)
        r0, r1 = self._rank(t0, pix.shape), self._rank(t1, pix.shape)
        both = self._lookup(torch.cat([pix, pix]), torch.cat([r1, r0]))
        return both[: pix.shape[0]] - both[pix.shape[0]:]

    def value_all(self, t: float | Tensor) -> Tensor:
        """``V(t)`` of every pixel of every view: ``[V, H, W]`` float64."""
        pix = torch.arange(self.n_pixels, device=self.device)
        return self.value(pix, t).reshape(self.n_views, self.height, self.width)

    def window_all(self, t0: float, t1: float) -> Tensor:
        """``E(t0, t1)`` of every pixel of every view: ``[V, H, W]`` float64.

        Used each iteration to find the pixels with events in the window. Only a pixel
        with an event between the two times can have ``E ≠ 0``, and its events there are
        one run of its CSR row: with ``lo, hi`` their first and last position,
        ``V(max(t0, t1)) = values[hi]`` and ``V(min(t0, t1)) = values[lo − 1]`` (0 when
        ``lo`` starts the row). The events in time order make the window's events one
        slice (:attr:`_time_order`), whose positions give ``lo, hi`` per pixel by a
        scatter of their minimum and maximum: no search. The same values as
        :meth:`window` on every pixel, to the bit.
        """
        r0, r1 = sorted(int(self._rank(t, torch.Size([1]))[0]) for t in (t0, t1))
        out = torch.zeros(self.n_pixels, dtype=torch.float64, device=self.device)
        if self.n_events:
            ranks, pixels, positions = self._time_order
            bounds = torch.tensor([r0, r1], dtype=ranks.dtype, device=self.device)
            a, b = torch.searchsorted(ranks, bounds, right=True).tolist()
            pix, pos = pixels[a:b].long(), positions[a:b].long()
            hi = torch.full_like(out, -1, dtype=torch.int64).scatter_reduce_(0, pix, pos, "amax")
            lo = torch.full_like(hi, self.n_events).scatter_reduce_(0, pix, pos, "amin")
            touched = (hi >= 0).nonzero().squeeze(1)
            lo, hi = lo[touched], hi[touched]
            later = self.values[hi]
            earlier = torch.where(lo > self.offsets[touched], self.values[(lo - 1).clamp_min(0)],
                                  0.0)
            out[touched] = later - earlier if t0 <= t1 else earlier - later
        return out.reshape(self.n_views, self.height, self.width)

    @functools.cached_property
    def _time_order(self) -> tuple[Tensor, Tensor, Tensor]:
        """The events in time order: ``rank + 1`` (the ``r`` of :meth:`_lookup` from which
        an event counts) ascending, each event's pixel and its position in :attr:`keys`
        (``[n]`` each; int32 where all fit, 12 bytes per event kept for the object's
        life, else int64)."""
        stride = self.times.shape[0] + 1
        small = max(stride, self.n_pixels, self.n_events) < 2**31
        ranks, order = torch.sort(self.keys % stride, stable=True)
        pixels = self.keys[order] // stride
        return (ranks.int(), pixels.int(), order.int()) if small else (ranks, pixels, order)

    def _check_pix(self, pix: Tensor) -> Tensor:
        pix = pix.to(device=self.device, dtype=torch.int64)
        if pix.numel() and (int(pix.min()) < 0 or int(pix.max()) >= self.n_pixels):
            raise InputError("DecayedEvents", "pix", f"indices in [0, {self.n_pixels})",
                             f"range [{int(pix.min())}, {int(pix.max())}]")
        return pix

    def _rank(self, t: Tensor | float, shape: torch.Size) -> Tensor:
        """``#{distinct event times ≤ t}`` broadcast to ``shape`` (int64)."""
        t = torch.as_tensor(t, dtype=torch.float64, device=self.device)
        if bool(torch.isnan(t).any()):
            raise InputError("DecayedEvents", "t", "non-NaN query times", "NaN")
        rank = torch.searchsorted(self.times, t.reshape(-1), right=True)
        return rank.reshape(t.shape).expand(shape)

    def _lookup(self, pix: Tensor, rank: Tensor) -> Tensor:
        """``V`` after the last event of ``pix`` with time rank ``≤ rank`` (0 if none): the
        last key ``≤ pix·(U+1) + rank`` by one ``searchsorted`` over all keys, kept where
        it lies in the pixel's own row (``≥ offsets[pix]``)."""
        if self.n_events == 0:
            return torch.zeros(pix.shape, dtype=torch.float64, device=self.device)
        query = pix * (self.times.shape[0] + 1) + rank
        idx = torch.searchsorted(self.keys, query, right=True) - 1
        found = idx >= self.offsets[pix]
        return torch.where(found, self.values[idx.clamp_min(0)], 0.0)

    def event_counts(self) -> Tensor:
        """Number of events per pixel: ``[V, H, W]`` int64."""
        return (self.offsets[1:] - self.offsets[:-1]).reshape(
            self.n_views, self.height, self.width)


def _validate_stream(s: EventStream, view: int, height: int, width: int) -> None:
    """Raise :class:`InputError` for a malformed stream of view ``view``."""
    where = f"events view {view}"
    n = len(s.t)
    for name in ("x", "y", "p"):
        arr = np.asarray(getattr(s, name))
        if arr.shape != (n,):
            raise InputError(where, name, f"shape ({n},) like t", arr.shape)
        if n and not np.issubdtype(arr.dtype, np.integer):
            if not np.all(np.mod(arr, 1) == 0):
                raise InputError(where, name, "integer values", arr.dtype)
    if n == 0:
        return
    x, y, p = np.asarray(s.x), np.asarray(s.y), np.asarray(s.p)
    if x.min() < 0 or x.max() >= width:
        raise InputError(where, "x", f"0 <= x < {width}", f"range [{x.min()}, {x.max()}]")
    if y.min() < 0 or y.max() >= height:
        raise InputError(where, "y", f"0 <= y < {height}", f"range [{y.min()}, {y.max()}]")
    if not np.all((p == 1) | (p == -1)):
        raise InputError(where, "p", "values in {-1, +1}", np.unique(p)[:5].tolist())
    if not np.all(np.isfinite(np.asarray(s.t, dtype=np.float64))):
        raise InputError(where, "t", "finite times", "NaN or inf")
