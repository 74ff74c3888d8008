"""What both widgets share (imports napari): finding the plugin's layers, adding or updating them, and
showing the core's messages in the widget and as napari notifications.

Layers find each other through their metadata (``napari_fdt.napari.layers``): an acquisition layer has an
``fdt_id``; the sources, RI, masks, coverage and comparison layers derived from it carry that id as
``fdt_owner`` and their ``fdt_kind``. Layer names are for people and may be changed freely.
"""

from __future__ import annotations

import contextlib
import threading
import time
import warnings
from typing import Any, Callable, Iterator

import numpy as np
from magicgui.widgets import Label
from napari.layers import Image, Layer, Points
from napari.utils.notifications import show_error, show_warning

from napari_fdt.data.acquisition import Acquisition
from napari_fdt.errors import FDTInputError, FDTWarning
from napari_fdt.napari.layers import (
    META_ACQUISITION,
    META_ID,
    META_KIND,
    META_NEEDS_OPTICS,
    META_OWNER,
    META_PATH,
    LayerDataTuple,
    acquisition_layer,
    new_id,
    points_to_sources,
    source_point_size_um,
    sources_layer,
)
from napari_fdt.napari.result_view import oblique_camera

__all__ = [
    "acquisition_layer_choices", "find_layer", "put_layer", "sources_for", "set_sources", "Feedback",
    "acquisition_of", "no_layer", "BackgroundTasks", "CloseWatcher", "track_thread", "adopt_layer", "sections_panel",
    "follow_ndisplay", "watch_wrong_reader", "DERIVED_KINDS", "tighten", "claim_dock_height",
]

# Python's warning state (filters, ``showwarning``) is global to the process, and a worker thread from
# superqt holds ``warnings.catch_warnings()`` for as long as it runs. If the GUI thread entered its own
# ``catch_warnings`` inside that span and left it after the worker did, the worker's handler would stay
# installed for ever (and later warnings would go to a dead thread). So ``Feedback.guard`` records warnings
# only while no plugin thread can be inside its span; meanwhile warnings from the GUI thread reach the
# running thread's ``warned`` signal, whose widget shows them.
_THREADS: dict[int, Callable[[], bool]] = {}


def track_thread(worker, done: threading.Event) -> None:
    """Count ``worker`` as running until ``done`` is set and its ``run()`` has left its warning capture."""
    key = id(worker)
    _THREADS[key] = lambda: not done.is_set() or bool(worker.is_running)
    worker.finished.connect(lambda: _THREADS.pop(key, None))  # emitted after run() left its warning capture


def _threads_running() -> bool:
    for key, alive in list(_THREADS.items()):
        if alive():
            return True
        _THREADS.pop(key, None)
    return False

def no_layer() -> FDTInputError:
    """The error for actions that need an acquisition layer when none is open."""
    return FDTInputError(
        "images", "no image stack is open",
        "open an acquisition folder (File > Open Folder…, reader napari-fdt) or a TIFF stack (File > Open File(s)…), "
        "or a sample (File > Open Sample > napari-fdt)",
    )


#: Layer kinds the plugin derives from an acquisition: never offered as the images of a reconstruction.
DERIVED_KINDS = frozenset({"ri", "truth", "masks", "preview", "coverage", "comparison"})


def is_image_stack(layer) -> bool:
    """An image layer that can hold a stack of camera images (N, H, W) or (N, 1, H, W), whichever reader opened it."""
    if not isinstance(layer, Image) or getattr(layer, "rgb", False) or layer.metadata.get(META_KIND) in DERIVED_KINDS:
        return False
    shape = tuple(np.shape(layer.data))
    return len(shape) == 3 or (len(shape) == 4 and shape[1] == 1)


def acquisition_layer_choices(viewer) -> list[tuple[str, Image]]:
    """(name, layer) of every image layer that may be a stack: the plugin's own, and those of any other reader."""
    return [(layer.name, layer) for layer in viewer.layers if is_image_stack(layer)]


def adopt_layer(viewer, layer: Image, acq: Acquisition) -> Image:
    """Make ``layer`` the acquisition ``acq`` (metadata, physical scale, the image index on its own axis).

    A stack from another reader is (N, H, W): it is replaced, at the same place in the layer list and with the
    same name, by the plugin's (N, 1, H, W) layer (the data are shared, not copied). Returns the layer now shown.
    """
    data, kwargs, _ = acquisition_layer(acq, path=layer.metadata.get(META_PATH), name=layer.name)
    meta = dict(layer.metadata)
    meta.update(kwargs.pop("metadata"))
    meta[META_ID] = layer.metadata.get(META_ID) or new_id()
    meta.pop(META_NEEDS_OPTICS, None)
    if np.ndim(layer.data) == 4:
        layer.metadata.update(meta)
        layer.metadata.pop(META_NEEDS_OPTICS, None)
        layer.units = kwargs["units"]
        layer.scale = kwargs["scale"]
        layer.translate = kwargs["translate"]
        return layer
    index = list(viewer.layers).index(layer)
    kwargs.update(metadata=meta, contrast_limits=layer.contrast_limits, visible=layer.visible)
    new = viewer.add_image(data, **kwargs)
    viewer.layers.remove(layer)
    viewer.layers.move(list(viewer.layers).index(new), index)
    new.name = layer.name
    return new


def follow_layers(viewer, combo, refresh) -> None:
    """Keep a layer combo box in step with the viewer: ``refresh`` runs now and whenever layers come or go."""
    events = viewer.layers.events
    events.inserted.connect(refresh)
    events.removed.connect(refresh)
    refresh()


def refresh_layer_choice(combo) -> None:
    """Re-read the combo's choices and select the first one when nothing is selected."""
    combo.reset_choices()
    if combo.value is None and combo.choices:
        combo.value = combo.choices[0]


def acquisition_of(layer: Image | None) -> Acquisition:
    """The layer's acquisition; :class:`FDTInputError` when there is no layer or its optics are not set."""
    if layer is None:
        raise no_layer()
    acq = layer.metadata.get(META_ACQUISITION)
    if acq is None:
        from napari_fdt.napari.layers import META_FILE_OPTICS, META_OPTICS_ENTRIES
        from napari_fdt.napari.settings import format_entry, missing_optics

        entries = {k: format_entry(v) for k, v in (layer.metadata.get(META_FILE_OPTICS) or {}).items()}
        entries.update({k: v for k, v in (layer.metadata.get(META_OPTICS_ENTRIES) or {}).items() if v})
        missing = missing_optics(entries)
        raise FDTInputError("optics", f"{layer.name} has no optics yet" + (f" (missing {', '.join(missing)})" if missing else ""),
                            "enter them in the FDT acquisition widget and press Apply optics")
    return acq


def find_layer(viewer, owner: str | None, kind: str, layer_type: type[Layer] = Layer) -> Layer | None:
    """The most recent layer of ``kind`` belonging to acquisition ``owner`` (None if none)."""
    found = [layer for layer in viewer.layers if isinstance(layer, layer_type)
             and layer.metadata.get(META_KIND) == kind and layer.metadata.get(META_OWNER) == owner]
    return found[-1] if found else None


def put_layer(viewer, layer_data: LayerDataTuple) -> Layer:
    """Update the layer of the same kind and owner in place (data, scale, placement, metadata), or add it."""
    data, kwargs, layer_type = layer_data
    meta = kwargs.get("metadata", {})
    cls = {"image": Image, "points": Points}[layer_type]
    layer = find_layer(viewer, meta.get(META_OWNER), meta.get(META_KIND), cls)
    if layer is None or (layer_type == "image" and np.ndim(layer.data) != np.ndim(data)):
        if layer is not None:
            viewer.layers.remove(layer)
        return getattr(viewer, f"add_{layer_type}")(data, **kwargs)
    layer.data = data
    for key in ("scale", "translate"):
        if key in kwargs:
            setattr(layer, key, kwargs[key])
    layer.metadata.update(meta)
    if layer_type == "image":
        layer.reset_contrast_limits()
    return layer


def sources_for(viewer, layer: Image, acq: Acquisition, required: bool = True) -> np.ndarray | None:
    """Source positions (N, 3) µm for an acquisition: the (edited) points layer, else the file's, else None/error."""
    points = find_layer(viewer, layer.metadata.get(META_ID), "sources", Points)
    if points is not None:
        return points_to_sources(points.data, acq.n_images)
    if acq.sources_um is not None:
        return acq.sources_um
    if required:
        raise FDTInputError("sources", f"{layer.name} has no source positions",
                            "press Fit sources in the FDT acquisition widget")
    return None


def set_sources(viewer, layer: Image, sources_um: np.ndarray, *, kind: str = "sources", name: str | None = None) -> Points:
    """Show ``sources_um`` (N, 3) in the acquisition's points layer of ``kind`` (updated in place, or added).

    ``kind`` ``sources``: the editable start of a run (Fit sources, Sources from file); ``calibrated``: a run's
    calibrated positions, in a layer of their own (``name``), so a calibration never overwrites the edited points.
    """
    acq = layer.metadata.get(META_ACQUISITION)
    size = source_point_size_um(acq.image_shape, acq.optics.pixel_size_um) if acq is not None else 1.0
    colour = "cyan" if kind == "sources" else "orange"
    data = sources_layer(sources_um, name or f"{layer.name} sources", layer.metadata.get(META_ID), size_um=size,
                         kind=kind, colour=colour)
    if kind != "sources" and name is not None:  # one layer per run, found by name
        for old in viewer.layers:
            if isinstance(old, Points) and old.name == name and old.metadata.get(META_KIND) == kind:
                old.data = data[0]
                return old
        return viewer.add_points(data[0], **data[1])
    return put_layer(viewer, data)


class Feedback:
    """A label in the widget for messages, mirrored as napari notifications.

    ``with feedback.guard():`` turns :class:`FDTInputError` into an error message and :class:`FDTWarning` into warnings, so the widget stays usable.
    """

    def __init__(self) -> None:
        self.label = Label(value="")
        self.label.native.setWordWrap(True)
        self.last_error: str | None = None

    def error(self, message: str) -> None:
        self.last_error = message
        self.label.value = f"error: {message}"
        self.label.native.setStyleSheet("color: #ff6060;")
        show_error(message)

    def info(self, message: str) -> None:
        self.last_error = None
        self.label.value = message
        self.label.native.setStyleSheet("")

    def warn(self, message: str) -> None:
        self.label.value = f"warning: {message}"
        self.label.native.setStyleSheet("color: #ffb040;")
        show_warning(message)

    def on_notification(self, event) -> None:
        """A napari notification: napari's error for a folder of ours opened by another reader gets the hint."""
        message = str(getattr(event, "message", event))
        hint = wrong_reader_hint(message)
        if hint is not None and not message.startswith("this looks like"):
            self.label.value = f"hint: {hint}"
            self.label.native.setStyleSheet("color: #ffb040;")

    def show_warning(self, args: tuple) -> None:
        """A warning relayed by a worker thread (``warnings.showwarning`` arguments): the core's are shown."""
        message, category = args[0], args[1]
        if isinstance(category, type) and issubclass(category, FDTWarning):
            self.warn(str(message))
        else:
            import sys

            print(warnings.formatwarning(*args[:4]), file=sys.stderr, end="")

    def exception(self, exc: BaseException) -> None:
        """An exception from a worker thread: a user error's message, or a bug's type and message (traceback to the log)."""
        if not isinstance(exc, FDTInputError):
            import traceback

            traceback.print_exception(type(exc), exc, exc.__traceback__)
        self.error(str(exc) if isinstance(exc, FDTInputError) else f"{type(exc).__name__}: {exc}")

    @contextlib.contextmanager
    def guard(self) -> Iterator[None]:
        """Run a user action: errors become one message, warnings are shown."""
        if _threads_running():  # see _THREADS: warnings go to the running thread's widget
            try:
                yield
            except FDTInputError as exc:
                self.error(str(exc))
            return
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", FDTWarning)
            try:
                yield
            except FDTInputError as exc:
                self.error(str(exc))
                return
        for w in caught:
            if issubclass(w.category, FDTWarning):
                self.warn(str(w.message))
            else:
                warnings.showwarning(w.message, w.category, w.filename, w.lineno)


class CloseWatcher:
    """Calls ``callback`` when a Qt window (napari's main window) closes, through public Qt API only.

    ``confirm()`` (optional) runs first when the user closes the window (a spontaneous close): False keeps the
    window open and the work running.
    """

    def __init__(self, window, callback, confirm: Callable[[], bool] | None = None) -> None:
        import weakref

        from qtpy.QtCore import QEvent, QObject

        # weak references: the main window must not keep a closed viewer's widgets alive
        def ref(fn):
            return None if fn is None else (weakref.WeakMethod(fn) if hasattr(fn, "__self__") else (lambda: fn))

        callback_ref, confirm_ref, window_ref = ref(callback), ref(confirm), weakref.ref(window)

        class _Filter(QObject):
            def eventFilter(self, obj, event):  # noqa: N802 (Qt name)
                if obj is window_ref() and event.type() == QEvent.Type.Close:
                    ask = confirm_ref() if confirm_ref is not None else None
                    if ask is not None and event.spontaneous() and not ask():
                        event.ignore()
                        return True
                    stop = callback_ref()
                    if stop is not None:
                        stop()
                return False

        self.filter = _Filter(window)
        window.installEventFilter(self.filter)


class _Task:
    """One background computation: its worker, the buttons it holds, and the event its thread sets when done."""

    def __init__(self, name: str, worker, buttons: tuple, done: threading.Event) -> None:
        self.name, self.worker, self.buttons, self.done = name, worker, buttons, done


class BackgroundTasks:
    """A widget's short computations (fits, previews, saving) in napari worker threads, off the GUI thread.

    :meth:`start` runs ``compute()`` in a ``thread_worker`` with the given buttons disabled; its result goes to
    ``on_result`` on the GUI thread (the ``returned`` signal), inside :meth:`Feedback.guard`. An error becomes
    the widget's message and a napari notification, a :class:`FDTWarning` a warning; the buttons come back
    either way (or ``refresh()`` decides which come back). One task per name at a time. Closing the viewer asks every task to stop, drops its result
    and waits (at most ``close_timeout_s``) until its thread has ended.
    """

    def __init__(self, viewer, feedback: Feedback, native, *, refresh: Callable[[], None] | None = None,
                 close_timeout_s: float = 60.0) -> None:
        self._viewer = viewer
        self._refresh = refresh
        self._feedback = feedback
        self._native = native
        self._tasks: dict[str, _Task] = {}
        self._closing = threading.Event()
        self._close_timeout_s = close_timeout_s
        self._close_watcher = None

    @property
    def running(self) -> bool:
        """True while any task's thread is alive."""
        return any(not t.done.is_set() for t in self._tasks.values())

    @property
    def idle(self) -> bool:
        """True when no task is pending: every thread has ended and its result or error has been shown."""
        return not self._tasks

    def is_running(self, name: str) -> bool:
        """True while task ``name`` runs."""
        task = self._tasks.get(name)
        return task is not None and not task.done.is_set()

    def start(self, name: str, compute: Callable[[], Any], on_result: Callable[[Any], None], *,
              buttons: tuple = (), message: str = ""):
        """Run ``compute()`` in a worker thread, then ``on_result(result)`` on the GUI thread; returns the worker.

        Returns None (and does nothing) while a task of the same name runs.
        """
        from superqt.utils import FunctionWorker  # public superqt API: errors and warnings are shown here

        if self.is_running(name) or self._closing.is_set():
            return None
        done = threading.Event()

        def job():
            try:
                return compute()
            finally:
                done.set()

        worker = FunctionWorker(job)
        task = _Task(name, worker, tuple(buttons), done)
        worker.returned.connect(lambda result: self._on_returned(task, on_result, result))
        worker.errored.connect(lambda exc: self._on_error(task, exc))
        worker.warned.connect(self._on_warning)
        worker.finished.connect(lambda: self._on_finished(task))
        self._tasks[name] = task
        for b in task.buttons:
            b.enabled = False
        if message:
            self._feedback.info(message)
        self._watch_close(task)
        track_thread(worker, done)
        worker.start()
        return worker

    # -- signals (GUI thread) ---------------------------------------------------------------------
    def _on_returned(self, task: _Task, on_result, result) -> None:
        if self._closing.is_set():
            return
        with self._feedback.guard():
            on_result(result)

    def _on_error(self, task: _Task, exc: Exception) -> None:
        if not self._closing.is_set():
            self._feedback.exception(exc)

    def _on_warning(self, args: tuple) -> None:
        if not self._closing.is_set():
            self._feedback.show_warning(args)

    def _on_finished(self, task: _Task) -> None:
        if self._tasks.get(task.name) is task:
            del self._tasks[task.name]
        if self._closing.is_set():
            return
        if self._refresh is not None:
            self._refresh()
        else:
            for b in task.buttons:
                b.enabled = True

    # -- closing the viewer -----------------------------------------------------------------------
    def _watch_close(self, task: _Task) -> None:
        if self._close_watcher is None:
            self._close_watcher = CloseWatcher(self._native.window(), self.close)

    def close(self) -> bool:
        """Stop every task (its result is dropped) and wait until their threads have ended."""
        tasks = list(self._tasks.values())
        if not any(not t.done.is_set() for t in tasks):
            return False
        self._closing.set()
        deadline = time.monotonic() + self._close_timeout_s
        for t in tasks:
            t.worker.quit()
        for t in tasks:
            t.done.wait(timeout=max(0.0, deadline - time.monotonic()))
        return True


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


def wrong_reader_hint(message: str) -> str | None:
    """The hint for napari's error when a folder of ours was opened with another reader, else None."""
    if "acquisition.json" in message or "images.tif" in message:
        return ("this looks like an FDT acquisition folder opened with another reader: open it with File > Open Folder… "
                "and choose napari-fdt in the Choose reader dialog (or File > Open File(s)… on its acquisition.json)")
    return None


def watch_wrong_reader(feedback: Feedback) -> None:
    """Show :func:`wrong_reader_hint` in the widget when napari reports such an error (a weak connection)."""
    from napari.utils.notifications import notification_manager

    notification_manager.notification_ready.connect(feedback.on_notification)
