"""How the widgets sit in napari (imports Qt through magicgui and napari): dock height, margins, collapsible sections,
and what 3D hides.
"""

from typing import Any

from napari_fdt.napari.layers import (
    META_KIND,
    META_NEEDS_OPTICS,
)
from napari_fdt.napari.result_view import oblique_camera

__all__ = ["claim_dock_height", "tighten", "sections_panel", "follow_ndisplay"]


def claim_dock_height(native, share: float = 0.55) -> None:
    """When ``native`` is first shown in a dock of a main window, ask for ``share`` of the window's height
    (public Qt: ``QMainWindow.resizeDocks``); the dock above keeps the rest. Its settings then need less scrolling."""
    from qtpy.QtCore import QEvent, QObject, Qt, QTimer
    from qtpy.QtWidgets import QDockWidget, QMainWindow

    def resize() -> None:
        dock, parent = None, native.parentWidget()
        while parent is not None and dock is None:
            dock = parent if isinstance(parent, QDockWidget) else None
            parent = parent.parentWidget()
        window = native.window()
        if dock is not None and isinstance(window, QMainWindow) and not dock.isFloating():
            window.resizeDocks([dock], [int(share * window.height())], Qt.Orientation.Vertical)

    class _OnFirstShow(QObject):
        def eventFilter(self, obj, event):  # noqa: N802 (Qt name)
            if event.type() == QEvent.Type.Show:
                native.removeEventFilter(self)
                QTimer.singleShot(0, resize)
            return False

    native._fdt_first_show = _OnFirstShow(native)  # kept alive with the widget
    native.installEventFilter(native._fdt_first_show)


def tighten(container, margins: tuple[int, int, int, int] = (2, 0, 2, 0)) -> None:
    """Small margins for a magicgui container and the containers inside it (a dock's height is precious)."""
    from magicgui.widgets import Container

    container.margins = margins
    for child in container:
        if isinstance(child, Container):
            tighten(child, (0, 0, 0, 0))


def sections_panel(sections: list[tuple[str, Any, bool]], height_px: int = 260):
    """A scroll area of collapsible sections ``(title, magicgui container, expanded)``: the widget fits any screen height.

    ``height_px``: the most height it asks for (napari shares the dock's height by what its widgets ask)."""
    from qtpy.QtCore import QSize, Qt
    from qtpy.QtWidgets import QFrame, QScrollArea, QVBoxLayout, QWidget
    from superqt import QCollapsible

    class _Scroll(QScrollArea):
        def sizeHint(self) -> QSize:  # noqa: N802 (Qt name): the content's height up to height_px, scroll for the rest
            content = self.widget().sizeHint().height() + 2 if self.widget() is not None else height_px
            return QSize(super().sizeHint().width(), min(height_px, content))

    inner = QWidget()
    layout = QVBoxLayout(inner)
    layout.setContentsMargins(0, 0, 0, 0)
    layout.setSpacing(2)
    boxes: list = []
    for title, container, expanded in sections:
        tighten(container)
        box = QCollapsible(title)
        box.addWidget(container.native)
        if expanded:
            box.expand(animate=False)
        else:
            box.collapse(animate=False)
        layout.addWidget(box)
        boxes.append(box)
    layout.addStretch(1)
    scroll = _Scroll()
    scroll.setWidgetResizable(True)
    scroll.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
    scroll.setFrameShape(QFrame.NoFrame)
    scroll.setWidget(inner)
    scroll.setMinimumHeight(60)
    for box in boxes:  # a section opened or closed: the panel asks for its new height
        box.toggled.connect(lambda _open: scroll.updateGeometry())
    return scroll


#: Kinds hidden in 3D: image stacks and their masks are images, not volumes (3D shows the RI volume and the sources).
_HIDDEN_IN_3D = frozenset({"acquisition", "stack", "masks"})


def follow_ndisplay(viewer) -> None:
    """In 3D hide the image stacks (and masks) the plugin knows and turn the camera oblique; back in 2D show again
    those it hid.

    Each widget connects its own follower; they agree (a layer already hidden is left to the one that hid it)."""
    hidden: list = []

    def on_ndisplay(event=None) -> None:
        if viewer.dims.ndisplay == 3:
            oblique_camera(viewer)  # not straight down the z axis, where the slices overlap into one block
            for layer in viewer.layers:
                if layer.visible and (layer.metadata.get(META_KIND) in _HIDDEN_IN_3D or layer.metadata.get(META_NEEDS_OPTICS)):
                    layer.visible = False
                    hidden.append(layer)
        else:
            for layer in hidden:
                if layer in viewer.layers:
                    layer.visible = True
            hidden.clear()

    viewer.dims.events.ndisplay.connect(on_ndisplay)
