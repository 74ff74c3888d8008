"""A small Qt plot of the training (grey) and validation (orange) error against iteration, drawn with QPainter.

The numbers and their mapping to pixels are :class:`napari_fdt.napari.curve.ErrorCurve`'s; this widget paints them.
"""

from __future__ import annotations

from typing import Any

from qtpy.QtCore import QPointF, Qt
from qtpy.QtGui import QColor, QPainter, QPen, QPolygonF
from qtpy.QtWidgets import QSizePolicy, QWidget

from napari_fdt.napari.curve import ErrorCurve

__all__ = ["ErrorCurveWidget"]

COLOURS = {"train": QColor(170, 170, 170), "validation": QColor(255, 150, 40)}


class ErrorCurveWidget(QWidget):
    """Plot of :attr:`curve`; :meth:`add` a snapshot and it repaints (call from the GUI thread)."""

    def __init__(self, parent: QWidget | None = None, height_px: int = 90) -> None:
        super().__init__(parent)
        self.curve = ErrorCurve()
        self.setMinimumHeight(height_px)
        self.setSizePolicy(QSizePolicy.Expanding, QSizePolicy.Fixed)
        self.setToolTip("relative image error against iteration (log scale): grey the training batch, "
                        "orange the held-out images (validation_fraction > 0)")

    def reset(self, total_iterations: int) -> None:
        self.curve.reset(total_iterations)
        self.update()

    def add(self, snapshot: Any) -> None:
        self.curve.add(snapshot)
        self.update()

    def paintEvent(self, event) -> None:  # noqa: N802 (Qt's name)
        painter = QPainter(self)
        painter.setRenderHint(QPainter.Antialiasing)
        painter.setPen(QPen(QColor(90, 90, 90), 1))
        painter.drawRect(0, 0, self.width() - 1, self.height() - 1)
        for name, points in self.curve.polylines(self.width(), self.height()).items():
            if len(points) < 2:
                continue
            painter.setPen(QPen(COLOURS[name], 2 if name == "validation" else 1, Qt.SolidLine))
            painter.drawPolyline(QPolygonF([QPointF(x, y) for x, y in points]))
        painter.end()
