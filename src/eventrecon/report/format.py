"""Cell formatting and Markdown/LaTeX table rendering shared by the report modules.

>>> fmt(27.0968, 3), fmt(None, 3), fmt_delta(-0.0004, 3)
('27.097', '—', '-0.000')
>>> print(markdown_table(["a", "b"], [["x", "1"]]))
| a | b |
|:--|--:|
| x | 1 |
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence

#: Shown for a value that does not exist (missing run, no paper counterpart).
DASH = "—"
#: Shown in place of our numbers when the run failed.
FAILED = "failed"
#: Shown in place of our numbers when every seed's run rendered the empty field.
COLLAPSED = "collapsed"
#: Shown when a run finished but the metric is unavailable (LPIPS without weights).
NOT_AVAILABLE = "n/a"


def fmt(value: float | None, decimals: int) -> str:
    """``value`` with ``decimals`` places; ``None``/NaN → "—"."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return DASH
    return f"{value:.{decimals}f}"


def fmt_delta(value: float | None, decimals: int) -> str:
    """Signed difference (``+0.123`` / ``-0.123``); ``None`` → "—"."""
    if value is None or math.isnan(value):
        return DASH
    return f"{value:+.{decimals}f}"


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """A GitHub Markdown table; the first column left-aligned, the others right-aligned."""
    lines = ["| " + " | ".join(header) + " |"]
    lines.append("|" + "|".join([":--"] + ["--:"] * (len(header) - 1)) + "|")
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


_LATEX_SPECIAL = {"&": r"\&", "%": r"\%", "#": r"\#", "_": r"\_", "$": r"\$"}


def latex_text(s: str) -> str:
    """Escape plain text for LaTeX; ``L_name`` → ``$\\mathcal{L}_\\mathrm{name}$``,
    arrows, "—" and "Δ" to their LaTeX forms.

    >>> latex_text("w/o L_event ↑ a_b —")
    'w/o $\\\\mathcal{L}_\\\\mathrm{event}$ $\\\\uparrow$ a\\\\_b --'
    """
    parts = re.split(r"(\bL_[A-Za-z]+)", s)
    out = []
    for part in parts:
        if re.fullmatch(r"L_[A-Za-z]+", part):
            out.append(r"$\mathcal{L}_\mathrm{" + part[2:] + "}$")
            continue
        for k, v in _LATEX_SPECIAL.items():
            part = part.replace(k, v)
        part = (
            part.replace("↑", r"$\uparrow$")
            .replace("↓", r"$\downarrow$")
            .replace("Δ", r"$\Delta$")
            .replace("—", "--")
            .replace("`", "")
        )
        out.append(part)
    return "".join(out)
