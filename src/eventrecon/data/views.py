"""Views of a split: listing a folder's per-view files and matching their names.

The published layout names one file per camera view in each folder (``pose/``,
``intrinsics/``, ``events/``, ``rgb/<frame>/``, ``background/``); views are matched by
sorted file order, and the names at the same position must agree on
:func:`view_key` (the trailing integer, so ``r_003`` and ``3`` are the same view).
"""

from __future__ import annotations

import re
from pathlib import Path

from eventrecon.common.errors import InputError

__all__ = ["view_key", "list_views", "match_views"]

_TRAILING_INT = re.compile(r"(\d+)$")


def view_key(stem: str) -> int | str:
    """The key two view names are matched on: the trailing integer, else the stem.

    >>> view_key("r_003"), view_key("3"), view_key("left")
    (3, 3, 'left')
    """
    m = _TRAILING_INT.search(stem)
    return int(m.group(1)) if m else stem


def list_views(folder: Path, suffix: str) -> list[Path]:
    """Files ``folder/*<suffix>`` sorted by name (hidden files ignored)."""
    return sorted((f for f in folder.iterdir()
                   if f.is_file() and f.suffix.lower() == suffix and not f.name.startswith(".")),
                  key=lambda f: f.name)


def match_views(reference: list[str], ref_where: Path | str, other: list[str],
                other_where: Path | str) -> None:
    """Check that ``other`` names the same views as ``reference`` in sorted order.

    Raises:
        InputError: different counts (``view count``) or a stem whose
            :func:`view_key` differs from the reference's at the same position.
    """
    if len(other) != len(reference):
        raise InputError(other_where, "view count",
                         f"{len(reference)} views as in {ref_where}", len(other))
    for a, b in zip(reference, other):
        if view_key(a) != view_key(b):
            raise InputError(other_where, "view names",
                             f"the views of {ref_where} in sorted order ({a!r})", repr(b))
