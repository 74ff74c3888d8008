"""Background work and messages of the widgets (imports napari): the core's errors and warnings shown in the widget and as
napari notifications (:class:`Feedback`), work in napari worker threads (:class:`BackgroundTasks`: short computations, and
the reconstruction's run as a stream of updates), the
threads the plugin runs (warnings go to the running one), and a watcher of the main window's closing
(:class:`CloseWatcher`), and the hint when another reader opened an acquisition file.
"""

import contextlib
import threading
import time
import warnings
from typing import Any, Callable, Iterator

from magicgui.widgets import Label
from napari.utils.notifications import show_error, show_warning

from napari_fdt.errors import FDTInputError, FDTWarning

__all__ = ["Feedback", "BackgroundTasks", "CloseWatcher", "track_thread", "wrong_reader_hint", "watch_wrong_reader"]


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


def new_worker(function: Callable, *args, **kwargs):
    """An unstarted napari worker for ``function(*args, **kwargs)`` (``napari.qt.threading.create_worker``: a
    ``FunctionWorker`` for a function, a ``GeneratorWorker`` for a generator function): the one way the plugin's widgets
    run work in the background (:meth:`BackgroundTasks.start`, :meth:`BackgroundTasks.stream`)."""
    from napari.qt.threading import create_worker

    # _ignore_errors: the widgets show a worker's errors themselves (napari would re-raise them in the event loop)
    return create_worker(function, *args, _start_thread=False, _ignore_errors=True, **kwargs)


def _threads_running() -> bool:
    for key, alive in list(_THREADS.items()):
        if alive():
            return True
        _THREADS.pop(key, None)
    return False


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
        if self.is_running(name) or self._closing.is_set():
            return None
        done = threading.Event()

        def job():
            try:
                return compute()
            finally:
                done.set()

        worker = new_worker(job)
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

    def stream(self, function: Callable[..., Iterator], *args, done: threading.Event, on_yield: Callable[[Any], None],
               on_result: Callable[[Any], None], on_error: Callable[[Exception], None],
               on_warning: Callable[[tuple], None], on_finished: Callable[[], None], **kwargs):
        """A long run: generator function ``function(*args, **kwargs)`` in a napari worker thread, wired and returned
        unstarted (start it outside :meth:`Feedback.guard`'s warning capture: see ``_THREADS``).

        Each value it yields goes to ``on_yield``, its return value to ``on_result``, its exception to ``on_error``,
        warnings to ``on_warning``, then ``on_finished``, all on the GUI thread. ``done`` is passed on to the function, which
        sets it when it ends; the thread counts as running until then (:func:`track_thread`). Stopping it and the viewer's closing are the caller's (the run
        has its own stop event and asks before the viewer closes): :meth:`close` leaves it alone.
        """
        worker = new_worker(function, *args, done=done, **kwargs)
        worker.yielded.connect(on_yield)
        worker.returned.connect(on_result)
        worker.errored.connect(on_error)
        worker.warned.connect(on_warning)
        worker.finished.connect(on_finished)
        track_thread(worker, done)
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
