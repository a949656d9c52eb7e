"""The supplementary's Tables 3–7 (Dynamic EventNeRF) as data.

Every value is transcribed from the supplementary material; the rows and columns keep the
paper's order. ``PAPER_TABLES["table3"].value("Full Model", "Spheres")`` gives the
paper's ``(PSNR, SSIM, LPIPS)`` for that cell.

>>> PAPER_TABLES["table3"].value("Full Model", "Average")
(27.097, 0.893, 0.145)
>>> PAPER_TABLES["table7"].value("6", "Dress")
(30.88,)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

#: Metric keys (as in metrics.json) and their display names.
METRIC_LABELS: dict[str, str] = {"psnr": "PSNR↑", "ssim": "SSIM↑", "lpips": "LPIPS-Alex↓"}


@dataclass(frozen=True)
class PaperTable:
    """One table: ``rows`` × ``columns`` (scene groups) × ``metrics``.

    ``values[(row, column)]`` is a tuple aligned with ``metrics``. ``decimals`` is the
    paper's printed precision; ``average_column`` names a column that is the mean of
    the others (Tab. 3), ``None`` otherwise.
    """

    key: str
    title: str
    caption: str
    row_header: str
    rows: tuple[str, ...]
    columns: tuple[str, ...]
    metrics: tuple[str, ...]
    values: dict[tuple[str, str], tuple[float, ...]] = field(repr=False)
    decimals: int = 3
    average_column: str | None = None

    def value(self, row: str, column: str) -> tuple[float, ...] | None:
        """The paper's metric tuple for a cell, or ``None`` if the paper has none."""
        return self.values.get((row, column))

    def repeated(self, row: str, column: str) -> str | None:
        """Another row whose cell in ``column`` equals ``row``'s in every metric, or
        ``None``. Three metrics printed to three decimals do not agree by chance, so such
        a cell is most likely a copy in the paper's table. Tables of one metric and the
        average column are not checked.

        >>> PAPER_TABLES["table3"].repeated("w/o L_event", "Blender")
        'w/o clipping'
        """
        v = self.value(row, column)
        if v is None or len(self.metrics) < 2 or column == self.average_column:
            return None
        return next((r for r in self.rows if r != row and self.value(r, column) == v), None)

    def difference(self, a: str, b: str, metric: str, columns: Sequence[str],
                   skip_repeated: bool = False) -> float | None:
        """The paper's ``a − b`` in ``metric``, averaged over ``columns`` (each column
        once); ``None`` without columns or where the paper lacks a cell or the metric.
        ``skip_repeated`` leaves out the columns where ``a``'s or ``b``'s cell repeats
        another row's (:meth:`repeated`).

        >>> round(PAPER_TABLES["table5"].difference("100", "0.5", "psnr", ["Sword"]), 3)
        0.378
        >>> t3, cols = PAPER_TABLES["table3"], ["Blender", "Dress", "Spheres", "Lego"]
        >>> [round(t3.difference("Full Model", "w/o L_event", "psnr", cols, s), 3)
        ...  for s in (False, True)]
        [3.014, 1.527]
        """
        if metric not in self.metrics:
            return None
        k, cols = self.metrics.index(metric), sorted(set(columns))
        if skip_repeated:
            cols = [c for c in cols if not (self.repeated(a, c) or self.repeated(b, c))]
        cells = [(self.value(a, c), self.value(b, c)) for c in cols]
        if not cells or any(va is None or vb is None for va, vb in cells):
            return None
        return sum(va[k] - vb[k] for va, vb in cells) / len(cells)


def _grid(columns: tuple[str, ...], rows: dict[str, tuple[float, ...]], width: int):
    """Split each row's flat list (``width`` metrics per column) into per-column tuples."""
    out: dict[tuple[str, str], tuple[float, ...]] = {}
    for row, flat in rows.items():
        assert len(flat) == width * len(columns), row
        for j, col in enumerate(columns):
            out[(row, col)] = tuple(flat[j * width : (j + 1) * width])
    return out


_T3_COLUMNS = ("Blender", "Dress", "Spheres", "Lego", "Static Lego", "Average")
# fmt: off
_T3_ROWS: dict[str, tuple[float, ...]] = {
    # Blender | Dress | Spheres | Lego | Static Lego | Average   (PSNR, SSIM, LPIPS each)
    "TensoRF-CP":     (24.727, 0.879, 0.227, 28.091, 0.915, 0.202, 23.971, 0.866, 0.280,
                       21.444, 0.752, 0.408, 22.604, 0.783, 0.310, 24.167, 0.839, 0.285),
    "NGP":            (25.687, 0.888, 0.184, 29.131, 0.933, 0.179, 28.755, 0.915, 0.120,
                       17.134, 0.594, 0.556, 15.490, 0.552, 0.598, 23.239, 0.777, 0.327),
    "HexPlane":       (23.119, 0.864, 0.275, 23.580, 0.866, 0.336, 21.636, 0.853, 0.334,
                       20.093, 0.711, 0.452, 20.042, 0.725, 0.423, 21.694, 0.804, 0.364),
    "w/o clipping":   (19.959, 0.851, 0.426, 27.926, 0.926, 0.147, 28.786, 0.916, 0.093,
                       22.996, 0.814, 0.272, 22.687, 0.814, 0.262, 24.471, 0.864, 0.240),
    "w/o L_sparsity": (27.501, 0.926, 0.135, 31.292, 0.950, 0.081, 29.358, 0.920, 0.086,
                       22.416, 0.798, 0.281, 23.698, 0.839, 0.203, 26.853, 0.887, 0.157),
    "w/o L_event":    (19.959, 0.851, 0.426, 29.884, 0.941, 0.108, 27.744, 0.913, 0.114,
                       21.980, 0.792, 0.305, 22.986, 0.821, 0.226, 24.511, 0.864, 0.236),
    "w/o L_acc":      (26.835, 0.899, 0.125, 30.650, 0.946, 0.079, 28.847, 0.920, 0.087,
                       23.178, 0.820, 0.247, 16.057, 0.714, 0.483, 25.113, 0.860, 0.204),
    "w/o L_RGB":      (27.321, 0.928, 0.122, 30.540, 0.946, 0.086, 29.129, 0.920, 0.089,
                       22.332, 0.799, 0.292, 23.644, 0.836, 0.206, 26.593, 0.886, 0.159),
    "only L_event":   (27.362, 0.905, 0.148, 31.308, 0.951, 0.073, 29.447, 0.921, 0.084,
                       23.009, 0.814, 0.262, 16.500, 0.729, 0.444, 25.525, 0.864, 0.202),
    "only L_acc":     (25.683, 0.912, 0.159, 30.234, 0.944, 0.106, 28.132, 0.915, 0.107,
                       22.088, 0.794, 0.312, 22.840, 0.819, 0.228, 25.795, 0.877, 0.182),
    "Full Model":     (27.431, 0.929, 0.119, 31.396, 0.952, 0.076, 29.765, 0.924, 0.081,
                       23.029, 0.818, 0.258, 23.863, 0.842, 0.193, 27.097, 0.893, 0.145),
}
_T4_ROWS: dict[str, tuple[float, ...]] = {
    "Ours (TensoRF-CP)":      (26.202, 0.784, 0.164),
    "Ours (NGP)":             (26.278, 0.787, 0.163),
    "Ours (HexPlane)":        (24.941, 0.758, 0.210),
    "w/o clipping":           (25.288, 0.810, 0.163),
    "w/o decay":              (27.119, 0.816, 0.133),
    "w/o multi-segment":      (26.673, 0.809, 0.142),
    "w/o L_sparsity":         (26.920, 0.814, 0.128),
    "w/o L_event":            (27.620, 0.820, 0.123),
    "w/o L_acc":              (25.517, 0.802, 0.139),
    "w/o L_RGB":              (27.062, 0.818, 0.120),
    "only L_event":           (25.029, 0.799, 0.143),
    "only L_acc":             (27.754, 0.821, 0.122),
    "only L_RGB":             (26.019, 0.806, 0.144),
    "Our Full Model (Final)": (27.048, 0.819, 0.120),
}
_T5_ROWS: dict[str, tuple[float, ...]] = {
    "0.5": (26.950, 0.817, 0.123), "1": (26.932, 0.817, 0.123), "2": (27.055, 0.818, 0.119),
    "5": (27.061, 0.820, 0.115), "10": (27.289, 0.821, 0.117), "20": (27.226, 0.821, 0.114),
    "30": (27.337, 0.821, 0.116), "50": (27.310, 0.820, 0.117), "100": (27.328, 0.821, 0.116),
}
_T6_ROWS: dict[str, tuple[float, ...]] = {
    "2": (24.667, 0.784, 0.166), "3": (26.081, 0.808, 0.149),
    "4": (26.891, 0.815, 0.118), "5": (27.061, 0.820, 0.115),
}
_T7_ROWS: dict[str, tuple[float, ...]] = {
    "2": (16.05,), "3": (28.97,), "4": (27.90,), "6": (30.88,),
    "12": (32.19,), "24": (33.36,), "36": (33.27,),
}
# fmt: on

_M3 = ("psnr", "ssim", "lpips")

PAPER_TABLES: dict[str, PaperTable] = {
    "table3": PaperTable(
        key="table3",
        title="Table 3. Ablation and design choices on the synthetic scenes",
        caption="Quantitative ablation and design choice study with all synthetic scenes.",
        row_header="Method",
        rows=tuple(_T3_ROWS),
        columns=_T3_COLUMNS,
        metrics=_M3,
        values=_grid(_T3_COLUMNS, _T3_ROWS, 3),
        average_column="Average",
    ),
    "table4": PaperTable(
        key="table4",
        title='Table 4. Ablation and design choices on the real "Sword" scene',
        caption='Quantitative ablation and design choice study on the "Sword" real scene.',
        row_header="Method",
        rows=tuple(_T4_ROWS),
        columns=("Sword",),
        metrics=_M3,
        values=_grid(("Sword",), _T4_ROWS, 3),
    ),
    "table5": PaperTable(
        key="table5",
        title="Table 5. Frame rate of the supporting RGB frames",
        caption="Quantitative study on the number of supporting RGB frames (default 5 FPS).",
        row_header="FPS",
        rows=tuple(_T5_ROWS),
        columns=("Sword",),
        metrics=_M3,
        values=_grid(("Sword",), _T5_ROWS, 3),
    ),
    "table6": PaperTable(
        key="table6",
        title='Table 6. Number of input views on the real "Sword" scene',
        caption='Quantitative study on the number of input views on the "Sword" real scene.',
        row_header="Input Views",
        rows=tuple(_T6_ROWS),
        columns=("Sword",),
        metrics=_M3,
        values=_grid(("Sword",), _T6_ROWS, 3),
    ),
    "table7": PaperTable(
        key="table7",
        title='Table 7. PSNR on "Dress" with a varying number of views',
        caption='PSNR scores on "Dress" with varying number of views.',
        row_header="Views",
        rows=tuple(_T7_ROWS),
        columns=("Dress",),
        metrics=("psnr",),
        values=_grid(("Dress",), _T7_ROWS, 1),
        decimals=2,
    ),
}
