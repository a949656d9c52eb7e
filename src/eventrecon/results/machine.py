"""Which machine a run trained on, as its record names it (``machine`` in ``metrics.json``).

Wall-clock figures compare backbones only between runs of one machine: a sweep resumed on
another CPU mixes speeds (docs/results/README.md, "What accuracy costs in time"). The name
is the CUDA device's for a GPU run, else the CPU's model name from ``/proc/cpuinfo`` (the
platform's processor string where that file is missing) with the logical core count.
"""

from __future__ import annotations

import os
import platform
from pathlib import Path

__all__ = ["cpu_model", "machine_name"]


def cpu_model(cpuinfo: str | None = None) -> str:
    """The CPU's model name: the first ``model name`` line of ``cpuinfo`` (the text of
    ``/proc/cpuinfo``, read when ``None``), else :func:`platform.processor`, else
    ``"unknown CPU"``.

    >>> cpu_model("processor : 0\\nmodel name\\t: Intel(R) Xeon(R) Platinum 8481C CPU @ 2.70GHz\\n")
    'Intel(R) Xeon(R) Platinum 8481C CPU @ 2.70GHz'
    >>> cpu_model("processor : 0\\n") == (platform.processor() or "unknown CPU")
    True
    """
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            cpuinfo = ""
    for line in cpuinfo.splitlines():
        key, sep, value = line.partition(":")
        if sep and key.strip() == "model name" and value.strip():
            return " ".join(value.split())
    return platform.processor() or "unknown CPU"


def machine_name(cuda: bool = False) -> str:
    """``"<CUDA device name>"`` for a GPU run, else ``"<CPU model> ×<logical cores>"``."""
    if cuda:
        import torch  # lazily: the records and the report do not need torch

        return torch.cuda.get_device_name()
    return f"{cpu_model()} ×{os.cpu_count() or 1}"
