"""The renderer protocol: what training, evaluation and the viewer ask of a representation.

A :class:`Renderer` turns a scene representation (a :class:`~eventrecon.fields.base.Field`
for the volume renderer, any ``nn.Module`` for others) into the colour, opacity and depth
of ``(view, pixel, time)`` samples:

.. math:: (v_n, \\mathbf{u}_n, t_n, \\mathbf{c}_{bg,n}) \\mapsto
          (\\hat C_n \\in [0, 1]^3,\\ O_n \\in [0, 1],\\ D_n \\ge 0),

``v`` a camera of a :class:`~eventrecon.render.cameras.Cameras` set, ``u = (column, row)``
a pixel position (integers are pixel centres; training jitters them by ±0.5), ``t`` the
segment-normalised time in ``[0, 1]`` and ``c_bg`` the linear background the sample shows
where nothing is in front of it. :meth:`Renderer.forward` returns one dict per level
(a coarse and a fine level for the volume renderer; one for a rasteriser), each with
``rgb [N, 3]``, ``opacity [N]`` and ``depth [N]``; every level's colour and opacity enter
the losses. :meth:`Renderer.render_image` renders a whole camera image. Nothing else in the
training module, the losses or the evaluation depends on how the values are made: a new
representation is one :class:`Renderer` subclass (and its ``conf/render/`` file).

``copies``: the ``N`` samples may be ``copies`` stacked blocks of the same pixels at
different times (training renders each pixel at ``t0``, ``t1`` and ``t_ref``); a renderer
may share work between the copies (the volume renderer draws its coarse samples once per
pixel) but must give each row its own time.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor, nn

from eventrecon.common.colour import GREY_LINEAR
from eventrecon.common.errors import InputError
from eventrecon.render.clipping import NO_CLIPPING, Cylinder

if TYPE_CHECKING:
    from eventrecon.render.cameras import Cameras

__all__ = ["Renderer", "image_autocast", "background_rows"]


def image_autocast(dtype: torch.dtype | None,
                   device: torch.device | str) -> contextlib.AbstractContextManager:
    """Autocast to ``dtype`` on ``device`` for renders without gradients, or fp32 where
    ``dtype`` is ``None``; on a CPU only bf16 autocast is used (fp16 is emulated there)."""
    kind = torch.device(device).type
    if dtype is None or (kind == "cpu" and dtype != torch.bfloat16):
        return contextlib.nullcontext()
    return torch.autocast(kind, dtype=dtype)


def background_rows(bg_image: Tensor | float | None, h: int, w: int,
                    device: torch.device) -> Tensor:
    """``[H·W, 3]`` linear background of an image's pixels (row-major) from an
    ``[H, W, 3]`` image, a ``[3]`` colour, a float, or ``None`` for the method's grey
    (:data:`~eventrecon.common.colour.GREY_LINEAR`).

    >>> background_rows(0.5, 1, 2, torch.device("cpu")).tolist()
    [[0.5, 0.5, 0.5], [0.5, 0.5, 0.5]]
    """
    bg = torch.as_tensor(GREY_LINEAR if bg_image is None else bg_image,
                         dtype=torch.float32, device=device)
    if bg.shape == (h, w, 3):
        return bg.reshape(h * w, 3)
    if bg.numel() in (1, 3):
        return bg.reshape(1, -1).expand(h * w, 3)
    raise InputError("render_image", "bg_image", f"[{h}, {w}, 3], [3] or a float",
                     tuple(bg.shape))


class Renderer(nn.Module):
    """Base class of the renderers (the protocol in the module docstring).

    Subclasses implement :meth:`forward`; :meth:`render_image` defaults to rendering
    every pixel centre of the view through it, ``chunk`` pixels at a time, and a renderer
    that draws whole images (a rasteriser) overrides both.

    Args:
        radius, y_min, y_max: the scene's clipping cylinder
            (:class:`~eventrecon.render.clipping.Cylinder`): the volume that holds the
            subject (density outside it is zero for the volume renderer).
        clipping: ``False`` replaces the cylinder by
            :data:`~eventrecon.render.clipping.NO_CLIPPING` (the "w/o clipping" ablation).
        chunk: pixels per call when rendering full images.
    """

    def __init__(self, radius: float = 0.5, y_min: float = -0.75, y_max: float = 0.25,
                 clipping: bool = True, chunk: int = 8192) -> None:
        super().__init__()
        if chunk < 1:
            raise InputError("renderer", "chunk", "an integer >= 1", chunk)
        self.cylinder = (Cylinder(radius, y_min, y_max) if clipping
                         else Cylinder(**NO_CLIPPING))
        self.chunk = int(chunk)
        #: autocast dtype of renders without gradients (images, curve points), set by the
        #: builder from the run's precision; ``None``: fp32
        self.image_dtype: torch.dtype | None = None

    def forward(self, model: nn.Module, cams: Cameras, view: Tensor, uv: Tensor, t: Tensor,
                bg: Tensor, perturb: bool = False, gen: torch.Generator | None = None,
                copies: int = 1) -> list[dict[str, Tensor]]:
        """Render samples ``(view [N] long, uv [N, 2], t [N, 1])`` over backgrounds
        ``bg [N, 3]`` (on the model's device; ``view``/``uv`` may be on the CPU).

        Args:
            model: the representation.
            cams: the cameras ``view`` indexes.
            perturb: training randomness (jittered samples); ``False`` for evaluation.
            gen: optional generator of that randomness.
            copies: ``N`` is ``copies`` stacked blocks of the same pixels (module docstring).

        Returns:
            one dict per level, the final level last, each with ``rgb [N, 3]`` in
            ``[0, 1]``, ``opacity [N]`` and ``depth [N]`` (float32); a renderer may add
            keys of its own.
        """
        raise NotImplementedError

    def callbacks(self, seed: int = 0) -> list[Any]:
        """Lightning callbacks that keep the renderer's own state up to date during
        training (e.g. an occupancy grid); default none."""
        return []

    def step_stats(self, n_samples: int) -> dict[str, float]:
        """Diagnostics of the last :meth:`forward` call on ``n_samples`` rows, logged
        every ``log_every`` steps as ``train/<key>``; default none."""
        return {}

    def image_autocast(self, device: torch.device | str) -> contextlib.AbstractContextManager:
        """:func:`image_autocast` of :attr:`image_dtype` on ``device``."""
        return image_autocast(self.image_dtype, device)

    def image_rows(self, model: nn.Module, cams: Cameras, view: int, device: torch.device
                   ) -> Callable[[slice, Tensor, Tensor], dict[str, Tensor]]:
        """How :meth:`render_image` renders a slice of the view's row-major pixels:
        ``(rows, t [n, 1], bg [n, 3]) -> the last level's dict``. By default the pixel
        centres through :meth:`forward`; a renderer with a cheaper image path overrides it."""
        uv = cams.pixel_grid()
        views = torch.full((uv.shape[0],), int(view), dtype=torch.long)
        return lambda j, t, bg: self.forward(model, cams, views[j], uv[j], t, bg)[-1]

    @torch.no_grad()
    def render_image(self, model: nn.Module, cams: Cameras, view: int, t: float,
                     bg_image: Tensor | float | None = None, chunk: int | None = None
                     ) -> dict[str, Tensor]:
        """Render a full image of camera ``view`` at normalised time ``t`` (final level,
        no randomness), under :meth:`image_autocast`.

        Args:
            model: the representation.
            cams: the cameras.
            view: camera index.
            t: normalised time.
            bg_image: background (:func:`background_rows`).
            chunk: pixels per call (default :attr:`chunk`).

        Returns:
            dict with ``rgb [H, W, 3]``, ``opacity [H, W]``, ``depth [H, W]`` (float32, on
            the model's device).
        """
        device = model_device(model)
        h, w = cams.height, cams.width
        render_rows = self.image_rows(model, cams, view, device)
        bg = background_rows(bg_image, h, w, device)
        tt = torch.full((h * w, 1), float(t), device=device)
        chunk = int(chunk or self.chunk)
        parts: dict[str, list[Tensor]] = {"rgb": [], "opacity": [], "depth": []}
        with self.image_autocast(device):
            for i in range(0, h * w, chunk):
                j = slice(i, i + chunk)
                level = render_rows(j, tt[j], bg[j])
                for key in parts:
                    parts[key].append(level[key].float())
        return {"rgb": torch.cat(parts["rgb"]).reshape(h, w, 3),
                "opacity": torch.cat(parts["opacity"]).reshape(h, w),
                "depth": torch.cat(parts["depth"]).reshape(h, w)}


def model_device(model: nn.Module) -> torch.device:
    """The device of a module's first parameter or buffer (the CPU for an empty one)."""
    for tensor in (*model.parameters(), *model.buffers()):
        return tensor.device
    return torch.device("cpu")
