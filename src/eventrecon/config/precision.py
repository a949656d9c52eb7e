"""The training precision, chosen for the machine: ``trainer.lightning.precision: auto``.

The authors train with mixed precision (fp16 AMP on their GPUs). On a CPU the mixed
counterpart is bf16 autocast, which pays only where the CPU computes in bf16 natively
(AVX512-BF16 or AMX): there the NeRF MLP's step is about twice as fast, while on a CPU
with AVX2 only oneDNN emulates bf16 and the same step is several times *slower*. So
``auto`` resolves to

- ``16-mixed`` on a GPU (the authors' AMP);
- ``bf16-mixed`` on a CPU with native bf16, for a backbone whose step it speeds up
  (``model.cpu_bf16: true``: the NeRF MLP);
- ``32-true`` on any other CPU, and for the grid backbones everywhere on a CPU
  (``model.cpu_bf16: false``): their steps are gathers, scatters and interpolations, which
  autocast leaves in fp32, so fp32 costs nothing and keeps their records alike on every CPU.

Any other value is passed to Lightning as written. The run's record names the precision
it trained with (``precision`` in ``metrics.json``). Renders without gradients (held-out
images, the training curve's points) run under the same autocast (:func:`image_dtype`;
``render.image_autocast``), as the authors' ``render_single_image.py`` renders test
images under ``autocast()``.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from eventrecon.common.errors import InputError

__all__ = ["AUTO", "LIGHTNING_PRECISIONS", "cpu_has_native_bf16", "image_dtype",
           "mixed_dtype", "resolve_precision", "run_precision"]

AUTO = "auto"
_GPU = ("gpu", "cuda")
#: The values of Lightning's ``precision`` (2.x), as written in a config.
LIGHTNING_PRECISIONS = ("transformer-engine", "transformer-engine-float16", "16-true",
                        "16-mixed", "bf16-true", "bf16-mixed", "32-true", "64-true", "64",
                        "32", "16", "bf16")


def cpu_has_native_bf16() -> bool:
    """Whether this CPU computes in bf16 natively (AVX512-BF16 or AMX tiles): torch's own
    probes where it has them, else the flags of ``/proc/cpuinfo``."""
    import torch  # lazily: the records and the report do not need torch

    probes = [getattr(torch.cpu, name, None)
              for name in ("_is_avx512_bf16_supported", "_is_amx_tile_supported")]
    if all(callable(p) for p in probes):
        return any(bool(p()) for p in probes)
    try:
        flags = Path("/proc/cpuinfo").read_text().split()
    except OSError:
        return False
    return "avx512_bf16" in flags or "amx_bf16" in flags


def resolve_precision(value: str | int, accelerator: str = "cpu",
                      native_bf16: bool | None = None, bf16_pays: bool = True) -> str | int:
    """Lightning's ``precision`` for ``trainer.lightning.precision = value`` (module
    docstring); ``native_bf16`` overrides the CPU probe; ``bf16_pays`` is the backbone's
    ``model.cpu_bf16`` (see :func:`run_precision`).

    >>> resolve_precision("auto", "cpu", native_bf16=False)
    '32-true'
    >>> resolve_precision("auto", "cpu", native_bf16=True)
    'bf16-mixed'
    >>> resolve_precision("auto", "cpu", native_bf16=True, bf16_pays=False)
    '32-true'
    >>> resolve_precision("auto", "gpu"), resolve_precision("bf16-mixed", "cpu", False)
    ('16-mixed', 'bf16-mixed')

    Raises:
        InputError: ``value`` is neither ``auto``, ``None`` (Lightning's default) nor one
            of :data:`LIGHTNING_PRECISIONS`.
    """
    if str(value) != AUTO:
        if value is not None and (isinstance(value, bool)
                                  or str(value) not in LIGHTNING_PRECISIONS):
            raise InputError("config", "trainer.lightning.precision",
                             "auto or one of Lightning's: " + ", ".join(LIGHTNING_PRECISIONS),
                             value)
        return value
    import torch

    if str(accelerator) in _GPU or (str(accelerator) == AUTO and torch.cuda.is_available()):
        return "16-mixed"
    if not bf16_pays:
        return "32-true"
    if native_bf16 is None:
        native_bf16 = cpu_has_native_bf16()
    return "bf16-mixed" if native_bf16 else "32-true"


def run_precision(cfg: Mapping[str, Any]) -> str | int:
    """The precision a run's config trains with: ``trainer.lightning.precision`` and
    ``.accelerator`` resolved by :func:`resolve_precision`, with the backbone's
    ``model.cpu_bf16`` (whether bf16 autocast speeds up its CPU step; true where absent).
    The trainer and the run's record both take it from here.

    >>> cfg = {"trainer": {"lightning": {"precision": "auto", "accelerator": "cpu"}},
    ...        "model": {"name": "hexplane", "cpu_bf16": False}}
    >>> run_precision(cfg)
    '32-true'
    """
    lightning = cfg["trainer"].get("lightning") or {}
    return resolve_precision(lightning.get("precision", AUTO),
                             lightning.get("accelerator", "cpu"),
                             bf16_pays=bool((cfg.get("model") or {}).get("cpu_bf16", True)))


def mixed_dtype(precision: str | int | None) -> Any:
    """The autocast dtype of a Lightning precision: ``torch.bfloat16`` for ``bf16-mixed``,
    ``torch.float16`` for ``16-mixed``, ``None`` for any other (``32-true``, ``64``, …).

    >>> mixed_dtype("bf16-mixed"), mixed_dtype("32-true"), mixed_dtype(None)
    (torch.bfloat16, None, None)
    """
    import torch

    return {"bf16-mixed": torch.bfloat16, "16-mixed": torch.float16}.get(str(precision))


def _pays_on(dtype: Any, device_type: str | None) -> bool:
    """Whether autocast to ``dtype`` suits ``device_type``: anywhere but on a CPU, and there
    only for bf16 where the CPU computes in it natively (fp16 and emulated bf16 are slow)."""
    import torch

    return device_type != "cpu" or (dtype == torch.bfloat16 and cpu_has_native_bf16())


def image_dtype(render_cfg: Mapping[str, Any], precision: str | int | None,
                device_type: str | None = None) -> Any:
    """The autocast dtype of a run's renders without gradients (held-out images, curve
    points, the occupancy grid's density queries): :func:`mixed_dtype` of the run's
    ``precision``, as the authors render their test images under the AMP they train
    with (``render_single_image.py``). ``None`` (fp32) where ``render.image_autocast`` is
    false, and on a CPU (``device_type`` "cpu") for fp16 or for bf16 without native bf16
    (both emulated there, and slow)."""
    dtype = mixed_dtype(precision) if render_cfg.get("image_autocast", True) else None
    return dtype if dtype is not None and _pays_on(dtype, device_type) else None
