"""The reconstruction as the napari widget runs it in a worker thread: a generator around the solver loop.

:func:`reconstruction_job` drives :meth:`napari_fdt.recon.solver.Reconstructor.run` (the loop ``fdt reconstruct``
runs) and yields an :class:`Update` per snapshot. The absolute RI on the acquisition grid is attached
(computed here, in the worker, not in the GUI thread) at every stage end and otherwise at most every
``min_interval_s``. Setting ``stop`` cancels at the next iteration; the job then returns to the last
complete stage (:meth:`~napari_fdt.recon.solver.Reconstructor.restore_last_complete`) and reports it. No Qt here.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Any, Iterator

import numpy as np

from napari_fdt.data.acquisition import Acquisition
from napari_fdt.physics.optics import Optics
from napari_fdt.recon.config import SolverConfig
from napari_fdt.recon.phases import TV_CHOICE

__all__ = ["Update", "JobResult", "reconstruction_job", "stage_costs", "TimeLeft"]


@dataclass
class Update:
    """One step of the job: ``kind`` is ``"started"`` (``rec`` set), ``"snapshot"`` or ``"evaluating"``.

    ``ri`` (n_slices, H, W) absolute RI, or None when this snapshot is throttled away.
    """

    kind: str
    snapshot: Any = None
    ri: np.ndarray | None = None
    rec: Any = None


@dataclass
class JobResult:
    """What the job ended with. ``ri`` is None when nothing is kept (cancelled before the first stage ended,
    or stopped because the viewer closed); ``report`` is the content of ``RI.json``."""

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
) -> Iterator[Update]:
    """Generator: yields :class:`Update` s, returns a :class:`JobResult` (``StopIteration.value``).

    ``closing`` set (the viewer is closing) skips the final evaluation so the thread ends at once.
    ``done`` is set when the generator ends, however it ends.
    """
    from napari_fdt.recon.report import build_report
    from napari_fdt.recon.solver import Reconstructor

    try:
        rec = Reconstructor(acquisition, config, device=device, initial_sources_um=initial_sources_um)
        yield Update("started", rec=rec)
        n_b = np.float32(acquisition.optics.n_background)
        last = -float("inf")
        for snap in rec.run(should_stop=stop.is_set):
            now = time.perf_counter()
            ri = None
            # the pilot's volumes (phase "tv_choice") are trials, not the result: no RI for them
            if snap.phase != TV_CHOICE and (snap.stage_complete or now - last >= min_interval_s):
                ri = n_b + snap.delta_n_full()
                last = time.perf_counter()
            yield Update("snapshot", snapshot=snap, ri=ri)
        cancelled = stop.is_set() and rec.completed_stages < len(config.stages)
        if closing is not None and closing.is_set():
            return JobResult(rec, True, rec.completed_stages)
        if cancelled:
            if rec.completed_stages == 0:
                return JobResult(rec, True, 0)
            rec.restore_last_complete()
        yield Update("evaluating")
        report = build_report(rec, acquisition_path=acquisition_path, cancelled=cancelled)
        sources = rec.sources_um()
        return JobResult(rec, cancelled, rec.completed_stages, ri=rec.ri_full(), sources_um=sources, report=report)
    finally:
        if done is not None:
            done.set()


def stage_costs(optics: Optics, image_shape: tuple[int, int], config: SolverConfig, n_images: int | None = None,
                device_type: str = "cpu") -> list[float]:
    """Relative cost of one iteration of every stage, known before the run: field-grid pixels × images per batch.

    A stage of factor f works on a field grid of ``(H/g)·(W/g)`` pixels (``g`` the field factor of
    :func:`napari_fdt.recon.stages.field_factor`, or f itself for the envelope model, which ``coarse_model`` ``auto``
    picks off CUDA), one image of the batch at a time.
    """
    from napari_fdt.recon.config import resolve_coarse_model
    from napari_fdt.recon.stages import field_factor

    coarse = resolve_coarse_model(config.coarse_model, device_type)
    h, w = image_shape
    out = []
    for s in config.stages:
        g = s.factor if (s.factor > 1 and coarse == "envelope") else field_factor(optics, s.factor)
        batch = s.batch_size or config.batch_size
        if n_images is not None:
            batch = min(batch, n_images)
        out.append((h / g) * (w / g) * batch)
    return out


class TimeLeft:
    """Time-left estimate of a run from measured per-stage cost.

    ``iterations[s]`` and ``costs[s]`` (relative cost of one iteration, :func:`stage_costs`) of every stage are known
    before the run. :meth:`add` takes each snapshot's (stage, iteration within the stage, elapsed seconds of the run).
    The time of an interval between two snapshots of one stage, divided by its iterations × the stage's cost, measures
    seconds per cost unit; the first interval of each stage (which holds the stage's set-up) is left out while a
    later one exists. The current stage's rest is priced at its own measured seconds per iteration, the later stages
    at the run's measured seconds per cost unit × their cost, plus the measured set-up time of a stage.
    """

    def __init__(self, iterations: list[int], costs: list[float]) -> None:
        if len(iterations) != len(costs) or not iterations:
            raise ValueError("need one cost per stage")
        self.iterations = [int(i) for i in iterations]
        self.costs = [float(c) for c in costs]
        self._last: tuple[int, int, float] | None = None
        #: per stage: [seconds, iterations] of its steady intervals, and of its first interval
        self._steady = [[0.0, 0] for _ in iterations]
        self._first = [[0.0, 0] for _ in iterations]
        self._current = (0, 0)

    def add(self, stage: int, iteration: int, elapsed_s: float) -> None:
        """Record a snapshot: ``iteration`` iterations of ``stage`` done after ``elapsed_s`` seconds of the run."""
        if self._last is None or stage != self._last[0]:
            # a new stage: its first interval counts from the end of the previous stage (or the run's start)
            start = 0.0 if self._last is None else self._last[2]
            acc = self._first[stage]
            acc[0] += max(0.0, elapsed_s - start)
            acc[1] += int(iteration)
        else:
            d_it = int(iteration) - self._last[1]
            if d_it > 0:
                acc = self._steady[stage]
                acc[0] += max(0.0, elapsed_s - self._last[2])
                acc[1] += d_it
        self._last = (int(stage), int(iteration), float(elapsed_s))
        self._current = (int(stage), int(iteration))

    def seconds_per_cost(self) -> float | None:
        """Measured seconds per cost unit over the stages seen (steady intervals where a stage has them)."""
        seconds = units = 0.0
        have_steady = any(acc[1] > 0 for acc in self._steady)
        for s, cost in enumerate(self.costs):
            acc = self._steady[s] if (self._steady[s][1] > 0 or have_steady) else self._first[s]
            seconds += acc[0]
            units += acc[1] * cost
        return seconds / units if units > 0 else None

    def setup_seconds(self) -> float:
        """Measured set-up time of a stage: the excess of a first interval over its stage's steady pace (mean)."""
        extra = [max(0.0, first[0] - first[1] * steady[0] / steady[1])
                 for first, steady in zip(self._first, self._steady) if steady[1] > 0 and first[1] > 0]
        return sum(extra) / len(extra) if extra else 0.0

    def seconds_left(self) -> float | None:
        """Estimated seconds to the end of the run; None before the first snapshot."""
        rate = self.seconds_per_cost()
        if rate is None:
            return None
        stage, it = self._current
        steady = self._steady[stage]
        if steady[1] > 0:  # this stage's own pace
            per_it = steady[0] / steady[1]
        elif stage > 0:  # only the first interval (with the set-up): the earlier stages' pace × this stage's cost
            per_it = rate * self.costs[stage]
        else:
            per_it = self._first[stage][0] / max(1, self._first[stage][1])
        left = max(0, self.iterations[stage] - it) * per_it
        setup = self.setup_seconds()
        for s in range(stage + 1, len(self.iterations)):
            left += setup + self.iterations[s] * rate * self.costs[s]
        return left
