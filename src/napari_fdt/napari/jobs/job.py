"""The reconstruction as the napari widget runs it in a worker thread: a generator around the solver loop.

:func:`reconstruction_job` drives :meth:`napari_fdt.recon.run.solver.Reconstructor.run` (the loop ``fdt reconstruct``
runs) and yields an :class:`Update` per snapshot. The absolute RI on the acquisition grid is attached
(computed here, in the worker, not in the GUI thread) at every stage end and otherwise at most every
``min_interval_s``. Setting ``stop`` cancels at the next iteration; the job then returns to the last
complete stage and reports it. The run starts and ends as ``fdt reconstruct``'s (:mod:`napari_fdt.recon.run.session`:
``open_run``, ``finish_run``). No Qt here.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from napari_fdt.data.acquisition import Acquisition
from napari_fdt.recon.loop.phases import CANDIDATE_PHASES
from napari_fdt.recon.settings.config import SolverConfig

__all__ = ["Update", "JobResult", "reconstruction_job"]


@dataclass
class Update:
    """One step of the job: ``kind`` is ``"started"`` (``rec`` set), ``"snapshot"``, ``"evaluating"`` or
    ``"resolution"`` (the half-set resolution's two runs begin, ``half_set_resolution``) or ``"bounds"`` (the error
    bound's re-simulated runs begin, ``error_bounds``).

    ``ri`` (n_slices, H, W) absolute RI, or None when this snapshot is throttled away.
    """

    kind: str
    snapshot: Any = None
    ri: np.ndarray | None = None
    rec: Any = None


@dataclass
class JobResult:
    """What the job ended with. ``ri`` is None when nothing is kept (cancelled before the first stage ended,
    or stopped because the viewer closed); ``report`` is the content of ``RI.json``; ``extra["error_bounds"]`` the
    bound (n_slices, H, W) in RI units where ``error_bounds`` made one."""

    rec: Any
    cancelled: bool
    completed_stages: int
    ri: np.ndarray | None = None
    sources_um: np.ndarray | None = None
    report: dict[str, Any] | None = None
    extra: dict[str, Any] = field(default_factory=dict)


def reconstruction_job(
    acquisition: Acquisition,
    config: SolverConfig,
    *,
    device: str = "auto",
    initial_sources_um: np.ndarray | None = None,
    stop: threading.Event,
    done: threading.Event | None = None,
    closing: threading.Event | None = None,
    min_interval_s: float = 0.5,
    acquisition_path: str | None = None,
    checkpoint_dir: str | None = None,
    resume: bool = False,
) -> Iterator[Update]:
    """Generator: yields :class:`Update` s, returns a :class:`JobResult` (``StopIteration.value``).

    ``closing`` set (the viewer is closing) skips the final evaluation so the thread ends at once.
    ``done`` is set when the generator ends, however it ends. ``checkpoint_dir``: where the run writes its checkpoints
    (:mod:`napari_fdt.napari.jobs.resume`); with ``resume`` it continues the run they hold (its own settings; ``config``
    and ``initial_sources_um`` are not used), else the old ones are deleted first. A run that ends deletes them; a
    cancelled one keeps them, to be resumed.
    """
    from napari_fdt.napari.jobs.resume import clear
    from napari_fdt.recon.run.error_bounds import error_bounds
    from napari_fdt.recon.run.session import add_resolution, bounds_due, finish_run, open_run, resolution_due

    try:
        folder = None if checkpoint_dir is None else Path(checkpoint_dir)
        resumed = resume and folder is not None
        if not resumed:
            clear(folder)
        rec = open_run(acquisition, config, device=device, resume=folder if resumed else None,
                       initial_sources_um=initial_sources_um)
        yield Update("started", rec=rec)
        n_b = np.float32(acquisition.optics.n_background)
        last = -float("inf")
        for snap in rec.run(should_stop=stop.is_set, checkpoint_dir=folder):
            now = time.perf_counter()
            ri = None
            # a TV trial's volume (phase "tv_choice") is a candidate, the pupil pilot's is zero: not the run's, no RI for it
            if snap.phase not in CANDIDATE_PHASES and (snap.stage_complete or now - last >= min_interval_s):
                ri = n_b + snap.delta_n_full()
                last = time.perf_counter()
            yield Update("snapshot", snapshot=snap, ri=ri)
        cancelled = stop.is_set() and rec.completed_stages < len(rec.config.stages)
        if closing is not None and closing.is_set():  # the checkpoints stay: the run can be resumed
            return JobResult(rec, True, rec.completed_stages)
        if not cancelled:
            clear(folder)  # the run ended: nothing to resume
        if cancelled and rec.completed_stages == 0:
            return JobResult(rec, True, 0)  # nothing to keep
        yield Update("evaluating")
        report = finish_run(rec, cancelled, acquisition_path=acquisition_path)
        if resolution_due(rec, cancelled):  # a cancel now stops only the halves: the run's result is kept as it is
            yield Update("resolution")
            report = add_resolution(rec, report, should_stop=stop.is_set) or report
        extra: dict[str, Any] = {}
        if bounds_due(rec, cancelled) and not stop.is_set():  # a cancel stops only the bound's runs: the result stays
            yield Update("bounds")
            made = error_bounds(rec, should_stop=stop.is_set)
            if made is not None:
                report = {**report, "error_bounds": made.to_dict()}
                extra["error_bounds"] = made.bound
        sources = rec.sources_um()
        return JobResult(rec, cancelled, rec.completed_stages, ri=rec.ri_full(), sources_um=sources, report=report, extra=extra)
    finally:
        if done is not None:
            done.set()
