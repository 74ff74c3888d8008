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
    LayerDataTuple,
    points_to_sources,
    sources_layer,
)

__all__ = [
    "acquisition_layer_choices", "find_layer", "put_layer", "sources_for", "set_sources", "Feedback",
    "acquisition_of", "no_layer", "BackgroundTasks", "CloseWatcher", "track_thread",
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
    _THREADS[key] = lambda: not done.is_set() or bool(getattr(worker, "_running", False))


def _threads_running() -> bool:
    for key, alive in list(_THREADS.items()):
        if alive():
            return True
        _THREADS.pop(key, None)
    return False

def no_layer() -> FDTInputError:
    """The error for actions that need an acquisition layer when none is open."""
    return FDTInputError(
        "layer", "no acquisition or image stack is open",
        "open an acquisition folder or a TIFF stack (File > Open), or a sample (File > Open Sample > napari-fdt)",
    )


def acquisition_layer_choices(viewer) -> list[tuple[str, Image]]:
    """(name, layer) of every image layer that is an acquisition or a bare stack waiting for optics."""
    return [(layer.name, layer) for layer in viewer.layers
            if isinstance(layer, Image) and (META_ACQUISITION in layer.metadata or layer.metadata.get(META_NEEDS_OPTICS))]


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
        raise FDTInputError("optics", f"{layer.name} has no optics yet",
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


def set_sources(viewer, layer: Image, sources_um: np.ndarray) -> Points:
    """Show ``sources_um`` (N, 3) in the acquisition's points layer (updated in place, or added)."""
    return put_layer(viewer, sources_layer(sources_um, f"{layer.name} sources", layer.metadata.get(META_ID)))


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
    """Calls ``callback`` when a Qt window closes (used where napari's task-status hook is missing)."""

    def __init__(self, window, callback) -> None:
        from qtpy.QtCore import QEvent, QObject

        class _Filter(QObject):
            def eventFilter(self, obj, event):  # noqa: N802 (Qt name)
                if event.type() == QEvent.Type.Close:
                    callback()
                return False

        self.filter = _Filter(window)
        window.installEventFilter(self.filter)


class _Task:
    """One background computation: its worker, the buttons it holds, and the event its thread sets when done."""

    def __init__(self, name: str, worker, buttons: tuple, done: threading.Event) -> None:
        self.name, self.worker, self.buttons, self.done = name, worker, buttons, done
        self.status_id = None


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
        from napari.qt.threading import create_worker
        from superqt.utils import FunctionWorker  # without napari's relay: errors and warnings are shown here

        if self.is_running(name) or self._closing.is_set():
            return None
        done = threading.Event()

        def job():
            try:
                return compute()
            finally:
                done.set()

        worker = create_worker(job, _start_thread=False, _ignore_errors=True, _worker_class=FunctionWorker)
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
        self._status(task, "FAILED", str(exc))
        if not self._closing.is_set():
            self._feedback.exception(exc)

    def _on_warning(self, args: tuple) -> None:
        if not self._closing.is_set():
            self._feedback.show_warning(args)

    def _on_finished(self, task: _Task) -> None:
        self._status(task, "COMPLETED")
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
        window = getattr(self._viewer, "window", None)
        register = getattr(window, "_register_task_status", None)
        if register is not None:
            from napari.utils.task_status import Status

            task.status_id = register("napari-fdt", Status.BUSY, task.name, cancel_callback=self.close)
        elif self._close_watcher is None:
            self._close_watcher = CloseWatcher(self._native.window(), self.close)

    def _status(self, task: _Task, status: str, text: str = "") -> None:
        update = getattr(getattr(self._viewer, "window", None), "_update_task_status", None)
        if update is not None and task.status_id is not None:
            from napari.utils.task_status import Status

            update(task.status_id, getattr(Status, status), text or task.name)

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
