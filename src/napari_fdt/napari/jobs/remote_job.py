"""The reconstruction run in a process of its own, as the napari widget drives it (no Qt here).

:func:`remote_reconstruction` is a generator with the interface of :func:`napari_fdt.napari.jobs.job.reconstruction_job`
(it yields :class:`~napari_fdt.napari.jobs.job.Update` s and returns a :class:`~napari_fdt.napari.jobs.job.JobResult`) that
runs that job in a child Python process (:mod:`napari_fdt.napari.jobs.compute_process`) and relays what it sends. Why a
process: napari's process must never import Triton (``torch.optim`` does; with Mesa's OpenGL driver loaded, whose LLVM
clashes with Triton's, that segfaults napari), and a native crash, an out-of-memory kill or a CUDA error of the
computation must not close the viewer. When the child dies, the generator raises :class:`ComputeProcessDied`, which
carries the last complete stage's volume that had reached the widget.

The finished run's solver stays in the child (its GPU memory too) as long as the :class:`RunResult` is open, to
answer *Predicted vs measured*; :meth:`RunResult.close` ends the child (a new run closes the previous one).
"""

from __future__ import annotations

import os
import secrets
import signal
import subprocess
import sys
import threading
import time
import warnings
from multiprocessing.connection import Client, Connection, Listener
from typing import Any, Iterator

import numpy as np

from napari_fdt.data.acquisition import Acquisition
from napari_fdt.errors import FDTInputError
from napari_fdt.napari.jobs.compute_process import AUTHKEY_ENV
from napari_fdt.napari.jobs.job import JobResult, Update
from napari_fdt.recon.loop.phases import CANDIDATE_PHASES
from napari_fdt.recon.settings.config import SolverConfig

__all__ = ["remote_reconstruction", "RunResult", "ComputeProcessDied", "JOB_TARGET", "START_TIMEOUT_S"]

#: The job the child runs, ``"module:function"`` (tests swap in one that crashes on purpose).
JOB_TARGET = "napari_fdt.napari.jobs.job:reconstruction_job"
#: Longest wait for the child to start and connect (importing torch on a cold disk takes a while), s.
START_TIMEOUT_S = 180.0


class ComputeProcessDied(FDTInputError):
    """The computation process ended without a result (crash, kill, out of memory).

    ``ri`` (n_slices, H, W) absolute RI of the last complete stage that reached the widget (None: no stage ended),
    ``completed_stages`` how many stages it had completed, ``exit_code`` the process's (negative: the signal)."""

    def __init__(self, exit_code: int | None, completed_stages: int = 0, ri: np.ndarray | None = None) -> None:
        self.exit_code, self.completed_stages, self.ri = exit_code, completed_stages, ri
        super().__init__("reconstruction", f"the computation process ended unexpectedly ({describe_exit(exit_code)})",
                         "napari and its layers are unaffected; the RI layer keeps the last complete stage "
                         f"({completed_stages} done). Run again; if it recurs, try a smaller batch size or another device")

    def __reduce__(self):
        return type(self), (self.exit_code, self.completed_stages, self.ri)


def describe_exit(code: int | None) -> str:
    """``killed by signal 9 (SIGKILL): often the system ran out of memory``, ``exit status 1``, …"""
    if code is None:
        return "it closed its connection"
    if code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = "unknown signal"
        hint = {"SIGKILL": ": often the system ran out of memory", "SIGSEGV": ": a crash in native code"}.get(name, "")
        return f"killed by signal {-code} ({name}){hint}"
    return f"exit status {code}"


class _Child:
    """The child process and its connection (both ends' lifetime)."""

    def __init__(self, proc: subprocess.Popen, conn: Connection) -> None:
        self.proc, self.conn = proc, conn
        self.lock = threading.Lock()  # one request at a time once the run has ended (tasks run in threads)

    @classmethod
    def start(cls, request: dict[str, Any], timeout_s: float = START_TIMEOUT_S) -> "_Child":
        authkey = secrets.token_bytes(32)
        listener = Listener(authkey=authkey)  # AF_UNIX on Linux and macOS, a named pipe on Windows
        env = {**os.environ, AUTHKEY_ENV: authkey.hex()}
        proc = subprocess.Popen([sys.executable, "-m", "napari_fdt.napari.jobs.compute_process", str(listener.address)],
                                env=env, stdin=subprocess.DEVNULL)
        box: list = []

        def accept() -> None:
            try:
                box.append(listener.accept())
            except Exception as exc:  # noqa: BLE001 (our own wake-up call below, or a failed handshake)
                box.append(exc)

        thread = threading.Thread(target=accept, daemon=True, name="napari-fdt accept")
        thread.start()
        t_end = time.monotonic() + timeout_s
        while thread.is_alive() and proc.poll() is None and time.monotonic() < t_end:
            thread.join(0.05)
        if thread.is_alive():  # the child died or never connected: wake the accept with a connection of our own
            try:
                Client(listener.address, authkey=authkey).close()
            except Exception:  # noqa: BLE001
                pass
            thread.join(5.0)
        listener.close()
        conn = box[0] if box and isinstance(box[0], Connection) else None
        if conn is None or proc.poll() is not None:
            if conn is not None:
                conn.close()
            if proc.poll() is None:
                proc.kill()
            proc.wait()
            raise ComputeProcessDied(proc.returncode)
        conn.send(("job", request))
        return cls(proc, conn)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def close(self, kill: bool = False) -> None:
        """End the child: ask it to leave (or kill it, also when a request holds the connection), then reap it."""
        if not self.lock.acquire(timeout=1.0):
            kill = True
        else:
            self.lock.release()
        if self.alive() and not kill:
            try:
                self.conn.send(("close",))
            except OSError:
                pass
            try:
                self.proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                kill = True
        if kill and self.alive():
            self.proc.kill()
        self.conn.close()
        self.proc.wait()


class RunResult:
    """A finished (or cancelled) run as the widget keeps it: the volume, sources and report, with the solver left in the
    computation process for :meth:`predicted_vs_measured`. Duck-types what :func:`napari_fdt.recon.run.report.write_result`
    needs of a :class:`~napari_fdt.recon.run.solver.Reconstructor` (``acquisition``, :meth:`ri_full`)."""

    def __init__(self, acquisition: Acquisition, config: SolverConfig, child: _Child | None, fields: dict[str, Any]) -> None:
        self.acquisition = acquisition
        self.config = config
        self._child = child
        self._ri = np.asarray(fields["ri"], dtype=np.float32)
        self._sources = np.asarray(fields["sources_um"], dtype=np.float64)
        self.report: dict[str, Any] | None = fields.get("report")
        self.cancelled: bool = bool(fields.get("cancelled"))
        self.completed_stages: int = int(fields.get("completed_stages", 0))
        self.elapsed_s: float = float(fields.get("elapsed_s", 0.0))
        self.device: str = str(fields.get("device", "?"))
        self.initial_sources_um = np.asarray(fields.get("initial_sources_um", self._sources))

    def ri_full(self) -> np.ndarray:
        """(n_slices, H, W) absolute RI, float32."""
        return self._ri

    def sources_um(self) -> np.ndarray:
        """(N, 3) calibrated ``[x, y, depth]`` µm."""
        return self._sources

    def predicted_vs_measured(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """Image ``index`` as the run's state predicts it and as measured, computed in the computation process."""
        child = self._child
        if child is None or not child.alive():
            raise FDTInputError("Predicted vs measured", "the computation process of this run has ended",
                                "run the reconstruction again")
        with child.lock:
            try:
                child.conn.send(("predict", int(index)))
                kind, value = child.conn.recv()
            except (EOFError, OSError):
                raise ComputeProcessDied(child.proc.poll(), self.completed_stages) from None
        if kind == "error":
            raise value
        return value

    def close(self) -> None:
        """End the computation process (the volume, sources and report stay here)."""
        if self._child is not None:
            self._child.close()
            self._child = None


def remote_reconstruction(
    acquisition: Acquisition,
    config: SolverConfig,
    *,
    stop: threading.Event,
    done: threading.Event | None = None,
    closing: threading.Event | None = None,
    target: str | None = None,
    poll_s: float = 0.05,
    **job_kwargs: Any,
) -> Iterator[Update]:
    """:func:`~napari_fdt.napari.jobs.job.reconstruction_job` (same keyword arguments) in a computation process.

    Yields its :class:`Update` s (``rec`` None) and returns a :class:`JobResult` whose ``rec`` is a :class:`RunResult`.
    ``stop`` set: the child stops at its next iteration and returns the last complete stage. ``closing`` set (the viewer
    closes): the child is killed at once and the generator returns a result with nothing kept. Warnings of the
    child are shown here again (``warnings.showwarning``: the worker thread's capture relays them). Raises
    :class:`ComputeProcessDied` when the child dies, and re-raises the child's exceptions (:class:`FDTInputError` …).
    """
    request = dict(target=target or JOB_TARGET, sys_path=list(sys.path),
                   kwargs=dict(acquisition=acquisition, config=config, **job_kwargs))
    child = None
    kept = False
    completed, last_ri = 0, None
    try:
        child = _Child.start(request)
        asked_stop = False
        while True:
            if closing is not None and closing.is_set():
                child.close(kill=True)
                return JobResult(None, True, completed)
            if stop.is_set() and not asked_stop:
                try:
                    child.conn.send(("stop",))
                except OSError:
                    pass
                asked_stop = True
            try:
                if not child.conn.poll(poll_s):
                    if not child.alive():
                        raise EOFError
                    continue
                msg = child.conn.recv()
            except (EOFError, OSError):
                try:
                    code = child.proc.wait(timeout=5.0)
                except subprocess.TimeoutExpired:
                    code = None
                raise ComputeProcessDied(code, completed, last_ri) from None
            kind = msg[0]
            if kind == "update":
                _, ukind, snap, ri = msg
                if ukind == "snapshot" and snap.stage_complete and ri is not None and snap.phase not in CANDIDATE_PHASES:
                    completed, last_ri = snap.stage + 1, ri
                yield Update(ukind, snapshot=snap, ri=ri)
            elif kind == "warning":
                _, message, category, filename, lineno = msg
                warnings.showwarning(message, category, filename, lineno)
            elif kind == "error":
                raise msg[1]
            elif kind == "returned":
                fields = msg[1]
                if fields.get("ri") is None:
                    return JobResult(None, bool(fields.get("cancelled")), int(fields.get("completed_stages", 0)),
                                     extra=fields.get("extra") or {})
                result = RunResult(acquisition, config, child, fields)
                kept = True
                return JobResult(result, result.cancelled, result.completed_stages, ri=result.ri_full(),
                                 sources_um=result.sources_um(), report=result.report, extra=fields.get("extra") or {})
    finally:
        if child is not None and not kept:
            child.close(kill=True)
        if done is not None:
            done.set()
