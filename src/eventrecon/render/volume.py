"""Volume rendering: alpha compositing and the two-level (coarse + fine) renderer.

Quadrature (per ray, samples ``s_i`` sorted in the clipping interval ``[near, far]``;
the authors' steps ``δ_i = s_{i+1} − s_i`` and ``δ_{K−1} = far − s_{K−1}``, see
:func:`eventrecon.render.samplers.step_sizes`):

.. math::
    \\tau_i = \\sigma_i \\delta_i,\\quad
    \\alpha_i = 1 - e^{-\\tau_i},\\quad
    T_i = \\exp\\Big(-\\sum_{j<i} \\tau_j\\Big),\\quad
    w_i = T_i \\alpha_i,

    \\hat C = \\sum_i w_i \\mathbf{c}_i + T_{last}\\,\\mathbf{c}_{bg},\\quad
    \\text{opacity} = 1 - T_{last},\\quad
    \\text{depth} = \\sum_i w_i s_i + T_{last}\\,\\text{far},

with :math:`T_{last} = e^{-\\sum_i \\tau_i}`. Depth puts the light that passes through at
the exit point ``far`` (finite, no division by the opacity). Transmittance is the
exponential of a cumulative sum (never a product of ``1 − α``, which loses all precision
for tiny steps), ``α`` uses ``expm1``, and ``τ`` is clamped to ``[0, 10^4]`` (beyond
that ``e^{-τ}`` is 0 in float32 anyway) so densities up to 10⁶ and steps down to 10⁻⁸ give
finite colours in [0, 1] and finite gradients. Compositing runs in float32 even under
autocast. The authors' product ``∏(1 − α_j + 10⁻⁶)`` carries a guard that lets ``T``
exceed 1 (an empty ray of 64 samples has opacity −6·10⁻⁵); the exponential of the sum needs
none, so it is left out: the one place where this quadrature differs from theirs.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from eventrecon.common.errors import InputError
from eventrecon.fields.base import Field
from eventrecon.render.clipping import INSIDE_TOL
from eventrecon.render.occupancy import OccupancyGrid, OccupancyUpdate
from eventrecon.render.queries import query_density, query_field
from eventrecon.render.renderer import Renderer
from eventrecon.render.samplers import TAU_MAX, pdf_bins, sample_pdf, step_sizes, stratified

if TYPE_CHECKING:
    from eventrecon.render.cameras import Cameras

__all__ = ["TAU_MAX", "render_weights", "composite", "VolumeRenderer"]


def render_weights(sigma: Tensor, delta: Tensor) -> tuple[Tensor, Tensor]:
    """Compositing weights ``w_i = T_i α_i`` and the final transmittance.

    Args:
        sigma: ``[N, K]`` densities (≥ 0).
        delta: ``[N, K]`` step sizes (≥ 0).

    Returns:
        ``(weights [N, K], T_last [N])`` float32, all in [0, 1].

    >>> w, T = render_weights(torch.tensor([[1.0, 1.0]]), torch.tensor([[0.5, 0.5]]))
    >>> torch.allclose(T, torch.exp(torch.tensor([-1.0])))
    True
    """
    tau = (sigma.float().clamp(min=0) * delta.float().clamp(min=0)).clamp(max=TAU_MAX)
    excl = torch.cat([torch.zeros_like(tau[:, :1]), tau[:, :-1].cumsum(dim=-1)], dim=-1)
    weights = torch.exp(-excl) * -torch.expm1(-tau)
    t_last = torch.exp(-tau.sum(dim=-1))
    return weights, t_last


def composite(
    sigma: Tensor, rgb: Tensor, s: Tensor, far: Tensor, bg: Tensor
) -> dict[str, Tensor]:
    """Composite samples over a background (maths in the module docstring).

    Args:
        sigma: ``[N, K]`` densities.
        rgb: ``[N, K, 3]`` linear colours in [0, 1].
        s: ``[N, K]`` sorted sample distances.
        far: ``[N]`` the clipping interval's far end (the last step reaches it).
        bg: ``[N, 3]`` background colour.

    Returns:
        dict with ``rgb [N, 3]`` (clamped to [0, 1]), ``opacity [N]``, ``depth [N]``,
        ``weights [N, K]``, ``s [N, K]`` (the last two for importance sampling/debugging).

    >>> out = composite(torch.tensor([[0.0]]), torch.ones(1, 1, 3), torch.tensor([[0.5]]),
    ...                 torch.tensor([1.0]), torch.full((1, 3), 0.25))
    >>> out["rgb"], out["opacity"], out["depth"]
    (tensor([[0.2500, 0.2500, 0.2500]]), tensor([0.]), tensor([1.]))
    """
    weights, t_last = render_weights(sigma, step_sizes(s, far))
    colour = (weights[..., None] * rgb.float()).sum(dim=-2) + t_last[:, None] * bg.float()
    depth = (weights * s.float()).sum(dim=-1) + t_last * far.float()
    return {"rgb": colour.clamp(0.0, 1.0), "opacity": 1.0 - t_last, "depth": depth,
            "weights": weights, "s": s}



class VolumeRenderer(Renderer):
    """Two-level volume renderer of a :class:`~eventrecon.fields.base.Field`, clipped to
    the cylinder ∩ unit sphere.

    One field serves both levels (supplementary Sec. 9). The coarse level takes
    ``n_coarse`` stratified samples in the clipping interval; the fine level adds
    ``n_fine`` importance samples drawn from the coarse weights and composites the sorted
    union. The field's outputs at the coarse samples are reused, not recomputed, in the
    fine level: the field is a deterministic function of ``(x, t)`` with the same
    parameters at both levels, so values and gradients are identical to evaluating the
    union afresh, with 192 field evaluations per ray instead of 256 at 64 + 128 samples.
    Rays that miss the clipping volume show the background; points outside get ``σ = 0``.

    Empty-space skipping (``skip="grid"``): a time-aware
    :class:`~eventrecon.render.occupancy.OccupancyGrid` (kept up to date from the field by
    :class:`~eventrecon.render.occupancy.OccupancyUpdate`, :meth:`callbacks`) says which
    samples can hold density; the others get ``σ = 0`` without reaching the field. The
    coarse samples are taken front to back in ``march_chunks`` groups, and a ray stops
    once its transmittance is below ``stop_transmittance`` at the start of a group
    (:meth:`_march`); fine samples beyond that point are not evaluated either.
    ``skip="none"`` evaluates every sample of a ray that hits the cylinder (the authors'
    renderer).

    ``clip_scale`` (in [0, 1]) multiplies the radius of the cylinder outside which density
    is zero; samples always span the full cylinder (the NGP baseline's annealing sets it
    through ``pl_module.renderer.clip_scale``).

    >>> from eventrecon.fields import NeRFField
    >>> renderer = VolumeRenderer(n_coarse=8, n_fine=8)
    >>> o, d = torch.tensor([[-2.0, -0.25, 0.0]]), torch.tensor([[1.0, 0.0, 0.0]])
    >>> levels = renderer.render_rays(NeRFField(depth=2, width=16), o, d, torch.zeros(1, 1),
    ...                               torch.ones(1, 3))
    >>> [tuple(level["rgb"].shape) for level in levels], tuple(levels[-1]["s"].shape)
    ([(1, 3), (1, 3)], (1, 16))

    Args:
        n_coarse: stratified samples per ray (≥ 2; ≥ 3 with a fine level, whose histogram
            has ``n_coarse − 2`` bins).
        n_fine: importance samples per ray (0: one level only).
        radius, y_min, y_max, clipping, chunk: see :class:`~eventrecon.render.renderer.Renderer`.
        clip_scale: initial radius factor of the density mask.
        skip: ``"none"`` or ``"grid"`` (empty-space skipping).
        occupancy: arguments of the :class:`~eventrecon.render.occupancy.OccupancyGrid`
            (``skip="grid"``).
        march_chunks, stop_transmittance: front-to-back groups of coarse samples and the
            transmittance below which a ray stops (``skip="grid"``).
        query_rows: most samples per field call without autograd (images, grid updates;
            0: no limit; the same values up to rounding, :mod:`eventrecon.render.queries`).
        query_buckets: row counts of field calls rounded up to this many sizes per doubling
            (:func:`~eventrecon.render.queries.padded_rows`; 0: exact; the same results).
    """

    def __init__(self, n_coarse: int = 64, n_fine: int = 128, radius: float = 0.5,
                 y_min: float = -0.75, y_max: float = 0.25, clip_scale: float = 1.0,
                 chunk: int = 8192, clipping: bool = True, skip: str = "none",
                 occupancy: dict[str, Any] | None = None, march_chunks: int = 4,
                 stop_transmittance: float = 1e-4, query_rows: int = 16384,
                 query_buckets: int = 8) -> None:
        super().__init__(radius, y_min, y_max, clipping, chunk)
        if n_fine < 0:
            raise InputError("renderer", "n_fine", "an integer >= 0", n_fine)
        if n_coarse < (3 if n_fine else 2):
            raise InputError("renderer", "n_coarse",
                             f"an integer >= {3 if n_fine else 2} (with n_fine = {n_fine})",
                             n_coarse)
        for name, value in (("query_rows", query_rows), ("query_buckets", query_buckets)):
            if value < 0:
                raise InputError("renderer", name, "an integer >= 0", value)
        if skip not in ("none", "grid"):
            raise InputError("config", "render.skip", "none or grid", skip)
        self.n_coarse, self.n_fine = int(n_coarse), int(n_fine)
        self.clip_scale = float(clip_scale)
        self.march_chunks = max(1, int(march_chunks))
        self.stop_transmittance = float(stop_transmittance)
        self.query_rows, self.query_buckets = int(query_rows), int(query_buckets)
        self.occupancy = (OccupancyGrid(*self.cylinder.box(), **dict(occupancy or {}))
                          if skip == "grid" else None)
        #: samples sent to the field since the last reset (a counter for logging: samples
        #: per ray is ``field_inputs / rays``; never part of any result)
        self.field_inputs = 0

    def extra_repr(self) -> str:
        return (f"n_coarse={self.n_coarse}, n_fine={self.n_fine}, cylinder={self.cylinder}, "
                f"clip_scale={self.clip_scale}, skip={self.occupancy is not None}")

    @property
    def skipping(self) -> bool:
        """Whether samples are skipped now (``skip="grid"`` and past its start step)."""
        return self.occupancy is not None and self.occupancy.active

    def callbacks(self, seed: int = 0) -> list[Any]:
        """The occupancy grid's updates (``skip="grid"``)."""
        return [OccupancyUpdate(seed)] if self.occupancy is not None else []

    def step_stats(self, n_samples: int) -> dict[str, float]:
        """``samples_per_ray`` (field evaluations per rendered ray of the last call) and
        ``clip_scale``."""
        return {"samples_per_ray": self.field_inputs / max(1, n_samples),
                "clip_scale": self.clip_scale}

    def masked_density(self, field: Field, x: Tensor, t: Tensor) -> Tensor:
        """``[N]`` density (``Field.density_only``) at ``x [N, 3]``, ``t [N, 1]``, zero
        outside the full cylinder (an annealed ``clip_scale`` masks samples at render time
        only), asked as images are: blocks of ``query_rows``, under :meth:`image_autocast`."""
        inside = self.cylinder.inside(x, 1.0, tol=INSIDE_TOL)
        with self.image_autocast(x.device):
            sigma = query_density(field, x, t, self.query_buckets, self.query_rows)
        return sigma.float() * inside

    def _query(self, field: Field, o: Tensor, d: Tensor, t: Tensor, s: Tensor,
               keep: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Field at ``o + s d`` (``[n, K]`` samples) at time ``t``; σ = 0 outside the
        cylinder. With ``keep`` (``[n, K]`` bool) only those reach the field (σ, rgb = 0)."""
        n, k = s.shape
        pts = o[:, None, :] + s[..., None] * d[:, None, :]
        inside = self.cylinder.inside(pts, self.clip_scale, tol=INSIDE_TOL)
        tt = t[:, None, :].expand(n, k, 1).reshape(n * k, 1)
        if keep is None:
            self.field_inputs += n * k
            sigma, rgb = query_field(field, pts.reshape(n * k, 3), tt, self.query_buckets,
                                     self.query_rows)
            return sigma.reshape(n, k) * inside, rgb.reshape(n, k, 3)
        idx = (keep & inside).reshape(-1).nonzero().squeeze(1)
        self.field_inputs += int(idx.numel())
        sig_k, rgb_k = query_field(field, pts.reshape(n * k, 3).index_select(0, idx),
                                   tt.index_select(0, idx), self.query_buckets, self.query_rows)
        sigma = pts.new_zeros(n * k, dtype=sig_k.dtype).index_copy(0, idx, sig_k)
        rgb = pts.new_zeros(n * k, 3, dtype=rgb_k.dtype).index_copy(0, idx, rgb_k)
        return sigma.reshape(n, k), rgb.reshape(n, k, 3)

    def march_groups(self, k: int) -> list[tuple[int, int]]:
        """The ``march_chunks`` front-to-back groups ``[a, b)`` of ``k`` coarse samples."""
        bounds = torch.linspace(0, k, self.march_chunks + 1).round().long().tolist()
        return [(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]

    def _march(self, field: Field, o: Tensor, d: Tensor, t: Tensor, s: Tensor,
               far: Tensor) -> tuple[Tensor, Tensor]:
        """The coarse samples front to back in ``march_chunks`` groups: occupied samples of
        rays whose transmittance is above ``stop_transmittance`` at a group's start count
        (``[n, K]`` σ, ``[n, K, 3]`` rgb; 0 for the others). Without autograd the field is
        asked group by group; with it, once on all occupied samples, the stops applied as
        masks afterwards: the same values and gradients, one backward pass."""
        n, k = s.shape
        keep = self.occupancy.occupied_rays(o, d, t, s)
        delta = step_sizes(s, far).float()
        tau = torch.zeros(n, device=s.device)
        groups = self.march_groups(k)
        if torch.is_grad_enabled():
            sig, rgb = self._query(field, o, d, t, s, keep)
            alive, tau_i = torch.ones_like(keep), sig.detach().float().clamp(min=0) * delta
            for a, b in groups:
                alive[:, a:b] = (torch.exp(-tau) > self.stop_transmittance)[:, None]
                tau = tau + (tau_i[:, a:b] * alive[:, a:b]).sum(-1)
            return sig * alive, rgb * alive[..., None]
        sig_parts, rgb_parts = [], []
        for a, b in groups:
            alive = torch.exp(-tau) > self.stop_transmittance
            sig, rgb = self._query(field, o, d, t, s[:, a:b], keep[:, a:b] & alive[:, None])
            tau = tau + (sig.detach().float().clamp(min=0) * delta[:, a:b]).sum(-1)
            sig_parts.append(sig)
            rgb_parts.append(rgb)
        return torch.cat(sig_parts, 1), torch.cat(rgb_parts, 1)

    def _render_hit(self, field: Field, o: Tensor, d: Tensor, t: Tensor, bg: Tensor,
                    near: Tensor, far: Tensor, perturb: bool, gen: torch.Generator | None,
                    copies: int = 1) -> list[dict[str, Tensor]]:
        """Both levels for rays that all hit the clipping volume."""
        s_c = stratified(near, far, self.n_coarse, perturb, gen, copies)
        skipping = self.skipping
        if skipping:
            sigma_c, rgb_c = self._march(field, o, d, t, s_c, far)
        else:
            sigma_c, rgb_c = self._query(field, o, d, t, s_c)
        levels = [composite(sigma_c, rgb_c, s_c, far, bg)]
        if self.n_fine == 0:
            return levels
        s_f = sample_pdf(*pdf_bins(s_c, levels[0]["weights"]), self.n_fine, not perturb, gen)
        keep_f = None
        if skipping:  # occupied, and in front of the point where the coarse ray stopped
            trans = 1.0 - levels[0]["weights"].detach().cumsum(-1)
            stopped = trans < self.stop_transmittance
            ends = torch.cat([s_c[:, 1:], far[:, None].to(s_c.dtype)], -1)   # each step's end
            stop_s = torch.where(stopped.any(-1),
                                 ends.gather(1, stopped.float().argmax(-1)[:, None])[:, 0], far)
            keep_f = self.occupancy.occupied_rays(o, d, t, s_f) & (s_f <= stop_s[:, None])
        sigma_f, rgb_f = self._query(field, o, d, t, s_f, keep_f)
        s_all, order = torch.sort(torch.cat([s_c, s_f], dim=-1), dim=-1)
        sigma = torch.cat([sigma_c, sigma_f], dim=-1).gather(1, order)
        rgb = torch.cat([rgb_c, rgb_f], dim=-2).gather(1, order[..., None].expand(-1, -1, 3))
        levels.append(composite(sigma, rgb, s_all, far, bg))
        return levels

    def render_rays(self, field: Field, o: Tensor, d: Tensor, t: Tensor, bg: Tensor,
                    perturb: bool = False, gen: torch.Generator | None = None,
                    copies: int = 1) -> list[dict[str, Tensor]]:
        """Render rays at one time each.

        Args:
            field: the :class:`~eventrecon.fields.base.Field` (used for both levels).
            o, d: ``[N, 3]`` ray origins and unit directions.
            t: ``[N, 1]`` normalised times.
            bg: ``[N, 3]`` background colours.
            perturb: stratified jitter and random importance draws (training).
            gen: optional generator on the rays' device.
            copies: the rays are ``copies`` stacked blocks of the same rays (one ray at
                several times, as in training: ``t0``, ``t1``, ``t_ref``). The coarse
                samples are drawn once per ray and shared by its copies, as the
                authors' code does; the fine samples are drawn from each copy's own
                coarse weights. A static field then renders the copies identically at
                the coarse level, so ``L_event`` sees no Monte Carlo noise there.

        Returns:
            one dict per level (coarse, then fine if ``n_fine > 0``) with ``rgb [N, 3]``,
            ``opacity [N]``, ``depth [N]`` (0 for rays that miss), ``weights [N, K]`` and
            ``s [N, K]`` (zeros for rays that miss). Outputs stay connected to the field's
            parameters even when no ray hits (zero gradients, no autograd error).
        """
        n = o.shape[0]
        if d.shape != o.shape or t.shape != (n, 1) or bg.shape != (n, 3) or o.shape[-1:] != (3,):
            raise InputError("renderer", "o/d/t/bg", "shapes [N,3], [N,3], [N,1], [N,3]",
                             f"{tuple(o.shape)}, {tuple(d.shape)}, {tuple(t.shape)}, "
                             f"{tuple(bg.shape)}")
        near, far, hit = self.cylinder.ray_interval(o, d)
        idx = hit.nonzero().squeeze(1)
        if idx.numel() == n:
            return self._render_hit(field, o, d, t, bg, near, far, perturb, gen, copies)
        # copies of a ray hit or miss together, so the hits keep the block structure
        sub = self._render_hit(field, o[idx], d[idx], t[idx], bg[idx], near[idx], far[idx],
                               perturb, gen, copies)
        # a miss is the background: opacity, weights and s 0, depth far (0 for a miss)
        missed = {"rgb": bg.float(), "opacity": far.new_zeros(n, dtype=torch.float32),
                  "depth": far.float(), "weights": far.new_zeros((n, 1), dtype=torch.float32),
                  "s": far.new_zeros((n, 1))}
        return [{key: missed[key].expand(n, *value.shape[1:]).index_put((idx,), value)
                 for key, value in level.items()} for level in sub]

    def forward(self, model: Field, cams: Cameras, view: Tensor, uv: Tensor, t: Tensor,
                bg: Tensor, perturb: bool = False, gen: torch.Generator | None = None,
                copies: int = 1) -> list[dict[str, Tensor]]:
        """The protocol's call (:meth:`Renderer.forward`): the rays through ``uv`` of the
        cameras ``view`` (computed once per block of ``copies``), then :meth:`render_rays`."""
        n = view.shape[0]
        if copies < 1 or n % copies:
            raise InputError("renderer", "copies", f"a divisor of the sample count {n}", copies)
        m = n // copies
        o, d = cams.rays(view[:m].cpu(), uv[:m].cpu())
        o, d = o.to(t.device).repeat(copies, 1), d.to(t.device).repeat(copies, 1)
        self.field_inputs = 0
        return self.render_rays(model, o, d, t, bg, perturb, gen, copies)

    def image_rows(self, model: Field, cams: Cameras, view: int, device: torch.device
                   ) -> Callable[[slice, Tensor, Tensor], dict[str, Tensor]]:
        """:meth:`Renderer.image_rows` through the view's cached rays
        (:meth:`~eventrecon.render.cameras.Cameras.image_rays`)."""
        o, d = cams.image_rays(view)
        o, d = o.to(device), d.to(device)
        return lambda j, t, bg: self.render_rays(model, o[j], d[j], t, bg)[-1]
