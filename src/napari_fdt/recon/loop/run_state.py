"""The state of a run in one object: what training changes and what the run has decided so far.

:class:`RunState` holds the RI grid, the calibration (its parameters and their Adam optimiser), the batch order, the
completed stages and their records, the history, the solver's seconds, the choices made (TV weights, model parts, the
trials of parts made early that kept nothing) and the last complete stage (what a cancel returns to). A checkpoint is its :meth:`~RunState.state_dict` beside the
configuration and the acquisition's size (:mod:`napari_fdt.recon.loop.checkpoint`); resuming loads it back
(:meth:`~RunState.load_state_dict`); a choice that sends the run back to its first stage replaces it by a fresh one
(:meth:`~RunState.fresh`) that keeps the choices. The :class:`~napari_fdt.recon.run.solver.Reconstructor` reads and writes
these fields as its own attributes (:class:`InState`), so the loop reads as before.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch

from napari_fdt.recon.calibration.calibration import Calibration
from napari_fdt.recon.loop.model_parts import EarlyTrials, PartsChoice
from napari_fdt.recon.loop.regularisation import TVChoice
from napari_fdt.recon.loop.snapshot import Snapshot, StageRecord
from napari_fdt.recon.problem.batches import BatchOrder
from napari_fdt.recon.problem.volume import RIVolume

__all__ = ["RunState", "InState"]


@dataclass(eq=False)
class RunState:
    """Everything a run changes. Shapes: the volume on the current stage's grid (factor ``volume_factor``)."""

    calibration: Calibration
    batches: BatchOrder
    volume: RIVolume | None = None
    volume_factor: int | None = None
    completed_stages: int = 0
    stages: list[StageRecord] = field(default_factory=list)
    history: list[dict[str, Any]] = field(default_factory=list)
    #: the solver's own seconds (the consumer's pauses not counted)
    elapsed_s: float = 0.0
    final_losses: dict[str, float] = field(default_factory=dict)
    #: the "auto" TV weights chosen (None until chosen, or when the weights are numbers)
    tv_choice: TVChoice | None = None
    #: what the choice of the "auto" model parts tried and chose (None until made)
    parts_choice: PartsChoice | None = None
    #: trials of parts made before the finest stage's choice that kept nothing (None: none made)
    early_trials: EarlyTrials | None = None
    #: the snapshot of the last complete stage, and copies of the state it ended with (a cancel returns there)
    last_complete: Snapshot | None = None
    last_complete_state: dict[str, Any] | None = None

    def fresh(self, calibration: Calibration, batches: BatchOrder, keep_last_complete: bool) -> "RunState":
        """The state before any stage ran, with the choices made so far and the seconds spent (and, if asked, the last
        complete stage)."""
        return RunState(calibration, batches, elapsed_s=self.elapsed_s, tv_choice=self.tv_choice, parts_choice=self.parts_choice,
                        early_trials=self.early_trials,
                        last_complete=self.last_complete if keep_last_complete else None,
                        last_complete_state=self.last_complete_state if keep_last_complete else None)

    def state_dict(self) -> dict[str, Any]:
        """The checkpoint's part of the state (tensors on the CPU); the calibration's and batch order's keys at the
        top level, as in the checkpoints written before this object existed."""
        return {
            "completed_stages": self.completed_stages,
            "volume": None if self.volume is None else self.volume.state_dict(), "volume_factor": self.volume_factor,
            **self.calibration.state_dict(),
            **self.batches.state_dict(),
            "stages": [r.to_dict() for r in self.stages], "history": self.history, "elapsed_s": self.elapsed_s,
            "tv_choice": None if self.tv_choice is None else self.tv_choice.to_dict(),
            "parts_choice": None if self.parts_choice is None else self.parts_choice.to_dict(),
            "early_trials": None if self.early_trials is None else self.early_trials.to_dict(),
        }

    def load_state_dict(self, state: dict[str, Any], device: torch.device, dtype: torch.dtype) -> None:
        """Load a checkpoint's state (the parts choice is applied by the caller first: it switches the calibration's
        parameters that the state then fills). Written inside a stage (``in_stage``), the calibration is that stage's."""
        self.completed_stages = int(state["completed_stages"])
        in_stage = state.get("in_stage")
        self.calibration.load_state_dict(state, self.completed_stages if in_stage else max(0, self.completed_stages - 1))
        if state["volume"] is not None:
            self.volume = RIVolume.from_state_dict(state["volume"], device, dtype)
        self.volume_factor = state["volume_factor"]
        self.batches.load_state_dict(state)
        self.stages = [StageRecord.from_dict(r) for r in state["stages"]]
        choice = state.get("tv_choice")  # absent in checkpoints written before automatic regularisation
        if choice is not None:
            self.tv_choice = TVChoice(**choice)
        early = state.get("early_trials")  # absent in checkpoints written before 2026-11-27 (their report lists fewer trials)
        self.early_trials = None if early is None else EarlyTrials.from_dict(early)
        self.history = list(state["history"])
        self.elapsed_s = float(state["elapsed_s"])


class InState:
    """An attribute of the solver that lives in its :class:`RunState` (``obj.state``)."""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    def __get__(self, obj: Any, owner: type | None = None) -> Any:
        return self if obj is None else getattr(obj.state, self.name)

    def __set__(self, obj: Any, value: Any) -> None:
        setattr(obj.state, self.name, value)
