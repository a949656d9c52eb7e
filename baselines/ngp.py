"""Instant-NGP style 4D multiresolution hash grid over (x, y, z, t), pure PyTorch.

Level ``l`` has resolution ``R_l = floor(base * scale^l)``; axis ``k`` of it has
``R_{l,k} = floor(R_l · a_k)`` cells, vertices ``i / R_{l,k}``, ``i = 0..R_{l,k}``, over
``u_k in [0, 1]`` (``u`` is clamped to the box). A vertex ``v`` indexes the level's table
of ``T_l`` entries by

- dense indexing ``v_0 + (R_0+1) v_1 + (R_0+1)(R_1+1) v_2 + …`` when
  ``prod_k (R_{l,k}+1) <= T`` (``T_l`` = that product), otherwise
- spatial hashing ``(v_0 pi_0 XOR v_1 pi_1 XOR v_2 pi_2 XOR v_3 pi_3) mod T`` with
  ``pi = (1, 2654435761, 805459861, 3674653429)``, in int64 (products < 2^43: no
  overflow), masked by ``T - 1`` (``T = 2^log2_table_size``) per axis before the XOR
  (the low bits of a XOR are the XOR of the low bits), then combined in int32.

The level's feature is the quadrilinear interpolation over the 16 corners,
``sum_c prod_k w_k(c) F_l[idx(c)]`` with ``w_k = u_k R_{l,k} - i_k`` or its complement.
All levels share one flat table with per-level offsets; the 16 corners and all levels
of one kind (dense / hashed) are computed at once, then every level is gathered by one
``embedding_bag`` (weighted sum of 16 rows), whose autograd backward scatters into the
table. ``implementation`` (:mod:`eventrecon.kernels`) chooses between that reference and
the compiled CPU loops of :mod:`eventrecon.kernels.hash_grid` (the same values to
rounding). Gradients flow to the table and the MLPs, not to the input coordinates (no
loss of the method needs them).

The field (:class:`NGPField`) feeds the grid as the authors' code does: their
tiny-cuda-nn grid expects coordinates in ``[0, 1]`` but receives the raw ``x, y, z in
[-1, 1]`` and ``t in [0, 1]`` (the rescale in their ``TCNNNet`` indexes rows, not
columns), so space is resolved with twice the configured cells per unit: here
``u = ((x, y, z) + 1) / 2, t`` with axis factors ``a = (2, 2, 2, 1)``. Decoder:
:class:`~baselines.heads.NGPDecoder` (bias-free, as tiny-cuda-nn's). Schedule: the
clipping cylinder's density mask grows from 0 to its full radius over the first
``anneal_steps`` steps (10⁴ in the paper).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from baselines.heads import NGPDecoder
from baselines.schedules import CylinderAnneal
from eventrecon.common.errors import InputError
from eventrecon.fields.base import Field
from eventrecon.kernels import hash_grid, resolve, use_kernel

PRIMES: tuple[int, ...] = (1, 2654435761, 805459861, 3674653429)


class HashEncoding(nn.Module):
    """Multiresolution hash encoding of ``u [N, D]`` in ``[0, 1]^D`` -> ``[N, L * F]``.

    Args:
        n_dims: input dimension ``D`` (4 for x, y, z, t).
        n_levels: ``L``; n_features: ``F`` per level.
        log2_table_size: ``T = 2^log2_table_size`` entries per hashed level.
        base_resolution, per_level_scale: ``R_l = floor(base * scale^l)``.
        init_scale: table initialised uniform in ``[-init_scale, init_scale]``.
        seed: initialisation seed.
        axis_scale: factors ``a_k`` of the cells per axis (default all 1).
        implementation: ``"auto"``, ``"torch"`` or ``"numba"`` (:mod:`eventrecon.kernels`).

    >>> enc = HashEncoding(n_levels=2, log2_table_size=9, base_resolution=2)
    >>> enc.resolutions, enc.dense, enc(torch.rand(3, 4)).shape
    ([2, 4], [True, False], torch.Size([3, 4]))
    """

    def __init__(self, n_dims: int = 4, n_levels: int = 8, n_features: int = 2,
                 log2_table_size: int = 19, base_resolution: int = 8,
                 per_level_scale: float = 2.0, init_scale: float = 1e-4, seed: int = 0,
                 axis_scale: Sequence[float] | None = None, implementation: str = "auto"):
        super().__init__()
        self.implementation = resolve(implementation)
        if not (1 <= n_dims <= len(PRIMES) and n_levels >= 1 and 1 <= log2_table_size <= 30
                and per_level_scale >= 1.0 and base_resolution >= 1):
            raise InputError("conf/model", "hash grid", "1..4 dims, >= 1 level, log2_table_size "
                             "in 1..30, per_level_scale >= 1, base_resolution >= 1",
                             (n_dims, n_levels, log2_table_size, per_level_scale, base_resolution))
        self.n_dims, self.n_levels, self.n_features = n_dims, n_levels, n_features
        self.table_size = 2**log2_table_size
        self.resolutions = [int(math.floor(base_resolution * per_level_scale**lvl))
                            for lvl in range(n_levels)]
        scale = [1.0] * n_dims if axis_scale is None else [float(a) for a in axis_scale]
        if len(scale) != n_dims or min(scale) <= 0:
            raise InputError("conf/model", "axis_scale", f"{n_dims} positive factors", scale)
        self.axis_resolutions = [tuple(max(1, int(math.floor(r * a + 1e-9))) for a in scale)
                                 for r in self.resolutions]
        self.dense = [math.prod(k + 1 for k in res) <= self.table_size
                      for res in self.axis_resolutions]
        sizes = [math.prod(k + 1 for k in res) if d else self.table_size
                 for res, d in zip(self.axis_resolutions, self.dense)]
        self.offsets = [0, *itertools.accumulate(sizes)]
        if self.offsets[-1] >= 2**31:
            raise InputError("conf/model", "hash grid", "fewer than 2^31 table rows in all",
                             self.offsets[-1])
        gen = torch.Generator().manual_seed(seed)
        table = (torch.rand(self.offsets[-1], n_features, generator=gen) * 2 - 1) * init_scale
        self.table = nn.Parameter(table)
        # per-level constants [L, D]: cells per axis, and each axis' index multiplier, the
        # dense strides prod_{j<k} (R_j+1) or the hash primes
        res = torch.tensor(self.axis_resolutions, dtype=torch.int64).reshape(n_levels, n_dims)
        strides = torch.cat([torch.ones(n_levels, 1, dtype=torch.int64),
                             (res[:, :-1] + 1).cumprod(1)], dim=1)
        dense = torch.tensor(self.dense)
        mult = torch.where(dense[:, None], strides,
                           torch.tensor(PRIMES[:n_dims], dtype=torch.int64))
        self.plan = hash_grid.Plan(res.numpy(), mult.numpy(), ~dense.numpy(), self.offsets,
                                  self.table_size)
        # the same per kind, for the vectorised paths (buffers follow .to(device))
        for kind, sel in (("dense", True), ("hash", False)):
            lv = (dense == sel).nonzero().squeeze(1)
            self.register_buffer(f"{kind}_levels", lv, False)
            self.register_buffer(f"{kind}_res", res[lv], persistent=False)
            self.register_buffer(f"{kind}_mult", mult[lv], persistent=False)
            self.register_buffer(f"{kind}_offset", torch.tensor(
                [self.offsets[i] for i in lv.tolist()], dtype=torch.int32), persistent=False)

    def corners(self, u: Tensor, kind: str) -> tuple[Tensor, Tensor]:
        """Global table rows and weights of the 16 corners at the ``dense`` or ``hash`` levels.

        Args:
            u: ``[N, D]`` in ``[0, 1]`` (clamped).
            kind: ``"dense"`` or ``"hash"``.

        Returns:
            ``(idx [2^D, N, L_k] int32 in [0, total rows), w [2^D, N, L_k])``, corner-major;
            corner ``c`` has offset bit ``b_k = (c >> k) & 1`` along axis ``k``.

        Corner-major, every doubling of the corners is a broadcast over whole contiguous
        ``[N, L_k]`` planes.
        """
        res = getattr(self, f"{kind}_res").t()[:, None, :]                # [D, 1, Lk]
        mult = getattr(self, f"{kind}_mult").t()[:, None, :]
        pos = u.clamp(0.0, 1.0).t()[:, :, None] * res.to(u.dtype)        # [D, N, Lk]
        i0 = torch.minimum(pos.floor().long(), res - 1)
        frac = pos - i0.to(pos.dtype)
        v0 = i0 * mult
        v = torch.stack([v0, v0 + mult], dim=1)                           # [D, 2, N, Lk] int64
        if kind == "hash":  # low bits of a XOR are the XOR of low bits: mask before combining
            v = v & (self.table_size - 1)
        v = v.int()  # < T <= 2^30 per axis term (dense: sum < prod (R_k+1) <= T): int32 exact
        w = torch.stack([1 - frac, frac], dim=1)
        idx, wt = v[0], w[0]                                              # [2, N, Lk]
        for k in range(1, self.n_dims):  # corner c = b_k 2^k + (lower bits)
            a, b = v[k][:, None], idx[None]
            idx = (a + b if kind == "dense" else a ^ b).flatten(0, 1)    # [2^(k+1), N, Lk]
            wt = (w[k][:, None] * wt[None]).flatten(0, 1)
        return idx + getattr(self, f"{kind}_offset")[None, None, :], wt

    def all_corners(self, u: Tensor) -> tuple[Tensor, Tensor]:
        """Table rows and weights of the 16 corners at every level, bag-major for
        ``embedding_bag``: ``(idx [N, L, 2^D] int32, w [N, L, 2^D])``, level ``l`` at
        ``[:, l]`` (the dense levels are the coarse ones: they come first). Both kinds go
        to one gather, so a field call's backward writes one table-sized gradient, not
        one per kind."""
        n, c = u.shape[0], 2 ** self.n_dims
        idx = torch.empty(n, self.n_levels, c, dtype=torch.int32, device=u.device)
        w = torch.empty(n, self.n_levels, c, dtype=u.dtype, device=u.device)
        start = 0
        for kind in ("dense", "hash"):
            count = getattr(self, f"{kind}_levels").numel()
            if count:
                idx_k, w_k = self.corners(u, kind)
                idx[:, start:start + count] = idx_k.permute(1, 2, 0)
                w[:, start:start + count] = w_k.permute(1, 2, 0)
                start += count
        return idx, w

    def forward(self, u: Tensor) -> Tensor:
        """``u [N, D] -> [N, L * F]`` (level-major: level ``l`` at ``[:, l F:(l + 1) F]``):
        ``e_l = sum_c w_c F[idx_c]`` over the 16 corners of :meth:`all_corners`, one
        ``embedding_bag``; or the compiled loops where ``implementation`` chooses them."""
        u = u.detach().float()         # the table's gradient only (module docstring)
        if use_kernel(self.implementation, hash_grid.unsupported(self.table, u, self.plan)):
            return hash_grid.encode(self.table, u, self.plan)
        idx, w = self.all_corners(u)
        feat = F.embedding_bag(idx.flatten(0, 1), self.table, mode="sum",
                               per_sample_weights=w.flatten(0, 1).to(self.table.dtype))
        return feat.reshape(u.shape[0], self.n_levels * self.n_features)


def hash_encode_reference(enc: HashEncoding, u: Tensor) -> Tensor:
    """Slow, obviously-correct reference of :meth:`HashEncoding.forward`: Python loops over
    levels and corners, the index written out per corner. Same table, same output."""
    out = []
    uc = u.float().clamp(0.0, 1.0)
    for lvl, res in enumerate(enc.axis_resolutions):
        r = torch.tensor(res, dtype=uc.dtype)
        pos = uc * r
        i0 = torch.minimum(pos.floor().long(), r.long() - 1)
        frac = pos - i0
        acc = torch.zeros(u.shape[0], enc.n_features, dtype=enc.table.dtype)
        for corner in itertools.product((0, 1), repeat=enc.n_dims):
            vert = [i0[:, k] + b for k, b in enumerate(corner)]
            if enc.dense[lvl]:
                row = sum(vert[k] * math.prod(res[j] + 1 for j in range(k))
                          for k in range(enc.n_dims))
            else:
                row = torch.zeros_like(vert[0])
                for k in range(enc.n_dims):
                    row = row ^ (vert[k] * PRIMES[k])
                row = row % enc.table_size
            w = torch.ones_like(frac[:, 0])
            for k, b in enumerate(corner):
                w = w * (frac[:, k] if b else 1 - frac[:, k])
            acc = acc + w[:, None] * enc.table[enc.offsets[lvl] + row]
        out.append(acc)
    return torch.cat(out, dim=1)


class NGPField(Field):
    """NGP backbone: 4D hash encoding of ``(x, y, z, t)`` + :class:`NGPDecoder`.

    Args:
        n_levels, n_features, log2_table_size, base_resolution, per_level_scale,
            init_scale: see :class:`HashEncoding` (paper: 8, 2, 19, 8, 2.0, 1e-4).
        density_hidden, geo_features, colour_hidden, colour_layers: decoder sizes
            (paper: 16, 10, 64, 2).
        space_scale: cells per unit of space relative to time (2: the authors' raw
            ``[-1, 1]`` coordinates, module docstring; 1: space mapped to the grid's box).
        anneal_steps: the cylinder's density mask grows from 0 to 1 over these steps
            (0: none).
        implementation: the encoding's (:mod:`eventrecon.kernels`).
        seed: initialisation seed (table and MLPs).

    >>> f = NGPField(log2_table_size=12)
    >>> [s.shape for s in f(torch.zeros(2, 3), torch.zeros(2, 1))]
    [torch.Size([2]), torch.Size([2, 3])]
    """

    def __init__(self, n_levels: int = 8, n_features: int = 2, log2_table_size: int = 19,
                 base_resolution: int = 8, per_level_scale: float = 2.0,
                 init_scale: float = 1e-4, density_hidden: int = 16, geo_features: int = 10,
                 colour_hidden: int = 64, colour_layers: int = 2, space_scale: float = 2.0,
                 anneal_steps: int = 10000, implementation: str = "auto", seed: int = 0):
        super().__init__()
        self.encoding = HashEncoding(4, n_levels, n_features, log2_table_size,
                                     base_resolution, per_level_scale, init_scale, seed,
                                     axis_scale=(space_scale,) * 3 + (1.0,),
                                     implementation=implementation)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            self.decoder = NGPDecoder(n_levels * n_features, density_hidden, geo_features,
                                      colour_hidden, colour_layers)
        self.anneal_steps = int(anneal_steps)

    def forward(self, xyz: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        """``xyz [N, 3], t [N, 1] -> (sigma [N], rgb [N, 3])``."""
        return self.decoder(self.encoding(self._unit(xyz, t)))

    def density_only(self, xyz: Tensor, t: Tensor) -> Tensor:
        """``sigma [N]`` without the colour MLP: :meth:`forward`'s density, to the bit."""
        return self.decoder.density(self.encoding(self._unit(xyz, t)))

    @staticmethod
    def _unit(xyz: Tensor, t: Tensor) -> Tensor:
        """``[N, 4]`` encoder input ``((x + 1) / 2, t)``: the unit cube and time."""
        return torch.cat([(xyz + 1.0) * 0.5, t.reshape(-1, 1).to(xyz.dtype)], dim=-1)

    def callbacks(self) -> list[Any]:
        """The cylinder's density mask annealed over the first ``anneal_steps`` steps."""
        return [CylinderAnneal(self.anneal_steps)] if self.anneal_steps > 0 else []
