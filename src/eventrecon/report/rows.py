"""Which row of a paper table a run fills.

Tab. 3/4 rows by ``(model, loss)``: a backbone other than ``nerf`` with ``loss=full``
gives a backbone row, ``nerf`` the ablation row of its loss; Tab. 5 rows by ``fps``,
Tab. 6/7 by ``views`` (``loss=full`` runs). :data:`FIXED` lists, per table, the settings
held fixed (their most common value among the table's runs).
"""

from __future__ import annotations

from collections.abc import Callable

from eventrecon.report.paper import PAPER_TABLES
from eventrecon.report.runs import Run

__all__ = ["method_row", "ROW_OF", "FIXED", "setting_label"]

_BACKBONES = {"tensorf_cp": "TensoRF-CP", "ngp": "NGP", "hexplane": "HexPlane"}
_ABLATIONS = {
    "no_clipping": "w/o clipping",
    "no_decay": "w/o decay",
    "no_multiseg": "w/o multi-segment",
    "no_sparsity": "w/o L_sparsity",
    "no_event": "w/o L_event",
    "no_acc": "w/o L_acc",
    "no_rgb": "w/o L_RGB",
    "only_event": "only L_event",
    "only_acc": "only L_acc",
    "only_rgb": "only L_RGB",
}


def method_row(run: Run, table: str) -> str | None:
    """Tab. 3/4 row label of a run's ``(model, loss)``; ``None`` if the table has no such row."""
    if run.model != "nerf":
        if run.loss != "full" or run.model not in _BACKBONES:
            return None
        name = _BACKBONES[run.model]
        label = name if table == "table3" else f"Ours ({name})"
    elif run.loss == "full":
        label = "Full Model" if table == "table3" else "Our Full Model (Final)"
    else:
        label = _ABLATIONS.get(run.loss)
    return label if label in PAPER_TABLES[table].rows else None


def setting_label(v: float | str | None) -> str:
    """``5.0`` → "5", ``0.5`` → "0.5", ``None`` (the config's null) → "all", a name as is."""
    return "all" if v is None else v if isinstance(v, str) else f"{v:g}"


def _setting_row(attr: str) -> Callable[[Run, str], str | None]:
    def row(run: Run, table: str) -> str | None:
        return setting_label(getattr(run, attr)) if run.loss == "full" else None

    return row


#: How a run finds its row, and which run settings are held fixed, per table.
ROW_OF: dict[str, Callable[[Run, str], str | None]] = {
    "table3": method_row,
    "table4": method_row,
    "table5": _setting_row("fps"),
    "table6": _setting_row("views"),
    "table7": _setting_row("views"),
}
FIXED: dict[str, tuple[str, ...]] = {
    "table3": ("views", "fps"),
    "table4": ("views", "fps"),
    "table5": ("model", "views"),
    "table6": ("model", "fps"),
    "table7": ("model", "fps"),
}
