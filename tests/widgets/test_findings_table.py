"""The console's findings table: one row per tumour and map, whichever areas told of it."""

from __future__ import annotations

import math

from session.detect import Tumour
from widgets.findings_table import FindingsTable


def _tumour(x_mm: float, source: str = "stiffness", depth_model_mm: float = math.nan) -> Tumour:
    return Tumour(x_mm * 1e-3, 0.015, 1.7e-3, 1.0, source, 30.0, 0.5, (1.0,), depth_model_mm * 1e-3,
                  (depth_model_mm - 1) * 1e-3, (depth_model_mm + 1) * 1e-3)


def test_a_tumour_the_areas_beside_it_each_told_of_is_one_row_with_the_newest_figures(qtbot):
    table = FindingsTable()
    qtbot.addWidget(table)
    # the paper's flat phantom as the console tells it: each tumour by the area over it and the ones beside
    told = [(0, _tumour(12.1, depth_model_mm=2.0)), (0, _tumour(12.0, "force")), (1, _tumour(12.2, depth_model_mm=1.9)),
            (2, _tumour(12.1, depth_model_mm=1.8)), (4, _tumour(36.0, depth_model_mm=5.3))]
    table.set_findings(told)
    rows = [[table.item(r, c).text() for c in range(table.columnCount())] for r in range(table.rowCount())]
    assert [(r[0], r[1], r[2]) for r in rows] == [("1, 2, 3", "stiffness", "12.1, 15.0"), ("1", "force", "12.0, 15.0"),
                                                 ("5", "stiffness", "36.0, 15.0")]
    assert rows[0][5] == "1.8 [0.8, 2.8]"  # the newest telling's depth, with the most areas behind it
    moved = []
    table.move_requested.connect(lambda x, y: moved.append((round(x * 1e3, 1), round(y * 1e3, 1))))
    table.cellDoubleClicked.emit(2, 0)
    assert moved == [(36.0, 15.0)]
