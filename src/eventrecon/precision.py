"""The training precision, chosen for the machine: ``trainer.lightning.precision: auto``.

The authors train with mixed precision (fp16 AMP on their GPUs). On a CPU the mixed
counterpart is bf16 autocast, which pays only where the CPU computes in bf16 natively
(AVX512-BF16 or AMX tiles): there it made the 4×64 NeRF step 2.1× faster, while on a CPU
with AVX2 only oneDNN falls back to a slow path and the same step is ~10× *slower*
(measured on a 2-core AMD EPYC whose hypervisor hides AVX-512: 99.8 ms → 1138 ms per
field step, 113 → 1035 ms per training step; ``python -m benchmarks compile``). So
``auto`` resolves to

- ``16-mixed`` on a GPU (the authors' AMP);
- ``bf16-mixed`` on a CPU with native bf16;
- ``32-true`` on any other CPU.

Any other value is passed to Lightning as written. The run's record names the precision
it trained with (``precision`` in ``metrics.json``).
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["AUTO", "cpu_has_native_bf16", "resolve_precision"]

AUTO = "auto"
_GPU = ("gpu", "cuda")


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
                      native_bf16: bool | None = None) -> str | int:
    """Lightning's ``precision`` for ``trainer.lightning.precision = value`` (module
    docstring); ``native_bf16`` overrides the CPU probe.

    >>> resolve_precision("auto", "cpu", native_bf16=False)
    '32-true'
    >>> resolve_precision("auto", "cpu", native_bf16=True)
    'bf16-mixed'
    >>> resolve_precision("auto", "gpu"), resolve_precision("bf16-mixed", "cpu", False)
    ('16-mixed', 'bf16-mixed')
    """
    if str(value) != AUTO:
        return value
    import torch

    if str(accelerator) in _GPU or (str(accelerator) == AUTO and torch.cuda.is_available()):
        return "16-mixed"
    if native_bf16 is None:
        native_bf16 = cpu_has_native_bf16()
    return "bf16-mixed" if native_bf16 else "32-true"
