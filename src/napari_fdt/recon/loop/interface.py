"""What the loop's helpers and the choices may touch of a run: the :class:`Run` interface.

The stage loop (:mod:`~napari_fdt.recon.loop.stage_loop`), its snapshots, validation and checkpoints, and every choice
plugged into it (:mod:`napari_fdt.recon.choices`) receive the run as a :class:`Run`, never as the solver class: they
import this module, not :mod:`napari_fdt.recon.run.solver`, so no import circle runs through the solver. The
:class:`~napari_fdt.recon.run.solver.Reconstructor` is the one implementation; ``tests/test_import_graph.py`` checks that
every member a helper reads or writes is listed here and that the solver has each.

The members, by what they are for:

- the run's settings and data: ``config`` (as run), ``requested_config`` (as given), ``acquisition``, ``device``,
  ``dtype``, ``full_shape`` (the acquisition's image shape (H, W)), ``initial_sources_um`` (N, 3) µm,
  ``coarse_model``, ``validation_indices`` (V,) held-out images, ``group`` (a distributed run's rank, else None);
- the state (:class:`~napari_fdt.recon.loop.run_state.RunState`, read and written as attributes): ``state``,
  ``volume``, ``volume_factor``, ``calibration``, ``batches``, ``completed_stages``, ``stages``, ``history``,
  ``elapsed_s``, ``final_losses``, ``tv_choice``, ``parts_choice``, ``early_trials``, ``last_complete``,
  ``last_complete_state``;
- the model as now switched: ``parts`` (part → on), ``_auto_parts`` (those chosen from the data),
  ``_choose_again``, ``_parts_chosen_by``, ``loss_weights``, ``wavelengths`` / ``weights`` (the spectral model's),
  ``apply_parts_choice``, ``_build_stage``, ``_loss_mask``, ``_carry_volume_to``;
- one iteration: ``_step``, ``_set_step_size``, ``_predict_normalised``, ``_stop_requested``;
- branches and restarts: ``_capture``, ``_restore``, ``_restart``;
- the plan: ``plan``, ``pace``, ``_phase_index``, ``_revise_plan``, ``_stage_phase``, ``_enter_stage_phase``;
- results and bookkeeping: ``sources_um``, ``gains``, ``validation_error``, ``_gather``, ``_share_per_source_rows``,
  ``_checkpoint_in_stage``, ``_resume_in_stage``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, Protocol

if TYPE_CHECKING:
    import numpy as np
    import torch

    from napari_fdt.data.acquisition import Acquisition
    from napari_fdt.recon.calibration.calibration import Calibration
    from napari_fdt.recon.loop.model_parts import EarlyTrials, PartsChoice
    from napari_fdt.recon.loop.pace import Pace
    from napari_fdt.recon.loop.plan import Phase, Plan
    from napari_fdt.recon.loop.regularisation import TVChoice
    from napari_fdt.recon.problem.batches import BatchOrder
    from napari_fdt.recon.problem.distributed import Group
    from napari_fdt.recon.problem.losses import LossWeights
    from napari_fdt.recon.problem.stages import Stage
    from napari_fdt.recon.problem.volume import RIVolume
    from napari_fdt.recon.settings.config import SolverConfig

__all__ = ["Run"]


class Run(Protocol):
    """A run as its loop's helpers and choices see it (the members listed in this module's docstring)."""

    # settings and data
    config: SolverConfig
    requested_config: SolverConfig
    acquisition: Acquisition
    device: torch.device
    dtype: torch.dtype
    full_shape: tuple[int, int]
    initial_sources_um: np.ndarray
    coarse_model: str
    validation_indices: Any
    group: Group | None
    # the state
    state: Any  # the RunState (recon/loop/run_state.py, which imports this module's users: not imported here)
    volume: RIVolume | None
    volume_factor: int | None
    calibration: Calibration
    batches: BatchOrder
    completed_stages: int
    stages: list[Any]  # StageRecords (recon/loop/snapshot.py)
    history: list[dict[str, Any]]
    elapsed_s: float
    final_losses: dict[str, float]
    tv_choice: TVChoice | None
    parts_choice: PartsChoice | None
    early_trials: EarlyTrials | None
    last_complete: Any  # a Snapshot (recon/loop/snapshot.py) or None
    last_complete_state: dict[str, Any] | None
    # the model as now switched
    parts: dict[str, bool]
    _auto_parts: list[str]
    _choose_again: list[str]
    _parts_chosen_by: dict[str, str]
    loss_weights: LossWeights
    wavelengths: Any
    weights: Any
    # the plan
    plan: Plan
    pace: Pace
    _phase_index: int
    _resume_in_stage: Any

    def apply_parts_choice(self, choice: PartsChoice) -> None: ...
    def _build_stage(self, stage_index: int) -> Stage: ...
    def _loss_mask(self, stage: Stage) -> torch.Tensor | None: ...
    def _carry_volume_to(self, stage: Stage) -> None: ...
    def _step(self, stage: Stage, mask: torch.Tensor | None, vol_opt: torch.optim.Optimizer, batch_size: int,
              data_range: float, progress: float, with_error: bool = False) -> tuple[dict[str, torch.Tensor], float | None]: ...
    def _set_step_size(self, vol_opt: torch.optim.Optimizer, stage: Stage, it: int) -> None: ...
    def _predict_normalised(self, stage: Stage, dn: torch.Tensor, idx: torch.Tensor, held_out: bool = False) -> torch.Tensor: ...
    def _stop_requested(self, should_stop: Callable[[], bool] | None) -> bool: ...
    def _capture(self) -> dict[str, Any]: ...
    def _restore(self, state: dict[str, Any], keep_bookkeeping: bool = False) -> None: ...
    def _restart(self, keep_last_complete: bool = False) -> None: ...
    def _revise_plan(self, plan: Plan) -> None: ...
    def _stage_phase(self, stage: int, pass_name: str, parts: tuple[str, ...]) -> Phase: ...
    def _enter_stage_phase(self, stage_index: int) -> None: ...
    def sources_um(self) -> np.ndarray: ...
    def gains(self) -> np.ndarray: ...
    def validation_error(self, stage: Stage, mask: torch.Tensor | None = None) -> float | None: ...
    def _gather(self, terms: dict, optimiser_state: bool = False) -> dict: ...
    def _share_per_source_rows(self, optimiser_state: bool = False) -> None: ...
    def _checkpoint_in_stage(self, work: Any) -> None: ...
