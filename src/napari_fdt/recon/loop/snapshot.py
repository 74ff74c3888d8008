"""What a run reports: its :class:`Snapshot` (the state every ``snapshot_every`` iterations and at the end of every
stage) and each stage's :class:`StageRecord`, and how :class:`~napari_fdt.recon.run.solver.Reconstructor` takes them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from napari_fdt.recon.loop.phases import RUN, probe_iterations
from napari_fdt.recon.loop.phases import phase_label as _phase_label
from napari_fdt.recon.loop.regularisation import TV_PATH, candidate_weights
from napari_fdt.recon.problem.losses import as_floats
from napari_fdt.recon.problem.stages import Stage
from napari_fdt.recon.problem.volume import upsample_to

if TYPE_CHECKING:
    from napari_fdt.recon.loop.interface import Run

__all__ = ["Snapshot", "StageRecord", "take_snapshot", "complete_stage", "rerun_parts"]


@dataclass
class Snapshot:
    """The state of a running reconstruction.

    ``delta_n`` is Δn on the stage grid (n_slices, h, w) (``delta_n_full()`` upsamples it to the
    acquisition grid); ``sources_um`` (N, 3) the calibrated positions (acquisition coordinates);
    ``gains`` (N,); ``calibration`` the global parameters; ``losses`` the loss terms of the last
    iteration (unweighted); ``validation_error`` / ``train_error`` the relative image errors of the held-out
    images and of the last batch (:mod:`napari_fdt.recon.assess.validation`); times in seconds.
    """

    stage: int
    n_stages: int
    factor: int
    iteration: int
    stage_iterations: int
    global_iteration: int
    total_iterations: int
    delta_n: np.ndarray
    sources_um: np.ndarray
    gains: np.ndarray
    calibration: dict[str, float]
    losses: dict[str, float]
    elapsed_s: float
    eta_s: float
    stage_complete: bool
    full_shape: tuple[int, int]
    #: relative RMS error of the held-out images predicted through the volume (closed-form gains; None: no split)
    validation_error: float | None = None
    #: the same error on the last training batch (its trained gains; this rank's part in a distributed run)
    train_error: float | None = None
    #: the model parts the data needed when the stages run again with them (``parts_rerun``): the iteration count
    #: then starts again from the first stage; empty during the first pass
    rerun_with: tuple[str, ...] = ()
    #: "run" for the pass, "tv_choice" for the trials of the TV weights, "rerun" for the stages run again with kept
    #: model parts (:mod:`napari_fdt.recon.loop.phases`)
    phase: str = RUN
    #: iterations done in the plan's current phase, and its iterations in all
    phase_iteration: int = 0
    phase_iterations: int = 0
    #: (τ_xy, τ_z) a trial has just tried (its snapshot: ``validation_error`` is the trial's); None otherwise
    tv_weights: tuple[float, float] | None = None
    #: iterations done along the run's whole plan (:mod:`napari_fdt.recon.loop.plan`: stages, TV trials, stages run again), and
    #: the plan's iterations in all (it grows when a larger TV weight or a kept part adds phases; the count never starts again)
    plan_iteration: int = 0
    plan_iterations: int = 0
    #: the plan's phase in words ("stage 2/3 (x2)", "choosing the TV weight at stage 2/3 (x2)", ASCII)
    phase_name: str = ""
    #: seconds left where the choices still open (the TV weight, the model parts) ask for the costliest work
    #: (:attr:`~napari_fdt.recon.loop.plan.Plan.most_extra_s`, scaled as ``eta_s`` is); None once none is open
    eta_most_s: float | None = None

    @property
    def eta_up_to_s(self) -> float | None:
        """:attr:`eta_most_s` where it is worth saying beside :attr:`eta_s` (over 5 % more), else None."""
        most = self.eta_most_s
        return most if most is not None and most > 1.05 * self.eta_s else None

    @property
    def phase_label(self) -> str:
        """The phase in plain English: "choosing the smoothing (TV) weight", "reconstructing", "reconstructing again with …"."""
        return _phase_label(self.phase, self.rerun_with, self.tv_weights)

    @property
    def phase_progress(self) -> float:
        """The share of this phase done (:attr:`progress` when the phase's count is not given)."""
        return self.phase_iteration / self.phase_iterations if self.phase_iterations > 0 else self.progress

    def delta_n_full(self) -> np.ndarray:
        """Δn on the acquisition grid (n_slices, H, W), float32."""
        t = torch.from_numpy(self.delta_n)
        return upsample_to(t, self.factor, self.full_shape).numpy()

    @property
    def progress(self) -> float:
        """The share of the whole run done (along its plan; of the pass when no plan count is given)."""
        if self.plan_iterations > 0:
            return self.plan_iteration / self.plan_iterations
        return self.global_iteration / max(1, self.total_iterations)


@dataclass
class StageRecord:
    """What one stage did, for the report."""

    stage: int
    factor: int
    field_factor: int
    grid: tuple[int, int, int]
    window: tuple[int, int]
    na: float
    iterations: int
    seconds: float = 0.0
    model: str = "multislice"
    #: seconds of the choices made in this stage that are not its own iterations: the TV trials that lost (tried at its
    #: start and dropped), the pupil's pilot (before the first stage), the model parts' choice (at its end)
    choice_s: float = 0.0
    #: validation error the stage ended on, its iteration (earlier than ``iterations`` when the best iterate was
    #: kept), and the iteration early stopping ended the stage at (None: it ran to the end)
    validation_error: float | None = None
    best_iteration: int | None = None
    stopped_at: int | None = None

    @property
    def seconds_per_iteration(self) -> float:
        ran = self.stopped_at or self.iterations  # early stopping ends a stage before its iterations
        return (self.seconds - self.choice_s) / ran if ran else 0.0

    def to_dict(self) -> dict[str, Any]:
        return {"stage": self.stage, "factor": self.factor, "field_factor": self.field_factor, "grid": list(self.grid), "window": list(self.window),
                "na": self.na, "model": self.model, "iterations": self.iterations, "seconds": self.seconds,
                "seconds_per_iteration": self.seconds_per_iteration, "validation_error": self.validation_error,
                "best_iteration": self.best_iteration, "stopped_at": self.stopped_at, "choice_s": self.choice_s}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "StageRecord":
        """The inverse of :meth:`to_dict`."""
        return cls(d["stage"], d["factor"], d["field_factor"], tuple(d["grid"]), tuple(d["window"]), d["na"], d["iterations"],
                   d["seconds"], d["model"], d.get("choice_s", 0.0), d.get("validation_error"), d.get("best_iteration"),
                   d.get("stopped_at"))


def complete_stage(rec: Run, stage: Stage, record: StageRecord, global_it: int, terms: dict, t0: float,
                   validation_error: float | None, train_error: float | None) -> Snapshot:
    """Close the stage's record and time, take its snapshot and remember it as the last complete state."""
    record.seconds = time.perf_counter() - t0
    snap = take_snapshot(rec, stage, stage.iterations, global_it, terms, t0, True, validation_error, train_error)
    rec.elapsed_s += record.seconds
    snap.elapsed_s = rec.elapsed_s
    rec.completed_stages = stage.index + 1
    rec.last_complete = snap
    rec.last_complete_state = rec._capture()
    rec.final_losses = snap.losses
    return snap


def take_snapshot(rec: Run, stage: Stage, it: int, global_it: int, terms: dict, stage_t0: float, complete: bool,
                  validation_error: float | None = None, train_error: float | None = None, trial: int | None = None,
                  in_history: bool = True) -> Snapshot:
    """The snapshot now (``trial``: the index in the TV path of the weight just tried; ``in_history`` False: not a
    point of the run's loss history, as a trial's or the pupil pilot's)."""
    cfg = rec.config
    rerun_with = rerun_parts(rec)
    terms = rec._gather(terms, optimiser_state=complete)
    now = time.perf_counter()
    elapsed = rec.elapsed_s + (now - stage_t0)
    # where along the plan: the trials' iterations so far, or the stage's iteration in its phase
    index = rec._phase_index
    current = rec.plan.phases[index]
    within = (trial + 1) * probe_iterations(stage.iterations) if trial is not None else it - current.first_iteration
    within = min(max(0, within), current.iterations)
    plan_iteration = rec.plan.iterations_before(index) + within
    rec.pace.observe(index, plan_iteration, elapsed)
    remaining = 0.0 if complete and index == len(rec.plan.phases) - 1 else rec.pace.seconds_left()
    open_s = rec.plan.most_extra_s
    most_left = remaining + rec.pace.correction() * open_s if open_s is not None and remaining > 0 else None
    losses = as_floats(terms) if terms else {}
    snap = Snapshot(
        stage=stage.index, n_stages=len(cfg.stages), factor=stage.factor, iteration=it,
        stage_iterations=stage.iterations, global_iteration=global_it, total_iterations=cfg.total_iterations,
        delta_n=rec.volume.delta_n().detach().cpu().numpy().astype(np.float32),
        sources_um=rec.sources_um(), gains=rec.gains(),
        calibration=rec.calibration.summary(), losses=losses, elapsed_s=elapsed, eta_s=remaining,
        stage_complete=complete, full_shape=rec.full_shape, validation_error=validation_error, train_error=train_error,
        rerun_with=rerun_with, phase=current.pass_name, tv_weights=None if trial is None else candidate_weights(cfg, TV_PATH[trial]),
        phase_iteration=within, phase_iterations=current.iterations,
        plan_iteration=plan_iteration, plan_iterations=rec.plan.iterations, phase_name=current.name, eta_most_s=most_left,
    )
    if trial is None and in_history:  # (a trial's losses are a candidate's, not the run's)
        rec.history.append({"stage": stage.index, "iteration": it, "global_iteration": global_it,
                            "elapsed_s": elapsed, **losses, "validation_error": validation_error, "train_error": train_error})
    return snap


def rerun_parts(rec: Run) -> tuple[str, ...]:
    """The parts kept by the data while the stages run again with them (:attr:`Snapshot.rerun_with`)."""
    choice = rec.parts_choice
    if choice is None or choice.rerun != "stages":
        return ()
    return tuple(p for p, on in choice.parts.items() if on and choice.chosen_by.get(p) == "validation")
