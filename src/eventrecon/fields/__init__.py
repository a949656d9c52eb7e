"""Fields: the interface every backbone implements, and the paper's NeRF MLP.

``NeRFField`` is imported lazily (its schedule callback pulls in Lightning), so modules
that only need the :class:`Field` interface, such as the renderer, stay light to import.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from eventrecon.fields.base import Field

if TYPE_CHECKING:
    from eventrecon.fields.nerf import NeRFField

__all__ = ["Field", "NeRFField"]


def __getattr__(name: str) -> Any:
    if name == "NeRFField":
        from eventrecon.fields.nerf import NeRFField

        return NeRFField
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
