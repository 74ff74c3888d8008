"""The computation process of the napari plugin: ``python -m napari_fdt.napari.jobs.compute_process ADDRESS``.

The widget never runs the solver in napari's own process (:mod:`napari_fdt.napari.jobs.remote_job` starts this one).
Two reasons: napari's process has loaded its OpenGL driver (Mesa's brings its own LLVM, and importing Triton, which
``torch.optim`` does, then segfaults), and a native crash, an out-of-memory kill or a CUDA error here must not close
the viewer. No Qt, no napari here.

Protocol, over a :mod:`multiprocessing.connection` (pickled tuples; the authentication key comes in the environment
variable ``NAPARI_FDT_AUTHKEY``, hex):

* parent → child, first: ``("job", request)``: ``request["target"]`` ``"module:function"``, a generator like
  :func:`napari_fdt.napari.jobs.job.reconstruction_job`, called with ``request["kwargs"]`` plus ``stop`` (an object
  whose ``is_set()`` says whether the parent asked to stop); ``request["sys_path"]``, entries to import from.
* child → parent: ``("update", kind, snapshot, ri)`` for each :class:`~napari_fdt.napari.jobs.job.Update` (the snapshot
  without its stage-grid volume, ``ri`` the absolute RI or None); ``("warning", message, category, filename, lineno)``;
  then ``("returned", fields)`` (the :class:`~napari_fdt.napari.jobs.job.JobResult` without the solver) or
  ``("error", exception)``.
* parent → child during the run: ``("stop",)``: stop at the next iteration (the job keeps the last complete stage).
* after ``returned`` the child keeps the solver and answers ``("predict", index)`` with ``("ok", (predicted,
  measured))`` or ``("error", exception)``, until ``("close",)`` or the parent's end of the connection closes.
"""

from __future__ import annotations

import dataclasses
import importlib
import os
import sys
import traceback
import warnings
from multiprocessing.connection import Client, Connection
from typing import Any

import numpy as np

__all__ = ["main", "AUTHKEY_ENV", "portable_exception", "ComputeError"]

#: Environment variable holding the connection's authentication key (hex).
AUTHKEY_ENV = "NAPARI_FDT_AUTHKEY"


class ComputeError(Exception):
    """An exception of the computation process that cannot cross to napari's as itself: its type's name and message.

    (Not a RuntimeError: superqt's workers take a RuntimeError for a deleted Qt object and drop the error signal.)"""


def portable_exception(exc: BaseException) -> BaseException:
    """``exc`` if it survives pickling (and is no RuntimeError, see :class:`ComputeError`), else a :class:`ComputeError`."""
    import pickle

    if not isinstance(exc, RuntimeError):
        try:
            pickle.loads(pickle.dumps(exc))
            return exc
        except Exception:  # noqa: BLE001 (any exception that cannot cross the process boundary)
            pass
    return ComputeError(f"{type(exc).__name__}: {exc}")


class _ParentStop:
    """``is_set()``: whether the parent sent ``("stop",)`` (polled without blocking: the solver asks every iteration)."""

    def __init__(self, conn: Connection) -> None:
        self._conn = conn
        self._set = False
        self.closed = False

    def is_set(self) -> bool:
        if not self._set:
            try:
                while self._conn.poll(0):
                    msg = self._conn.recv()
                    if msg and msg[0] in ("stop", "close"):
                        self._set = True
                        self.closed = self.closed or msg[0] == "close"
            except (EOFError, OSError):  # the parent is gone: stop
                self._set = self.closed = True
        return self._set


def _send_warning(conn: Connection):
    def show(message, category, filename, lineno, file=None, line=None) -> None:  # warnings.showwarning's signature
        try:
            conn.send(("warning", str(message), category, str(filename), int(lineno)))
        except Exception:  # noqa: BLE001 (a category that cannot be pickled, or the parent gone: print it here)
            sys.stderr.write(warnings.formatwarning(message, category, filename, lineno))
    return show


def _run(conn: Connection, request: dict[str, Any]) -> Any:
    """Run the job, forwarding its updates; return the solver (``rec``) of a finished job, or None."""
    for entry in request.get("sys_path", ()):
        if entry not in sys.path:
            sys.path.append(entry)
    module, _, name = request["target"].partition(":")
    job = getattr(importlib.import_module(module), name)
    stop = _ParentStop(conn)
    gen = job(**request["kwargs"], stop=stop)
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = _send_warning(conn)
        try:
            while True:
                try:
                    update = next(gen)
                except StopIteration as end:
                    result = end.value
                    break
                snap = update.snapshot
                if snap is not None and getattr(snap, "delta_n", None) is not None:
                    snap = dataclasses.replace(snap, delta_n=np.zeros((0, 0, 0), np.float32))  # the parent uses ``ri``
                conn.send(("update", update.kind, snap, update.ri))
        except Exception as exc:  # noqa: BLE001 (every error goes to the widget, which shows it)
            traceback.print_exc()
            conn.send(("error", portable_exception(exc)))
            return None
    if stop.closed:
        return None
    rec = result.rec
    fields = dict(cancelled=result.cancelled, completed_stages=result.completed_stages, ri=result.ri,
                  sources_um=result.sources_um, report=result.report, extra=result.extra)
    if rec is not None:
        fields.update(elapsed_s=float(rec.elapsed_s), device=str(rec.device),
                      initial_sources_um=np.asarray(rec.initial_sources_um), n_stages=len(rec.config.stages))
    conn.send(("returned", fields))
    return rec if result.ri is not None else None


def _serve(conn: Connection, rec: Any) -> None:
    """Answer the parent's requests about the finished run until it closes."""
    from napari_fdt.napari.jobs.compute import predicted_vs_measured

    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg[0] == "close":
            return
        try:
            if msg[0] == "predict":
                conn.send(("ok", predicted_vs_measured(rec, msg[1])))
            else:
                raise ValueError(f"unknown request {msg[0]!r}")
        except Exception as exc:  # noqa: BLE001
            conn.send(("error", portable_exception(exc)))


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1 or AUTHKEY_ENV not in os.environ:
        print("usage: python -m napari_fdt.napari.jobs.compute_process ADDRESS (started by the napari-fdt widget)", file=sys.stderr)
        return 2
    conn = Client(argv[0], authkey=bytes.fromhex(os.environ.pop(AUTHKEY_ENV)))
    try:
        kind, request = conn.recv()
        if kind != "job":
            return 2
        rec = _run(conn, request)
        if rec is not None:
            _serve(conn, rec)
    except (EOFError, BrokenPipeError, ConnectionResetError):  # the parent closed the connection: nothing to tell
        return 0
    finally:
        conn.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
