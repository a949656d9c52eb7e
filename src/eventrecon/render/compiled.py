"""numba for the renderer's compiled loops: one decorator, one availability flag.

The simulator has its own (:mod:`eventrecon.sim.jit`), which this package may not import:
the simulator imports the renderer's cameras, and subpackages must not import one another
in a cycle (``tests/test_structure.py``). Nor does that module's stale-cache check cover
these files: numba keys a function's cache on its own file alone, so each module here
keeps its compiled loops self-contained (no compiled helper from another module).
"""

from __future__ import annotations

from typing import Any

try:
    import numba
except ImportError:                              # pragma: no cover - numba is a dependency
    numba = None

__all__ = ["AVAILABLE", "compiled"]

#: Whether numba could be imported (else the compiled paths decline and PyTorch's run).
AVAILABLE = numba is not None


def compiled(fn: Any) -> Any:
    """``fn`` compiled with the options of the simulator's loops
    (:func:`eventrecon.sim.jit.njit_borrowing`): cached beside its file, NumPy's error
    model (a division by zero gives inf/NaN), no GIL, no reference counting (the loop may
    not create arrays: its caller allocates them). Without numba, ``fn`` itself."""
    if numba is None:                            # pragma: no cover
        return fn
    return numba.njit(cache=True, error_model="numpy", nogil=True, _nrt=False)(fn)
