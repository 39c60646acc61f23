"""The whole-tissue view: stitched pressure, stiffness and coverage that fill in as areas are palpated.

It shows a :class:`session.live.LiveMaps`, which keeps every recorded level and stitches them the way the
reviewer and the exported maps do, one map per force level. The view is fixed on the phantom (when its
extent is known): palpated areas fill in against the grey of what has not been touched yet, with the
planned areas numbered and the TSI's footprint drawn where it is now. Double-clicking a point asks to move
the TSI there (the window decides whether it may).

It is drawn the way the live maps are: y (the TSI's long axis, its 15 elements) to the right and x upwards,
in mm in the tissue frame, so the TSI's footprint and a hot spot look the same here as on the live maps, the
jog keys move the footprint the way their arrows point (left/right along y, up/down along x), and the
phantom's long side runs up the tall dock it lives in. That is the one orientation of every whole-tissue
map: the reviewer's (:mod:`widgets.review.map_view`), ``stitch -o`` and the report
(:mod:`widgets.map_painting`) draw x upwards and y to the right too, so a tumour up and to the left here is
up and to the left there. Drawing x across instead would have kept the exported pages' rows of wide maps,
but turned the footprint and the jog arrows a quarter turn from the live maps; the report stays readable
upright, its levels in columns. The colour ranges follow the data from 0 as on the live maps, with the same
floors, so the same colour means the same value on both.
"""

from __future__ import annotations

import math

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtGui, QtWidgets

from control.messages import LevelRecord
from hardware.interfaces import TactileConstraints
from session.flatfield import MIN_VOUCHING
from session.live import LiveMaps
from session.stitch import StitchResult
from widgets.colormaps import CONTOUR_COLORMAP, contrast_range
from widgets.plot_style import add_map_layers, follow_palette, map_view
from widgets.tactile_map import auto_levels

COVERAGE_LEVELS = (0.0, 2.0)  # 1 = palpated once, 2 = two areas overlap
# (objectName, label, LevelMap field, unit, display scale)
QUANTITIES = (
    ("tissuePressure", "Pressure", "pressure_pa", "kPa", 1e-3),
    ("tissueStiffness", "Stiffness", "stiffness_pa", "kPa", 1e-3),
    ("tissueStiffnessContrast", "Stiffness contrast", "stiffness_contrast", "%", 100.0),
    ("tissueCoverage", "Coverage", "coverage", "×", 1.0),
)
# the map whose tumours each quantity marks
_SOURCE = {"pressure_pa": "force", "stiffness_pa": "stiffness", "stiffness_contrast": "stiffness",
           "coverage": "stiffness"}


class WholeTissueView(QtWidgets.QWidget):
    """Signal ``move_requested(x_m, y_m)`` on a double-click. Child objectNames: ``tissueLevel`` (force
    level combo), the radio buttons of :data:`QUANTITIES`, ``tissueSummary``, ``tissuePlot``; scene items
    ``tissueImage``, ``tissueColorBar``; the TSI footprint is :meth:`footprint_rect_mm`."""

    move_requested = QtCore.Signal(float, float)

    def __init__(self, sensor: TactileConstraints, *, min_indentation_m: float, pressure_floor_pa: float,
                 stiffness_floor_pa: float, extent_m: tuple[float, float, float, float] | None = None,
                 areas: tuple[tuple[float, float], ...] = (), parent: QtWidgets.QWidget | None = None):
        super().__init__(parent)
        self._sensor = sensor
        self._maps = LiveMaps(sensor, min_indentation_m)
        self._floors = {"pressure_pa": pressure_floor_pa * 1e-3, "stiffness_pa": stiffness_floor_pa * 1e-3}
        self._extent = extent_m
        self._result: StitchResult | None = None
        self._levels: dict[str, tuple[float, float] | None] = {"pressure_pa": None, "stiffness_pa": None}
        self._chosen_force: float | None = None  # None: follow the highest level
        self._quantity = "pressure_pa"
        self._tsi: tuple[float, float] | None = None

        self._level_combo = QtWidgets.QComboBox(objectName="tissueLevel")
        self._level_combo.setToolTip("Force level of the stitched maps")
        self._level_combo.setMinimumWidth(120)
        self._level_combo.setPlaceholderText("no level recorded yet")
        self._level_combo.activated.connect(self._level_chosen)
        self._buttons: dict[str, QtWidgets.QRadioButton] = {}
        group = QtWidgets.QButtonGroup(self)
        top = QtWidgets.QHBoxLayout()
        for name, label, field, *_ in QUANTITIES:
            button = QtWidgets.QRadioButton(label, objectName=name)
            button.toggled.connect(lambda on, f=field: on and self.set_quantity(f))
            group.addButton(button)
            self._buttons[field] = button
            top.addWidget(button)
        self._buttons[self._quantity].setChecked(True)
        top.addStretch(1)
        at = QtWidgets.QHBoxLayout()  # a row of its own: beside the quantities the view could not be narrow
        at.addWidget(QtWidgets.QLabel("at"))
        at.addWidget(self._level_combo)
        at.addStretch(1)
        self._summary = QtWidgets.QLabel("no area palpated yet", objectName="tissueSummary", wordWrap=True)

        self._build_plot(areas)
        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(2, 2, 2, 2)
        layout.setSpacing(2)
        layout.addLayout(top)
        layout.addLayout(at)
        layout.addWidget(self._plot, 1)
        layout.addWidget(self._summary)
        self._refresh_levels()
        self._show()
        # Until someone chooses a map, the view turns to the stiffness contrast once it can be had: the raw
        # maps' brightest cells are the face's edge rows, striped at every seam between areas.
        self._contrast_when_ready = True

    # ---- construction --------------------------------------------------------------------------------

    def _build_plot(self, areas) -> None:
        self._plot = pg.PlotWidget()
        self._plot.setObjectName("tissuePlot")
        item = self._plot.getPlotItem()
        self._view = map_view(self._plot, "y (mm)", "x (mm)")
        self._view.setMouseEnabled(x=False, y=False)
        self._no_data, self._image = add_map_layers(self._view, "tissueImage")
        sx, sy = self._sensor.size_m
        for k, (x, y) in enumerate(areas):
            # beside the area, left of the TSI's footprint: over its middle a tumour's circle hid the number
            label = pg.TextItem(str(k + 1), color=(255, 255, 255, 200), anchor=(1.0, 0.5))
            label.setPos((y - sy / 2) * 1e3 - 1.0, x * 1e3)
            label.setZValue(4)
            self._view.addItem(label)
        self._footprint = QtWidgets.QGraphicsRectItem(-sy * 500, -sx * 500, sy * 1e3, sx * 1e3)
        self._footprint.setPen(pg.mkPen((255, 255, 255), width=2.5))
        self._footprint.setBrush(QtGui.QBrush(QtCore.Qt.BrushStyle.NoBrush))
        self._footprint.setZValue(8)
        self._footprint.setVisible(False)
        self._view.addItem(self._footprint)
        self._spots = pg.ScatterPlotItem(symbol="o", size=16, pen=pg.mkPen((255, 255, 255), width=2.5),
                                         brush=None, pxMode=True)
        self._spots.setObjectName("tissueSpots")
        self._spots.setZValue(9)
        self._view.addItem(self._spots)
        self._depth_labels: list[pg.TextItem] = []  # each circle's depth, beside it
        self._told: list = []  # the tumours as the surgeon was told of them (their depths)
        self._bar = pg.ColorBarItem(values=(0.0, 1.0), colorMap=CONTOUR_COLORMAP, label="kPa", interactive=False,
                                    colorMapMenu=False, width=16)
        self._bar.setObjectName("tissueColorBar")
        item.layout.addItem(self._bar, 2, 5)
        self._plot.scene().sigMouseClicked.connect(self._clicked)
        if self._extent is not None:
            self._show_extent(self._extent)
        self._apply_palette()

    def _apply_palette(self) -> None:
        axes = [self._plot.getPlotItem().getAxis(side) for side in ("bottom", "left")]
        follow_palette(self, [self._plot], axes + [self._bar.getAxis(side) for side in ("left", "right")])

    def changeEvent(self, event: QtCore.QEvent) -> None:
        if event.type() == QtCore.QEvent.Type.PaletteChange:
            self._apply_palette()
        super().changeEvent(event)

    # ---- public API ----------------------------------------------------------------------------------

    def add_record(self, record: LevelRecord) -> None:
        """Keep one recorded level; the maps are re-stitched by the next :meth:`refresh`."""
        self._maps.add(record)

    def refresh(self) -> None:
        """Re-stitch if levels were recorded since the last call (cheap otherwise; call per display frame)."""
        if not self._maps.changed:
            return
        self._result = self._maps.stitched()
        self._refresh_levels()
        if self._contrast_when_ready and self._maps.flat_field_ready():
            self.set_quantity("stiffness_contrast")  # shows it
        else:
            self._show()

    def result(self) -> StitchResult | None:
        return self._result

    def set_reference(self, reference) -> None:
        """A reference palpation (:class:`session.flatfield.Reference`) for the live flat field, or None;
        raises FlatFieldError for one the live maps cannot use."""
        self._maps.set_reference(reference)
        self.refresh()

    def reference(self):
        return self._maps.reference

    def reference_from_levels(self, description: str):
        """The levels recorded so far as a reference palpation (raises FlatFieldError before the first)."""
        return self._maps.reference_from_levels(description)

    def frame_contrast(self, values, map_name: str, force_N: float):
        """A live frame flat-fielded (:meth:`session.live.LiveMaps.frame_contrast`), or None."""
        return self._maps.frame_contrast(values, map_name, force_N)

    def set_depth_model(self, model) -> None:
        """What gives the findings their model-based depth (:class:`session.analysis.DepthModel`), or None."""
        self._maps.depth_model = model

    def findings_in(self, region: int, told=()) -> list | None:
        """The tumours found so far that area ``region`` saw, but those ``told`` of already; None while the
        flat field cannot be had."""
        self.refresh()
        return self._maps.findings_in(region, told) if self._maps.flat_field_ready() else None

    def expect_physics(self, expected: bool) -> None:
        """Whether the contrast waits for the physics (:meth:`set_physics`), or does without it."""
        if expected:
            self._maps.physics_expected = True
        else:
            self._maps.drop_physics()
        self.refresh()

    def set_physics(self, records: int, patterns: dict, description: str) -> None:
        """The physics of the first ``records`` levels (:meth:`session.live.LiveMaps.set_physics`)."""
        self._maps.set_physics(records, patterns, description)
        self.refresh()

    def set_told(self, tumours) -> None:
        """The tumours as the surgeon was told of them: each circle on the map carries the depth told."""
        self._told = list(tumours)
        if self._result is not None:
            self._show()

    def depth_labels(self) -> list[str]:
        return [label.toPlainText() for label in self._depth_labels]

    def _show_depths(self, found) -> None:
        for label in self._depth_labels:
            self._view.removeItem(label)
        self._depth_labels = []
        for tumour in found:
            told = [t for t in self._told if t.source == tumour.source
                    and math.hypot(t.x_m - tumour.x_m, t.y_m - tumour.y_m) <= self._maps.detect_params.merge_radius_m]
            if not told:
                continue
            depth = told[0].depth_model_m if math.isfinite(told[0].depth_model_m) else told[0].depth_m
            if not math.isfinite(depth):
                continue
            label = pg.TextItem(f"{depth * 1e3:.1f} mm", color=(255, 255, 255), anchor=(-0.25, 0.5),
                                fill=pg.mkBrush(0, 0, 0, 150))
            label.setPos(tumour.y_m * 1e3, tumour.x_m * 1e3)
            label.setZValue(10)
            self._view.addItem(label)
            self._depth_labels.append(label)

    def findings_pending(self, region: int) -> bool:
        """Whether area ``region`` waits for its physics before its findings can be told."""
        return self._maps.pending(region)

    def levels(self):
        """Every level recorded so far."""
        return self._maps.levels()

    def spot_count(self) -> int:
        return len(self._spots.data)

    def record_count(self) -> int:
        return self._maps.level_count

    def quantity(self) -> str:
        return self._quantity

    def set_quantity(self, field: str) -> None:
        if field not in self._buttons:
            raise ValueError(f"unknown whole-tissue map {field!r} (known: {', '.join(self._buttons)})")
        self._contrast_when_ready = False
        if field == self._quantity:
            return
        self._quantity = field
        self._buttons[field].setChecked(True)
        self._show()

    def level_force_N(self) -> float | None:
        """The force level shown (None before any level is recorded)."""
        index = self._level_index()
        return self._result.levels[index].force_N if index is not None else None

    def set_level_force_N(self, force_N: float | None) -> None:
        """Show the level nearest ``force_N``; None follows the highest level recorded."""
        self._chosen_force = force_N
        self._refresh_levels()
        self._show()

    def set_tsi_position(self, x_m: float, y_m: float) -> None:
        """Where the TSI's face is now (its footprint is drawn there)."""
        position = (round(x_m * 1e4), round(y_m * 1e4))  # redraw only after 0.1 mm of travel
        if position == self._tsi:
            return
        self._tsi = position
        self._footprint.setPos(y_m * 1e3, x_m * 1e3)
        self._footprint.setVisible(True)

    def footprint_rect_mm(self) -> QtCore.QRectF | None:
        """The footprint as drawn: left/width along y, top/height along x, in mm."""
        if not self._footprint.isVisible():
            return None
        return self._footprint.mapRectToParent(self._footprint.rect())

    def shown_values(self) -> np.ndarray | None:
        """The shown map in SI units, shaped (nx, ny) (None before any level is recorded)."""
        index = self._level_index()
        return None if index is None else self._result.levels[index].quantity(self._quantity)

    def levels_shown(self) -> tuple[float, float]:
        """The colour range in display units (kPa, or × for coverage)."""
        return tuple(self._bar.levels())

    # ---- internals -----------------------------------------------------------------------------------

    def _level_index(self) -> int | None:
        if self._result is None or not self._result.levels:
            return None
        if self._chosen_force is None:
            return len(self._result.levels) - 1
        forces = np.array(self._result.level_forces_N())
        return int(np.argmin(np.abs(forces - self._chosen_force)))

    def _refresh_levels(self) -> None:
        combo = self._level_combo
        forces = self._result.level_forces_N() if self._result is not None else []
        items = [f"{f:g} N" for f in forces]
        if [combo.itemText(i) for i in range(combo.count())] != items:
            combo.clear()
            combo.addItems(items)
        index = self._level_index()
        combo.setEnabled(index is not None)
        if index is not None and combo.currentIndex() != index:
            combo.setCurrentIndex(index)

    def _level_chosen(self, index: int) -> None:
        forces = self._result.level_forces_N() if self._result is not None else []
        if 0 <= index < len(forces):
            # the highest entry means "follow the highest", so later, higher levels keep showing up
            self._chosen_force = None if index == len(forces) - 1 else forces[index]
            self._show()

    def _show(self) -> None:
        index = self._level_index()
        unit, scale = next((u, s) for _, _, f, u, s in QUANTITIES if f == self._quantity)
        self._bar.getAxis("left").setLabel(unit)
        if index is None:
            self._image.clear()
            self._summary.setText("no area palpated yet")
            return
        result = self._result
        level = result.levels[index]
        if self._quantity == "coverage":
            values = np.where(level.coverage > 0, level.coverage, np.nan)
            levels = COVERAGE_LEVELS
        elif self._quantity.endswith("_contrast"):
            values = level.extra.get(self._quantity, np.full(level.coverage.shape, np.nan))
            levels = tuple(v * scale for v in contrast_range(values))
        else:
            values = level.quantity(self._quantity)
            finite = values[np.isfinite(values)]
            top = float(finite.max()) * scale if finite.size else 0.0
            levels = auto_levels(top, self._levels[self._quantity], self._floors[self._quantity])
            self._levels[self._quantity] = levels
        x0, x1, y0, y1 = (v * 1e3 for v in result.grid.extent_m)
        image = np.ascontiguousarray(values * scale, dtype=np.float32)  # rows along x: x upwards
        self._image.setImage(image, autoLevels=False, levels=levels, rect=QtCore.QRectF(y0, x0, y1 - y0, x1 - x0))
        self._bar.setLevels(levels, update_items=False)
        if self._extent is None:
            self._show_extent(result.grid.extent_m)
        found = [t for t in self._maps.tumours()
                 if t.source == _SOURCE[self._quantity] and level.force_N >= t.first_level_N - 1e-9]
        self._spots.setData([t.y_m * 1e3 for t in found], [t.x_m * 1e3 for t in found])
        self._show_depths(found)
        self._summary.setText(self._describe(level))

    def _describe(self, level) -> str:
        regions = self._maps.region_count
        text = f"{self._maps.level_count} levels recorded in {regions} area{'s' if regions != 1 else ''}"
        if self._extent is not None:
            share = self._result.covered_fraction(self._result.levels.index(level), extent_m=self._extent)
            text += f" · {share * 100:.0f} % of the phantom covered at {level.force_N:g} N"
        else:
            covered_m2 = float(np.count_nonzero(level.coverage > 0.5)) * self._result.grid.cell_m ** 2
            text += f" · {covered_m2 * 1e6:.0f} mm² covered at {level.force_N:g} N"
        if math.isfinite(level.tsi_indentation_m):
            text += f" · mean depth {level.tsi_indentation_m * 1e3:.1f} mm"
        if not self._maps.flat_field_ready():
            if self._maps.physics_expected and regions > MIN_VOUCHING:
                text += " · contrast and tumours once the tissue model of the areas palpated is computed"
            else:
                text += " · contrast and tumours from the 4th area on (or with a reference palpation)"
        else:
            text += f" · {sum(1 for t in self._maps.tumours() if t.source == 'stiffness')} tumour(s) so far"
        return text

    def _show_extent(self, extent_m) -> None:
        x0, x1, y0, y1 = (v * 1e3 for v in extent_m)
        rect = QtCore.QRectF(y0, x0, y1 - y0, x1 - x0)
        self._no_data.setRect(rect)
        self._view.setRange(rect, padding=0.03)

    def _clicked(self, event) -> None:
        if not event.double():
            return
        point = self._view.mapSceneToView(event.scenePos())
        self.move_requested.emit(point.y() * 1e-3, point.x() * 1e-3)
